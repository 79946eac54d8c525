//! `pathfarm-worker`: render a scene locally (`render`), or run as a farm worker daemon (`run`).

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(name = "pathfarm-worker", version, about = "pathfarm renderer and worker daemon")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Render a scene locally to an EXR (same plan and merge as the farm).
    Render(pathfarm_worker::cli::RenderArgs),
    /// Run as a worker daemon of a coordinator.
    Run(pathfarm_worker::daemon::RunArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Render(args) => pathfarm_worker::cli::render(args),
        Command::Run(args) => pathfarm_worker::daemon::run(args),
    }
}
