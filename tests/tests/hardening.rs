//! Attacks that got through on a running farm (the hardening issue), against real coordinator
//! processes: each test shows the attack is refused and the farm keeps serving.
//!
//! Needs the release binaries: `cargo build --release -p pathfarm-coordinator -p pathfarm-worker`
//! then `cargo test --release -p pathfarm-tests --test hardening`.

mod support;

use pathfarm_common::protocol::WORKER_SECRET_HEADER;
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_tests::procs::Coordinator;
use reqwest::StatusCode;
use serde_json::json;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

fn start(extra: &[&str]) -> Coordinator {
    Coordinator::start(extra).expect("start the coordinator")
}

/// Reads until the server closes the connection; the time it took (None: still open after
/// `limit`).
fn time_to_close(s: &mut TcpStream, limit: Duration) -> Option<Duration> {
    let t0 = Instant::now();
    s.set_read_timeout(Some(limit)).expect("read timeout");
    let mut buf = [0u8; 4096];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return Some(t0.elapsed()),
            Ok(_) => continue,
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {
                return None;
            }
            // Reset by the server: closed as well.
            Err(_) => return Some(t0.elapsed()),
        }
    }
}

/// A metric's value from `/metrics`.
fn metric(c: &Coordinator, name: &str) -> u64 {
    let text = c.http.get(format!("{}/metrics", c.url)).send().expect("metrics").text().expect("text");
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|v| v.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no {name} in\n{text}"))
}

// ------------------------------------------------------------------------------- slowloris

#[test]
fn idle_and_half_sent_connections_do_not_lock_out_the_farm() {
    let c = start(&["--max-connections", "64", "--header-timeout-ms", "1000", "--idle-timeout-ms", "1500"]);
    let addr = c.url.trim_start_matches("http://").to_string();
    // 400 connections, six times the cap: three in four send nothing, one in four half a request.
    let mut held: Vec<TcpStream> = (0..400)
        .map(|i| {
            let mut s = TcpStream::connect(&addr).expect("connect");
            if i % 4 == 0 {
                s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").expect("half a request");
            }
            s
        })
        .collect();
    // Health, scene upload and job submission answer at once (one connection per request: a
    // pooled connection may be the quietest one when the next attacker comes in).
    let fresh = reqwest::blocking::Client::builder()
        .timeout(Duration::from_secs(10))
        .pool_max_idle_per_host(0)
        .build()
        .expect("client");
    let t0 = Instant::now();
    let r = fresh.get(format!("{}/healthz", c.url)).send().expect("healthz under attack");
    assert_eq!(r.status(), StatusCode::OK);
    let r = fresh.post(c.api("/scenes")).body(cornell_demo_glb()).send().expect("upload under attack");
    assert_eq!(r.status(), StatusCode::CREATED);
    let scene: serde_json::Value = r.json().expect("scene");
    let r = fresh
        .post(c.api("/jobs"))
        .json(&json!({"scene_id": scene["scene_id"], "width": 16, "height": 16, "spp": 1}))
        .send()
        .expect("submit under attack");
    assert_eq!(r.status(), StatusCode::CREATED);
    assert!(t0.elapsed() < Duration::from_secs(5), "answers took {:?}", t0.elapsed());
    // Every attacking connection is closed by the server (evicted or timed out), none is left.
    for (i, s) in held.iter_mut().enumerate() {
        assert!(time_to_close(s, Duration::from_secs(5)).is_some(), "connection {i} is still open");
    }
    let closed = metric(&c, "pathfarm_connections_evicted_total") + metric(&c, "pathfarm_connections_timed_out_total");
    assert!(closed >= 400, "{closed} connections closed by the server");

    // Half a request line is closed after the header timeout (1 s; checked every 250 ms).
    let mut s = TcpStream::connect(&addr).expect("connect");
    s.write_all(b"GET /heal").expect("half a request line");
    let t = time_to_close(&mut s, Duration::from_secs(10)).expect("the half request is never closed");
    assert!(t >= Duration::from_millis(800) && t < Duration::from_secs(5), "closed after {t:?}");

    // A kept-alive connection after an answer: closed after the idle timeout (1.5 s), not the
    // header timeout.
    let mut s = TcpStream::connect(&addr).expect("connect");
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").expect("request");
    let mut buf = [0u8; 1024];
    let n = s.read(&mut buf).expect("answer");
    assert!(String::from_utf8_lossy(&buf[..n]).starts_with("HTTP/1.1 200"), "{}", String::from_utf8_lossy(&buf[..n]));
    let t = time_to_close(&mut s, Duration::from_secs(10)).expect("the idle connection is never closed");
    assert!(t >= Duration::from_millis(1300) && t < Duration::from_secs(5), "closed after {t:?}");

    // A lease long poll (3 s) outlives both timeouts: a request being handled is not idle.
    let reg: serde_json::Value = fresh
        .post(c.api("/workers/register"))
        .json(&json!({"name": "w", "threads": 1}))
        .send()
        .expect("register")
        .json()
        .expect("registered");
    let worker = reg["worker_id"].as_u64().expect("worker id");
    let secret = reg["worker_secret"].as_str().expect("worker secret");
    // Take the one unit of the job, so the next lease request waits.
    let r = fresh
        .post(c.api(&format!("/workers/{worker}/lease")))
        .header(WORKER_SECRET_HEADER, secret)
        .send()
        .expect("lease");
    assert_eq!(r.status(), StatusCode::OK);
    let t0 = Instant::now();
    let r = fresh
        .post(c.api(&format!("/workers/{worker}/lease?wait_ms=3000")))
        .header(WORKER_SECRET_HEADER, secret)
        .send()
        .expect("long poll");
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    assert!(t0.elapsed() >= Duration::from_millis(2900), "the long poll returned after {:?}", t0.elapsed());
}

