#!/usr/bin/env bash
# Runs a command with a time limit; on a hang, says where it hangs before it kills it.
#
#   bash scripts/watchdog.sh SECONDS COMMAND [ARGS...]
#
# The command runs in a session of its own, so that everything it starts (cargo's test binaries,
# the servers the tests start) can be found and killed together. Its exit status is returned as
# it is. If it is still running after SECONDS, every process of that session is listed, the
# threads' stacks of each process that is not cargo, rustc or a shell are printed (gdb in batch
# mode, at most 120 s per process; without gdb, each thread's kernel wait channel), the session
# is killed, and the exit status is 124 (as timeout(1)'s).
#
# Why: a test that hangs otherwise runs until CI's own limit ends the whole job, which keeps no
# output; this ends the step early and prints what the hung threads were waiting for. By hand:
# `bash scripts/watchdog.sh 600 cargo test --release`.
set -uo pipefail

if [ $# -lt 2 ] || ! [[ $1 =~ ^[0-9]+$ ]]; then
  echo "usage: $0 SECONDS COMMAND [ARGS...]" >&2
  exit 2
fi
limit=$1
shift

# A background job of a non-interactive shell is not a process-group leader, so setsid(1) calls
# setsid(2) in place (no fork): $! is the command's pid and its session id.
setsid "$@" &
pid=$!
trap 'kill -TERM -- -"$pid" 2>/dev/null; wait "$pid" 2>/dev/null; exit 130' INT TERM

start=$SECONDS
while kill -0 "$pid" 2>/dev/null; do
  if (( SECONDS - start >= limit )); then
    break
  fi
  sleep 2
done

if ! kill -0 "$pid" 2>/dev/null; then
  wait "$pid"
  exit $?
fi

echo "== watchdog: still running after ${limit} s: $*" >&2
echo "== watchdog: the processes of its session" >&2
ps -o pid=,ppid=,etimes=,time=,stat=,args= -s "$pid" >&2 || true
for p in $(ps -o pid= -s "$pid"); do
  comm=$(cat "/proc/$p/comm" 2>/dev/null) || continue
  case "$comm" in
    cargo | rustc | bash | sh | setsid | sleep) continue ;;
  esac
  echo "== watchdog: threads of $p ($comm)" >&2
  if command -v gdb >/dev/null; then
    timeout 120 gdb -p "$p" -batch -nx -q -iex 'set auto-load off' -ex 'set pagination off' -ex 'thread apply all bt' \
      2>&1 | grep -v '^\[New LWP\|^\[Thread debugging\|^Using host libthread' >&2 || true
  else
    for t in /proc/"$p"/task/*; do
      echo "  thread ${t##*/} ($(cat "$t/comm" 2>/dev/null)): waits in $(cat "$t/wchan" 2>/dev/null)" >&2
    done
  fi
done
kill -KILL -- -"$pid" 2>/dev/null
wait "$pid" 2>/dev/null
echo "== watchdog: killed after ${limit} s: $*" >&2
exit 124
