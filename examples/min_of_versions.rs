//! Two versions of every shape, compared by the smaller of the two dissimilarities: a
//! measurement of "min of two cuts" (docs/quality.md §16) without any change to the pipeline.
//!
//! ```text
//! cargo run --release --example cut_handles -- M /tmp/v/s9 '{"max_loop_rel":0.5,"max_neck_aspect":3,"max_side_aspect":0.9}'
//! cargo run --release --example cut_handles -- M /tmp/v/d '{"max_loop_rel":0.5,"max_neck_aspect":1e9}'
//! python3 scripts/analysis/combine_manifests.py s9=/tmp/v/s9/manifest.csv d=/tmp/v/d/manifest.csv > /tmp/v/both.csv
//! shapeseek eval --manifest /tmp/v/both.csv --config docs/quality/default-nocut-first-stage.json --window-percentile 0.9 --matrices /tmp/v/m.json
//! cargo run --release --example min_of_versions -- /tmp/v/m.json s9 d [1,1.1,1.2]
//! ```
//!
//! The matrices file must hold one configuration without re-ranking stages (its values are then
//! the first-stage dissimilarities; `docs/quality/default-nocut-first-stage.json` is the
//! default's first stage, for meshes cut beforehand) over a manifest whose ids end in `~A` and
//! `~B` for the two versions of the same shapes in the same order (`combine_manifests.py`
//! writes it; one eval run ranks both under one calibration). The dissimilarity matrices formed
//! over the shapes are `A`, `B` and, per margin `f` of `MARGINS` (comma-separated, each ≥ 1;
//! default `1`), `min(A, f·B)` entry by entry: a pair is as similar as its more similar version
//! pair, the second version counting only when closer by the factor `f`. Each is re-ranked by
//! the default's reciprocal stage ([`ReciprocalStage::default`], with eval's own machinery) and
//! scored as eval scores: mAP per transformation class and per strength of topology and
//! isometry+topology over the full set, then eval's leave-one-class-out protocol with
//! candidates `A` and every minimum (per fold, the best held-in All, ties to the earlier, with
//! queries and candidates restricted to the other classes and the stage re-run; `B` is reported
//! held fixed only, as the version whose cutting need not keep genuine handles). Columns are
//! the manifest's transformations in manifest order, as in eval's report (`–` where a class has
//! none).

use shapeseek::eval::metrics::{self, Evaluation};
use shapeseek::eval::rerank::{rerank_matrix, PairCache};
use shapeseek::rerank::ReciprocalStage;
use shapeseek::search::Stage;

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

