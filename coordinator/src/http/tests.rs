use super::*;
use crate::service::ServerConfig;
use pathfarm_common::job::RenderSettings;

async fn get(app: &Router, uri: &str) -> (StatusCode, Option<String>, serde_json::Value) {
    use tower::ServiceExt;
    let req = axum::http::Request::builder().uri(uri).body(axum::body::Body::empty()).expect("request");
    let resp = app.clone().oneshot(req).await.expect("response");
    let status = resp.status();
    let link = resp.headers().get(header::LINK).and_then(|v| v.to_str().ok()).map(str::to_string);
    let body = axum::body::to_bytes(resp.into_body(), 64 << 20).await.expect("body");
    (status, link, serde_json::from_slice(&body).expect("JSON"))
}

fn ids(v: &serde_json::Value) -> Vec<u64> {
    v.as_array().expect("array").iter().map(|j| j["id"].as_u64().expect("id")).collect()
}

async fn send(app: &Router, method: &str, uri: &str, body: Vec<u8>) -> (StatusCode, serde_json::Value) {
    use tower::ServiceExt;
    let req = axum::http::Request::builder()
        .method(method)
        .uri(uri)
        .header(header::CONTENT_TYPE, "application/json")
        .body(axum::body::Body::from(body))
        .expect("request");
    let resp = app.clone().oneshot(req).await.expect("response");
    let status = resp.status();
    let body = axum::body::to_bytes(resp.into_body(), 64 << 20).await.expect("body");
    (status, serde_json::from_slice(&body).unwrap_or(serde_json::Value::Null))
}

async fn status_of(app: &Router, method: &str, uri: &str) -> StatusCode {
    use tower::ServiceExt;
    let req = axum::http::Request::builder().method(method).uri(uri).body(axum::body::Body::empty()).expect("req");
    app.clone().oneshot(req).await.expect("response").status()
}

async fn upload(app: &Router, glb: Vec<u8>) -> String {
    let (status, scene) = send(app, "POST", "/api/v1/scenes", glb).await;
    assert_eq!(status, StatusCode::CREATED, "{scene}");
    scene["scene_id"].as_str().expect("scene_id").to_string()
}

async fn submit(app: &Router, scene: &str) -> u64 {
    let job = serde_json::json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1});
    let (status, created) = send(app, "POST", "/api/v1/jobs", serde_json::to_vec(&job).expect("json")).await;
    assert_eq!(status, StatusCode::CREATED, "{created}");
    created["id"].as_u64().expect("id")
}

/// `DELETE /scenes/{id}`: 409 naming the job while a running job uses the scene; once the
/// job is cancelled (finished, still referencing it) 204, after which the bundle is gone
/// (download 404, a second delete 404, a new job for it 422) while the finished job's image
/// is still served. A malformed id is 400.
#[tokio::test]
async fn a_scene_is_deleted_only_when_no_unfinished_job_uses_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    let state = Arc::new(AppState::new(cfg).expect("state"));
    let app = router(state.clone());
    let scene = upload(&app, pathfarm_common::scene::demo::cornell_demo_glb()).await;
    let job = submit(&app, &scene).await;
    {
        let mut farm = state.farm.lock();
        let w = farm.register("w".into(), 1, now_ms());
        assert!(farm.lease(w, now_ms()).expect("lease").is_some());
        assert_eq!(farm.job(job).expect("job").state, pathfarm_common::protocol::JobState::Running);
    }
    let uri = format!("/api/v1/scenes/{scene}");
    let (status, err) = send(&app, "DELETE", &uri, Vec::new()).await;
    assert_eq!(status, StatusCode::CONFLICT, "{err}");
    assert_eq!(err["error"]["code"], "scene_in_use");
    assert!(err["error"]["message"].as_str().is_some_and(|m| m.contains(&format!("[{job}]"))), "{err}");
    assert_eq!(status_of(&app, "GET", &uri).await, StatusCode::OK);

    let (status, _) = send(&app, "POST", &format!("/api/v1/jobs/{job}/cancel"), Vec::new()).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(status_of(&app, "DELETE", &uri).await, StatusCode::NO_CONTENT);
    assert_eq!(status_of(&app, "GET", &uri).await, StatusCode::NOT_FOUND);
    assert_eq!(status_of(&app, "DELETE", &uri).await, StatusCode::NOT_FOUND);
    assert!(!dir.path().join("scenes").join(format!("{scene}.bundle")).exists());
    assert!(!dir.path().join("scenes").join(format!("{scene}.json")).exists());
    let job2 = serde_json::json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1});
    let (status, err) = send(&app, "POST", "/api/v1/jobs", serde_json::to_vec(&job2).expect("json")).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{job}/image.exr")).await, StatusCode::OK);
    let (status, err) = send(&app, "DELETE", "/api/v1/scenes/not-a-scene", Vec::new()).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    assert_eq!(err["error"]["code"], "bad_id");
    // A restart does not bring it back.
    drop(app);
    drop(state);
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    assert!(AppState::new(cfg).expect("state").scenes.meta(&scene).is_none());
}

