//! Reports: the JSON document, Markdown tables (Tables 1–3 of the bench REFERENCE, with its
//! figures side by side when available), and reference parsing (`reference-map.json` style JSON or
//! REFERENCE.md tables).

use super::metrics::{Evaluation, GroupSummary, ALL, ALL_WO_SCALE};
use serde_json::{json, Map, Value};
use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::Path;

/// One configuration's evaluation.
#[derive(Debug, Clone)]
pub struct ConfigResult {
    /// Configuration name.
    pub name: String,
    /// Metrics.
    pub eval: Evaluation,
    /// The name under which a reference lists the same method, when it differs from `name`
    /// (e.g. `default` is a paper configuration under another name).
    pub alias: Option<String>,
}

impl ConfigResult {
    /// The reference mAP of this configuration for `group` (by name, else by alias).
    pub fn reference_map(&self, reference: &Reference, group: &str) -> Option<f64> {
        reference.get_map(&self.name, group).or_else(|| {
            self.alias
                .as_deref()
                .and_then(|a| reference.get_map(a, group))
        })
    }
}

/// A mesh that could not be used.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Failure {
    /// Shape id.
    pub id: String,
    /// Path as in the manifest.
    pub path: String,
    /// Stable error code (`shapeseek::Error::code`).
    pub code: String,
    /// Message.
    pub message: String,
}

/// Reference figures: config → group (manifest transform name, `All`, `All w/o scale`) → fraction.
#[derive(Debug, Clone, Default)]
pub struct Reference {
    /// mAP.
    pub map: BTreeMap<String, BTreeMap<String, f64>>,
    /// Mean ROC AUC.
    pub auc: BTreeMap<String, BTreeMap<String, f64>>,
    /// EER.
    pub eer: BTreeMap<String, BTreeMap<String, f64>>,
    /// Where it came from.
    pub source: String,
}

type Table = BTreeMap<String, BTreeMap<String, f64>>;

fn json_table(v: &Value) -> Table {
    let mut out = Table::new();
    if let Some(o) = v.as_object() {
        for (cfg, row) in o {
            if let Some(r) = row.as_object() {
                let m: BTreeMap<String, f64> = r
                    .iter()
                    .filter_map(|(k, x)| x.as_f64().map(|f| (k.clone(), f)))
                    .collect();
                if !m.is_empty() {
                    out.insert(cfg.clone(), m);
                }
            }
        }
    }
    out
}

impl Reference {
    /// Parses a reference file: JSON (`config → transform → fraction`, `_meta` ignored except
    /// `auc_by_transform` / `eer_by_transform`) or Markdown (REFERENCE.md tables).
    pub fn load(path: &Path) -> crate::Result<Reference> {
        let text = std::fs::read_to_string(path)?;
        let mut r = if path.extension().and_then(|e| e.to_str()) == Some("json") {
            Reference::from_json(&text)?
        } else {
            Reference::from_markdown(&text)
        };
        r.source = path.display().to_string();
        Ok(r)
    }

    /// From `reference-map.json` style JSON.
    pub fn from_json(text: &str) -> crate::Result<Reference> {
        let v: Value = serde_json::from_str(text)
            .map_err(|e| crate::Error::InvalidArgument(format!("reference JSON: {e}")))?;
        let mut map = json_table(&v);
        map.remove("_meta");
        let meta = v.get("_meta").cloned().unwrap_or(Value::Null);
        Ok(Reference {
            map,
            auc: json_table(meta.get("auc_by_transform").unwrap_or(&Value::Null)),
            eer: json_table(meta.get("eer_by_transform").unwrap_or(&Value::Null)),
            source: String::new(),
        })
    }

