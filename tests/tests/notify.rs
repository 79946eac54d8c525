//! Job webhooks end to end: a coordinator with `--webhook-secret`, a worker, and a tiny HTTP
//! receiver in the test that answers 500 to the first delivery and 200 to the next. The
//! completed event arrives twice (the retry after the 500), signed with HMAC-SHA256 of the
//! exact body, and the job's log says it was delivered. Invalid `notify` fields are 422.
//!
//! Needs the release binaries: `cargo build --release --bins` then
//! `cargo test --release -p pathfarm-tests --test notify`.

use hmac::{Hmac, Mac};
use pathfarm_common::protocol::JobState;
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_tests::procs::{Coordinator, expect_error};
use reqwest::StatusCode;
use serde_json::json;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// One request the receiver got: its headers (names lower-cased) and body.
struct Received {
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Received {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// Serves on 127.0.0.1:0 in a thread: request `i` (0-based) is answered `statuses[i]` (200
/// beyond them) and sent down the channel. Returns the URL.
fn receiver(statuses: Vec<u16>) -> (String, mpsc::Receiver<Received>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let url = format!("http://{}/hooks/pathfarm?k=1", listener.local_addr().expect("addr"));
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for (i, stream) in listener.incoming().enumerate() {
            let Ok(stream) = stream else { continue };
            let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
            let mut reader = BufReader::new(stream);
            let mut line = String::new();
            if reader.read_line(&mut line).is_err() || !line.starts_with("POST /hooks/pathfarm?k=1 ") {
                continue;
            }
            let mut headers = Vec::new();
            loop {
                let mut h = String::new();
                if reader.read_line(&mut h).is_err() || h.trim().is_empty() {
                    break;
                }
                if let Some((k, v)) = h.trim_end().split_once(':') {
                    headers.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
                }
            }
            let len: usize =
                headers.iter().find(|(k, _)| k == "content-length").and_then(|(_, v)| v.parse().ok()).unwrap_or(0);
            let mut body = vec![0; len];
            if reader.read_exact(&mut body).is_err() {
                continue;
            }
            let status = statuses.get(i).copied().unwrap_or(200);
            let mut stream = reader.into_inner();
            let _ = write!(stream, "HTTP/1.1 {status} X\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
            let _ = stream.flush();
            if tx.send(Received { headers, body }).is_err() {
                return;
            }
        }
    });
    (url, rx)
}

fn hmac_hex(key: &[u8], body: &[u8]) -> String {
    let mut mac = <Hmac<sha2::Sha256> as Mac>::new_from_slice(key).expect("hmac key");
    mac.update(body);
    hex::encode(mac.finalize().into_bytes())
}

fn job_log(c: &Coordinator, id: u64) -> Vec<String> {
    c.client(c.http.get(c.api(&format!("/jobs/{id}/log")))).send().expect("log").json().expect("log json")
}

#[test]
fn completed_job_is_notified_signed_and_retried_after_a_500() {
    let c = Coordinator::start(&["--webhook-secret", "s3cret", "--webhook-retry-ms", "100"]).expect("coordinator");
    let scene = c.upload_ok(cornell_demo_glb());
    let (url, rx) = receiver(vec![500]);
    let id = c.submit_ok(&json!({
        "scene_id": scene, "name": "hooked", "width": 16, "height": 16, "spp": 2, "tile_size": 16,
        "notify": {"url": url, "events": ["completed", "failed"]},
    }));
    let _worker = c.start_worker().expect("worker");
    let info = c.wait_job(id, Duration::from_secs(120));
    assert_eq!(info.state, JobState::Completed, "{info:?}");

    let mut got = Vec::new();
    for n in 0..2 {
        got.push(
            rx.recv_timeout(Duration::from_secs(30))
                .unwrap_or_else(|e| panic!("delivery {n} did not arrive ({e}); log: {:?}", job_log(&c, id))),
        );
    }
    for r in &got {
        assert_eq!(r.header("x-pathfarm-event"), Some("completed"));
        assert_eq!(r.header("content-type"), Some("application/json"));
        let sig = r.header("x-pathfarm-signature").expect("signature header");
        assert_eq!(sig, format!("sha256={}", hmac_hex(b"s3cret", &r.body)), "signature of the exact body");
        assert_ne!(sig, format!("sha256={}", hmac_hex(b"wrong", &r.body)));
        let v: serde_json::Value = serde_json::from_slice(&r.body).expect("JSON body");
        assert_eq!(v["event"], "completed", "{v}");
        assert_eq!(v["job"]["id"], id, "{v}");
        assert_eq!(v["job"]["state"], "completed", "{v}");
        assert_eq!(v["job"]["name"], "hooked", "{v}");
        assert!(v["sent_ms"].as_u64().is_some_and(|t| t > 1_600_000_000_000), "{v}");
    }

    // The log says what happened: the 500, then the delivery.
    let t0 = Instant::now();
    let log = loop {
        let log = job_log(&c, id);
        if log.iter().any(|l| l == "notified completed: 200") {
            break log;
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "no delivery in the job log: {log:?}");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(log.iter().any(|l| l.contains("attempt 1 failed") && l.contains("500")), "{log:?}");
    // Only the events asked for: no third delivery.
    assert!(rx.recv_timeout(Duration::from_millis(500)).is_err(), "an unexpected extra delivery");
}

#[test]
fn invalid_notify_is_refused_with_422() {
    let c = Coordinator::start(&["--webhook-secret", "s3cret"]).expect("coordinator");
    let scene = c.upload_ok(cornell_demo_glb());
    let job =
        |notify: serde_json::Value| json!({"scene_id": scene, "width": 8, "height": 8, "spp": 1, "notify": notify});
    let cases = [
        (json!({"url": "ftp://example.com/x", "events": ["completed"]}), vec!["notify.url", "http:// or https://"]),
        (json!({"url": "not a url", "events": ["completed"]}), vec!["notify.url"]),
        (json!({"url": format!("https://example.com/{}", "a".repeat(2048)), "events": ["completed"]}), vec!["2048"]),
        (json!({"url": "https://example.com/h", "events": ["exploded"]}), vec!["notify", "exploded"]),
        (json!({"url": "https://example.com/h", "events": []}), vec!["notify.events", "empty"]),
    ];
    for (notify, needles) in cases {
        expect_error(c.submit(&job(notify)), StatusCode::UNPROCESSABLE_ENTITY, &needles);
    }
    // Without a secret nothing could be signed: refused, naming the flag.
    let plain = Coordinator::start(&[]).expect("coordinator");
    let scene = plain.upload_ok(cornell_demo_glb());
    let body = json!({"scene_id": scene, "width": 8, "height": 8, "spp": 1,
        "notify": {"url": "https://example.com/h", "events": ["completed"]}});
    expect_error(plain.submit(&body), StatusCode::UNPROCESSABLE_ENTITY, &["--webhook-secret"]);
}
