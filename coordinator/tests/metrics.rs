//! `GET /metrics` is valid exposition text: every sample line is `name{labels} value`, every
//! metric family has one `# TYPE`, no family or series twice, the text ends with `# EOF`; every
//! `pathfarm_*` metric of the versions before `prometheus-client` is there under its old name,
//! and so are the standard process metrics (Linux).

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use pathfarm_coordinator::server::{AppState, ServerConfig};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::time::Duration;
use tower::ServiceExt;

/// One sample: the series (name and labels as written) and its value.
struct Sample {
    name: String,
    labels: String,
    value: f64,
}

fn is_name(s: &str) -> bool {
    let mut c = s.chars();
    c.next().is_some_and(|f| f.is_ascii_alphabetic() || f == '_' || f == ':')
        && c.all(|x| x.is_ascii_alphanumeric() || x == '_' || x == ':')
}

/// `k="v",k2="v2"`: every pair a label name and a quoted value (no escapes in ours).
fn labels_ok(s: &str) -> bool {
    s.is_empty()
        || s.split(',').all(|kv| {
            kv.split_once('=')
                .is_some_and(|(k, v)| is_name(k) && v.len() >= 2 && v.starts_with('"') && v.ends_with('"'))
        })
}

/// Parses the exposition, panicking with the offending line on any violation. Returns the
/// families (name -> type) and the samples.
fn parse(text: &str) -> (BTreeMap<String, String>, Vec<Sample>) {
    let mut types = BTreeMap::new();
    let mut samples = Vec::new();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.last().copied(), Some("# EOF"), "the exposition must end with # EOF");
    for line in &lines[..lines.len() - 1] {
        if let Some(rest) = line.strip_prefix("# ") {
            let mut it = rest.splitn(3, ' ');
            let (kind, name) = (it.next().unwrap_or(""), it.next().unwrap_or(""));
            assert!(is_name(name), "bad metric name in {line:?}");
            match kind {
                "TYPE" => {
                    let t = it.next().unwrap_or("").to_string();
                    assert!(
                        ["counter", "gauge", "histogram", "summary", "info", "stateset", "unknown"]
                            .contains(&t.as_str()),
                        "{line:?}"
                    );
                    assert!(types.insert(name.to_string(), t).is_none(), "# TYPE {name} twice");
                }
                "HELP" | "UNIT" => {}
                _ => panic!("unknown comment {line:?}"),
            }
            continue;
        }
        let (series, value) = line.rsplit_once(' ').unwrap_or_else(|| panic!("no value in {line:?}"));
        let value: f64 = match value {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            v => v.parse().unwrap_or_else(|_| panic!("bad value in {line:?}")),
        };
        let (name, labels) = match series.split_once('{') {
            Some((n, l)) => (n, l.strip_suffix('}').unwrap_or_else(|| panic!("unclosed labels in {line:?}"))),
            None => (series, ""),
        };
        assert!(is_name(name) && labels_ok(labels), "bad sample line {line:?}");
        samples.push(Sample { name: name.into(), labels: labels.into(), value });
    }
    // Every sample belongs to a declared family, under a suffix its type allows; no series twice.
    let mut seen = BTreeSet::new();
    for s in &samples {
        let family = types.iter().find(|(f, t)| {
            let suffixes: &[&str] = match t.as_str() {
                "counter" => &["_total", "_created"],
                "histogram" => &["_bucket", "_sum", "_count", "_created"],
                _ => &[""],
            };
            suffixes.iter().any(|suf| s.name.strip_suffix(suf) == Some(f.as_str()))
        });
        assert!(family.is_some(), "sample {} has no # TYPE", s.name);
        assert!(seen.insert((s.name.clone(), s.labels.clone())), "series {}{{{}}} twice", s.name, s.labels);
    }
    (types, samples)
}

#[tokio::test]
async fn metrics_are_valid_exposition_with_process_metrics() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), tmp.path().to_path_buf());
    let state = Arc::new(AppState::new(cfg).expect("state"));
    state.metrics.observe_merge(Duration::from_micros(300));
    state.metrics.observe_merge(Duration::from_secs(1));
    let app = pathfarm_coordinator::http::router(state);
    let resp =
        app.oneshot(Request::builder().uri("/metrics").body(Body::empty()).expect("request")).await.expect("response");
    assert_eq!(resp.status(), StatusCode::OK);
    let ct = resp.headers()[header::CONTENT_TYPE].to_str().expect("content type").to_string();
    assert!(ct.starts_with("application/openmetrics-text"), "{ct}");
    let text = String::from_utf8(axum::body::to_bytes(resp.into_body(), 1 << 20).await.expect("body").to_vec())
        .expect("utf-8");
    let (types, samples) = parse(&text);
    let value = |name: &str, labels: &str| {
        samples
            .iter()
            .find(|s| s.name == name && s.labels == labels)
            .unwrap_or_else(|| panic!("no {name}{{{labels}}} in\n{text}"))
            .value
    };
    // The names and labels of the hand-written exposition, unchanged.
    for s in ["queued", "running", "paused", "completed", "failed", "cancelled"] {
        assert_eq!(value("pathfarm_jobs", &format!("state=\"{s}\"")), 0.0);
    }
    for s in ["idle", "busy", "offline"] {
        assert_eq!(value("pathfarm_workers", &format!("state=\"{s}\"")), 0.0);
    }
    for c in [
        "pathfarm_units_leased_total",
        "pathfarm_units_merged_total",
        "pathfarm_units_failed_total",
        "pathfarm_leases_expired_total",
        "pathfarm_results_rejected_total",
        "pathfarm_samples_total",
        "pathfarm_bytes_received_total",
        "pathfarm_connections_timed_out_total",
        "pathfarm_connections_evicted_total",
        "pathfarm_connections_refused_total",
        "pathfarm_leases_held",
        "pathfarm_connections_open",
    ] {
        assert_eq!(value(c, ""), 0.0, "{c}");
    }
    // The two observations: one at 300 us, one above the last bucket.
    assert_eq!(value("pathfarm_merge_seconds_bucket", "le=\"0.00025\""), 0.0);
    assert_eq!(value("pathfarm_merge_seconds_bucket", "le=\"0.0005\""), 1.0);
    assert_eq!(value("pathfarm_merge_seconds_bucket", "le=\"+Inf\""), 2.0);
    assert_eq!(value("pathfarm_merge_seconds_count", ""), 2.0);
    assert!((value("pathfarm_merge_seconds_sum", "") - 1.0003).abs() < 1e-9);
    assert_eq!(value("pathfarm_lease_seconds_count", ""), 0.0);
    assert_eq!(types["pathfarm_merge_seconds"], "histogram");
    if cfg!(target_os = "linux") {
        assert_eq!(types["process_cpu_seconds"], "counter");
        assert!(value("process_resident_memory_bytes", "") > 0.0, "{text}");
        assert!(value("process_virtual_memory_bytes", "") >= value("process_resident_memory_bytes", ""));
        assert!(value("process_cpu_seconds_total", "") >= 0.0);
        assert!(value("process_open_fds", "") >= 3.0);
        assert!(value("process_start_time_seconds", "") > 1.577e9);
        if types.contains_key("process_max_fds") {
            assert!(value("process_max_fds", "") >= value("process_open_fds", ""));
        }
    }
}
