//! `pathfarm`: the client CLI (submit, status, cancel, fetch).

use anyhow::Context;
use clap::{Parser, Subcommand};
use pathfarm_common::protocol::{FrameOrder, JobId, JobRequest};
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

// Parsed once per run: the size of the largest variant does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand, Debug)]
enum Command {
    /// Upload a scene (.glb, .gltf, or a tar bundle) and submit a job. A .gltf goes up with every
    /// file it names (buffers, images), packed into a tar bundle.
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
        #[command(flatten)]
        sequence: SequenceArgs,
        /// Wait for the job to finish, with a progress bar.
        #[arg(long)]
        wait: bool,
        /// With --wait: write the EXR here; for --frames, a pattern whose `####` becomes each
        /// frame's number (`out/shot.####.exr`).
        #[arg(long)]
        out: Option<String>,
    },
    /// Show one job, or all jobs.
    Status { job: Option<JobId> },
    /// Cancel a job.
    Cancel { job: JobId },
    /// Download a job's current EXR; for a sequence every started frame, to `--out`'s `####`
    /// pattern.
    Fetch {
        job: JobId,
        #[arg(long)]
        out: String,
    },
}

/// A sequence: which frames, in which order, at which frame rate.
#[derive(clap::Args, Debug)]
struct SequenceArgs {
    /// Render these frames (`1-24`, `1-100x5`, `1,5,10-20`); each is written as its own image.
    #[arg(long)]
    frames: Option<pathfarm_common::frames::FrameSet>,
    /// `frame`: frame by frame; `sequence-preview`: every frame's first pass before any second.
    #[arg(long, value_enum, default_value = "frame")]
    order: OrderArg,
    /// Frames per second: frame f is the scene at f / fps seconds.
    #[arg(long, default_value_t = 24.0)]
    fps: f32,
    /// Motion blur: the shutter is open this fraction of a frame (0 = off).
    #[arg(long, default_value_t = 0.0)]
    shutter: f32,
    /// Only these glTF animations play (comma list); default all.
    #[arg(long, value_delimiter = ',')]
    animations: Option<Vec<String>>,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum OrderArg {
    Frame,
    SequencePreview,
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
        Command::Submit { scene, settings, name, priority, requires, sequence, wait, out } => {
            let is_gltf = scene.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("gltf"));
            let bytes = if is_gltf {
                pathfarm_common::scene::bundle::pack_gltf(&scene)?
            } else {
                std::fs::read(&scene).with_context(|| format!("reading {}", scene.display()))?
            };
            let created = client.upload_scene(bytes)?;
            for w in &created.warnings {
                eprintln!("scene warning: {w}");
            }
            let mut settings = settings.to_settings();
            settings.fps = sequence.fps;
            settings.shutter = sequence.shutter;
            settings.animations = sequence.animations;
            let job = JobRequest {
                frames: sequence.frames,
                order: match sequence.order {
                    OrderArg::Frame => FrameOrder::Frame,
                    OrderArg::SequencePreview => FrameOrder::SequencePreview,
                },
                scene_id: created.scene_id,
                name,
                priority,
                requires,
                notify: None,
                settings,
            };
            let created = client.submit_job(&job)?;
            for w in &created.warnings {
                eprintln!("job warning: {w}");
            }
            let id = created.id;
            writeln!(stdout, "{id}")?;
            if wait {
                let info = client.wait(id, true)?;
                eprintln!("job {id} {} in {:.1} s", info.state.as_str(), info.elapsed_secs);
                if let Some(out) = out {
                    for path in client.fetch_images(id, &out)? {
                        eprintln!("wrote {}", path.display());
                    }
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
            for path in client.fetch_images(job, &out)? {
                eprintln!("wrote {}", path.display());
            }
        }
    }
    Ok(())
}
