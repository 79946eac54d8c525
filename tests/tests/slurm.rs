//! Slurm end to end: a real single-node cluster (munge, slurmctld and slurmd from Debian's
//! packages, started in a scratch folder by `tests/slurm/cluster.sh`), a real coordinator, and
//! workers started by `sbatch deploy/slurm/pathfarm-workers.sbatch`, exactly as an admin would.
//! Without the Slurm tools (`tests/build.rs` looks for them; `scripts/test` installs them) the
//! tests are ignored with that reason.

mod support;

use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{API, JobId, JobRequest, JobState, WorkerInfo};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use pathfarm_tests::procs::bin_dir;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;
use support::*;

/// The repository root (the tests crate lives in `tests/`).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("repo root").to_path_buf()
}

/// A running single-node cluster; stopped when dropped.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
}

impl Cluster {
    fn start(dir: &Path) -> Cluster {
        let out = Command::new(repo().join("tests/slurm/cluster.sh"))
            .arg("start")
            .arg(dir)
            .output()
            .expect("run tests/slurm/cluster.sh");
        assert!(
            out.status.success(),
            "the Slurm cluster did not start:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        Cluster { dir: dir.to_path_buf(), conf: dir.join("slurm.conf") }
    }

    /// A Slurm command against this cluster.
    fn cmd(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// `sbatch` of the deploy script with the coordinator's address; returns the job id.
    fn sbatch_workers(&self, coordinator: &str, args: &[&str]) -> String {
        let path = format!("{}:{}", bin_dir().display(), std::env::var("PATH").unwrap_or_default());
        let out = self
            .cmd("sbatch")
            .arg("--parsable")
            .arg(format!("--output={}/worker-%A_%a.log", self.dir.display()))
            .args(args)
            .arg(repo().join("deploy/slurm/pathfarm-workers.sbatch"))
            .env("PATH", path)
            .env("PATHFARM_COORDINATOR", coordinator)
            // The test coordinator runs with --no-auth; the script insists on a token.
            .env("PATHFARM_WORKER_TOKEN", "unused-with-no-auth")
            .env("RUST_LOG", "info")
            .env("TMPDIR", &self.dir)
            .output()
            .expect("sbatch");
        assert!(out.status.success(), "sbatch failed: {}", String::from_utf8_lossy(&out.stderr));
        let id = String::from_utf8_lossy(&out.stdout).trim().split(';').next().unwrap_or_default().to_string();
        assert!(!id.is_empty() && id.chars().all(|c| c.is_ascii_digit()), "sbatch printed {out:?}");
        id
    }

    /// `scontrol show job ID` (every array task).
    fn show_job(&self, id: &str) -> String {
        let out = self.cmd("scontrol").args(["show", "job", id]).output().expect("scontrol");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn cancel(&self, id: &str) {
        let _ = self.cmd("scancel").arg(id).status();
    }

    /// Every log the array's tasks wrote.
    fn worker_logs(&self) -> String {
        let mut all = String::new();
        if let Ok(entries) = std::fs::read_dir(&self.dir) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with("worker-") {
                    all += &format!("--- {name}\n{}", std::fs::read_to_string(e.path()).unwrap_or_default());
                }
            }
        }
        all
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new(repo().join("tests/slurm/cluster.sh")).arg("stop").arg(&self.dir).status();
    }
}

fn settings(width: u32, height: u32, spp: u32, tile: u32) -> RenderSettings {
    let mut s = RenderSettings::new(width, height, spp);
    s.tile_size = tile;
    s.seed = 11;
    s.integrator = IntegratorSettings::Path {
        max_depth: 6,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s
}

fn submit(client: &Client, s: &RenderSettings, name: &str) -> JobId {
    let created = client.upload_scene(cornell_demo_glb()).expect("upload");
    let req = JobRequest {
        scene_id: created.scene_id,
        name: Some(name.into()),
        priority: 0,
        requires: Vec::new(),
        notify: None,
        frames: None,
        order: Default::default(),
        settings: s.clone(),
    };
    client.submit(&req).expect("submit")
}

fn workers(url: &str) -> Vec<WorkerInfo> {
    reqwest::blocking::get(format!("{url}{API}/workers")).expect("workers").json().expect("json")
}

/// The array's two tasks register as two workers and render a job whose EXR is bit-identical
/// to a local render.
#[test]
#[cfg_attr(
    not(slurm_tools),
    ignore = "slurm: needs munged, slurmctld, slurmd and sbatch (Debian packages munge \
                                       slurmctld slurmd slurm-client; scripts/test installs them)"
)]
fn a_slurm_job_array_of_workers_renders_the_same_bits_as_a_local_render() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cluster = Cluster::start(&dir.path().join("slurm"));
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let s = settings(64, 48, 16, 16);
    let id = submit(&client, &s, "slurm-bits");
    // One node: the script asks for it exclusively, so the test lets the two tasks share it.
    let array = cluster.sbatch_workers(&coord.url, &["--array=0-1", "--oversubscribe"]);
    let names = wait_for("both array tasks to register", Duration::from_secs(60), || {
        let ws = workers(&coord.url);
        (ws.len() == 2).then(|| ws.into_iter().map(|w| w.name).collect::<Vec<_>>())
    });
    for task in 0..2 {
        let want = format!("slurm-{array}-{task}");
        assert!(names.iter().any(|n| n.contains(&want)), "no worker named {want}: {names:?}");
    }
    let info = wait_for("the job to complete", Duration::from_secs(180), || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "{:?}\n{}", info.error, cluster.worker_logs());
        (info.state == JobState::Completed).then_some(info)
    });
    assert_eq!(info.units_merged, info.units_total);
    assert!(client.image_exr(id).expect("exr") == local_exr(&cornell_demo_glb(), &s), "farm image differs");
    let done: u64 = workers(&coord.url).iter().map(|w| w.units_done).sum();
    assert_eq!(done, info.units_total);
    cluster.cancel(&array);
}