// ------------------------------------------------------------------------------- empty tokens

/// Runs the coordinator until it exits (it must, within 20 s); its exit status and stderr.
fn run_to_exit(args: &[&str], env: &[(&str, &str)]) -> (std::process::ExitStatus, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cmd = std::process::Command::new(pathfarm_tests::procs::bin("pathfarm-coordinator"));
    cmd.args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(dir.path())
        .args(args)
        .env_remove("PATHFARM_CLIENT_TOKEN")
        .env_remove("PATHFARM_WORKER_TOKEN")
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = pathfarm_tests::procs::Proc { child: cmd.spawn().expect("spawn") };
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.child.try_wait().expect("try_wait") {
            break s;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "the coordinator started with {args:?} {env:?}");
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    if let Some(mut e) = child.child.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    (status, err)
}

#[test]
fn empty_tokens_are_refused_at_start_up() {
    type Case<'a> = (&'a [&'a str], &'a [(&'a str, &'a str)]);
    let cases: [Case<'_>; 6] = [
        (&["--client-token", "", "--worker-token", "w"], &[]),
        (&["--no-auth", "--metrics-token", ""], &[]),
        (&["--no-auth"], &[("PATHFARM_METRICS_TOKEN", " ")]),
        (&["--client-token", "c", "--worker-token", ""], &[]),
        (&[], &[("PATHFARM_CLIENT_TOKEN", ""), ("PATHFARM_WORKER_TOKEN", "w")]),
        (&["--client-token", "c"], &[("PATHFARM_WORKER_TOKEN", "")]),
    ];
    for (args, env) in cases {
        let (status, err) = run_to_exit(args, env);
        assert!(!status.success(), "{args:?} {env:?}");
        assert!(err.contains("empty") && err.contains("token"), "{args:?} {env:?}: {err}");
    }
}

