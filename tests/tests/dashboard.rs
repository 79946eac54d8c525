//! The web dashboard in a real browser: a coordinator process, a job, headless Chromium driven
//! by `tests/browser/dashboard.mjs` (playwright-core), then a worker process. The page must show
//! the job going to `completed` through live updates (no reload) and load its preview image,
//! then a 3-frame sequence's frame strip with a thumbnail per frame and the chosen frame's preview.
//!
//! Needs `node`, `tests/browser/node_modules` (`npm ci` there) and Chromium (`/usr/bin/chromium`
//! or `$PATHFARM_CHROMIUM`); `scripts/test` installs them. Where they were missing at build time
//! (tests/build.rs) the tests are `#[ignore]`d with that reason; run anyway (`--include-ignored`)
//! without them, they fail naming what is missing.

use pathfarm_common::scene::demo::cornell_demo_glb;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A child process killed when dropped.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("workspace root").to_path_buf()
}

/// A binary of this workspace: target/release/deps/this-test -> target/release/NAME.
fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current exe");
    let path = exe.parent().and_then(Path::parent).expect("target dir").join(name);
    assert!(path.exists(), "{} is missing: build the binaries first (cargo build --release --bins)", path.display());
    path
}

/// What the browser check needs, or why it cannot run.
fn browser_tools() -> Result<(PathBuf, PathBuf), String> {
    let chromium =
        std::env::var_os("PATHFARM_CHROMIUM").map_or_else(|| PathBuf::from("/usr/bin/chromium"), PathBuf::from);
    if !chromium.exists() {
        return Err(format!(
            "Chromium not found at {} (apt-get install chromium, or set PATHFARM_CHROMIUM)",
            chromium.display()
        ));
    }
    let node_ok = Command::new("node").arg("--version").output().is_ok_and(|o| o.status.success());
    if !node_ok {
        return Err("node is not on PATH".into());
    }
    let dir = workspace_root().join("tests/browser");
    if !dir.join("node_modules/playwright-core").exists() {
        return Err(format!("{}/node_modules is missing (run npm ci there)", dir.display()));
    }
    Ok((chromium, dir.join("dashboard.mjs")))
}

fn wait_for_file(path: &Path, timeout: Duration) -> String {
    let t0 = Instant::now();
    loop {
        if let Ok(s) = std::fs::read_to_string(path)
            && !s.trim().is_empty()
        {
            return s.trim().to_string();
        }
        assert!(t0.elapsed() < timeout, "{} did not appear in {timeout:?}", path.display());
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// One browser at a time (the machines are small).
static BROWSER: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
#[cfg_attr(
    not(browser_tools),
    ignore = "browser tools missing at build time: Chromium, node, npm ci in tests/browser (scripts/test installs them)"
)]
fn dashboard_shows_a_job_completing_live() {
    run_scenario(None, "dashboard.png");
}

#[test]
#[cfg_attr(
    not(browser_tools),
    ignore = "browser tools missing at build time: Chromium, node, npm ci in tests/browser (scripts/test installs them)"
)]
fn dashboard_asks_for_the_client_token() {
    run_scenario(Some(("client-token-for-the-browser", "worker-token-for-the-browser")), "dashboard-token.png");
}

