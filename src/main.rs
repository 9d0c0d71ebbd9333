//! The `shapeseek` command line: a thin shell around the library.

use clap::{Args, Parser, Subcommand};
use serde_json::json;
use shapeseek::eigen::{EigenOptions, Method};
use shapeseek::laplace::LaplacianKind;
use shapeseek::mesh::prepare::{ComponentPolicy, PrepareOptions};
use shapeseek::mesh::{generate, read_mesh, Format, Mesh, ReadLimits};
use shapeseek::spectrum::{analyze, AnalyzeOptions};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

mod bench;
mod cli;

use cli::CliError;

#[derive(Parser)]
#[command(
    name = "shapeseek",
    version,
    about = "Non-rigid 3D shape retrieval with spectral shape distances"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Read a mesh (or generate one), prepare it and print its Laplace–Beltrami spectrum.
    Spectrum(SpectrumArgs),
    /// Run the REST service on an embedded index (default ./shapeseek-data, 127.0.0.1:8080).
    Serve(shapeseek::server::ServeArgs),
    /// Analyse uploads queued by serving nodes (`serve --store postgres://… --queue nats://…`):
    /// pull jobs from the JetStream work queue, store the shapes in PostgreSQL.
    Worker(cli::worker::WorkerArgs),
    /// Add mesh files, folders or CSV manifests to an index (via a server, or a data directory).
    Ingest(cli::ingest::IngestArgs),
    /// Find the shapes most similar to a mesh file or a stored shape (asks a running server).
    Search(cli::search::SearchArgs),
    /// Upgrade an index directory to this build's schema version (after a backup copy kept in
    /// DATA/backups/).
    Migrate(shapeseek::server::MigrateArgs),
    /// Evaluate retrieval on a benchmark manifest (mAP per transformation, ROC, PR).
    Eval(cli::eval::EvalArgs),
    /// Performance benchmarks (spectrum: Laplacian + factorisation + eigensolve, vs SciPy).
    Bench(bench::BenchArgs),
    /// Write the labelled sample meshes (6 classes x 5 poses/remeshings, mixed formats) and a manifest.
    Samples(SamplesArgs),
}

#[derive(Args)]
struct SamplesArgs {
    /// Output directory (created if needed).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct SpectrumArgs {
    /// Mesh file (OBJ, glTF/GLB, PLY, OFF, STL); the format comes from its bytes first.
    #[arg(required_unless_present = "generate")]
    file: Option<PathBuf>,
    /// Generate the mesh instead: `icosphere[:SUBDIVISIONS]`, `torus[:NU:NV]`,
    /// `bumpy-torus[:NU:NV]`, `rectangle[:NX:NY]`.
    #[arg(long, conflicts_with = "file")]
    generate: Option<String>,
    /// Format hint when the bytes are ambiguous (obj, gltf, glb, ply, off, stl).
    #[arg(long)]
    format: Option<Format>,
    /// Number of eigenpairs.
    #[arg(long, default_value_t = 100)]
    k: usize,
    /// Accepted relative residual of every eigenpair.
    #[arg(long, default_value_t = 1e-9)]
    tolerance: f64,
    /// Eigensolver: auto, dense or krylov.
    #[arg(long, default_value = "auto", value_parser = parse_method)]
    method: Method,
    /// Operator: cotangent (the paper's) or intrinsic-delaunay (robust to bad triangulations).
    #[arg(long, default_value = "cotangent", value_parser = parse_laplacian)]
    laplacian: LaplacianKind,
    /// Keep every connected component (default: the largest by area).
    #[arg(long)]
    keep_all_components: bool,
    /// Weld vertices closer than this fraction of the bounding-box diagonal (default: exact
    /// duplicates only).
    #[arg(long)]
    weld_tolerance: Option<f64>,
    /// Do not normalise to unit total area.
    #[arg(long)]
    no_normalize: bool,
    /// Print one JSON object instead of a readable report.
    #[arg(long)]
    json: bool,
    /// Also print every eigenpair's residual (JSON: `residuals`).
    #[arg(long)]
    residuals: bool,
}

fn parse_laplacian(s: &str) -> Result<LaplacianKind, String> {
    match s {
        "cotangent" => Ok(LaplacianKind::Cotangent),
        "intrinsic-delaunay" => Ok(LaplacianKind::IntrinsicDelaunay),
        _ => Err(format!(
            "unknown Laplacian {s:?} (cotangent, intrinsic-delaunay)"
        )),
    }
}

fn parse_method(s: &str) -> Result<Method, String> {
    match s {
        "auto" => Ok(Method::Auto),
        "dense" => Ok(Method::Dense),
        "krylov" => Ok(Method::Krylov),
        _ => Err(format!("unknown method {s:?} (auto, dense, krylov)")),
    }
}