/// The maintenance loop removes a scene that no job references once it is older than
/// `scene_gc_after_ms`, and keeps one a (finished) job references.
#[tokio::test]
async fn unreferenced_old_scenes_are_garbage_collected() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    cfg.scene_gc_after_ms = Some(300);
    let server = crate::server::Server::start(cfg).await.expect("server");
    let app = router(server.state.clone());
    let used = upload(&app, pathfarm_common::scene::demo::cornell_demo_glb()).await;
    let unused = upload(&app, pathfarm_common::scene::demo::furnace_glb(1.0, 0.5)).await;
    let job = submit(&app, &used).await;
    let (status, _) = send(&app, "POST", &format!("/api/v1/jobs/{job}/cancel"), Vec::new()).await;
    assert_eq!(status, StatusCode::OK);
    // Young scenes stay, referenced or not.
    assert!(crate::service::collect_scenes(&server.state, now_ms() - 60_000).is_empty());
    let deadline = Instant::now() + std::time::Duration::from_secs(10);
    while server.state.scenes.meta(&unused).is_some() {
        assert!(Instant::now() < deadline, "the unreferenced scene was never collected");
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/scenes/{unused}")).await, StatusCode::NOT_FOUND);
    tokio::time::sleep(std::time::Duration::from_millis(600)).await;
    assert!(server.state.scenes.meta(&used).is_some(), "a referenced scene was collected");
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/scenes/{used}")).await, StatusCode::OK);
}

/// Only what is durable is acknowledged: once the database refuses writes, a submission is
/// 503 and the job is not there, a cancel is 503 naming the job; a full disk is 507.
#[tokio::test]
async fn changes_that_cannot_be_saved_are_not_acknowledged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    let state = Arc::new(AppState::new(cfg).expect("state"));
    let app = router(state.clone());
    let glb = pathfarm_common::scene::demo::cornell_demo_glb();
    let (status, scene) = send(&app, "POST", "/api/v1/scenes", glb).await;
    assert_eq!(status, StatusCode::CREATED);
    let job = serde_json::json!({"scene_id": scene["scene_id"], "width": 16, "height": 16, "spp": 1});
    let body = serde_json::to_vec(&job).expect("json");
    let (status, created) = send(&app, "POST", "/api/v1/jobs", body.clone()).await;
    assert_eq!(status, StatusCode::CREATED);
    let first = created["id"].as_u64().expect("id");

    state.store.lock().expect("store").refuse_writes();
    let (status, err) = send(&app, "POST", "/api/v1/jobs", body).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{err}");
    assert_eq!(err["error"]["code"], "storage_unavailable");
    let (_, _, list) = get(&app, "/api/v1/jobs").await;
    assert_eq!(ids(&list), vec![first], "the unsaved job must not exist");
    let (status, err) = send(&app, "POST", &format!("/api/v1/jobs/{first}/cancel"), Vec::new()).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{err}");
    assert!(err["error"]["message"].as_str().is_some_and(|m| m.contains(&format!("job {first}"))), "{err}");

    let full = rusqlite::Error::SqliteFailure(
        rusqlite::ffi::Error { code: rusqlite::ErrorCode::DiskFull, extended_code: 13 },
        None,
    );
    let e = crate::service::database_error(&anyhow::Error::from(full), "job 7");
    assert_eq!(ApiError::from(e).status, StatusCode::INSUFFICIENT_STORAGE);
}