struct Shapes {
    classes: Vec<usize>,
    class_names: Vec<String>,
    transforms: Vec<String>,
    /// The distinct transformations, in manifest order (the report's columns, as eval's).
    columns: Vec<String>,
    strengths: Vec<i64>,
}

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() != 3 && args.len() != 4 {
        return Err("usage: min_of_versions MATRICES_JSON A B [MARGINS]".into());
    }
    let margins: Vec<f64> = match args.get(3) {
        None => vec![1.0],
        Some(m) => m
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("MARGINS {m:?}: {e}"))?,
    };
    if margins.iter().any(|f| !(f.is_finite() && *f >= 1.0)) {
        return Err(format!("MARGINS {margins:?}: every margin must be ≥ 1").into());
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&args[0])?)?;
    let shapes = v["shapes"].as_array().ok_or("no `shapes` array")?;
    let matrices = v["matrices"].as_object().ok_or("no `matrices` object")?;
    if matrices.len() != 1 {
        return Err("the matrices file must hold exactly one configuration".into());
    }
    let m = matrices
        .values()
        .next()
        .and_then(|m| m.as_array())
        .ok_or("bad matrix")?;
    let id = |i: usize| shapes[i]["id"].as_str().unwrap_or_default().to_string();
    let version = |name: &str| -> Vec<usize> {
        let suffix = format!("~{name}");
        (0..shapes.len())
            .filter(|&i| id(i).ends_with(&suffix))
            .collect()
    };
    let (a, b) = (version(&args[1]), version(&args[2]));
    let n = a.len();
    if n == 0 || b.len() != n {
        return Err(format!("{} shapes `~{}`, {} `~{}`", n, args[1], b.len(), args[2]).into());
    }
    for (&i, &j) in a.iter().zip(&b) {
        let (x, y) = (id(i), id(j));
        if x.rsplit_once('~').map(|p| p.0) != y.rsplit_once('~').map(|p| p.0) {
            return Err(format!("versions out of order: {x} / {y}").into());
        }
    }
    let at = |i: usize, j: usize| -> Res<f64> {
        m[i][j]
            .as_f64()
            .ok_or_else(|| format!("no dissimilarity for {} / {}", id(i), id(j)).into())
    };
    let mut da = vec![0.0; n * n];
    let mut db = vec![0.0; n * n];
    for x in 0..n {
        for y in (0..n).filter(|&y| y != x) {
            da[x * n + y] = at(a[x], a[y])?;
            db[x * n + y] = at(b[x], b[y])?;
        }
    }

    let mut class_names: Vec<String> = Vec::new();
    let mut classes = Vec::new();
    for &i in &a {
        let c = shapes[i]["class"].as_str().unwrap_or_default().to_string();
        let k = class_names.iter().position(|u| *u == c).unwrap_or_else(|| {
            class_names.push(c);
            class_names.len() - 1
        });
        classes.push(k);
    }
    let mut s = Shapes {
        classes,
        class_names,
        transforms: a
            .iter()
            .map(|&i| {
                shapes[i]["transform"]
                    .as_str()
                    .unwrap_or_default()
                    .to_string()
            })
            .collect(),
        strengths: a
            .iter()
            .map(|&i| shapes[i]["strength"].as_i64().unwrap_or(0))
            .collect(),
        columns: Vec::new(),
    };
    for t in &s.transforms {
        if !s.columns.contains(t) {
            s.columns.push(t.clone());
        }
    }
    let mut names = vec![args[1].clone(), args[2].clone()];
    let mins: Vec<Vec<f64>> = margins
        .iter()
        .map(|&f| da.iter().zip(&db).map(|(p, q)| p.min(f * q)).collect())
        .collect();
    for &f in &margins {
        names.push(if f == 1.0 {
            format!("min({},{})", args[1], args[2])
        } else {
            format!("min({},{}·{f})", args[1], args[2])
        });
    }
    let mut variants: Vec<Vec<f64>> = vec![da, db];
    variants.extend(mins);
    // Candidates of the protocol: A and every minimum (B is reported held fixed only).
    let candidates: Vec<usize> = std::iter::once(0).chain(2..variants.len()).collect();
    let all = vec![true; n];
    let full: Vec<Evaluation> = variants.iter().map(|d| ranked(d, n, &s, &all)).collect();

    println!("## Full set, after the reciprocal stage (mAP %)\n");
    println!(
        "| version | {} | All | topology 1-4 | isometry+topology 1-4 |",
        s.columns.join(" | ")
    );
    println!("|---|{}---|---|---|", "---|".repeat(s.columns.len()));
    for (name, e) in names.iter().zip(&full) {
        let per = |t: &str| {
            (1..=4)
                .map(|k| pct(e.per_strength.get(&format!("{t}@{k}")).and_then(|g| g.map)))
                .collect::<Vec<_>>()
                .join(" / ")
        };
        println!(
            "| {name} | {} | {} | {} | {} |",
            s.columns
                .iter()
                .map(|t| pct(e.group(t).and_then(|g| g.map)))
                .collect::<Vec<_>>()
                .join(" | "),
            pct(e.group(metrics::ALL).and_then(|g| g.map)),
            per("topology"),
            per("isometry+topology")
        );
    }

    let cand_names: Vec<&str> = candidates.iter().map(|&v| names[v].as_str()).collect();
    println!(
        "\n## Leave-one-class-out, candidates {} (mAP %)\n",
        cand_names.join(", ")
    );
    println!(
        "| held out | held-in All {} | chosen | {} | All | held fixed: All {} |",
        cand_names.join(" / "),
        s.columns.join(" | "),
        names.join(" / ")
    );
    println!("|---|---|---|{}---|---|", "---|".repeat(s.columns.len()));
    let mut selected = FoldMeans::default();
    let mut fixed: Vec<FoldMeans> = names.iter().map(|_| FoldMeans::default()).collect();
    let mut chosen_count = vec![0usize; variants.len()];
    let all_col = s.columns.len();
    for (c, cname) in s.class_names.iter().enumerate() {
        let held_in: Vec<bool> = s.classes.iter().map(|&k| k != c).collect();
        let hin: Vec<f64> = candidates
            .iter()
            .map(|&v| {
                ranked(&variants[v], n, &s, &held_in)
                    .group(metrics::ALL)
                    .and_then(|g| g.map)
                    .unwrap_or(0.0)
            })
            .collect();
        // The best held-in All; ties: the earlier candidate (as eval's protocol).
        let best = (0..candidates.len()).fold(0, |b, i| if hin[i] > hin[b] { i } else { b });
        let ch = candidates[best];
        chosen_count[ch] += 1;
        let row = held_out(&full[ch], &s, c);
        selected.add(&row);
        let rows: Vec<Vec<Option<f64>>> = full.iter().map(|e| held_out(e, &s, c)).collect();
        for (f, r) in fixed.iter_mut().zip(&rows) {
            f.add(r);
        }
        println!(
            "| {cname} | {} | {} | {} | {} |",
            hin.iter()
                .map(|x| format!("{:.2}", 100.0 * x))
                .collect::<Vec<_>>()
                .join(" / "),
            names[ch],
            cells_line(&row),
            cells_line(&rows.iter().map(|r| r[all_col]).collect::<Vec<_>>()).replace(" | ", " / "),
        );
    }
    let chosen: Vec<String> = candidates
        .iter()
        .filter(|&&v| chosen_count[v] > 0)
        .map(|&v| format!("{} in {}", names[v], chosen_count[v]))
        .collect();
    println!(
        "| **selected, mean** | | {} of {} folds | {} | |",
        chosen.join(", "),
        s.class_names.len(),
        selected.line()
    );
    for (name, f) in names.iter().zip(&fixed) {
        println!("| {name} held fixed, mean | | | {} | |", f.line());
    }
    Ok(())
}