/// Builds a generated mesh from a `name[:a[:b]]` description.
pub(crate) fn generated_mesh(desc: &str) -> shapeseek::Result<Mesh> {
    let mut parts = desc.split(':');
    let name = parts.next().unwrap_or_default();
    let nums: Vec<usize> = parts
        .map(|p| {
            p.parse::<usize>().map_err(|_| {
                shapeseek::Error::InvalidArgument(format!("bad number {p:?} in {desc:?}"))
            })
        })
        .collect::<Result<_, _>>()?;
    let arg = |i: usize, default: usize| nums.get(i).copied().unwrap_or(default);
    let too_big = |v: usize| v > 4_000_000;
    let mesh = match name {
        "icosphere" if arg(0, 4) <= 9 => generate::icosphere(arg(0, 4) as u32),
        "torus" if !too_big(arg(0, 64) * arg(1, 32)) => generate::torus(1.0, 0.35, arg(0, 64).max(3), arg(1, 32).max(3)),
        "bumpy-torus" if !too_big(arg(0, 125) * arg(1, 80)) => {
            generate::bumpy_torus(arg(0, 125).max(3), arg(1, 80).max(3))
        }
        "rectangle" if !too_big(arg(0, 80) * arg(1, 40)) => generate::rectangle(2.0, 1.0, arg(0, 80).max(1), arg(1, 40).max(1)),
        _ => {
            return Err(shapeseek::Error::InvalidArgument(format!(
                "unknown or too large generated mesh {desc:?} (icosphere[:S≤9], torus[:NU:NV], bumpy-torus[:NU:NV], rectangle[:NX:NY])"
            )))
        }
    };
    Ok(mesh)
}

