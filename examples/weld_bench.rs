//! Heavier topological noise than the benchmark has: welds shapes of one class of a benchmark
//! manifest with more bridges, for measuring with `shapeseek eval` how retrieval fails.
//!
//! ```text
//! cargo run --release --example weld_bench -- MANIFEST OUT_DIR --class crane-man \
//!     --sources null,iso1,iso2,iso3 --bridges 5,6,8 [--disc-edges 3.0] [--seed N] \
//!     [--separation-edges 4.0] [--max-gap-edges 20.0] [--min-geodesic-rel 0.2] [--pull 0.6]
//! ```
//!
//! `MANIFEST` has the columns `id,path,class,transform,strength,source_pose` (paths relative to
//! the manifest). For every source `S` of `--sources` (the id `<class>-<S>`) and every bridge
//! count `B` of `--bridges`, the source mesh is read, prepared with the default
//! `PrepareOptions` (as eval does) and welded (`mesh::weld::weld`, disc radius `--disc-edges`
//! mean edge lengths, default 3.0 as the benchmark's strongest level, seed `--seed`, default 0;
//! the last four flags set the `WeldOptions` of the same names, defaults as there: fewer
//! bridges than asked are made where the shape has too few contacts, and a smaller separation,
//! a larger gap or a smaller relative geodesic distance admits more).
//! The result is written to `OUT_DIR/meshes/<class>-weld<B>-<S>.obj`, read back and prepared
//! again, and its genus checked against the welded mesh's (an OBJ round trip must not lose a
//! handle). `OUT_DIR/manifest.csv` is every row of `MANIFEST` (paths made absolute) followed by
//! one row per welded shape (transform `topology` for the null source, else
//! `isometry+topology`; strength = `B`; `source_pose` of the source row); `OUT_DIR/report.csv`
//! gives per welded shape the bridges requested and made, the genus before, after and after the
//! round trip, the candidate contacts, the gaps (in mean edge lengths), the number of tube
//! triangles (the last ones of the welded mesh) and the seconds of the weld.

use shapeseek::mesh::prepare::{prepare, PrepareOptions};
use shapeseek::mesh::topology::surface_stats;
use shapeseek::mesh::weld::{weld, WeldOptions};
use shapeseek::mesh::{read_path, write_mesh, Format, ReadLimits};
use std::io::Write;
use std::path::{Path, PathBuf};

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

const USAGE: &str = "usage: weld_bench MANIFEST OUT_DIR --class CLASS --sources S1,S2,.. \
                     --bridges B1,B2,.. [--disc-edges R] [--seed N] [--separation-edges E] \
                     [--max-gap-edges G] [--min-geodesic-rel F] [--pull P]";

struct Args {
    manifest: PathBuf,
    out: PathBuf,
    class: String,
    sources: Vec<String>,
    bridges: Vec<usize>,
    disc_edges: f64,
    seed: u64,
    /// Other `WeldOptions` fields (the defaults unless given).
    base: WeldOptions,
}

fn parse_args() -> Res<Args> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut pos = Vec::new();
    let (mut class, mut sources, mut bridges) = (None, None, None);
    let (mut disc_edges, mut seed) = (3.0, 0u64);
    let mut base = WeldOptions::default();
    let mut it = args.into_iter();
    while let Some(a) = it.next() {
        let mut val = || {
            it.next()
                .ok_or_else(|| format!("{a} needs a value; {USAGE}"))
        };
        match a.as_str() {
            "--class" => class = Some(val()?),
            "--sources" => sources = Some(val()?),
            "--bridges" => bridges = Some(val()?),
            "--disc-edges" => disc_edges = val()?.parse()?,
            "--seed" => seed = val()?.parse()?,
            "--separation-edges" => base.separation_edges = val()?.parse()?,
            "--max-gap-edges" => base.max_gap_edges = val()?.parse()?,
            "--min-geodesic-rel" => base.min_geodesic_rel = val()?.parse()?,
            "--pull" => base.pull = val()?.parse()?,
            s if s.starts_with("--") => return Err(format!("unknown option {s}; {USAGE}").into()),
            _ => pos.push(a),
        }
    }
    if pos.len() != 2 {
        return Err(USAGE.into());
    }
    let list = |s: Option<String>, what: &str| -> Res<Vec<String>> {
        let s = s.ok_or_else(|| format!("--{what} is required; {USAGE}"))?;
        Ok(s.split(',')
            .map(str::trim)
            .filter(|x| !x.is_empty())
            .map(str::to_string)
            .collect())
    };
    let bridges = list(bridges, "bridges")?
        .iter()
        .map(|b| b.parse::<usize>())
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Args {
        manifest: PathBuf::from(&pos[0]),
        out: PathBuf::from(&pos[1]),
        class: class.ok_or_else(|| format!("--class is required; {USAGE}"))?,
        sources: list(sources, "sources")?,
        bridges,
        disc_edges,
        seed,
        base,
    })
}