    /// From REFERENCE.md: Tables 1–3 and the "ten best" table (mAP in %), and the ROC summary
    /// (AUC / EER of `All`). Column headers are mapped to configuration names as in REFERENCE.md
    /// (Table 2's labels through the ROC summary rows "| H-L2 (t=0.1) (`name`) | auc | eer |").
    pub fn from_markdown(text: &str) -> Reference {
        let mut labels: BTreeMap<String, String> = BTreeMap::new();
        let (mut auc, mut eer) = (Table::new(), Table::new());
        for line in text.lines() {
            let l = line.trim();
            if !l.starts_with('|') {
                continue;
            }
            let cells = table_cells(l);
            if cells.len() < 3 {
                continue;
            }
            if let Some((label, name)) = split_label(&cells[0]) {
                labels.insert(label, name.clone());
                if let (Some(a), Some(e)) = (pct(&cells[1]), pct(&cells[2])) {
                    auc.entry(name.clone()).or_default().insert(ALL.into(), a);
                    eer.entry(name).or_default().insert(ALL.into(), e);
                }
            }
        }
        let mut r = Reference::from_markdown_with(text, &labels);
        r.auc = auc;
        r.eer = eer;
        r
    }

    fn from_markdown_with(text: &str, labels: &BTreeMap<String, String>) -> Reference {
        let mut r = Reference::default();
        let mut section = String::new();
        let mut header: Option<Vec<Option<String>>> = None;
        for line in text.lines() {
            let l = line.trim();
            if l.starts_with('#') {
                section = l.trim_start_matches('#').trim().to_string();
                header = None;
                continue;
            }
            if !l.starts_with('|') {
                header = None;
                continue;
            }
            let cells = table_cells(l);
            if cells
                .iter()
                .all(|c| c.chars().all(|ch| ch == '-' || ch == ':'))
            {
                continue;
            }
            match &header {
                None => {
                    header = (cells[0] == "Transform").then(|| {
                        cells[1..]
                            .iter()
                            .map(|h| column_config(&section, h, labels))
                            .collect()
                    });
                    if header.is_none() {
                        header = Some(Vec::new());
                    }
                }
                Some(cfgs) => {
                    if let Some(g) = row_group(&cells[0]) {
                        for (c, cell) in cfgs.iter().zip(&cells[1..]) {
                            if let (Some(c), Some(v)) = (c, pct(cell)) {
                                r.map.entry(c.clone()).or_default().insert(g.clone(), v);
                            }
                        }
                    }
                }
            }
        }
        r
    }

    /// Is there anything in it?
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// The reference mAP of `config` for `group`, matching names exactly or, failing that,
    /// case- and space-insensitively.
    pub fn get_map(&self, config: &str, group: &str) -> Option<f64> {
        lookup(&self.map, config, group)
    }
}

/// The cells of a Markdown table row, trimmed, bold markers removed.
fn table_cells(row: &str) -> Vec<String> {
    row.trim_matches('|')
        .split('|')
        .map(|c| c.trim().replace("**", ""))
        .collect()
}

fn norm_name(s: &str) -> String {
    s.chars()
        .filter(|c| !c.is_whitespace())
        .flat_map(|c| c.to_lowercase())
        .collect()
}

fn lookup(t: &Table, config: &str, group: &str) -> Option<f64> {
    let row = t.get(config).or_else(|| {
        let n = norm_name(config);
        t.iter().find(|(k, _)| norm_name(k) == n).map(|(_, v)| v)
    })?;
    row.get(group).copied()
}

fn pct(s: &str) -> Option<f64> {
    s.trim()
        .trim_end_matches('%')
        .parse::<f64>()
        .ok()
        .map(|v| v / 100.0)
}

fn split_label(s: &str) -> Option<(String, String)> {
    let a = s.find("(`")?;
    let b = s[a + 2..].find('`')? + a + 2;
    Some((s[..a].trim().to_string(), s[a + 2..b].to_string()))
}

/// REFERENCE.md row labels → manifest transform names / group names.
pub fn row_group(label: &str) -> Option<String> {
    Some(
        match label {
            "Null" => "null",
            "Isometry" => "isometry",
            "Iso+Topo" => "isometry+topology",
            "Partiality" => "partiality",
            "Topology" => "topology",
            "Triang." => "triangulation",
            "Noise" => "noise",
            "Scale" => "scale",
            "All" => ALL,
            "All w/o scale" => ALL_WO_SCALE,
            _ => return None,
        }
        .to_string(),
    )
}