#[test]
fn an_empty_presented_token_opens_nothing() {
    let c = start(&["--client-token", "client-secret", "--worker-token", "worker-secret"]);
    let r = c.http.get(c.api("/events?token=")).send().expect("events");
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    let r = c.http.get(c.api("/jobs")).header("authorization", "Bearer ").send().expect("jobs");
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    let r = c.http.get(c.api("/events")).bearer_auth("client-secret").send().expect("events");
    assert_eq!(r.status(), StatusCode::OK);
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

// ------------------------------------------------------------------------------- worker secrets

/// Leases are bound to the worker they were granted to: a second registration with the same
/// worker token cannot deliver, release or renew another worker's lease (all 403, nothing merged,
/// released or blocklisted); the honest worker's result then merges and the image stays
/// bit-identical to a local render.
#[test]
fn a_worker_cannot_act_for_another_worker() {
    use pathfarm_common::protocol::{LeaseGrant, ReleaseRequest, UnitResultFrame};
    use pathfarm_tests::procs::{assert_exr_identical, expect_error, render_local};
    let c = start(&["--client-token", "client-secret", "--worker-token", "worker-secret"]);
    let glb = cornell_demo_glb();
    let scene_file = c.dir.path().join("cornell.glb");
    std::fs::write(&scene_file, &glb).expect("write scene");
    let scene = c.upload_ok(glb.clone());
    let job = c.submit_ok(&json!({"scene_id": scene, "width": 32, "height": 32, "spp": 2, "tile_size": 16,
        "passes": {"type": "fixed", "spp": 1}}));
    let a = c.register("honest");
    let b = c.register("thief");
    assert_eq!(a.worker_secret.len(), 64, "32 bytes, hex");
    assert_ne!(a.worker_secret, b.worker_secret);
    let r = c.as_worker(c.http.post(c.api(&format!("/workers/{}/lease?wait_ms=2000", a.worker_id))), &a);
    let g: LeaseGrant = r.send().expect("lease").json().expect("grant");
    let loaded =
        pathfarm_common::scene::load_scene_from_slice(&glb, "cornell.glb", None, &Default::default()).expect("scene");
    let renderer = pathfarm_worker::render::Renderer::new(&loaded, &g.settings).expect("renderer");
    let out = renderer.render_unit(g.tile, g.pass);
    let body =
        UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum: out.accum, splats: out.splats }
            .encode();
    let result = c.api(&format!("/leases/{}/result", g.lease_id));
    let release = c.api(&format!("/leases/{}/release", g.lease_id));
    let fail = ReleaseRequest { failed: true, reason: "sabotage".into() };
    // B, with its own secret or none: every request for A's lease or as A is 403.
    for _ in 0..2 {
        let r = c.as_worker(c.http.put(&result), &b).body(body.clone()).send().expect("PUT");
        expect_error(r, StatusCode::FORBIDDEN, &[&format!("lease {}", g.lease_id), "another worker"]);
        let r = c.as_worker(c.http.post(&release), &b).json(&fail).send().expect("release");
        expect_error(r, StatusCode::FORBIDDEN, &["another worker"]);
    }
    let r = c.worker(c.http.put(&result)).body(body.clone()).send().expect("PUT");
    expect_error(r, StatusCode::FORBIDDEN, &["missing", "x-pathfarm-worker-secret"]);
    let r = c.worker(c.http.post(&release)).json(&fail).send().expect("release");
    expect_error(r, StatusCode::FORBIDDEN, &["missing", "x-pathfarm-worker-secret"]);
    let hb = c.api(&format!("/workers/{}/heartbeat", a.worker_id));
    let r = c.as_worker(c.http.post(&hb), &b).send().expect("heartbeat");
    expect_error(r, StatusCode::FORBIDDEN, &[&format!("worker {}", a.worker_id)]);
    let r = c.worker(c.http.post(&hb)).send().expect("heartbeat");
    expect_error(r, StatusCode::FORBIDDEN, &["missing"]);
    let r = c.as_worker(c.http.post(c.api(&format!("/workers/{}/lease", a.worker_id))), &b).send().expect("lease");
    expect_error(r, StatusCode::FORBIDDEN, &[&format!("worker {}", a.worker_id)]);
    // Nothing was merged, released or blocklisted; each worker may still act for itself.
    let info = c.job(job);
    assert_eq!(info.units_merged, 0);
    assert!(info.blocklist.is_empty(), "{info:?}");
    let log: Vec<String> =
        c.client(c.http.get(c.api(&format!("/jobs/{job}/log")))).send().expect("log").json().expect("log");
    assert!(!log.iter().any(|l| l.contains("sabotage") || l.contains("failed")), "{log:?}");
    let r = c.as_worker(c.http.post(c.api(&format!("/workers/{}/heartbeat", b.worker_id))), &b).send().expect("hb");
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let r = c.as_worker(c.http.post(&hb), &a).send().expect("heartbeat");
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    // A's result merges.
    let r = c.as_worker(c.http.put(&result), &a).body(body).send().expect("PUT");
    assert_eq!(r.status(), StatusCode::OK, "{}", r.text().unwrap_or_default());
    assert_eq!(c.job(job).units_merged, 1);
    // A real worker finishes the job: bit-identical to a local render.
    let _w = c.start_worker().expect("worker");
    let farm_exr = c.dir.path().join("farm.exr");
    c.wait_completed_exr(job, Duration::from_secs(60), &farm_exr);
    let local_exr = c.dir.path().join("local.exr");
    let args = ["--width", "32", "--height", "32", "--spp", "2", "--tile-size", "16", "--pass-spp", "1"];
    render_local(&scene_file, &local_exr, &args).expect("local render");
    assert_exr_identical(&farm_exr, &local_exr);
}