/// `tokens`: (client, worker) bearer tokens the coordinator requires.
fn run_scenario(tokens: Option<(&str, &str)>, screenshot: &str) {
    let _one = BROWSER.lock().unwrap_or_else(|e| e.into_inner());
    let (chromium, script) = browser_tools().unwrap_or_else(|why| panic!("the browser test cannot run: {why}"));
    let t_start = Instant::now();
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let log = std::fs::File::create(tmp.path().join("coordinator.log")).expect("log");
    let mut coordinator = Command::new(bin("pathfarm-coordinator"));
    coordinator.args(["--listen", "127.0.0.1:0", "--data-dir"]).arg(&data);
    if let Some((client, worker)) = tokens {
        coordinator.env("PATHFARM_CLIENT_TOKEN", client).env("PATHFARM_WORKER_TOKEN", worker);
    } else {
        coordinator.arg("--no-auth").env_remove("PATHFARM_CLIENT_TOKEN").env_remove("PATHFARM_WORKER_TOKEN");
    }
    let _coordinator = Proc(coordinator.stdout(Stdio::null()).stderr(log).spawn().expect("start the coordinator"));
    let addr = wait_for_file(&data.join("coordinator.addr"), Duration::from_secs(30));
    let url = format!("http://{addr}");

    // A small job, queued before any worker exists.
    let mut headers = reqwest::header::HeaderMap::new();
    if let Some((client, _)) = tokens {
        headers.insert(reqwest::header::AUTHORIZATION, format!("Bearer {client}").parse().expect("header"));
    }
    let http = reqwest::blocking::Client::builder().default_headers(headers).build().expect("http client");
    let scene: serde_json::Value = http
        .post(format!("{url}/api/v1/scenes"))
        .body(cornell_demo_glb())
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.json())
        .expect("upload the scene");
    let job: serde_json::Value = http
        .post(format!("{url}/api/v1/jobs"))
        .json(&serde_json::json!({
            "scene_id": scene["scene_id"], "name": "cornell (browser test)",
            "width": 96, "height": 96, "spp": 32, "tile_size": 32,
        }))
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.json())
        .expect("create the job");
    let job_id = job["id"].as_u64().expect("job id");
    // A sequence of three small frames, rendered after the job above: its panel shows the frame
    // strip with a thumbnail per written frame.
    let sequence: serde_json::Value = http
        .post(format!("{url}/api/v1/jobs"))
        .json(&serde_json::json!({
            "scene_id": scene["scene_id"], "name": "sequence (browser test)", "frames": "1-3",
            "width": 48, "height": 32, "spp": 4, "tile_size": 16,
        }))
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.json())
        .expect("create the sequence job");
    let sequence_id = sequence["id"].as_u64().expect("sequence job id");

    let shot = workspace_root().join("target").join(screenshot);
    let _ = std::fs::remove_file(&shot);
    let mut node = Command::new("node");
    match tokens {
        Some((client, _)) => node.env("PATHFARM_TOKEN", client),
        None => node.env_remove("PATHFARM_TOKEN"),
    };
    let mut node = node
        .arg(&script)
        .arg(&url)
        .arg(job_id.to_string())
        .arg(&shot)
        .arg(sequence_id.to_string())
        .env("PATHFARM_CHROMIUM", &chromium)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start node");
    let stdout = node.stdout.take().expect("node stdout");
    let mut node = Proc(node);
    let (tx, rx) = mpsc::channel();
    let reader = std::thread::spawn(move || {
        let mut lines = Vec::new();
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            eprintln!("[browser] {line}");
            let _ = tx.send(line.clone());
            lines.push(line);
        }
        lines
    });

    // Start the worker only once the page shows the queued job.
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(line) if line == "READY" => break,
            Ok(_) => {}
            Err(_) => panic!("the browser script did not get ready (see [browser] lines above)"),
        }
    }
    let mut worker = Command::new(bin("pathfarm-worker"));
    worker
        .args(["run", "--coordinator", &url, "--threads", "1", "--name", "browser-test-worker", "--cache-dir"])
        .arg(tmp.path().join("cache"));
    match tokens {
        Some((_, w)) => worker.env("PATHFARM_WORKER_TOKEN", w),
        None => worker.env_remove("PATHFARM_WORKER_TOKEN"),
    };
    let _worker = Proc(worker.stdout(Stdio::null()).stderr(Stdio::null()).spawn().expect("start the worker"));

    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = node.0.try_wait().expect("wait for node") {
            break s;
        }
        assert!(t0.elapsed() < Duration::from_secs(240), "the browser script did not finish in 240 s");
        std::thread::sleep(Duration::from_millis(100));
    };
    let lines = reader.join().expect("reader");
    assert!(status.success(), "the browser check failed ({status}); coordinator log in {}", tmp.path().display());
    assert!(lines.iter().any(|l| l == "PASS"), "no PASS line from the browser script");
    assert!(shot.exists(), "no screenshot at {}", shot.display());
    eprintln!(
        "dashboard browser test passed in {:.1} s; screenshot {}",
        t_start.elapsed().as_secs_f64(),
        shot.display()
    );
}