/// The display label of a group in tables shaped like REFERENCE.md.
pub fn group_label(group: &str) -> String {
    match group {
        "null" => "Null",
        "isometry" => "Isometry",
        "isometry+topology" => "Iso+Topo",
        "partiality" => "Partiality",
        "topology" => "Topology",
        "triangulation" => "Triang.",
        "noise" => "Noise",
        "scale" => "Scale",
        other => other,
    }
    .to_string()
}

const THREE: &str = "[t=0.016..0.1]";

fn column_config(section: &str, h: &str, labels: &BTreeMap<String, String>) -> Option<String> {
    if section.starts_with("Table 1") {
        return Some(format!("Heat-L2-{h}-Single[t=0.1]"));
    }
    if section.starts_with("Table 2") {
        return labels.get(h).cloned();
    }
    if section.starts_with("Table 3") {
        if let Some(t) = h.strip_prefix("t=") {
            return Some(format!("Heat-L2-nL1-Single[t={t}]"));
        }
        let agg = if h.starts_with("Sum²") {
            "Sum2"
        } else if h.starts_with("Sum") {
            "Sum"
        } else if h.starts_with("Max") {
            "Max"
        } else {
            return None;
        };
        let suffix = if h.contains("≤0.1") { THREE } else { "" };
        return Some(format!("Heat-L2-nL1-{agg}{suffix}"));
    }
    if section.starts_with("Ten best") {
        return Some(h.to_string());
    }
    None
}

