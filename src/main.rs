//! The `shapeseek` command line.

use clap::{Parser, Subcommand};
use shapeseek::server::{MigrateArgs, ServeArgs};

#[derive(Parser)]
#[command(name = "shapeseek", version, about = "Non-rigid 3D shape retrieval")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the REST service on an embedded index.
    Serve(ServeArgs),
    /// Upgrade an index directory to this build's schema version (after a backup copy).
    Migrate(MigrateArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => args.to_config().and_then(|cfg| {
            tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()
                .map_err(shapeseek::Error::Io)?
                .block_on(shapeseek::server::serve(cfg))
        }),
        Command::Migrate(args) => args.run().map(|msg| println!("{msg}")),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error [{}]: {e}", e.code());
            std::process::ExitCode::FAILURE
        }
    }
}
