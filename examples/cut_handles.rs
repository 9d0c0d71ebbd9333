//! Handle cutting over a benchmark manifest, for measuring its effect with `shapeseek eval`
//! without any change to eval.
//!
//! ```text
//! cargo run --release --example cut_handles -- MANIFEST OUT_DIR [OPTIONS_JSON]
//! ```
//!
//! Every mesh of `MANIFEST` (columns `id,path,class,transform,strength,source_pose`, paths
//! relative to the manifest) is read, prepared with the default `PrepareOptions` (as eval does)
//! and passed to `mesh::topology::cut_handles` with `OPTIONS_JSON` (a `HandleCutOptions` object,
//! missing fields = defaults; e.g. `'{"max_loop_rel": 0.35}'`). A mesh with at least one cut is
//! written to `OUT_DIR/meshes/<id>.obj`; `OUT_DIR/manifest.csv` lists every shape, pointing at the
//! cut mesh or at the original file (absolute path, so eval's cache serves the unchanged ones),
//! and `OUT_DIR/report.csv` gives per shape the genus before/after, the cuts, the area kept and
//! every loop examined (`length_rel:neck_aspect:side_aspect:handle_rel:cut`, `;`-separated).
//! `{"max_cuts": 0}` only measures (genus, no loop features); `{"max_loop_rel": 1e9,
//! "max_neck_aspect": 0, ...}` lists every basis loop's features without cutting.

use shapeseek::mesh::prepare::{prepare, PrepareOptions};
use shapeseek::mesh::topology::{cut_handles, HandleCutOptions};
use shapeseek::mesh::{read_path, write_mesh, Format, ReadLimits};
use std::io::Write;
use std::path::{Path, PathBuf};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: cut_handles MANIFEST OUT_DIR [OPTIONS_JSON]".into());
    }
    let manifest = PathBuf::from(&args[1]);
    let out = PathBuf::from(&args[2]);
    let opts: HandleCutOptions = match args.get(3) {
        Some(j) => serde_json::from_str(j)?,
        None => HandleCutOptions::default(),
    };
    let base = manifest
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default()
        .canonicalize()?;
    std::fs::create_dir_all(out.join("meshes"))?;
    let mut rdr = csv::Reader::from_path(&manifest)?;
    let headers = rdr.headers()?.clone();
    let col = |name: &str| -> Result<usize, Box<dyn std::error::Error>> {
        headers
            .iter()
            .position(|h| h == name)
            .ok_or_else(|| format!("manifest has no '{name}' column").into())
    };
    let (ci, cp, cc, ct, cs) = (
        col("id")?,
        col("path")?,
        col("class")?,
        col("transform")?,
        col("strength")?,
    );
    let mut man = csv::Writer::from_path(out.join("manifest.csv"))?;
    man.write_record(&headers)?;
    let mut rep = std::fs::File::create(out.join("report.csv"))?;
    writeln!(
        rep,
        "id,class,transform,strength,genus_before,genus_after,boundary_before,boundary_after,cuts,area_kept,seconds,loops"
    )?;
    let (mut total_cuts, mut changed) = (0usize, 0usize);
    for row in rdr.records() {
        let row = row?;
        let id = &row[ci];
        let src = base.join(&row[cp]);
        let mesh = read_path(&src, &ReadLimits::default())?;
        let (mesh, _) = prepare(&mesh, &PrepareOptions::default())?;
        let t0 = std::time::Instant::now();
        let (cut, report) = cut_handles(&mesh, &opts)?;
        let secs = t0.elapsed().as_secs_f64();
        let mut rec: Vec<String> = row.iter().map(str::to_string).collect();
        if report.cuts > 0 {
            let rel = format!("meshes/{id}.obj");
            let mut f = std::io::BufWriter::new(std::fs::File::create(out.join(&rel))?);
            write_mesh(&cut, Format::Obj, &mut f)?;
            rec[cp] = rel;
            changed += 1;
            total_cuts += report.cuts;
        } else {
            rec[cp] = src.to_string_lossy().into_owned();
        }
        man.write_record(&rec)?;
        let g = |x: Option<usize>| x.map_or("?".to_string(), |g| g.to_string());
        let loops: Vec<String> = report
            .loops
            .iter()
            .map(|l| {
                format!(
                    "{:.4}:{}:{}:{}:{}",
                    l.length_rel,
                    l.neck_aspect.map_or("-".into(), |a| format!("{a:.3}")),
                    l.side_aspect.map_or("-".into(), |a| format!("{a:.3}")),
                    l.handle_rel.map_or("-".into(), |a| format!("{a:.3}")),
                    u8::from(l.cut)
                )
            })
            .collect();
        writeln!(
            rep,
            "{id},{},{},{},{},{},{},{},{},{:.5},{:.3},{}",
            &row[cc],
            &row[ct],
            &row[cs],
            g(report.before.genus),
            g(report.after.genus),
            report.before.boundary_loops,
            report.after.boundary_loops,
            report.cuts,
            report.area_kept,
            secs,
            loops.join(";")
        )?;
        eprintln!(
            "{id}: genus {} -> {}, {} cut(s), area kept {:.4}, {:.2} s",
            g(report.before.genus),
            g(report.after.genus),
            report.cuts,
            report.area_kept,
            secs
        );
    }
    man.flush()?;
    eprintln!(
        "{changed} meshes changed, {total_cuts} cuts; wrote {}",
        out.display()
    );
    Ok(())
}