/// The layout of the three REFERENCE tables: (title, [(column label, config name)]).
pub fn reference_tables() -> Vec<(String, Vec<(String, String)>)> {
    let dis = ["L1", "L2", "nL1", "nL2", "KL", "Bhatt", "chi2", "EMD"];
    let t1 = dis
        .iter()
        .map(|d| (d.to_string(), format!("Heat-L2-{d}-Single[t=0.1]")))
        .collect();
    let t2 = [
        ("H-L2 (t=0.1)", "Heat-L2-nL1-Single[t=0.1]"),
        ("H-L2 Max(6 t)", "Heat-L2-nL1-Max"),
        ("H-L2 Sum²(t≤0.1)", "Heat-L2-nL1-Sum2[t=0.016..0.1]"),
        ("CT-L2", "CT-L2-nL1"),
        ("Step-L2 (λc=4π·10)", "Step-L2-nL1[lc=4pi*10]"),
        ("Step-L2 (λc=4π·30)", "Step-L2-nL1[lc=4pi*30]"),
        ("ShapeDNA (50 λ, L2)", "ShapeDNA[50]-L2"),
        ("GPS (CT-L2, L2 dissim.)", "CT-L2-L2"),
        ("D2 (nL1)", "D2-nL1"),
        ("Geo (nL1)", "Geo-nL1"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    let mut t3: Vec<(String, String)> = ["0.016", "0.04", "0.1", "0.25", "0.625", "1.5625"]
        .iter()
        .map(|t| (format!("t={t}"), format!("Heat-L2-nL1-Single[t={t}]")))
        .collect();
    for (suffix, lab) in [("", "6 t"), (THREE, "t≤0.1")] {
        for (agg, alab) in [("Sum", "Sum"), ("Sum2", "Sum²"), ("Max", "Max")] {
            t3.push((
                format!("{alab} ({lab})"),
                format!("Heat-L2-nL1-{agg}{suffix}"),
            ));
        }
    }
    vec![
        (
            "Table 1 — Heat-L2-Dissimilarity-Single, t = 0.1".to_string(),
            t1,
        ),
        ("Table 2 — Kernel-Norm-nL1 and baselines".to_string(), t2),
        ("Table 3 — H-L2-nL1-Aggregation".to_string(), t3),
    ]
}

fn f(x: Option<f64>) -> String {
    x.map(|v| format!("{:.2}", 100.0 * v))
        .unwrap_or_else(|| "–".into())
}

fn group_map(e: &Evaluation, get: impl Fn(&GroupSummary) -> Option<f64>) -> Map<String, Value> {
    e.groups
        .iter()
        .filter_map(|(g, s)| get(s).map(|v| (g.clone(), json!(v))))
        .collect()
}

/// The `--json` document.
pub fn json_document(
    results: &[ConfigResult],
    failures: &[Failure],
    timings: &Value,
    extra: Value,
) -> Value {
    let res: Vec<Value> = results
        .iter()
        .map(|r| {
            let e = &r.eval;
            let per_strength: Map<String, Value> = e
                .per_strength
                .iter()
                .filter_map(|(k, s)| s.map.map(|v| (k.clone(), json!(v))))
                .collect();
            json!({
                "config": r.name,
                "map": group_map(e, |s| s.map),
                "auc": group_map(e, |s| s.auc),
                "eer": e.group(ALL).and_then(|s| s.eer),
                "eer_by_transform": group_map(e, |s| s.eer),
                "per_strength": per_strength,
                "queries": e.group(ALL).map(|s| s.queries).unwrap_or(0),
                "queries_without_relevant": e.group(ALL).map(|s| s.queries - s.scored).unwrap_or(0),
            })
        })
        .collect();
    let mut doc = json!({ "results": res, "failures": failures, "timings": timings });
    if let (Some(d), Some(x)) = (doc.as_object_mut(), extra.as_object()) {
        for (k, v) in x {
            d.insert(k.clone(), v.clone());
        }
    }
    doc
}

/// Group names in report order for the given results.
fn groups_of(results: &[ConfigResult]) -> Vec<String> {
    results
        .first()
        .map(|r| r.eval.groups.iter().map(|g| g.0.clone()).collect())
        .unwrap_or_default()
}

/// The summary table: one row per configuration, mAP (%) per group, AUC and EER of `All`.
pub fn summary_table(results: &[ConfigResult], reference: Option<&Reference>) -> String {
    let groups = groups_of(results);
    let mut s = String::new();
    let _ = write!(s, "| config |");
    for g in &groups {
        let _ = write!(s, " {} |", group_label(g));
    }
    let _ = writeln!(
        s,
        " AUC All | EER All |{}",
        if reference.is_some() {
            " reference All |"
        } else {
            ""
        }
    );
    let _ = write!(s, "|---|");
    for _ in 0..groups.len() + 2 + reference.is_some() as usize {
        s.push_str("---|");
    }
    s.push('\n');
    for r in results {
        let own_ref = reference.is_some_and(|rf| rf.get_map(&r.name, ALL).is_some());
        match r.alias.as_ref().filter(|_| !own_ref) {
            Some(a) => {
                let _ = write!(s, "| {} (= `{a}`) |", r.name);
            }
            None => {
                let _ = write!(s, "| {} |", r.name);
            }
        }
        for g in &groups {
            let _ = write!(s, " {} |", f(r.eval.group(g).and_then(|x| x.map)));
        }
        let all = r.eval.group(ALL);
        let _ = write!(
            s,
            " {} | {} |",
            f(all.and_then(|x| x.auc)),
            f(all.and_then(|x| x.eer))
        );
        if let Some(rf) = reference {
            let _ = write!(s, " {} |", f(r.reference_map(rf, ALL)));
        }
        s.push('\n');
    }
    s
}

/// Tables 1–3 shaped like REFERENCE.md (rows = transforms, columns = configurations), each
/// cell `ours / reference` when a reference value exists. Columns whose configuration was not
/// run are left out; a table with no column is left out.
pub fn reference_shaped_tables(results: &[ConfigResult], reference: Option<&Reference>) -> String {
    let groups = groups_of(results);
    let mut s = String::new();
    for (title, cols) in reference_tables() {
        let cols: Vec<(&String, &ConfigResult)> = cols
            .iter()
            .filter_map(|(lab, name)| {
                results
                    .iter()
                    .find(|r| norm_name(&r.name) == norm_name(name))
                    .map(|r| (lab, r))
            })
            .collect();
        if cols.is_empty() {
            continue;
        }
        let _ = writeln!(s, "## {title}\n");
        if reference.is_some() {
            let _ = writeln!(s, "mAP %, ours / reference.\n");
        } else {
            let _ = writeln!(s, "mAP %.\n");
        }
        let _ = write!(s, "| Transform |");
        for (lab, r) in &cols {
            let _ = write!(s, " {lab} (`{}`) |", r.name);
        }
        s.push_str("\n|---|");
        for _ in &cols {
            s.push_str("---|");
        }
        s.push('\n');
        for g in &groups {
            let _ = write!(s, "| {} |", group_label(g));
            for (_, r) in &cols {
                let ours = f(r.eval.group(g).and_then(|x| x.map));
                match reference.and_then(|rf| r.reference_map(rf, g)) {
                    Some(v) => {
                        let _ = write!(s, " {ours} / {:.2} |", 100.0 * v);
                    }
                    None => {
                        let _ = write!(s, " {ours} |");
                    }
                }
            }
            s.push('\n');
        }
        s.push('\n');
    }
    s
}

/// The ROC summary of the Table 2 configurations that were run (like REFERENCE.md's): mean
/// per-query AUC and pooled EER of all queries, with the reference's side by side.
pub fn roc_summary_table(results: &[ConfigResult], reference: Option<&Reference>) -> String {
    let t2 = &reference_tables()[1].1;
    let rows: Vec<(&String, &ConfigResult)> = t2
        .iter()
        .filter_map(|(lab, name)| results.iter().find(|r| &r.name == name).map(|r| (lab, r)))
        .collect();
    if rows.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "## ROC summary (Table 2 configurations, all queries)\n\nMean per-query ROC AUC (%) / equal error rate (%) of the pooled query-vs-others distances",
    );
    s.push_str(if reference.is_some() {
        "; ours / reference.\n\n"
    } else {
        ".\n\n"
    });
    s.push_str("| config | AUC All | EER All |\n|---|---|---|\n");
    for (lab, r) in rows {
        let all = r.eval.group(ALL);
        let cell = |ours: Option<f64>, table: Option<&Table>| match table
            .and_then(|t| lookup(t, &r.name, ALL))
        {
            Some(v) => format!("{} / {:.2}", f(ours), 100.0 * v),
            None => f(ours),
        };
        let _ = writeln!(
            s,
            "| {lab} (`{}`) | {} | {} |",
            r.name,
            cell(all.and_then(|a| a.auc), reference.map(|x| &x.auc)),
            cell(all.and_then(|a| a.eer), reference.map(|x| &x.eer)),
        );
    }
    s.push('\n');
    s
}

/// The configurations of REFERENCE.md's per-strength table that were run, plus `default`; all
/// configurations when none of them was.
pub fn per_strength_selection(results: &[ConfigResult]) -> Vec<ConfigResult> {
    const NAMES: [&str; 9] = [
        "default",
        "Heat-L2-nL1-Sum2[t=0.016..0.1]",
        "Heat-L2-nL1-Single[t=0.016]",
        "Heat-L2-nL1-Single[t=0.1]",
        "CT-L2-nL1",
        "ShapeDNA[50]-L2",
        "CT-L2-L2",
        "D2-nL1",
        "Geo-nL1",
    ];
    let picked: Vec<ConfigResult> = NAMES
        .iter()
        .filter_map(|n| results.iter().find(|r| r.name == *n).cloned())
        .collect();
    if picked.is_empty() {
        results.to_vec()
    } else {
        picked
    }
}

/// Per-strength mAP table (rows `transform@strength`, columns configurations).
pub fn per_strength_table(results: &[ConfigResult]) -> String {
    let mut keys: Vec<&String> = results
        .iter()
        .flat_map(|r| r.eval.per_strength.keys())
        .collect();
    keys.sort();
    keys.dedup();
    let mut s = String::from("| transform@strength |");
    for r in results {
        let _ = write!(s, " `{}` |", r.name);
    }
    s.push_str("\n|---|");
    for _ in results {
        s.push_str("---|");
    }
    s.push('\n');
    for k in keys {
        let _ = write!(s, "| {k} |");
        for r in results {
            let _ = write!(
                s,
                " {} |",
                f(r.eval.per_strength.get(k).and_then(|x| x.map))
            );
        }
        s.push('\n');
    }
    s
}
