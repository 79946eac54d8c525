//! `pathfarm`: the client CLI (submit, status, cancel, fetch).

use anyhow::Context;
use clap::{Parser, Subcommand};
use pathfarm_common::protocol::{JobId, JobRequest};
use pathfarm_coordinator::client::Client;
use std::io::Write;
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(name = "pathfarm", version, about = "pathfarm client")]
struct Cli {
    /// Coordinator URL.
    #[arg(long, env = "PATHFARM_SERVER", default_value = "http://127.0.0.1:8080", global = true)]
    server: String,
    /// Client token (bearer).
    #[arg(long, env = "PATHFARM_CLIENT_TOKEN", hide_env_values = true, global = true)]
    token: Option<String>,
    /// PEM certificate(s) to trust for an https:// server besides the system's roots.
    #[arg(long, env = "PATHFARM_CA_CERT", global = true)]
    ca_cert: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Upload a scene (.glb, .gltf, or a tar bundle) and submit a job.
    Submit {
        scene: PathBuf,
        #[command(flatten)]
        settings: pathfarm_worker::cli::SettingsArgs,
        #[arg(long)]
        name: Option<String>,
        #[arg(long, default_value_t = 0)]
        priority: i32,
        /// Tags a worker must have to render the job (comma list, e.g. `highmem,avx512f`).
        #[arg(long, value_delimiter = ',')]
        requires: Vec<String>,
        /// Wait for the job to finish, with a progress bar.
        #[arg(long)]
        wait: bool,
        /// With --wait: write the EXR here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Show one job, or all jobs.
    Status { job: Option<JobId> },
    /// Cancel a job.
    Cancel { job: JobId },
    /// Download a job's current EXR.
    Fetch {
        job: JobId,
        #[arg(long)]
        out: PathBuf,
    },
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let client = Client::with_ca_cert(&cli.server, cli.token, cli.ca_cert.as_deref())?;
    let mut stdout = std::io::stdout().lock();
    match cli.command {
        Command::Submit { scene, settings, name, priority, requires, wait, out } => {
            let bytes = std::fs::read(&scene).with_context(|| format!("reading {}", scene.display()))?;
            let created = client.upload_scene(bytes)?;
            for w in &created.warnings {
                eprintln!("scene warning: {w}");
            }
            let job = JobRequest {
                frames: None,
                order: Default::default(),
                scene_id: created.scene_id,
                name,
                priority,
                requires,
                notify: None,
                settings: settings.to_settings(),
            };
            let id = client.submit(&job)?;
            writeln!(stdout, "{id}")?;
            if wait {
                let info = client.wait(id, true)?;
                eprintln!("job {id} {} in {:.1} s", info.state.as_str(), info.elapsed_secs);
                if let Some(out) = out {
                    std::fs::write(&out, client.image_exr(id)?)
                        .with_context(|| format!("writing {}", out.display()))?;
                    eprintln!("wrote {}", out.display());
                }
            }
        }
        Command::Status { job: Some(id) } => {
            writeln!(stdout, "{}", serde_json::to_string_pretty(&client.job(id)?)?)?;
        }
        Command::Status { job: None } => {
            for j in client.jobs()? {
                writeln!(
                    stdout,
                    "{:>6}  {:<10} {:>5.1}%  spp {:>5}/{:<5} {}",
                    j.id,
                    j.state.as_str(),
                    j.progress * 100.0,
                    j.spp_done,
                    j.settings.spp,
                    j.name
                )?;
            }
        }
        Command::Cancel { job } => {
            let info = client.cancel(job)?;
            writeln!(stdout, "job {job} {}", info.state.as_str())?;
        }
        Command::Fetch { job, out } => {
            std::fs::write(&out, client.image_exr(job)?).with_context(|| format!("writing {}", out.display()))?;
            eprintln!("wrote {}", out.display());
        }
    }
    Ok(())
}