// ------------------------------------------------------------------------------- unread bodies

/// Sends a request head declaring `declared` body bytes and 64 KiB of them, and reads the
/// answer's status line (the server must answer without waiting for the rest). Then tries to
/// send the rest as fast as it can: returns (status line, time to the answer, bytes sent).
fn put_declared(addr: &str, path: &str, headers: &[(&str, &str)], declared: u64) -> (String, Duration, u64) {
    let mut s = TcpStream::connect(addr).expect("connect");
    let mut head = format!("PUT {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {declared}\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    let t0 = Instant::now();
    s.write_all(head.as_bytes()).expect("head");
    let chunk = vec![0x55u8; 64 << 10];
    s.write_all(&chunk).expect("first bytes");
    let mut sent = chunk.len() as u64;
    s.set_read_timeout(Some(Duration::from_secs(5))).expect("timeout");
    let mut buf = [0u8; 4096];
    let n = s.read(&mut buf).unwrap_or(0);
    let took = t0.elapsed();
    let answer = String::from_utf8_lossy(&buf[..n]).to_string();
    let status = answer.lines().next().unwrap_or_default().to_string();
    assert!(answer.to_ascii_lowercase().contains("connection: close"), "{answer}");
    let big = vec![0x55u8; 1 << 20];
    while sent < declared {
        match s.write(&big) {
            Ok(0) | Err(_) => break,
            Ok(k) => sent += k as u64,
        }
    }
    (status, took, sent)
}

/// Peak resident memory of a process (`VmHWM`), in bytes.
fn vm_hwm(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .expect("VmHWM");
    kb * 1024
}

/// Result bodies are refused before they are read when the lease is not held or not the
/// sender's, or when they declare more than the lease's tile can need; scene uploads declaring
/// more than the upload limit likewise. Four 200 MB bodies leave the coordinator's peak memory
/// far below one of them (the bodies were buffered in full: four 500 MB uploads peaked at 2 GiB).
#[test]
fn large_bodies_are_refused_before_they_are_read() {
    let c = start(&["--max-upload-mb", "256"]);
    let addr = c.url.trim_start_matches("http://").to_string();
    let scene = c.upload_ok(cornell_demo_glb());
    let job = c.submit_ok(&json!({"scene_id": scene, "width": 32, "height": 32, "spp": 1, "tile_size": 16}));
    let a = c.register("a");
    let b = c.register("b");
    let r = c.as_worker(c.http.post(c.api(&format!("/workers/{}/lease?wait_ms=2000", a.worker_id))), &a);
    let g: pathfarm_common::protocol::LeaseGrant = r.send().expect("lease").json().expect("grant");
    let mb200 = 200_000_000;
    let result = |lease: u64| format!("/api/v1/leases/{lease}/result");
    let secret = |r: &pathfarm_common::protocol::Registered| ("x-pathfarm-worker-secret", r.worker_secret.clone());
    type Case<'a> = (String, Vec<(&'a str, String)>, &'a str);
    let cases: Vec<Case<'_>> = vec![
        (result(g.lease_id + 1000), vec![secret(&a)], "409"),
        (result(g.lease_id), vec![secret(&b)], "403"),
        (result(g.lease_id), vec![], "403"),
        (result(g.lease_id), vec![secret(&a)], "413"),
    ];
    for (path, headers, want) in &cases {
        let headers: Vec<(&str, &str)> = headers.iter().map(|(k, v)| (*k, v.as_str())).collect();
        let (status, took, sent) = put_declared(&addr, path, &headers, mb200);
        assert!(status.contains(want), "{path} {headers:?}: {status}");
        assert!(took < Duration::from_secs(2), "{path}: answered after {took:?}");
        assert!(sent < mb200 / 4, "{path}: the server took {sent} bytes of the body");
    }
    // A scene declaring more than --max-upload-mb.
    let mut s = TcpStream::connect(&addr).expect("connect");
    s.write_all(b"POST /api/v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Length: 300000000\r\n\r\n").expect("head");
    s.set_read_timeout(Some(Duration::from_secs(5))).expect("timeout");
    let mut buf = [0u8; 4096];
    let n = s.read(&mut buf).expect("answer to the scene upload");
    let answer = String::from_utf8_lossy(&buf[..n]);
    assert!(answer.starts_with("HTTP/1.1 413") && answer.contains("268435456"), "{answer}");
    let hwm = vm_hwm(c.proc.child.id());
    assert!(hwm < 100 << 20, "the coordinator's peak memory is {} MiB", hwm >> 20);
    // The honest result for the lease still merges.
    let loaded =
        pathfarm_common::scene::load_scene_from_slice(&cornell_demo_glb(), "cornell.glb", None, &Default::default())
            .expect("scene");
    let renderer = pathfarm_worker::render::Renderer::new(&loaded, &g.settings).expect("renderer");
    let out = renderer.render_unit(g.tile, g.pass);
    let body = pathfarm_common::protocol::UnitResultFrame {
        lease_id: g.lease_id,
        job_id: g.job_id,
        unit: g.unit,
        accum: out.accum,
        splats: out.splats,
    }
    .encode();
    let r = c.as_worker(c.http.put(c.api(&result(g.lease_id)[7..])), &a).body(body).send().expect("PUT");
    assert_eq!(r.status(), StatusCode::OK, "{}", r.text().unwrap_or_default());
    assert_eq!(c.job(job).units_merged, 1);
}

