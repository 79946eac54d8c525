//! A panic inside a handler becomes a 500 with the JSON error body, and the server keeps
//! serving: also when the handler panicked while holding the farm's lock.
//!
//! No production route panics on purpose, so the test merges panicking routes into the real
//! router (`api::routes` + `api::with_layers`) and serves it on 127.0.0.1.

use axum::extract::State;
use axum::routing::get;
use pathfarm_common::protocol::{API, ErrorBody};
use pathfarm_coordinator::http as api;
use pathfarm_coordinator::server::{AppState, ServerConfig};
use std::sync::Arc;

async fn boom() -> &'static str {
    panic!("boom in a handler")
}

async fn boom_locked(State(s): State<Arc<AppState>>) -> &'static str {
    let _farm = s.farm.lock();
    panic!("boom while holding the farm lock")
}

async fn serve(state: Arc<AppState>) -> String {
    let app = api::with_layers(
        api::routes(state.clone()).route("/test/panic", get(boom)).route("/test/panic-locked", get(boom_locked)),
        state,
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(async move { axum::serve(listener, app).await });
    format!("http://{addr}")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_handler_is_a_500_json_and_the_server_keeps_serving() {
    let dir = tempfile::tempdir().expect("tempdir");
    let state = Arc::new(
        AppState::new(ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into())).expect("state"),
    );
    let url = serve(state).await;
    let http = reqwest::Client::new();
    for _ in 0..3 {
        for path in ["/test/panic", "/test/panic-locked"] {
            let r = http.get(format!("{url}{path}")).send().await.expect("request");
            assert_eq!(r.status(), reqwest::StatusCode::INTERNAL_SERVER_ERROR, "{path}");
            let body: ErrorBody = r.json().await.expect("JSON error body");
            assert_eq!(body.error.code, "internal");
            assert!(body.error.message.contains("panicked"), "{}", body.error.message);
            // Still serving, and the farm (whose lock was poisoned) still answers.
            let r = http.get(format!("{url}/healthz")).send().await.expect("healthz");
            assert_eq!(r.text().await.expect("body"), "ok");
            let r = http.get(format!("{url}{API}/jobs")).send().await.expect("jobs");
            assert_eq!(r.status(), reqwest::StatusCode::OK);
            let r = http
                .post(format!("{url}{API}/workers/register"))
                .json(&serde_json::json!({"name": "w", "threads": 1}))
                .send()
                .await
                .expect("register");
            assert_eq!(r.status(), reqwest::StatusCode::OK);
            let r = http.get(format!("{url}/metrics")).send().await.expect("metrics");
            assert_eq!(r.status(), reqwest::StatusCode::OK);
        }
    }
}
