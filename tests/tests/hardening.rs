//! Attacks that got through on a running farm (the hardening issue), against real coordinator
//! processes: each test shows the attack is refused and the farm keeps serving.
//!
//! Needs the release binaries: `cargo build --release -p pathfarm-coordinator -p pathfarm-worker`
//! then `cargo test --release -p pathfarm-tests --test hardening`.

mod support;

use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_tests::procs::Coordinator;
use reqwest::StatusCode;
use serde_json::json;
use std::time::{Duration, Instant};

fn start(extra: &[&str]) -> Coordinator {
    Coordinator::start(extra).expect("start the coordinator")
}

// ------------------------------------------------------------------------------- database

#[test]
fn a_job_row_with_an_unknown_state_is_skipped_on_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let mut coord = support::start_coordinator(&data, &[]);
    let http = pathfarm_tests::procs::http();
    let api = |c: &support::Coordinator, p: &str| format!("{}/api/v1{p}", c.url);
    let scene: serde_json::Value =
        http.post(api(&coord, "/scenes")).body(cornell_demo_glb()).send().expect("upload").json().expect("scene");
    let job = json!({"scene_id": scene["scene_id"], "width": 16, "height": 16, "spp": 1});
    for _ in 0..2 {
        let r = http.post(api(&coord, "/jobs")).json(&job).send().expect("submit");
        assert_eq!(r.status(), StatusCode::CREATED);
    }
    assert!(coord.proc.terminate(Duration::from_secs(10)).is_some(), "the coordinator did not stop");
    // A row this version cannot read: a state it does not know.
    let db = rusqlite::Connection::open(data.join("pathfarm.db")).expect("open the database");
    db.execute(
        "INSERT INTO jobs (id, name, scene_id, priority, settings, state, created_ms) \
         VALUES (3, 'from the future', ?1, 0, '{\"width\":16,\"height\":16,\"spp\":1}', 'exploded', 0)",
        [scene["scene_id"].as_str().expect("scene id")],
    )
    .expect("insert the bad row");
    drop(db);
    let coord = support::start_coordinator(&data, &[]);
    let t0 = Instant::now();
    let healthy = loop {
        if let Ok(r) = http.get(format!("{}/healthz", coord.url)).send()
            && r.status() == StatusCode::OK
        {
            break true;
        }
        if t0.elapsed() > Duration::from_secs(20) {
            break false;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let log = std::fs::read_to_string(data.join("coordinator.log")).unwrap_or_default();
    assert!(healthy, "the coordinator does not serve after the bad row: {log}");
    let jobs: Vec<serde_json::Value> = http.get(api(&coord, "/jobs")).send().expect("jobs").json().expect("list");
    let ids: Vec<u64> = jobs.iter().filter_map(|j| j["id"].as_u64()).collect();
    assert_eq!(ids, vec![1, 2], "{jobs:?}");
    assert!(log.contains("skipping job 3") && log.contains("exploded"), "{log}");
    // The skipped row's id is not handed out again.
    let created: serde_json::Value =
        http.post(api(&coord, "/jobs")).json(&job).send().expect("submit").json().expect("created");
    assert_eq!(created["id"], 4, "{created}");
}

// ------------------------------------------------------------------------------- job names

#[test]
fn long_job_names_are_422_naming_the_limit() {
    let mut c = start(&[]);
    let scene = c.upload_ok(cornell_demo_glb());
    let job = |name: String| json!({"scene_id": scene, "name": name, "width": 16, "height": 16, "spp": 1});
    let r = c.submit(&job("x".repeat(1 << 20)));
    pathfarm_tests::procs::expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["name", "256 bytes"]);
    let r = c.submit(&job("x".repeat(257)));
    pathfarm_tests::procs::expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["name", "257", "256 bytes"]);
    let id = c.submit_ok(&job("x".repeat(256)));
    assert_eq!(c.job(id).name.len(), 256);
    c.assert_serving();
}