/// The evaluation of `d` after the default's reciprocal stage, over the `included` shapes.
fn ranked(d: &[f64], n: usize, s: &Shapes, included: &[bool]) -> Evaluation {
    let stage = Stage::Reciprocal(ReciprocalStage::default());
    let payloads = vec![None; n];
    let (r, _) = rerank_matrix(
        d,
        d,
        n,
        included,
        &payloads,
        &stage,
        &|_, _, _| f64::NAN,
        &mut PairCache::new(),
    );
    metrics::evaluate(&r, n, &s.classes, &s.transforms, &s.strengths, included)
}

/// mAP % of class `c`'s queries per transformation, then over all of them (`None` where the
/// class has no query of that transformation).
fn held_out(e: &Evaluation, s: &Shapes, c: usize) -> Vec<Option<f64>> {
    let mean = |t: Option<&str>| {
        let aps: Vec<f64> = e
            .queries
            .iter()
            .filter(|q| s.classes[q.index] == c && t.is_none_or(|t| s.transforms[q.index] == t))
            .filter_map(|q| q.ap)
            .collect();
        (!aps.is_empty()).then(|| 100.0 * aps.iter().sum::<f64>() / aps.len() as f64)
    };
    s.columns
        .iter()
        .map(|t| mean(Some(t)))
        .chain([mean(None)])
        .collect()
}

/// Mean over the folds per column, of the folds that have the column.
#[derive(Default)]
struct FoldMeans(Vec<(f64, usize)>);

impl FoldMeans {
    fn add(&mut self, row: &[Option<f64>]) {
        self.0.resize(row.len(), (0.0, 0));
        for (acc, x) in self.0.iter_mut().zip(row) {
            if let Some(x) = x {
                *acc = (acc.0 + x, acc.1 + 1);
            }
        }
    }

    fn line(&self) -> String {
        let cells: Vec<Option<f64>> = self
            .0
            .iter()
            .map(|&(s, n)| (n > 0).then(|| s / n as f64))
            .collect();
        cells_line(&cells)
    }
}

fn cells_line(v: &[Option<f64>]) -> String {
    v.iter()
        .map(|x| x.map_or_else(|| "–".into(), |x| format!("{x:.2}")))
        .collect::<Vec<_>>()
        .join(" | ")
}

fn pct(x: Option<f64>) -> String {
    x.map_or_else(|| "–".into(), |x| format!("{:.2}", 100.0 * x))
}
