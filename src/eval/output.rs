//! What a run writes: the Markdown report, ROC / PR curves and the matrices dump.

use super::*;

/// `--matrices`: one JSON document with the manifest rows and, per configuration, its row-major
/// `n × n` dissimilarity matrix (`null` on the diagonal and for rows that were not ranked).
pub(super) fn write_matrices(
    path: &Path,
    manifest: &Manifest,
    included: &[bool],
    n: usize,
    mats: &[(String, Vec<f64>)],
) -> Result<()> {
    let rows: Vec<Value> = manifest
        .entries
        .iter()
        .zip(included)
        .map(|(e, &inc)| {
            json!({"id": e.id, "class": e.class, "transform": e.transform, "strength": e.strength, "ranked": inc})
        })
        .collect();
    let matrices: serde_json::Map<String, Value> = mats
        .iter()
        .map(|(name, d)| {
            let m: Vec<Vec<Option<f64>>> = (0..n)
                .map(|i| {
                    (0..n)
                        .map(|j| {
                            let v = d[i * n + j];
                            (i != j && included[i] && included[j] && v.is_finite()).then_some(v)
                        })
                        .collect()
                })
                .collect();
            (name.clone(), json!(m))
        })
        .collect();
    let doc = json!({"shapes": rows, "matrices": matrices});
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)?;
    }
    cache::write_atomic(path, serde_json::to_string(&doc).expect("json").as_bytes())?;
    Ok(())
}

pub(super) fn safe_file_name(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.=".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

pub(super) fn write_curves(dir: &Path, results: &[ConfigResult]) -> Result<()> {
    let curves = dir.join("curves");
    std::fs::create_dir_all(&curves)?;
    for r in results {
        let base = safe_file_name(&r.name);
        let series = |pick: &dyn Fn(&metrics::GroupSummary) -> &Vec<(f64, f64)>| -> Vec<(String, Vec<(f64, f64)>)> {
            r.eval
                .groups
                .iter()
                .filter(|(_, s)| !pick(s).is_empty())
                .map(|(g, s)| {
                    let lab = match (s.auc, s.map) {
                        (Some(a), Some(m)) => format!("{} (AUC {:.1}, mAP {:.1})", report::group_label(g), 100.0 * a, 100.0 * m),
                        _ => report::group_label(g),
                    };
                    (lab, pick(s).clone())
                })
                .collect()
        };
        let roc = plot::line_chart(
            &format!("ROC — {}", r.name),
            "false positive rate",
            "true positive rate",
            &series(&|s| &s.mean_roc),
            true,
        );
        std::fs::write(curves.join(format!("{base}.roc.svg")), roc)?;
        let pr = plot::line_chart(
            &format!("Precision–recall — {}", r.name),
            "recall",
            "precision",
            &series(&|s| &s.mean_pr),
            false,
        );
        std::fs::write(curves.join(format!("{base}.pr.svg")), pr)?;
    }
    // All configurations on one chart, group All: the default and the five best by mAP in
    // colour, the others as grey lines; the ROC on a log false-positive axis.
    let all = |pick: &dyn Fn(&metrics::GroupSummary) -> &Vec<(f64, f64)>| -> Vec<plot::Series> {
        results
            .iter()
            .filter_map(|r| {
                r.eval.group(metrics::ALL).map(|s| plot::Series {
                    name: r.name.clone(),
                    points: pick(s).clone(),
                    score: s.map,
                })
            })
            .collect()
    };
    let default_name = crate::presets::default_config().name;
    let overview = |x_axis, diagonal| plot::Overview {
        default: Some(default_name.as_str()),
        best: 5,
        score_label: "mAP",
        x_axis,
        diagonal,
    };
    std::fs::write(
        dir.join("roc-all.svg"),
        plot::overview_chart(
            "Mean ROC, all queries",
            "false positive rate (log scale)",
            "true positive rate",
            &all(&|s| &s.mean_roc),
            &overview(plot::XAxis::Log { min: 0.01 }, true),
        ),
    )?;
    std::fs::write(
        dir.join("pr-all.svg"),
        plot::overview_chart(
            "Mean precision–recall, all queries",
            "recall",
            "precision",
            &all(&|s| &s.mean_pr),
            &overview(plot::XAxis::Linear, false),
        ),
    )?;
    Ok(())
}

#[allow(clippy::too_many_arguments)]
pub(super) fn markdown_report(
    args: &EvalOptions,
    manifest: &Manifest,
    results: &[ConfigResult],
    failures: &[Failure],
    t: &Timings,
    cache: (u64, u64, u64, u64),
    reference: Option<&Reference>,
    reference_path: Option<&Path>,
) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let n = manifest.entries.len();
    let _ = writeln!(s, "# shapeseek eval — {}\n", args.manifest.display());
    let mut per_t = String::new();
    for tr in manifest.transforms() {
        let c = manifest
            .entries
            .iter()
            .filter(|e| e.transform == tr)
            .count();
        let _ = write!(per_t, "{} {c}, ", report::group_label(&tr));
    }
    let _ = writeln!(
        s,
        "{n} shapes ({} ranked, {} left out); queries per transform: {}. k = {}. mAP, AUC and EER in %. \
         'All w/o scale' leaves out the scale queries.\n",
        n - failures.len(),
        failures.len(),
        per_t.trim_end_matches(", "),
        args.k
    );
    if !failures.is_empty() {
        let _ = writeln!(
            s,
            "## Left out of the ranking\n\n| id | path | code | message |\n|---|---|---|---|"
        );
        for f in failures {
            let _ = writeln!(
                s,
                "| {} | {} | `{}` | {} |",
                f.id,
                f.path,
                f.code,
                f.message.replace('|', "\\|")
            );
        }
        s.push('\n');
    }
    let _ = writeln!(
        s,
        "## All configurations\n\n{}",
        report::summary_table(results, reference)
    );
    if let (Some(_), Some(p)) = (reference, reference_path) {
        let _ = writeln!(s, "Reference figures from `{}`.\n", p.display());
    }
    s.push_str(&report::reference_shaped_tables(results, reference));
    s.push_str(&report::roc_summary_table(results, reference));
    let _ = writeln!(
        s,
        "## mAP per strength (%)\n\n{}",
        report::per_strength_table(&report::per_strength_selection(results))
    );
    let _ = writeln!(s, "## Time per stage\n");
    let _ = writeln!(s, "| stage | seconds |\n|---|---|");
    for (name, v) in [
        ("read (sum over shapes)", t.read_s),
        ("prepare (sum)", t.prepare_s),
        (
            "eigen: Laplacian + factorisation + eigensolve (sum)",
            t.eigen_s,
        ),
        ("signature (sum)", t.signature_s),
        ("cache I/O (sum)", t.cache_s),
        ("per-shape phase (wall)", t.per_shape_wall_s),
        (
            "calibration + histograms (wall)",
            t.calibration_histograms_s,
        ),
        ("ranking + metrics, all configurations (wall)", t.ranking_s),
        ("  of which dissimilarity matrices", t.scoring_s),
        ("  of which AP / ROC / PR", t.metrics_s),
        ("total (wall)", t.total_s),
    ] {
        let _ = writeln!(s, "| {name} | {v:.2} |");
    }
    let _ = writeln!(
        s,
        "\n{} worker threads; cache: {} hits, {} misses, {} corrupt (recomputed), {} write errors.",
        t.threads, cache.0, cache.1, cache.2, cache.3
    );
    s
}
