//! `shapeseek search FILE | --id ID`: asks a running server for the shapes most similar to a
//! mesh file (uploaded, analysed by the server, not stored) or to a stored shape, and prints a
//! table (rank, score, name, id, tags) or the server's JSON answer.

use super::http::{multipart, Client};
use super::{read_file, CliError};
use clap::Args;
use serde_json::{json, Value};
use std::path::PathBuf;

/// `shapeseek search` flags. The query is a file or a stored shape, one of them: the group
/// makes clap name both when neither is given (`<FILE|--id <ID>>`; it named `<FILE>` alone).
#[derive(Debug, Args)]
#[command(group(clap::ArgGroup::new("query").required(true).args(["file", "id"])))]
pub struct SearchArgs {
    /// The query mesh (OBJ, glTF/GLB, PLY, OFF, STL).
    #[arg(value_name = "FILE")]
    pub file: Option<PathBuf>,
    /// Search with a stored shape instead (it is left out of the hits).
    #[arg(long)]
    pub id: Option<String>,
    /// The server.
    #[arg(long, env = "SHAPESEEK_URL", default_value = "http://127.0.0.1:8080")]
    pub url: String,
    /// Number of hits.
    #[arg(long, default_value_t = 10)]
    pub top_k: usize,
    /// Only shapes having all of these tags (repeat, or separate by commas).
    #[arg(
        long = "tag",
        visible_alias = "tags",
        value_delimiter = ',',
        value_name = "TAG"
    )]
    pub tags: Vec<String>,
    /// Re-ranking stages as JSON: an array of stage objects (`[]` for the scan's ranking
    /// alone), or one object; default: the index's default stages.
    #[arg(long, value_name = "JSON")]
    pub rerank: Option<String>,
    /// Print the server's JSON answer instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Runs `shapeseek search`.
pub fn run(args: &SearchArgs) -> Result<(), CliError> {
    if args.top_k == 0 {
        return Err(CliError::usage("--top-k must be at least 1"));
    }
    let mut options = json!({ "top_k": args.top_k });
    if !args.tags.is_empty() {
        options["tags"] = json!(args.tags);
    }
    if let Some(r) = &args.rerank {
        let v: Value = serde_json::from_str(r)
            .map_err(|e| CliError::usage(format!("--rerank: not JSON ({e}): {r}")))?;
        options["rerank"] = match v {
            Value::Array(_) => v,
            Value::Object(_) => Value::Array(vec![v]),
            _ => {
                return Err(CliError::usage(
                    "--rerank: expected a JSON array of stages or one stage object",
                ))
            }
        };
    }
    let client = Client::new(&args.url)?;
    // The file is read before anything is sent: a wrong path is reported as such.
    let file = match &args.file {
        Some(p) => Some((p, read_file(p)?)),
        None => None,
    };
    let (query_label, answer) = match (&file, &args.id) {
        (Some((path, bytes)), _) => {
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| "query".into());
            let body = serde_json::to_vec(&options).unwrap_or_default();
            let (ct, body) = multipart(&name, bytes, "query", &body);
            let a = client.post("/v1/search", &[], &ct, &body).map_err(|f| {
                if f.status == 0 {
                    client.unreachable(&f)
                } else if f.code.starts_with("mesh.") || f.code.starts_with("limit.") {
                    CliError::new(f.code, format!("{}: {}", path.display(), f.detail), 65)
                } else {
                    CliError::new(f.code, f.detail, 65)
                }
            })?;
            (path.display().to_string(), a)
        }
        (None, Some(id)) => {
            options["id"] = json!(id);
            let body = serde_json::to_vec(&options).unwrap_or_default();
            let a = client
                .post("/v1/search", &[], "application/json", &body)
                .map_err(|f| {
                    if f.status == 0 {
                        client.unreachable(&f)
                    } else {
                        CliError::new(f.code, f.detail, 65)
                    }
                })?;
            (format!("shape {id}"), a)
        }
        (None, None) => return Err(CliError::usage("give a FILE or --id ID")),
    };
    if args.json {
        println!("{}", answer.json);
        return Ok(());
    }
    print_table(&client, &query_label, &answer.json);
    Ok(())
}

/// The tags of a hit: from the hit when the server sends them, else from its record.
fn hit_tags(client: &Client, hit: &Value) -> String {
    let tags = match hit.get("tags") {
        Some(t) => t.clone(),
        None => hit["id"]
            .as_str()
            .and_then(|id| client.get(&format!("/v1/shapes/{}", encode(id))).ok())
            .map(|a| a.json["tags"].clone())
            .unwrap_or(Value::Null),
    };
    match tags {
        Value::Array(v) => v
            .iter()
            .filter_map(|t| t.as_str())
            .collect::<Vec<_>>()
            .join(", "),
        _ => "?".into(),
    }
}

/// Percent-encodes a path segment.
fn encode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

fn print_table(client: &Client, query: &str, v: &Value) {
    let empty = Vec::new();
    let hits = v["hits"].as_array().unwrap_or(&empty);
    let stages: Vec<&str> = v["stages"]
        .as_array()
        .map(|a| a.iter().filter_map(|s| s.as_str()).collect())
        .unwrap_or_default();
    let mut head = format!(
        "{query}: {} hit(s) among {} candidate(s); stages {}; {:.1} ms",
        hits.len(),
        v["candidates"].as_u64().unwrap_or(0),
        if stages.is_empty() {
            "-".to_string()
        } else {
            stages.join(" → ")
        },
        v["timings"]["total_ms"].as_f64().unwrap_or(f64::NAN)
    );
    if let Some(a) = v["timings"]["analysis"]["total_ms"].as_f64() {
        head.push_str(&format!(" (query analysis {a:.1} ms)"));
    }
    println!("{head}");
    if hits.is_empty() {
        println!("no hits (is the index empty, or do the tag filters match nothing?)");
        return;
    }
    let rows: Vec<[String; 5]> = hits
        .iter()
        .map(|h| {
            [
                h["rank"]
                    .as_u64()
                    .map(|r| r.to_string())
                    .unwrap_or_default(),
                h["score"]
                    .as_f64()
                    .map(|s| format!("{s:.6}"))
                    .unwrap_or_else(|| "-".into()),
                h["name"].as_str().unwrap_or("").to_string(),
                h["id"].as_str().unwrap_or("").to_string(),
                hit_tags(client, h),
            ]
        })
        .collect();
    let titles = ["rank", "score", "name", "id", "tags"];
    let mut w = titles.map(|t| t.chars().count());
    for r in &rows {
        for (i, c) in r.iter().enumerate() {
            w[i] = w[i].max(c.chars().count());
        }
    }
    let line = |c: &[String; 5]| {
        format!(
            "{:>w0$}  {:>w1$}  {:<w2$}  {:<w3$}  {}",
            c[0],
            c[1],
            c[2],
            c[3],
            c[4],
            w0 = w[0],
            w1 = w[1],
            w2 = w[2],
            w3 = w[3]
        )
    };
    println!("{}", line(&titles.map(String::from)).trim_end());
    for r in &rows {
        println!("{}", line(r).trim_end());
    }
}