fn run_spectrum(args: &SpectrumArgs) -> Result<(), CliError> {
    let t0 = Instant::now();
    if args.k == 0 {
        return Err(CliError::usage("--k 0: ask for at least one eigenpair"));
    }
    let (mesh, source) = match (&args.file, &args.generate) {
        (Some(path), _) => {
            let bytes = cli::read_file(path)?;
            let hint = args.format.or_else(|| cli::format_hint(path));
            (
                read_mesh(&bytes, hint, &ReadLimits::default())
                    .map_err(|e| CliError::at(path, e))?,
                path.display().to_string(),
            )
        }
        (None, Some(desc)) => (generated_mesh(desc)?, format!("generated {desc}")),
        (None, None) => return Err(CliError::usage("give a FILE or --generate")),
    };
    let read_ms = t0.elapsed().as_secs_f64() * 1e3;
    let opts = AnalyzeOptions {
        prepare: PrepareOptions {
            weld_tolerance: args.weld_tolerance,
            components: if args.keep_all_components {
                ComponentPolicy::All
            } else {
                ComponentPolicy::Largest
            },
            normalize_area: !args.no_normalize,
            ..Default::default()
        },
        eigen: EigenOptions {
            k: args.k,
            tolerance: args.tolerance,
            method: args.method,
            // The check below says how many eigenpairs exist, naming the input.
            allow_fewer: true,
            ..Default::default()
        },
        laplacian: args.laplacian,
    };
    let a = analyze(&mesh, &opts).map_err(|e| match &args.file {
        Some(path) => CliError::at(path, e),
        None => e.into(),
    })?;
    // The solver clamps k to the vertex count: say so instead of printing fewer values.
    let n = a.mesh.vertices.len();
    if args.k > n {
        return Err(CliError::usage(format!(
            "--k {}: {source} has {n} vertices after preparation, so at most {n} eigenpairs \
             exist; ask for --k {n} or fewer",
            args.k
        )));
    }
    let total_ms = t0.elapsed().as_secs_f64() * 1e3;
    let s = &a.spectrum;
    let max_residual = shapeseek::eigen::max_or_nan(&s.residuals);
    if args.json {
        let mut out = json!({
            "source": source,
            "eigenvalues": s.eigenvalues,
            "k": s.eigenvalues.len(),
            "vertices": a.mesh.vertices.len(),
            "faces": a.mesh.faces.len(),
            "max_residual": max_residual,
            "timings_ms": {
                "read": read_ms,
                "prepare": a.timings.prepare_ms,
                "laplacian": a.timings.laplacian_ms,
                "factorization": a.timings.factorization_ms,
                "eigensolve": a.timings.eigensolve_ms,
                "total": total_ms,
            },
            "prepare": a.report,
            "solver": a.eigen_stats,
        });
        if args.residuals {
            out["residuals"] = json!(s.residuals);
        }
        println!("{out}");
    } else {
        let r = &a.report;
        println!("shapeseek spectrum — {source}");
        println!(
            "  mesh: {} vertices, {} faces in; {} vertices, {} faces after preparation",
            r.vertices_in, r.faces_in, r.vertices_out, r.faces_out
        );
        println!(
            "  preparation: {} welded, {} degenerate and {} duplicate faces dropped, {} component(s) ({} kept, {:.2}% of the area dropped)",
            r.welded_vertices, r.degenerate_faces, r.duplicate_faces, r.components, r.components_kept, 100.0 * r.dropped_area_fraction
        );
        println!(
            "  topology: {} boundary loop(s), {} non-manifold edge(s), {} face(s) reoriented, {} inconsistently oriented edge(s) left, Euler characteristic {}",
            r.boundary_loops, r.nonmanifold_edges, r.reoriented_faces, r.inconsistent_orientation_edges, r.euler_characteristic
        );
        println!(
            "  area: {:.6} (coordinates scaled by {:.6})",
            r.original_area, r.scale_factor
        );
        println!(
            "  solver: {} (block {}, basis {}, {} restarts, {} solves), max relative residual {:.2e}",
            a.eigen_stats.method,
            a.eigen_stats.block_size,
            a.eigen_stats.basis_size,
            a.eigen_stats.restarts,
            a.eigen_stats.operator_applications,
            max_residual
        );
        println!(
            "  time: read {:.1} ms, prepare {:.1} ms, Laplacian {:.1} ms, factorisation {:.1} ms, eigensolve {:.1} ms, total {:.1} ms",
            read_ms, a.timings.prepare_ms, a.timings.laplacian_ms, a.timings.factorization_ms, a.timings.eigensolve_ms, total_ms
        );
        println!("  eigenvalues (unit-area shape unless --no-normalize):");
        for (i, v) in s.eigenvalues.iter().enumerate() {
            if args.residuals {
                println!("    λ{i:<4} {v:>16.9}   residual {:.2e}", s.residuals[i]);
            } else {
                println!("    λ{i:<4} {v:>16.9}");
            }
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // `serve` sets up its own (text or JSON) structured logging from its configuration.
    if !matches!(cli.command, Command::Serve(_) | Command::Worker(_)) {
        // Collection commands print their own progress and summary: warnings only by default.
        let default = match cli.command {
            Command::Ingest(_) | Command::Search(_) => "warn",
            _ => "info",
        };
        tracing_subscriber::fmt()
            .with_env_filter(
                tracing_subscriber::EnvFilter::try_from_default_env()
                    .unwrap_or_else(|_| default.into()),
            )
            .with_writer(std::io::stderr)
            .init();
    }
    let keeps_ignoring = matches!(
        cli.command,
        Command::Serve(_) | Command::Worker(_) | Command::Migrate(_) | Command::Bench(_)
    );
    if !keeps_ignoring {
        // A command whose output goes to a pipe that closes (`shapeseek spectrum … | head`)
        // ends as other command-line tools do, by SIGPIPE, instead of panicking on the
        // failed print (Rust ignores SIGPIPE by default). TCP sockets are not concerned (the
        // standard library sends with MSG_NOSIGNAL); the commands that may reach PostgreSQL
        // over a Unix socket (written with `write`, which raises it) keep ignoring it.
        // SAFETY: resetting a signal's disposition at start-up, before any thread is spawned.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let result: Result<(), CliError> = match &cli.command {
        Command::Spectrum(a) => run_spectrum(a),
        Command::Serve(a) => run_serve(a),
        Command::Worker(a) => cli::worker::run(a),
        Command::Ingest(a) => match cli::ingest::run(a) {
            Ok(true) => Ok(()),
            // The failures are listed; the status says some inputs were not ingested.
            Ok(false) => return ExitCode::from(1),
            Err(e) => Err(e),
        },
        Command::Search(a) => cli::search::run(a),
        Command::Migrate(a) => run_migrate(a),
        Command::Eval(a) => match cli::eval::run(a) {
            Ok(true) => Ok(()),
            // Shapes were left out (listed in the report and on stderr).
            Ok(false) => return ExitCode::from(1),
            Err(e) => Err(CliError::from(e)),
        },
        Command::Bench(a) => bench::run(a).map_err(CliError::from),
        Command::Samples(a) => shapeseek::mesh::samples::write_samples(&a.out)
            .map(|s| {
                println!(
                    "wrote {} sample meshes and manifest.csv to {}",
                    s.len(),
                    a.out.display()
                )
            })
            .map_err(|e| CliError::at(&a.out, e)),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{e}");
            ExitCode::from(e.exit)
        }
    }
}

fn run_serve(a: &shapeseek::server::ServeArgs) -> Result<(), CliError> {
    let cfg = a.to_config()?;
    if cfg.store_url().is_none() {
        cli::datadir::ensure_writable(&cfg.data)?;
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError::new("io", format!("cannot start the runtime: {e}"), 74))?
        .block_on(shapeseek::server::serve(cfg))?;
    Ok(())
}

fn run_migrate(a: &shapeseek::server::MigrateArgs) -> Result<(), CliError> {
    if a.store_url().is_some() {
        println!("{}", a.run()?);
        return Ok(());
    }
    let dir = a.data_dir();
    // A missing or foreign directory is refused by the runner itself, untouched.
    if dir.join("db").is_dir() {
        cli::datadir::ensure_writable(&dir)?;
    }
    println!("{}", a.run()?);
    Ok(())
}
