//! The worker daemon: registers with a coordinator, leases units, renders, uploads.

/// `pathfarm-worker run` arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// Coordinator base URL, e.g. http://127.0.0.1:8080
    #[arg(long, env = "PATHFARM_COORDINATOR")]
    pub coordinator: String,
}

/// Runs the daemon until SIGTERM/SIGINT.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    anyhow::bail!("worker daemon for {} is not written yet", args.coordinator)
}