/// Sequences through the API: bad `frames` and `order` are 422 naming them, a sequence that
/// cannot fit the film budget in sequence-preview order is 422 saying why, the frame list is
/// paged, a frame not started is 409 and a frame not in the set 404, the job's own image 409.
#[tokio::test]
async fn sequences_are_validated_listed_and_served_per_frame() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    cfg.farm.film_budget_bytes = Some(pathfarm_common::film::Film::bytes_for(16, 16) * 4);
    let state = Arc::new(AppState::new(cfg).expect("state"));
    let app = router(state.clone());
    let scene = upload(&app, pathfarm_common::scene::demo::cornell_demo_glb()).await;
    let job = |extra: serde_json::Value| {
        let mut j = serde_json::json!({"scene_id": scene, "width": 16, "height": 16, "spp": 2});
        for (k, v) in extra.as_object().expect("object") {
            j[k] = v.clone();
        }
        serde_json::to_vec(&j).expect("json")
    };
    for (extra, needle) in [
        (serde_json::json!({"frames": "3-1"}), "backwards"),
        (serde_json::json!({"frames": "1-100001"}), "more than 100000 frames"),
        (serde_json::json!({"frames": "a"}), "not a frame number"),
        (serde_json::json!({"frames": "1-3", "order": "shuffle"}), "order must be"),
        (serde_json::json!({"frames": "1-5", "order": "sequence_preview"}), "5 frames x"),
    ] {
        let (status, v) = send(&app, "POST", "/api/v1/jobs", job(extra.clone())).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{extra}: {v}");
        assert!(v["error"]["message"].as_str().is_some_and(|m| m.contains(needle)), "{extra}: {v}");
    }
    let (status, created) = send(&app, "POST", "/api/v1/jobs", job(serde_json::json!({"frames": "10-14"}))).await;
    assert_eq!(status, StatusCode::CREATED, "{created}");
    let id = created["id"].as_u64().expect("id");
    let (status, _, info) = get(&app, &format!("/api/v1/jobs/{id}")).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(info["frames"]["total"], 5);
    assert_eq!(info["frames"]["sequence"], true);
    assert_eq!(info["frames"]["current"], serde_json::json!([]), "a queued job holds no frame");
    let (_, link, page) = get(&app, &format!("/api/v1/jobs/{id}/frames?limit=2")).await;
    let frames = |v: &serde_json::Value| -> Vec<i64> {
        v.as_array().expect("array").iter().map(|f| f["frame"].as_i64().expect("frame")).collect()
    };
    assert_eq!(frames(&page), vec![10, 11]);
    assert_eq!(link.as_deref(), Some(format!("</api/v1/jobs/{id}/frames?limit=2&after=1>; rel=\"next\"").as_str()));
    let (_, link, page) = get(&app, &format!("/api/v1/jobs/{id}/frames?limit=2&after=3")).await;
    assert_eq!((frames(&page), link), (vec![14], None));
    assert_eq!(page[0]["state"], "pending");
    // Not started: 409. Frame 10 starts with the first lease (its film exists): served; frame
    // 14 has not started: 409.
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/10/preview.png")).await, StatusCode::CONFLICT);
    let w = state.farm.lock().register("w".into(), 1, 0);
    assert!(state.farm.lock().lease(w, 0).expect("lease").is_some_and(|g| g.unit.frame == 10));
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/10/preview.png")).await, StatusCode::OK);
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/14/image.exr")).await, StatusCode::CONFLICT);
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/9/image.exr")).await, StatusCode::NOT_FOUND);
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/x/image.exr")).await, StatusCode::BAD_REQUEST);
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/image.exr")).await, StatusCode::CONFLICT);
    // A single-frame job serves its one frame under the frame route too.
    let single = submit(&app, &scene).await;
    assert!(state.farm.lock().lease(w, 0).expect("lease").is_some_and(|g| g.job_id == single));
    assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{single}/frames/0/preview.png")).await, StatusCode::OK);
    assert_eq!(
        status_of(&app, "GET", &format!("/api/v1/jobs/{single}/frames/1/preview.png")).await,
        StatusCode::NOT_FOUND
    );
}

