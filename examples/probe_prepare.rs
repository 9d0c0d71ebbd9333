//! Each mesh prepared as the default specification prepares it (smoothing, boundary capping,
//! handle cutting), written as OBJ with its preparation report printed as JSON, for looking at
//! what capping and cutting did (`docs/quality.md` §28 counts the loops left open with it):
//!
//! ```text
//! cargo run --release --example probe_prepare -- OUT_DIR MESH...
//! ```
//!
//! Writes `OUT_DIR/<file stem>.obj` and prints `<file stem>: <PrepareReport JSON>` per mesh.
//! With `NOCAP=1` in the environment it stops before capping and handle cutting (smoothing
//! only), so the loops capping would see can be examined; `BUDGET=N` sets the vertex budget
//! (default the server's, 0: full resolution).

use shapeseek::mesh::prepare::prepare;
use shapeseek::mesh::{read_path, write_mesh, Format, ReadLimits};
use shapeseek::spectrum::AnalyzeOptions;
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
        return Err("usage: probe_prepare OUT_DIR MESH...".into());
    }
    let out = PathBuf::from(&args[1]);
    std::fs::create_dir_all(&out)?;
    let spec = shapeseek::presets::default_config().signature;
    let mut opts = spec.analysis_options(&AnalyzeOptions::default()).prepare;
    // The server's vertex budget (`analysis_vertex_budget`); `BUDGET=0`: full resolution.
    opts.max_vertices = match std::env::var("BUDGET") {
        Ok(b) => Some(b.parse::<usize>()?).filter(|&b| b > 0),
        Err(_) => Some(shapeseek::presets::ANALYSIS_VERTEX_BUDGET),
    };
    if std::env::var_os("NOCAP").is_some() {
        opts.cap_boundaries = None;
        opts.cut_handles = None;
    }
    for p in &args[2..] {
        let path = Path::new(p);
        let mesh = read_path(path, &ReadLimits::default())?;
        let (prepared, report) = prepare(&mesh, &opts)?;
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "mesh".into());
        let mut f =
            std::io::BufWriter::new(std::fs::File::create(out.join(format!("{stem}.obj")))?);
        write_mesh(&prepared, Format::Obj, &mut f)?;
        println!("{stem}: {}", serde_json::to_string(&report)?);
    }
    Ok(())
}