// ------------------------------------------------------------------------------- registrations

/// Registrations are rate-limited per address (429 with Retry-After), and workers offline longer
/// than --prune-workers-after-ms are forgotten, in memory and in SQLite (65,638 registrations
/// made a 23 MB /workers).
#[test]
fn registrations_are_rate_limited_and_offline_workers_pruned() {
    let c = start(&[
        "--register-burst",
        "3",
        "--register-per-minute",
        "1",
        "--prune-workers-after-ms",
        "600",
        "--lease-timeout-ms",
        "300",
    ]);
    let regs: Vec<_> = (0..3).map(|i| c.register(&format!("w{i}"))).collect();
    let r = c.worker(c.http.post(c.api("/workers/register"))).json(&json!({"name": "w3", "threads": 1})).send();
    let r = r.expect("register");
    let retry: u64 =
        r.headers().get("retry-after").and_then(|v| v.to_str().ok()).and_then(|v| v.parse().ok()).expect("Retry-After");
    assert!((1..=60).contains(&retry), "{retry}");
    pathfarm_tests::procs::expect_error(r, StatusCode::TOO_MANY_REQUESTS, &["registrations", "retry after"]);
    let workers = |c: &Coordinator| -> Vec<serde_json::Value> {
        c.client(c.http.get(c.api("/workers"))).send().expect("workers").json().expect("list")
    };
    assert_eq!(workers(&c).len(), 3);
    // One keeps heartbeating, the others go silent and are pruned.
    let alive = &regs[0];
    let hb = |r: &pathfarm_common::protocol::Registered| {
        c.as_worker(c.http.post(c.api(&format!("/workers/{}/heartbeat", r.worker_id))), r).send().expect("hb").status()
    };
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_millis(1500) {
        assert_eq!(hb(alive), StatusCode::NO_CONTENT);
        std::thread::sleep(Duration::from_millis(100));
    }
    let left: Vec<u64> = workers(&c).iter().filter_map(|w| w["id"].as_u64()).collect();
    assert_eq!(left, vec![alive.worker_id]);
    assert_eq!(hb(&regs[1]), StatusCode::NOT_FOUND, "a pruned worker must register again");
    let db = rusqlite::Connection::open(c.dir.path().join("pathfarm.db")).expect("db");
    let rows: Vec<i64> = db
        .prepare("SELECT id FROM workers ORDER BY id")
        .expect("query")
        .query_map([], |r| r.get(0))
        .expect("rows")
        .collect::<Result<_, _>>()
        .expect("ids");
    assert_eq!(rows, vec![alive.worker_id as i64]);
}
