//! The Blender add-on (`clients/blender/pathfarm`) in real Blender: `bpy` from PyPI (Blender 4.5
//! as a Python module), driven by the Python scripts in `clients/blender/tests/`.
//!
//! - `addon_e2e.py` against a coordinator (with client and worker tokens) and a worker started
//!   here: install and enable the add-on, submit a frame and a 3-frame range, check the images it
//!   loads are bit for bit local renders of the GLB it exports, and that a 422 and a 401 reach
//!   the artist in words.
//! - `brightness.py`: Cycles and pathfarm render the same Blender scene; image means within 3%
//!   per channel with each light alone and all together.
//!
//! Needs `python3` with `bpy`, OpenEXR and numpy (`scripts/test` installs them). Where they were
//! missing at build time (tests/build.rs) the tests are `#[ignore]`d with that reason.

use pathfarm_tests::procs::{Coordinator, bin};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn scripts() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/blender/tests")
}

/// Runs a script to its end (at most `limit`); panics with its output unless it printed PASS.
fn run_python(script: &str, args: &[&str], env: &[(&str, &Path)], limit: Duration) {
    let mut cmd = Command::new("python3");
    cmd.arg(scripts().join(script)).args(args).stdout(Stdio::piped()).stderr(Stdio::piped());
    for (k, v) in env {
        cmd.env(k, v);
    }
    // bpy loads its own SYCL runtime, which an OIDN library folder on LD_LIBRARY_PATH (set for a
    // worker built with `denoise`) shadows with an older libur_loader: Python gets none, and the
    // scripts hand the folder to the pathfarm-worker processes they start.
    if let Some(path) = std::env::var_os("LD_LIBRARY_PATH") {
        cmd.env_remove("LD_LIBRARY_PATH").env("PATHFARM_WORKER_LD_LIBRARY_PATH", path);
    }
    let child = cmd.spawn().expect("start python3");
    let pid = child.id();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(child.wait_with_output());
    });
    let output = match rx.recv_timeout(limit) {
        Ok(out) => out.expect("python3 output"),
        Err(_) => {
            let _ = Command::new("kill").arg("-9").arg(pid.to_string()).status();
            panic!("{script} did not finish in {limit:?}");
        }
    };
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    let ours: Vec<&str> = stdout.lines().filter(|l| !l.contains("| INFO:") && !l.starts_with("Fra:")).collect();
    eprintln!("[{script}]\n{}", ours.join("\n"));
    assert!(
        output.status.success() && stdout.lines().any(|l| l == "PASS"),
        "{script} failed ({})\nstdout:\n{stdout}\nstderr:\n{stderr}",
        output.status
    );
}

#[test]
#[cfg_attr(
    not(bpy),
    ignore = "python3 could not import bpy, OpenEXR, numpy at build time (scripts/test installs them)"
)]
fn the_blender_addon_submits_and_loads_the_farms_images() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (client_token, worker_token) = ("blender-client-token", "blender-worker-token");
    let coordinator = Coordinator::start(&["--client-token", client_token, "--worker-token", worker_token])
        .expect("start the coordinator");
    let _worker = coordinator.start_worker().expect("start the worker");
    let url = coordinator.url.clone();
    let worker = bin("pathfarm-worker");
    let out = tmp.path().join("out");
    let resources = tmp.path().join("blender-user");
    run_python(
        "addon_e2e.py",
        &[
            "--url",
            &url,
            "--token",
            client_token,
            "--worker",
            &worker.to_string_lossy(),
            "--out",
            &out.to_string_lossy(),
        ],
        &[("BLENDER_USER_RESOURCES", &resources)],
        Duration::from_secs(300),
    );
}

#[test]
#[cfg_attr(
    not(bpy),
    ignore = "python3 could not import bpy, OpenEXR, numpy at build time (scripts/test installs them)"
)]
fn blender_scenes_render_as_bright_as_in_cycles() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let worker = bin("pathfarm-worker");
    run_python(
        "brightness.py",
        &["--worker", &worker.to_string_lossy(), "--out", &tmp.path().to_string_lossy(), "--tolerance", "0.03"],
        &[("BLENDER_USER_RESOURCES", &tmp.path().join("blender-user"))],
        Duration::from_secs(300),
    );
}