/// At the time limit Slurm signals the batch shell (`--signal=B:TERM@...`), which is the worker:
/// it delivers the unit in progress and exits 0, so the task ends COMPLETED, not TIMEOUT, and
/// no lease is left to expire.
#[test]
#[cfg_attr(
    not(slurm_tools),
    ignore = "slurm: needs munged, slurmctld, slurmd and sbatch (Debian packages munge \
                                       slurmctld slurmd slurm-client; scripts/test installs them)"
)]
fn a_slurm_time_limit_drains_the_worker() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cluster = Cluster::start(&dir.path().join("slurm"));
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    // Units of about a second each, far more than the task's minute can take.
    let mut s = settings(128, 128, 128 * 200, 128);
    s.passes = PassSchedule::Fixed { spp: 128 };
    let id = submit(&client, &s, "slurm-drain");
    // A one-minute limit; Slurm signals up to a minute early, here within the first minute.
    let job = cluster.sbatch_workers(&coord.url, &["--time=1", "--signal=B:TERM@50"]);
    let state = wait_for("the Slurm task to end", Duration::from_secs(150), || {
        let show = cluster.show_job(&job);
        let state = show.split_whitespace().find_map(|w| w.strip_prefix("JobState="))?.to_string();
        (!matches!(state.as_str(), "PENDING" | "RUNNING" | "CONFIGURING" | "COMPLETING" | "SIGNALING"))
            .then_some((state, show))
    });
    let logs = cluster.worker_logs();
    assert_eq!(state.0, "COMPLETED", "{}\n{logs}", state.1);
    assert!(state.1.contains("ExitCode=0:0"), "{}\n{logs}", state.1);
    assert!(logs.contains("stop requested: delivering the unit in progress"), "{logs}");
    assert!(logs.contains("worker stopped"), "{logs}");
    // The unit it was rendering was merged, not left to expire.
    let ws = workers(&coord.url);
    assert_eq!(ws.len(), 1, "{ws:?}");
    assert!(ws[0].current.is_none(), "{ws:?}");
    let info = client.job(id).expect("job");
    assert!(info.units_merged >= 1 && info.units_merged == ws[0].units_done, "{info:?} {ws:?}");
    let log = reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").text().expect("text");
    assert!(!log.contains("expired"), "a lease expired:\n{log}");
    client.cancel(id).ok();
}