fn run() -> Res<()> {
    let a = parse_args()?;
    let base = a
        .manifest
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default()
        .canonicalize()?;
    std::fs::create_dir_all(a.out.join("meshes"))?;
    let mut rdr = csv::Reader::from_path(&a.manifest)?;
    let headers = rdr.headers()?.clone();
    let col = |name: &str| -> Res<usize> {
        headers
            .iter()
            .position(|h| h == name)
            .ok_or_else(|| format!("manifest has no '{name}' column").into())
    };
    let (ci, cp, cc, ct, cs, cpose) = (
        col("id")?,
        col("path")?,
        col("class")?,
        col("transform")?,
        col("strength")?,
        col("source_pose")?,
    );
    let mut man = csv::Writer::from_path(a.out.join("manifest.csv"))?;
    man.write_record(&headers)?;
    let mut rows: Vec<Vec<String>> = Vec::new();
    for row in rdr.records() {
        let mut rec: Vec<String> = row?.iter().map(str::to_string).collect();
        rec[cp] = base.join(&rec[cp]).to_string_lossy().into_owned();
        man.write_record(&rec)?;
        rows.push(rec);
    }
    let mut rep = std::fs::File::create(a.out.join("report.csv"))?;
    writeln!(
        rep,
        "id,source,bridges_requested,bridges_made,genus_before,genus_after,genus_reread,\
         candidates,gaps_edges,tube_faces,seconds"
    )?;
    let g = |x: Option<usize>| x.map_or("?".to_string(), |g| g.to_string());
    let mut failures = Vec::new();
    for src in &a.sources {
        let sid = format!("{}-{src}", a.class);
        let row = rows
            .iter()
            .find(|r| r[ci] == sid && r[cc] == a.class)
            .ok_or_else(|| format!("no row with id {sid} and class {} in the manifest", a.class))?
            .clone();
        let mesh = read_path(&row[cp], &ReadLimits::default())?;
        let (mesh, _) = prepare(&mesh, &PrepareOptions::default())?;
        for &b in &a.bridges {
            let id = format!("{}-weld{b}-{src}", a.class);
            let opts = WeldOptions {
                bridges: b,
                disc_radius_edges: a.disc_edges,
                seed: a.seed,
                ..a.base.clone()
            };
            let t0 = std::time::Instant::now();
            let (welded, wr) = weld(&mesh, &opts)?;
            let secs = t0.elapsed().as_secs_f64();
            let path = a.out.join("meshes").join(format!("{id}.obj"));
            {
                let mut f = std::io::BufWriter::new(std::fs::File::create(&path)?);
                write_mesh(&welded, Format::Obj, &mut f)?;
                f.flush()?;
            }
            let back = read_path(&path, &ReadLimits::default())?;
            let (back, _) = prepare(&back, &PrepareOptions::default())?;
            let reread = surface_stats(&back)?.genus;
            if reread != wr.after.genus {
                failures.push(format!(
                    "{id}: genus {} after welding but {} after the OBJ round trip",
                    g(wr.after.genus),
                    g(reread)
                ));
            }
            let mut rec = vec![String::new(); headers.len()];
            rec[ci] = id.clone();
            rec[cp] = path.canonicalize()?.to_string_lossy().into_owned();
            rec[cc] = a.class.clone();
            rec[ct] = if row[ct] == "null" {
                "topology"
            } else {
                "isometry+topology"
            }
            .to_string();
            rec[cs] = b.to_string();
            rec[cpose] = row[cpose].clone();
            man.write_record(&rec)?;
            let gaps: Vec<String> = wr
                .bridges
                .iter()
                .map(|x| format!("{:.2}", x.gap_edges))
                .collect();
            writeln!(
                rep,
                "{id},{sid},{b},{},{},{},{},{},{},{},{secs:.3}",
                wr.made,
                g(wr.before.genus),
                g(wr.after.genus),
                g(reread),
                wr.candidates,
                gaps.join(";"),
                wr.bridges.iter().map(|x| x.tube_faces).sum::<usize>()
            )?;
            eprintln!(
                "{id}: {} of {b} bridges, genus {} -> {} (re-read {}), gaps {}, {secs:.2} s",
                wr.made,
                g(wr.before.genus),
                g(wr.after.genus),
                g(reread),
                gaps.join(" ")
            );
        }
    }
    man.flush()?;
    if !failures.is_empty() {
        return Err(failures.join("; ").into());
    }
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
