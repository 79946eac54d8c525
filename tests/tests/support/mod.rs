//! Helpers of the farm, restart and CLI end-to-end tests: a coordinator on a data dir the test
//! owns (so it can be restarted on it), named workers, and local reference renders. Processes
//! and binaries come from `pathfarm_tests::procs`.

#![allow(dead_code)]

use pathfarm_common::job::RenderSettings;
use pathfarm_common::scene::bundle::unpack_bundle;
use pathfarm_common::scene::{LoadOptions, load_job_environment, load_scene};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

pub use pathfarm_tests::procs::{Proc, bin};

/// A coordinator process on a free port, its data under `data_dir`.
pub struct Coordinator {
    pub proc: Proc,
    pub url: String,
    pub data_dir: PathBuf,
}

pub fn start_coordinator(data_dir: &Path, extra: &[&str]) -> Coordinator {
    start_coordinator_at(data_dir, "127.0.0.1:0", extra)
}

/// A coordinator process listening on `listen`.
pub fn start_coordinator_at(data_dir: &Path, listen: &str, extra: &[&str]) -> Coordinator {
    std::fs::create_dir_all(data_dir).expect("data dir");
    let addr_file = data_dir.join("coordinator.addr");
    let _ = std::fs::remove_file(&addr_file);
    let log =
        std::fs::OpenOptions::new().create(true).append(true).open(data_dir.join("coordinator.log")).expect("log file");
    let child = Command::new(bin("pathfarm-coordinator"))
        .args(["--listen", listen, "--no-auth", "--data-dir"])
        .arg(data_dir)
        .args(extra)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .expect("spawn coordinator");
    let proc = Proc { child };
    let t0 = Instant::now();
    loop {
        if let Ok(addr) = std::fs::read_to_string(&addr_file)
            && !addr.is_empty()
        {
            return Coordinator { proc, url: format!("http://{addr}"), data_dir: data_dir.to_path_buf() };
        }
        if t0.elapsed() > Duration::from_secs(30) {
            let log = std::fs::read_to_string(data_dir.join("coordinator.log")).unwrap_or_default();
            panic!("coordinator did not start; its log:\n{log}");
        }
        std::thread::sleep(Duration::from_millis(25));
    }
}

/// A worker process with one render thread.
pub fn start_worker(url: &str, name: &str, cache_dir: &Path, extra: &[&str]) -> Proc {
    let child = Command::new(bin("pathfarm-worker"))
        .args(["run", "--coordinator", url, "--threads", "1", "--name", name, "--cache-dir"])
        .arg(cache_dir)
        .args(extra)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn worker");
    Proc { child }
}

/// `n` workers named `{prefix}0..`, each with its cache `{cache}{i}` under `dir`.
pub fn start_workers(url: &str, prefix: &str, dir: &Path, cache: &str, n: usize) -> Vec<Proc> {
    (0..n).map(|i| start_worker(url, &format!("{prefix}{i}"), &dir.join(format!("{cache}{i}")), &[])).collect()
}

/// The EXR a local render of `settings` produces (same plan and merge as the farm).
pub fn local_exr(scene_bytes: &[u8], settings: &RenderSettings) -> Vec<u8> {
    let dir = tempfile::tempdir().expect("tempdir");
    let main = unpack_bundle(scene_bytes, dir.path()).expect("bundle unpacks");
    let scene = load_scene(&main, &LoadOptions::default()).expect("scene loads");
    let folder = main.parent().expect("the scene file's folder");
    let environment = load_job_environment(folder, settings, &LoadOptions::default()).expect("environment loads");
    let renderer =
        pathfarm_worker::render::Renderer::with_environment(&scene, settings, environment).expect("renderer");
    let film = pathfarm_worker::render::render_local(&renderer, |_, _| {});
    film.resolve().encode_exr().expect("encode")
}

/// Polls `f` until it returns `Some`, failing after `timeout`.
pub fn wait_for<T>(what: &str, timeout: Duration, mut f: impl FnMut() -> Option<T>) -> T {
    let t0 = Instant::now();
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(t0.elapsed() < timeout, "timed out after {timeout:?} waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}
