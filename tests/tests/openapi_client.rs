//! A client generated from our OpenAPI document by openapi-python-client (PyPI) works against a
//! real coordinator (with tokens) and worker: `tests/python/openapi_client.py` uploads a scene,
//! submits, waits and downloads the EXR, which equals a local render bit for bit. `#[ignore]`d
//! when `openapi-python-client` (with httpx, attrs) was missing at build time (tests/build.rs);
//! `scripts/test` installs it.

use pathfarm_tests::procs::{Coordinator, bin};
use std::path::Path;
use std::process::Command;

#[test]
#[cfg_attr(
    not(openapi_client),
    ignore = "openapi-python-client (with httpx, attrs) missing at build time (scripts/test installs it)"
)]
fn a_generated_python_client_uploads_submits_and_downloads() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (client_token, worker_token) = ("generated-client-token", "generated-worker-token");
    let coordinator = Coordinator::start(&["--client-token", client_token, "--worker-token", worker_token])
        .expect("start the coordinator");
    let _worker = coordinator.start_worker().expect("start the worker");
    let url = coordinator.url.clone();
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
