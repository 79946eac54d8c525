//! Shared helpers of the end-to-end tests: real coordinator and worker processes on 127.0.0.1.

#![allow(dead_code)]

use pathfarm_common::job::RenderSettings;
use pathfarm_common::scene::LoadOptions;
use pathfarm_common::scene::bundle::load_bundle;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A child process killed (SIGKILL) when dropped.
pub struct Proc {
    pub child: Child,
    pub name: String,
}

impl Proc {
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Sends SIGTERM and waits up to `timeout` for the process to exit.
    pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        let t0 = Instant::now();
        while t0.elapsed() < timeout {
            if let Ok(Some(s)) = self.child.try_wait() {
                return Some(s);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A binary of this workspace, next to the test executable's `deps` folder.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current exe");
    let dir = exe.parent().and_then(Path::parent).expect("target dir");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: build the workspace binaries first (cargo build --release --bins, or cargo test --release --workspace)",
        path.display()
    );
    path
}

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
    let proc = Proc { child, name: "coordinator".into() };
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
    Proc { child, name: name.into() }
}

/// The EXR a local render of `settings` produces (same plan and merge as the farm).
pub fn local_exr(scene_bytes: &[u8], settings: &RenderSettings) -> Vec<u8> {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = load_bundle(scene_bytes, dir.path(), &LoadOptions::default()).expect("scene loads");
    let renderer = pathfarm_worker::render::Renderer::new(&scene, settings).expect("renderer");
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