#[tokio::test]
async fn list_routes_are_paged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    let state = Arc::new(AppState::new(cfg).expect("state"));
    for _ in 0..7 {
        state.farm.lock().submit("s".into(), None, 0, RenderSettings::new(8, 8, 1), 0).expect("submit");
    }
    for i in 0..3 {
        state.farm.lock().register(format!("w{i}"), 1, 0);
    }
    let app = router(state.clone());
    let (status, link, v) = get(&app, "/api/v1/jobs?limit=3").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(ids(&v), vec![1, 2, 3]);
    assert_eq!(link.as_deref(), Some("</api/v1/jobs?limit=3&after=3>; rel=\"next\""));
    let (_, link, v) = get(&app, "/api/v1/jobs?limit=3&after=3").await;
    assert_eq!(ids(&v), vec![4, 5, 6]);
    assert!(link.is_some());
    let (_, link, v) = get(&app, "/api/v1/jobs?limit=3&after=6").await;
    assert_eq!((ids(&v), link), (vec![7], None));
    // Exactly a full last page: no next link.
    let (_, link, v) = get(&app, "/api/v1/jobs?limit=7").await;
    assert_eq!((ids(&v).len(), link), (7, None));
    // The default page holds all 7.
    let (_, link, v) = get(&app, "/api/v1/jobs").await;
    assert_eq!((ids(&v), link), ((1..=7).collect(), None));
    for bad in ["limit=0", "limit=1001"] {
        let (status, _, v) = get(&app, &format!("/api/v1/jobs?{bad}")).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{bad}");
        assert!(v["error"]["message"].as_str().is_some_and(|m| m.contains("1000")), "{v}");
    }
    let (status, _, _) = get(&app, "/api/v1/jobs?after=x").await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    let first_worker = state.farm.lock().workers(0)[0].id;
    let (_, link, v) = get(&app, "/api/v1/workers?limit=2").await;
    assert_eq!(ids(&v), vec![first_worker, first_worker + 1]);
    assert!(link.is_some_and(|l| l.contains(&format!("after={}", first_worker + 1))));
    let (_, link, v) = get(&app, &format!("/api/v1/workers?limit=2&after={}", first_worker + 1)).await;
    assert_eq!((ids(&v), link), (vec![first_worker + 2], None));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_reads_every_page() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    let server = crate::server::Server::start(cfg).await.expect("server");
    let n = pathfarm_common::protocol::MAX_PAGE_LIMIT + 5;
    for _ in 0..n {
        server.state.farm.lock().submit("s".into(), None, 0, RenderSettings::new(8, 8, 1), 0).expect("submit");
    }
    let url = server.url();
    let jobs = tokio::task::spawn_blocking(move || crate::client::Client::new(&url, None).expect("client").jobs())
        .await
        .expect("task")
        .expect("jobs");
    assert_eq!(jobs.iter().map(|j| j.id).collect::<Vec<_>>(), (1..=n as u64).collect::<Vec<_>>());
}

#[tokio::test]
async fn metrics_token_guards_metrics() {
    use tower::ServiceExt;
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    cfg.auth = Auth { client: Some("client-secret".into()), worker: Some("worker-secret".into()) };
    cfg.metrics_token = Some("metrics-secret".into());
    let app = router(Arc::new(AppState::new(cfg).expect("state")));
    let metrics = |auth: Option<&str>| {
        let mut b = axum::http::Request::builder().uri("/metrics");
        if let Some(a) = auth {
            b = b.header(header::AUTHORIZATION, a);
        }
        app.clone().oneshot(b.body(axum::body::Body::empty()).expect("request"))
    };
    for (auth, want) in [
        (None, StatusCode::UNAUTHORIZED),
        (Some("Bearer "), StatusCode::UNAUTHORIZED),
        (Some("Bearer metrics-secreT"), StatusCode::UNAUTHORIZED),
        (Some("Bearer client-secret"), StatusCode::UNAUTHORIZED),
        (Some("Bearer worker-secret"), StatusCode::UNAUTHORIZED),
        (Some("Basic metrics-secret"), StatusCode::UNAUTHORIZED),
        (Some("Bearer metrics-secret"), StatusCode::OK),
    ] {
        let resp = metrics(auth).await.expect("response");
        assert_eq!(resp.status(), want, "{auth:?}");
        let body = axum::body::to_bytes(resp.into_body(), 1 << 20).await.expect("body");
        let text = String::from_utf8_lossy(&body);
        if want == StatusCode::OK {
            assert!(text.contains("pathfarm_jobs{state=\"queued\"} 0"), "{text}");
        } else {
            assert!(text.contains("\"unauthorized\"") && !text.contains("pathfarm_jobs"), "{text}");
        }
    }
    // Without the flag, /metrics stays open (as the README says), whatever the API tokens.
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    cfg.auth = Auth { client: Some("client-secret".into()), worker: None };
    let app = router(Arc::new(AppState::new(cfg).expect("state")));
    let req = axum::http::Request::builder().uri("/metrics").body(axum::body::Body::empty()).expect("request");
    assert_eq!(app.oneshot(req).await.expect("response").status(), StatusCode::OK);
}

