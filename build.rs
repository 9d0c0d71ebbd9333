//! Build script: passes the fingerprint of the crate's sources to the crate as
//! `SHAPESEEK_SOURCE_FINGERPRINT` (16 hex digits), which `shapeseek eval` puts in its cache keys
//! (`src/eval/shapes.rs`, `analysis_version`): a build serves only the analyses and signatures
//! that the same sources computed. The function lives in `src/source_fingerprint.rs`, where the
//! library's tests check it.

include!("src/source_fingerprint.rs");

fn main() {
    let root =
        std::path::PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let fp = source_fingerprint(&root).expect("reading the crate's sources");
    println!("cargo:rustc-env=SHAPESEEK_SOURCE_FINGERPRINT={fp:016x}");
    println!("cargo:rerun-if-changed=src");
    println!("cargo:rerun-if-changed=Cargo.lock");
    println!("cargo:rerun-if-changed=build.rs");
}
