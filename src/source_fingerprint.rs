// The source fingerprint of the build, shared by `build.rs` (which `include!`s this file and
// passes the value to the crate as `SHAPESEEK_SOURCE_FINGERPRINT`) and the library's tests. Plain
// std only (FNV-1a is a few lines), so that the build script needs no build-dependencies.
//
// Why (`docs/quality.md` §29–§30): eval's cache keyed an analysis on the mesh bytes, the options
// and `ALGORITHM_REVISION`, not on the code, so two builds at the same revision that analyse
// differently (a candidate under measurement, a fix that forgot the bump) served each other's
// analyses, and two of §28's figures came from another build's caps. With this fingerprint in
// the key, a build serves only analyses made by the same sources.

/// FNV-1a (64 bits) over every `.rs` file under `root/src` (paths relative to `root`, `/`
/// separators, in sorted order; each path and each content followed by a 0 byte), then over
/// `root/Cargo.lock` when it exists (dependency versions move results too). Independent of the
/// order the directories list their entries in and of file times; any change of a source
/// file's bytes, name or place changes it.
pub fn source_fingerprint(root: &std::path::Path) -> std::io::Result<u64> {
    fn walk(
        dir: &std::path::Path,
        root: &std::path::Path,
        out: &mut Vec<(String, std::path::PathBuf)>,
    ) -> std::io::Result<()> {
        for entry in std::fs::read_dir(dir)? {
            let path = entry?.path();
            if path.is_dir() {
                walk(&path, root, out)?;
            } else if path.extension().is_some_and(|e| e == "rs") {
                let rel = path
                    .strip_prefix(root)
                    .unwrap_or(&path)
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect::<Vec<_>>()
                    .join("/");
                out.push((rel, path));
            }
        }
        Ok(())
    }
    // The bytes, then a 0 byte (so that a path's end cannot be taken for its content's start).
    fn eat(h: &mut u64, bytes: &[u8]) {
        for &b in bytes.iter().chain(std::iter::once(&0)) {
            *h ^= u64::from(b);
            *h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    let mut files = Vec::new();
    walk(&root.join("src"), root, &mut files)?;
    let lock = root.join("Cargo.lock");
    if lock.is_file() {
        files.push(("Cargo.lock".to_string(), lock));
    }
    files.sort();
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for (rel, path) in &files {
        eat(&mut h, rel.as_bytes());
        eat(&mut h, &std::fs::read(path)?);
    }
    Ok(h)
}

#[cfg(test)]
mod tests {
    use super::source_fingerprint;
    use std::fs;

    #[test]
    fn the_fingerprint_follows_the_sources_and_nothing_else() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path();
        fs::create_dir_all(root.join("src/sub")).unwrap();
        fs::write(root.join("src/lib.rs"), "pub mod sub;\n").unwrap();
        fs::write(root.join("src/sub/mod.rs"), "pub fn f() -> u32 { 1 }\n").unwrap();
        fs::write(root.join("src/notes.txt"), "not code\n").unwrap();
        fs::write(root.join("Cargo.lock"), "version = 3\n").unwrap();
        let fp = || source_fingerprint(root).unwrap();
        let base = fp();
        assert_eq!(fp(), base, "the same sources give the same fingerprint");

        fs::write(root.join("src/notes.txt"), "other words\n").unwrap();
        assert_eq!(fp(), base, "a file that is not Rust source does not count");

        fs::write(root.join("src/sub/mod.rs"), "pub fn f() -> u32 { 2 }\n").unwrap();
        let edited = fp();
        assert_ne!(edited, base, "an edited source file changes it");
        fs::write(root.join("src/sub/mod.rs"), "pub fn f() -> u32 { 1 }\n").unwrap();
        assert_eq!(
            fp(),
            base,
            "and undoing the edit gives the first value back"
        );

        fs::rename(root.join("src/sub/mod.rs"), root.join("src/sub/other.rs")).unwrap();
        assert_ne!(fp(), base, "a renamed source file changes it");
        fs::rename(root.join("src/sub/other.rs"), root.join("src/sub/mod.rs")).unwrap();

        fs::write(root.join("Cargo.lock"), "version = 4\n").unwrap();
        assert_ne!(fp(), base, "other dependency versions change it");
        fs::remove_file(root.join("Cargo.lock")).unwrap();
        assert_ne!(fp(), base, "so does a missing lock file");
    }

    #[test]
    fn the_build_fingerprint_is_that_of_the_sources_it_was_built_from() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let built = u64::from_str_radix(env!("SHAPESEEK_SOURCE_FINGERPRINT"), 16).unwrap();
        assert_eq!(source_fingerprint(root).unwrap(), built);
    }
}
