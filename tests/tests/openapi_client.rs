//! A client generated from our OpenAPI document by openapi-python-client (PyPI) works against a
//! real coordinator (with tokens) and worker: `tests/python/openapi_client.py` uploads a scene,
//! submits, waits and downloads the EXR, which equals a local render bit for bit. `#[ignore]`d
//! when `openapi-python-client` (with httpx, attrs) was missing at build time (tests/build.rs);
//! `scripts/test` installs it.

use pathfarm_tests::procs::{Proc, bin};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn wait_for_file(path: &Path, timeout: Duration) -> String {
    let t0 = Instant::now();
    loop {
        if let Ok(s) = std::fs::read_to_string(path)
            && !s.trim().is_empty()
        {
            return s.trim().to_string();
        }
        assert!(t0.elapsed() < timeout, "{} did not appear in {timeout:?}", path.display());
        std::thread::sleep(Duration::from_millis(25));
    }
}

#[test]
#[cfg_attr(
    not(openapi_client),
    ignore = "openapi-python-client (with httpx, attrs) missing at build time (scripts/test installs it)"
)]
fn a_generated_python_client_uploads_submits_and_downloads() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let (client_token, worker_token) = ("generated-client-token", "generated-worker-token");
    let log = std::fs::File::create(tmp.path().join("coordinator.log")).expect("log");
    let _coordinator = Proc {
        child: Command::new(bin("pathfarm-coordinator"))
            .args(["--listen", "127.0.0.1:0", "--data-dir"])
            .arg(&data)
            .env("PATHFARM_CLIENT_TOKEN", client_token)
            .env("PATHFARM_WORKER_TOKEN", worker_token)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("start the coordinator"),
    };
    let url = format!("http://{}", wait_for_file(&data.join("coordinator.addr"), Duration::from_secs(30)));
    let _worker = Proc {
        child: Command::new(bin("pathfarm-worker"))
            .args(["run", "--coordinator", &url, "--threads", "1", "--name", "generated-client-test", "--cache-dir"])
            .arg(tmp.path().join("cache"))
            .env("PATHFARM_WORKER_TOKEN", worker_token)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start the worker"),
    };
    let scene = tmp.path().join("cornell.glb");
    std::fs::write(&scene, pathfarm_common::scene::demo::cornell_demo_glb()).expect("write the scene");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/openapi_client.py");
    let output = Command::new("timeout")
        .arg("300")
        .arg("python3")
        .arg(&script)
        .args(["--url", &url, "--token", client_token, "--scene"])
        .arg(&scene)
        .arg("--worker")
        .arg(bin("pathfarm-worker"))
        .arg("--out")
        .arg(tmp.path().join("out"))
        .output()
        .expect("run python3");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    eprintln!("{stdout}");
    assert!(
        output.status.success() && stdout.lines().any(|l| l == "PASS"),
        "the generated client failed ({})\nstdout:\n{stdout}\nstderr:\n{stderr}",
        output.status
    );
}
