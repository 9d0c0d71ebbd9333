//! `shapeseek` command line. (Minimal: only the `eval` subcommand is wired here so far.)

use clap::{Parser, Subcommand};
use std::process::ExitCode;

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
    /// Evaluate retrieval on a benchmark manifest (mAP per transformation, ROC, PR).
    Eval(shapeseek::eval::EvalArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Eval(args) => shapeseek::eval::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error [{}]: {e}", e.code());
            ExitCode::FAILURE
        }
    }
}