#[test]
fn empty_tokens_never_authenticate() {
    // Even when an empty token is configured (main refuses that at start-up).
    let auth = Auth { client: Some(String::new()), worker: Some("worker-secret".into()) };
    for given in [Some(""), None] {
        let e = authorize_token(&auth, given, &[Role::Client]).expect_err("empty token");
        assert_eq!(e.status, StatusCode::UNAUTHORIZED, "{given:?}");
    }
    let e = crate::http::events::authorize_client(&auth, &HeaderMap::new(), Some("")).expect_err("?token=");
    assert_eq!(e.status, StatusCode::UNAUTHORIZED);
    let mut h = HeaderMap::new();
    h.insert(header::AUTHORIZATION, HeaderValue::from_static("Bearer "));
    let e = crate::http::events::authorize_client(&auth, &h, None).expect_err("Bearer with nothing");
    assert_eq!(e.status, StatusCode::UNAUTHORIZED);
    assert!(!token_matches("", ""));
    assert!(authorize_token(&auth, Some("worker-secret"), &[Role::Worker]).is_ok());
}

#[test]
fn banded_resolve_equals_whole_resolve() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    let state = AppState::new(cfg).expect("state");
    // 37 rows: bands of 16, 16 and 5.
    let id = state.farm.lock().submit("s".into(), None, 0, RenderSettings::new(23, 37, 4), 0).expect("submit");
    let expected = {
        let mut farm = state.farm.lock();
        // The job's film exists from its first lease.
        let w = farm.register("w".into(), 1, 0);
        assert!(farm.lease(w, 0).expect("lease").is_some());
        let mut film = farm.job_mut(id).expect("job").film_mut().expect("film");
        let mut x: u64 = 0x1234_5678_9abc_def1;
        for p in film.sums.iter_mut() {
            let mut b = [0u8; pathfarm_common::film::PIXEL_BYTES];
            for c in b.chunks_exact_mut(8) {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                c.copy_from_slice(&(x >> 20).to_le_bytes());
            }
            *p = pathfarm_common::film::PixelSums::read_le(&b);
            // Weights stay small so most pixels resolve to means; depths are numbers (a NaN
            // would differ from itself).
            p.weight %= 5;
            p.depth = ((x % 1000) as f32 * 0.25).to_bits();
        }
        film.resolve()
    };
    let banded = resolve_banded(&state, id).expect("banded");
    assert_eq!(banded, expected);
    assert!(matches!(resolve_banded(&state, id + 1), Err(e) if e.kind == crate::service::Failure::NotFound));
}

/// `Server::shutdown` (the shutdown future of `server::run`) stops accepting and the loops and
/// writes a final checkpoint: a merged unit and a priority change that no checkpoint loop saw
/// (its interval is an hour) are there when the data dir is opened again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_writes_a_final_checkpoint() {
    use pathfarm_common::film::{SampleValue, TileAccum, add_sample};
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
    cfg.checkpoint_interval = Duration::from_secs(3600);
    let server = crate::server::Server::start(cfg.clone()).await.expect("server");
    let addr = server.addr;
    let app = router(server.state.clone());
    let scene = upload(&app, pathfarm_common::scene::demo::cornell_demo_glb()).await;
    let job = json_of(&app, serde_json::json!({"scene_id": scene, "width": 64, "height": 64, "spp": 8})).await;
    {
        let mut farm = server.state.farm.lock();
        assert!(farm.job(job).expect("job").plan.unit_count() > 1, "the job must stay running");
        let w = farm.register("w".into(), 1, now_ms());
        let g = farm.lease(w, now_ms()).expect("lease").expect("a unit");
        let mut accum = TileAccum::new(g.tile);
        for y in 0..g.tile.y1 - g.tile.y0 {
            for x in 0..g.tile.x1 - g.tile.x0 {
                for _ in g.pass.samples() {
                    add_sample(accum.pixel_mut(x, y), &SampleValue { radiance: [0.5; 3], ..Default::default() });
                }
            }
        }
        let frame = UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None };
        farm.accept(g.lease_id, frame, now_ms()).expect("accept");
        farm.set_priority(job, 7).expect("priority");
    }
    assert!(!dir.path().join(format!("jobs/{job}/checkpoint.bin")).exists(), "no checkpoint before the shutdown");
    server.shutdown().await.expect("shutdown");
    assert!(tokio::net::TcpStream::connect(addr).await.is_err(), "still accepting after the shutdown");
    assert!(dir.path().join(format!("jobs/{job}/checkpoint.bin")).exists(), "no final checkpoint");
    let state = AppState::new(cfg).expect("reopen");
    let farm = state.farm.lock();
    let j = farm.job(job).expect("job restored");
    assert_eq!((j.priority, j.units_merged), (7, 1));
}

async fn json_of(app: &Router, job: serde_json::Value) -> u64 {
    let (status, created) = send(app, "POST", "/api/v1/jobs", serde_json::to_vec(&job).expect("json")).await;
    assert_eq!(status, StatusCode::CREATED, "{created}");
    created["id"].as_u64().expect("id")
}
