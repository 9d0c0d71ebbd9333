//! Finer copies of a benchmark's meshes, for measuring what the analysis vertex budget
//! (`PrepareOptions::max_vertices`, `shapeseek::mesh::decimate`) does to retrieval when shapes
//! come at several resolutions (`docs/quality.md` §36):
//!
//! ```text
//! cargo run --release --example upsample -- MANIFEST OUT_DIR [SUBDIVISIONS] [all|odd]
//! ```
//!
//! Each chosen mesh (every one, or every second row of the manifest: `odd`, the default) is
//! split `SUBDIVISIONS` times (default 2: 16 times the faces) at its edge midpoints, then given
//! two pairs of Taubin smoothing steps, so that its new vertices leave the flat faces they were
//! made on (a finer surface, not only a finer triangulation of the same one). The others are
//! copied as read. All are written as OFF under `OUT_DIR/meshes`, with `OUT_DIR/manifest.csv`
//! holding the input manifest's rows pointing at them.

use shapeseek::mesh::generate::midpoint_subdivide;
use shapeseek::mesh::smooth::{taubin, SmoothOptions};
use shapeseek::mesh::{read_path, write_mesh, Format, ReadLimits};
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
        return Err("usage: upsample MANIFEST OUT_DIR [SUBDIVISIONS] [all|odd]".into());
    }
    let manifest = PathBuf::from(&args[1]);
    let out = PathBuf::from(&args[2]);
    let subdivisions: usize = args.get(3).map_or(Ok(2), |s| s.parse())?;
    let every = match args.get(4).map_or("odd", |s| s.as_str()) {
        "all" => 1,
        "odd" => 2,
        o => return Err(format!("{o}: all or odd").into()),
    };
    let base = manifest.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(out.join("meshes"))?;
    let mut rd = csv::Reader::from_path(&manifest)?;
    let headers = rd.headers()?.clone();
    let path_col = headers
        .iter()
        .position(|h| h == "path")
        .ok_or("the manifest has no path column")?;
    let mut wr = csv::Writer::from_path(out.join("manifest.csv"))?;
    wr.write_record(&headers)?;
    let smooth = SmoothOptions::steps(2);
    for (row, rec) in rd.records().enumerate() {
        let rec = rec?;
        let src = base.join(&rec[path_col]);
        let mut mesh = read_path(&src, &ReadLimits::default())?;
        let finer = row % every == every - 1;
        if finer {
            for _ in 0..subdivisions {
                mesh = midpoint_subdivide(&mesh);
            }
            mesh = taubin(&mesh, &smooth);
        }
        let stem = src.file_stem().and_then(|s| s.to_str()).unwrap_or("mesh");
        let rel = format!("meshes/{stem}.off");
        let mut f = std::io::BufWriter::new(std::fs::File::create(out.join(&rel))?);
        write_mesh(&mesh, Format::Off, &mut f)?;
        let fields: Vec<&str> = rec
            .iter()
            .enumerate()
            .map(|(i, v)| if i == path_col { rel.as_str() } else { v })
            .collect();
        wr.write_record(&fields)?;
        eprintln!(
            "{stem}: {} vertices{}",
            mesh.vertices.len(),
            if finer { " (finer)" } else { "" }
        );
    }
    wr.flush()?;
    Ok(())
}
