#!/usr/bin/env bash
# Builds the two base images of docker/Dockerfile without a container registry, for podman or
# docker (run as root; needs debootstrap and a Debian mirror):
#
#   localhost/debian:bookworm              Debian bookworm (minbase): the runtime base
#   localhost/shapeseek-builder:bookworm   the same plus gcc, g++, libc6-dev, ca-certificates and the
#                                          host's Rust toolchain (rustc/cargo >= 1.85)
#
# Usage: docker/local-bases.sh [WORKDIR]    (ENGINE=docker to use docker instead of podman;
#        MIRROR=http://deb.debian.org/debian; TOOLCHAIN=path of a rustup toolchain;
#        HOST_CA_BUNDLE=the CA bundle copied into the builder, default the host's)
# Then:  podman build --build-arg BUILDER_IMAGE=localhost/shapeseek-builder:bookworm \
#          --build-arg RUNTIME_IMAGE=localhost/debian:bookworm -f docker/Dockerfile -t shapeseek .
set -euo pipefail
ENGINE=${ENGINE:-podman}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
WORK=${1:-/var/tmp/shapeseek-bases}
TOOLCHAIN=${TOOLCHAIN:-$(rustc --print sysroot)}
mkdir -p "$WORK"

if ! "$ENGINE" image inspect localhost/debian:bookworm >/dev/null 2>&1; then
  rm -rf "$WORK/runtime"
  debootstrap --variant=minbase bookworm "$WORK/runtime" "$MIRROR"
  rm -rf "$WORK/runtime/var/cache/apt/archives/"*.deb "$WORK/runtime/var/lib/apt/lists/"*
  tar -C "$WORK/runtime" -c . | "$ENGINE" import - localhost/debian:bookworm
fi

if ! "$ENGINE" image inspect localhost/shapeseek-builder:bookworm >/dev/null 2>&1; then
  rm -rf "$WORK/builder"
  debootstrap --variant=minbase --include=gcc,g++,libc6-dev,ca-certificates \
    bookworm "$WORK/builder" "$MIRROR"
  rm -rf "$WORK/builder/var/cache/apt/archives/"*.deb "$WORK/builder/var/lib/apt/lists/"*
  mkdir -p "$WORK/builder/usr/local/rust"
  cp -a "$TOOLCHAIN/bin" "$TOOLCHAIN/lib" "$WORK/builder/usr/local/rust/"
  # The host's CA bundle, so that cargo trusts what the host trusts (e.g. a TLS-inspecting
  # proxy's certificate authority) when it fetches crates.
  if [ -f "${HOST_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}" ]; then
    cp "${HOST_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}" \
       "$WORK/builder/etc/ssl/certs/ca-certificates.crt"
  fi
  tar -C "$WORK/builder" -c . | "$ENGINE" import \
    --change 'ENV PATH=/usr/local/rust/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV CARGO_HOME=/usr/local/cargo' \
    - localhost/shapeseek-builder:bookworm
fi
"$ENGINE" images | grep -E 'localhost/(debian|shapeseek-builder)'
