//! Which manifest rows a run evaluates: `--classes` and `--per-class`.

use super::*;

/// The manifest of the run, restricted to `--classes` and then to `--per-class` rows per class.
pub(super) fn select_rows(args: &EvalOptions) -> Result<Manifest> {
    let mut manifest = Manifest::read(&args.manifest)?;
    if !args.classes.is_empty() {
        manifest
            .entries
            .retain(|e| args.classes.iter().any(|c| c == &e.class));
        if manifest.entries.is_empty() {
            return Err(Error::InvalidArgument(format!(
                "--classes {}: no manifest row",
                args.classes.join(",")
            )));
        }
    }
    if let Some(m) = args.per_class {
        manifest.entries =
            per_class_subset(std::mem::take(&mut manifest.entries), m, args.sample_seed);
        if manifest.entries.is_empty() {
            return Err(Error::InvalidArgument("--per-class must be ≥ 1".into()));
        }
    }
    Ok(manifest)
}

/// `--per-class`: per class, the `m` rows with the smallest `hash(seed, id)`, in manifest order.
fn per_class_subset(entries: Vec<manifest::Entry>, m: usize, seed: u64) -> Vec<manifest::Entry> {
    let key = |e: &manifest::Entry| hash_parts(&[seed.to_string().as_bytes(), e.id.as_bytes()]);
    let mut keep = vec![false; entries.len()];
    let mut classes: Vec<&str> = entries.iter().map(|e| e.class.as_str()).collect();
    classes.sort_unstable();
    classes.dedup();
    for c in classes {
        let mut rows: Vec<(String, usize)> = entries
            .iter()
            .enumerate()
            .filter(|(_, e)| e.class == c)
            .map(|(i, e)| (key(e), i))
            .collect();
        rows.sort();
        for (_, i) in rows.into_iter().take(m) {
            keep[i] = true;
        }
    }
    entries
        .into_iter()
        .zip(keep)
        .filter_map(|(e, k)| k.then_some(e))
        .collect()
}
