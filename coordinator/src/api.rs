//! The REST API (axum): clients' routes, workers' routes, images, health and metrics.
//!
//! Every error is JSON `{"error": {"code", "message"}}` with a 4xx/5xx status; a panic inside a
//! handler becomes a 500 and the server keeps serving.

use crate::farm::FarmError;
use crate::server::{AppState, Auth, now_ms};
use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put};
use axum::{Json, Router};
use pathfarm_common::film::ImageLayers;
use pathfarm_common::protocol::{
    API, DEFAULT_PAGE_LIMIT, ErrorBody, ErrorDetail, JobCreated, JobId, JobInfo, JobRequest, LeaseId, MAX_PAGE_LIMIT,
    RegisterRequest, Registered, ReleaseRequest, ResultAccepted, SceneCreated, UnitResultFrame, WORKER_SECRET_HEADER,
    WorkerId, max_result_bytes, validate_tags,
};
use pathfarm_common::scene::bundle::is_scene_id;
use serde::Deserialize;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// An error response.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub code: &'static str,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        Self { status, code, message: message.into() }
    }
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not_found", message)
    }
    pub fn unprocessable(code: &'static str, message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, code, message)
    }
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = ErrorBody { error: ErrorDetail { code: self.code.into(), message: self.message } };
        (self.status, Json(body)).into_response()
    }
}

impl From<FarmError> for ApiError {
    fn from(e: FarmError) -> Self {
        let (status, code) = match &e {
            FarmError::NoJob(_) => (StatusCode::NOT_FOUND, "not_found"),
            FarmError::NoWorker(_) => (StatusCode::NOT_FOUND, "unknown_worker"),
            FarmError::LeaseLost(_) => (StatusCode::CONFLICT, "lease_lost"),
            FarmError::ResultMismatch { .. } => (StatusCode::UNPROCESSABLE_ENTITY, "result_mismatch"),
            FarmError::BadState { .. } => (StatusCode::CONFLICT, "bad_state"),
            FarmError::InvalidJob(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid_job"),
            FarmError::OverBudget(_) => (StatusCode::UNPROCESSABLE_ENTITY, "over_budget"),
            FarmError::WrongWorker(_) => (StatusCode::FORBIDDEN, "wrong_worker"),
        };
        ApiError::new(status, code, e.to_string())
    }
}

type ApiResult<T> = Result<T, ApiError>;

fn parse_id(kind: &str, raw: &str) -> ApiResult<u64> {
    raw.parse()
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "bad_id", format!("{kind} id {raw:?} is not a number")))
}

/// Who a token belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Client,
    Worker,
}

/// Constant-time comparison; an empty token never matches (not even an empty one configured).
pub fn token_matches(given: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    !expected.is_empty() && given.len() == expected.len() && bool::from(given.as_bytes().ct_eq(expected.as_bytes()))
}

/// The bearer token of a request, if any.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
}

/// Checks `token` for a route that `allowed` roles may use: missing or unknown 401, the wrong
/// kind 403; with no tokens configured everything is allowed.
pub fn authorize_token(auth: &Auth, token: Option<&str>, allowed: &[Role]) -> ApiResult<()> {
    if auth.client.is_none() && auth.worker.is_none() {
        return Ok(());
    }
    let token = token
        .filter(|t| !t.is_empty())
        .ok_or_else(|| ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", "missing bearer token"))?;
    let role = if auth.client.as_deref().is_some_and(|t| token_matches(token, t)) {
        Role::Client
    } else if auth.worker.as_deref().is_some_and(|t| token_matches(token, t)) {
        Role::Worker
    } else {
        return Err(ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", "invalid token"));
    };
    if allowed.contains(&role) {
        Ok(())
    } else {
        Err(ApiError::new(StatusCode::FORBIDDEN, "forbidden", format!("a {role:?} token may not use this route")))
    }
}

/// The `X-Pathfarm-Worker-Secret` header of a request, if any.
pub fn worker_secret(headers: &HeaderMap) -> Option<&str> {
    headers.get(WORKER_SECRET_HEADER).and_then(|v| v.to_str().ok())
}

/// A new worker's secret: 32 bytes from the operating system's CSPRNG, hex-encoded.
fn new_worker_secret() -> ApiResult<String> {
    let mut buf = [0u8; 32];
    getrandom::getrandom(&mut buf).map_err(|e| {
        tracing::error!(error = %e, "the operating system's random number generator failed");
        ApiError::internal("could not make a worker secret")
    })?;
    Ok(hex::encode(buf))
}

fn authorize(state: &AppState, headers: &HeaderMap, allowed: &[Role]) -> ApiResult<()> {
    authorize_token(&state.auth, bearer(headers), allowed)
}

async fn require_client(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Client]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

async fn require_worker(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Worker]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

async fn require_any(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Client, Role::Worker]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

/// The whole router.
pub fn router(state: Arc<AppState>) -> Router {
    with_layers(routes(state.clone()), state)
}

/// Every route, before the fallback, the error layers and the state are added; tests merge
/// routes of their own into this and finish it with [`with_layers`].
pub fn routes(state: Arc<AppState>) -> Router<Arc<AppState>> {
    let upload_limit = state.config.max_upload_bytes;
    let client = Router::new()
        .route(
            "/scenes",
            post(upload_scene)
                .layer(DefaultBodyLimit::max(upload_limit))
                .layer(middleware::from_fn_with_state(state.clone(), declared_length_within_limit)),
        )
        .route("/scenes/{id}", delete(delete_scene))
        .route("/jobs", post(create_job).get(list_jobs))
        .route("/jobs/{id}", get(get_job).delete(delete_job))
        .route("/jobs/{id}/cancel", post(cancel_job))
        .route("/jobs/{id}/pause", post(pause_job))
        .route("/jobs/{id}/resume", post(resume_job))
        .route("/jobs/{id}/priority", put(set_priority))
        .route("/jobs/{id}/log", get(job_log))
        .route("/jobs/{id}/tiles", get(job_tiles))
        .route("/jobs/{id}/image.exr", get(job_exr))
        .route("/jobs/{id}/preview.png", get(job_png))
        .route("/jobs/{id}/frames", get(job_frames))
        .route("/jobs/{id}/frames/{frame}/image.exr", get(frame_exr))
        .route("/jobs/{id}/frames/{frame}/preview.png", get(frame_png))
        .route("/workers", get(list_workers))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_client));
    let worker = Router::new()
        .route("/workers/register", post(register))
        .route("/workers/{id}/heartbeat", post(heartbeat))
        .route("/workers/{id}/lease", post(lease))
        // The result handler reads its body itself, bounded by the lease's tile.
        .route("/leases/{id}/result", put(upload_result))
        .route("/leases/{id}/release", post(release))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_worker));
    let shared = Router::new()
        .route("/scenes/{id}", get(download_scene))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_any));
    // Own auth (the token may come as `?token=`, for EventSource), and the public API document.
    let live = Router::new()
        .route("/events", get(crate::events::events))
        .route("/openapi.json", get(crate::openapi::openapi_json));
    let api = Router::new().merge(client).merge(worker).merge(shared).merge(live);
    Router::new()
        .nest(API, api)
        .route("/healthz", get(|| async { "ok" }))
        .route("/metrics", get(metrics))
        .merge(crate::dashboard::routes(&state))
}

/// The fallback (404), JSON bodies for axum's own errors, panics turned into 500s, the state.
pub fn with_layers(routes: Router<Arc<AppState>>, state: Arc<AppState>) -> Router {
    routes
        .fallback(|| async { ApiError::not_found("no such route") })
        .layer(middleware::from_fn_with_state(state.clone(), json_errors))
        .layer(tower_http::catch_panic::CatchPanicLayer::custom(|_: Box<dyn std::any::Any + Send>| {
            ApiError::internal("the request handler panicked; the server keeps running").into_response()
        }))
        .with_state(state)
}

/// Gives the errors axum makes itself (extractor rejections: body over the limit, bad path or
/// query, method not allowed) the JSON error body every other error has.
async fn json_errors(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    let resp = next.run(req).await;
    let status = resp.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return resp;
    }
    let is_json = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if is_json {
        return resp;
    }
    let (parts, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 64 << 10).await.unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let (code, message) = match status {
        StatusCode::PAYLOAD_TOO_LARGE => (
            "payload_too_large",
            format!("request body is larger than the upload limit of {} bytes ({text})", state.config.max_upload_bytes),
        ),
        StatusCode::METHOD_NOT_ALLOWED => ("method_not_allowed", "method not allowed on this route".to_string()),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => ("unsupported_media_type", text),
        s if s.is_server_error() => ("internal", text),
        _ => ("bad_request", text),
    };
    let message = if message.is_empty() { status.canonical_reason().unwrap_or("error").to_string() } else { message };
    let mut out = ApiError::new(status, code, message).into_response();
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        // The rest of the body is never read, so the connection cannot serve another request:
        // say so, or a client's pool reuses it and its next request fails.
        out.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    for (name, value) in &parts.headers {
        if name != header::CONTENT_TYPE && name != header::CONTENT_LENGTH {
            out.headers_mut().entry(name).or_insert_with(|| value.clone());
        }
    }
    out
}

// ------------------------------------------------------------------------------------ scenes

#[utoipa::path(
    post,
    path = "/api/v1/scenes",
    tag = "scenes",
    summary = "Upload a scene (.glb, .gltf or tar bundle); content-addressed by SHA-256",
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "A .glb, a self-contained .gltf, or a tar of a .gltf with its files"),
    security(("client_token" = [])),
    responses((status = 201, description = "Stored (or already stored)", body = SceneCreated), (status = 422, description = "Not a loadable scene, or over a limit", body = ErrorBody), (status = 413, description = "Body larger than --max-upload-mb (a declared `Content-Length` above it is refused before the body is read)", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn upload_scene(State(state): State<Arc<AppState>>, body: Bytes) -> ApiResult<(StatusCode, Json<SceneCreated>)> {
    if body.is_empty() {
        return Err(ApiError::unprocessable("invalid_scene", "empty body: send a .glb, a .gltf or a tar bundle"));
    }
    state.metrics.bytes_received.fetch_add(body.len() as u64, Ordering::Relaxed);
    // Decoding may use up to max_texture_bytes: only a few at once.
    let _permit = state.scene_decodes.acquire().await.map_err(|_| ApiError::internal("scene decoding is shut down"))?;
    let st = state.clone();
    let created = tokio::task::spawn_blocking(move || st.scenes.add(&body, &st.load_options()))
        .await
        .map_err(|e| ApiError::internal(format!("scene task: {e}")))??;
    Ok((StatusCode::CREATED, Json(created)))
}

#[utoipa::path(
    get,
    path = "/api/v1/scenes/{id}",
    tag = "scenes",
    summary = "Download a scene bundle (workers and clients)",
    params(("id" = String, Path, description = "Scene id (SHA-256, hex)")),
    security(("client_token" = []), ("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 200, description = "The bundle bytes", body = Vec<u8>, content_type = "application/octet-stream"), (status = 404, description = "No such scene", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn download_scene(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<Response> {
    if !is_scene_id(&id) {
        return Err(ApiError::not_found(format!("scene {id:?} does not exist")));
    }
    let path = state.scenes.bundle_path(&id);
    let bytes = tokio::fs::read(&path).await.map_err(|_| ApiError::not_found(format!("scene {id} does not exist")))?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

#[utoipa::path(
    delete,
    path = "/api/v1/scenes/{id}",
    tag = "scenes",
    summary = "Delete a scene bundle that no unfinished job uses (finished jobs keep their images)",
    params(("id" = String, Path, description = "Scene id (SHA-256, hex)")),
    security(("client_token" = [])),
    responses((status = 204, description = "Deleted"), (status = 409, description = "Queued, running or paused jobs use the scene (named in the message)", body = ErrorBody), (status = 404, description = "No such scene", body = ErrorBody), (status = 400, description = "The id is not a scene id (64 lowercase hex digits)", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn delete_scene(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    if !is_scene_id(&id) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_id",
            format!("scene id {id:?} is not a SHA-256 in lowercase hex"),
        ));
    }
    // Under the farm lock: no job can be submitted for the scene while it is checked and removed.
    let farm = state.farm.lock();
    let users: Vec<JobId> = farm.jobs().filter(|j| j.scene_id == id && !j.state.is_finished()).map(|j| j.id).collect();
    if !users.is_empty() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "scene_in_use",
            format!("scene {id} is used by unfinished jobs {users:?}; cancel or finish them first"),
        ));
    }
    let removed = state.scenes.remove(&id).map_err(|e| crate::server::storage_error(&e, "the scene's deletion"))?;
    drop(farm);
    if removed { Ok(StatusCode::NO_CONTENT) } else { Err(ApiError::not_found(format!("scene {id} does not exist"))) }
}

// ------------------------------------------------------------------------------------ jobs

#[utoipa::path(
    post,
    path = "/api/v1/jobs",
    tag = "jobs",
    summary = "Submit a job",
    request_body = crate::openapi::JobRequestBody,
    security(("client_token" = [])),
    responses((status = 201, description = "Queued", body = JobCreated), (status = 400, description = "Not JSON", body = ErrorBody), (status = 422, description = "Invalid settings, `notify` or unknown scene", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn create_job(State(state): State<Arc<AppState>>, body: Bytes) -> ApiResult<(StatusCode, Json<JobCreated>)> {
    let value: serde_json::Value = serde_json::from_slice(&body)
        .map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, "bad_json", format!("job body is not JSON: {e}")))?;
    let req = JobRequest::from_json(value).map_err(|e| ApiError::unprocessable("invalid_job", e))?;
    if req.notify.is_some() && state.config.webhooks.secret.is_none() {
        return Err(ApiError::unprocessable(
            "invalid_job",
            "notify needs a coordinator started with --webhook-secret (PATHFARM_WEBHOOK_SECRET) to sign the \
             notifications; this one has none",
        ));
    }
    let meta = state.scenes.meta(&req.scene_id).ok_or_else(|| {
        ApiError::unprocessable("unknown_scene", format!("scene_id {:?} has not been uploaded", req.scene_id))
    })?;
    if let Some(cam) = req.settings.camera
        && cam >= meta.cameras
    {
        return Err(ApiError::unprocessable(
            "invalid_job",
            format!("camera {cam} does not exist (the scene has {} cameras)", meta.cameras),
        ));
    }
    let mut warnings = Vec::new();
    if meta.warnings.iter().any(|w| w == pathfarm_common::scene::NO_LIGHT_WARNING) && req.settings.environment.is_none()
    {
        warnings.push(pathfarm_common::scene::DARK_JOB_WARNING.to_string());
    }
    let id = {
        let mut farm = state.farm.lock();
        // Checked again under the farm lock: a DELETE of the scene (or its GC) holds it too.
        if state.scenes.meta(&req.scene_id).is_none() {
            return Err(ApiError::unprocessable(
                "unknown_scene",
                format!("scene_id {:?} has been deleted", req.scene_id),
            ));
        }
        let spec = crate::farm::JobSpec {
            scene_id: req.scene_id,
            name: req.name,
            priority: req.priority,
            settings: req.settings,
            requires: req.requires,
            frames: req.frames,
            order: req.order,
        };
        let id = farm.submit_job(spec, now_ms())?;
        farm.set_notify(id, req.notify)?;
        for w in &warnings {
            farm.log_job(id, format!("warning: {w}"));
        }
        id
    };
    tracing::info!(job = id, "job submitted");
    if let Err(e) = state.persist_job(id) {
        // Not durable, so not accepted: the job goes away again.
        state.farm.lock().withdraw(id);
        return Err(e);
    }
    state.work_ready.notify_waiters();
    state.publish("job", id);
    for w in &warnings {
        tracing::warn!(job = id, "{w}");
    }
    Ok((StatusCode::CREATED, Json(JobCreated { id, warnings })))
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs",
    tag = "jobs",
    summary = "List jobs with their progress, a page at a time",
    description = "Jobs in id order, at most `limit` (default 100, at most 1000) with ids above `after`. \
        When more follow, the `Link` header holds the next page's URL (`rel=\"next\"`); a page shorter \
        than `limit` is the last.",
    params(PageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of jobs", body = Vec<pathfarm_common::protocol::JobInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more jobs follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 400, description = "`limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn list_jobs(State(state): State<Arc<AppState>>, Query(q): Query<PageQuery>) -> ApiResult<Response> {
    let limit = q.limit()?;
    let mut page: Vec<JobInfo> = {
        let farm = state.farm.lock();
        let now = now_ms();
        farm.jobs_after(q.after).take(limit + 1).map(|j| j.info(now)).collect()
    };
    let more = page.len() > limit;
    page.truncate(limit);
    let last = page.last().map(|j| j.id);
    Ok(paged(Json(page), "/jobs", limit, more, last))
}

/// Query of the list routes: `?limit=N&after=ID`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PageQuery {
    /// Items per page: 1 to 1000, default 100.
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<usize>,
    /// Only items with an id above this: the last id of the previous page.
    pub after: Option<u64>,
}

impl PageQuery {
    fn limit(&self) -> ApiResult<usize> {
        let limit = self.limit.unwrap_or(DEFAULT_PAGE_LIMIT);
        if !(1..=MAX_PAGE_LIMIT).contains(&limit) {
            return Err(ApiError::unprocessable(
                "invalid_query",
                format!("limit must be between 1 and {MAX_PAGE_LIMIT}, got {limit}"),
            ));
        }
        Ok(limit)
    }
}

/// A page of a list: ids ascending; when more items follow, a `Link: <...>; rel="next"` header
/// gives the next page's URL.
fn paged(body: impl IntoResponse, path: &str, limit: usize, more: bool, last: Option<u64>) -> Response {
    let mut resp = body.into_response();
    if more
        && let Some(last) = last
        && let Ok(v) = HeaderValue::from_str(&format!("<{API}{path}?limit={limit}&after={last}>; rel=\"next\""))
    {
        resp.headers_mut().insert(header::LINK, v);
    }
    resp
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}",
    tag = "jobs",
    summary = "A job's state and progress",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job", body = pathfarm_common::protocol::JobInfo), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn get_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    Ok(Json(farm.job(id)?.info(now_ms())))
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/log",
    tag = "jobs",
    summary = "A job's log (retries, failures, blocklists), oldest first",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "Log lines", body = Vec<String>), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn job_log(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    Ok(Json(farm.job(id)?.log.clone()))
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/tiles",
    tag = "jobs",
    summary = "Per-tile progress (the tile map)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "Tiles and passes merged per tile", body = crate::openapi::TileProgress), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn job_tiles(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    let job = farm.job(id)?;
    Ok(Json(serde_json::json!({
        "tiles": job.plan.tiles,
        "passes_merged": job.tile_passes(),
        "passes_total": job.plan.passes.len(),
    })))
}

async fn job_action(
    state: Arc<AppState>,
    id: String,
    action: impl FnOnce(&mut crate::farm::Farm, JobId, u64) -> Result<(), FarmError>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let info = {
        let mut farm = state.farm.lock();
        action(&mut farm, id, now_ms())?;
        farm.job(id)?.info(now_ms())
    };
    // The change is in effect; if it could not be saved, say so (the checkpoint loop retries).
    state.persist_job(id)?;
    state.work_ready.notify_waiters();
    state.publish("job", id);
    Ok(Json(info))
}

#[utoipa::path(
    post,
    path = "/api/v1/jobs/{id}/cancel",
    tag = "jobs",
    summary = "Cancel a job",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn cancel_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.cancel(id, now)).await
}

#[utoipa::path(
    post,
    path = "/api/v1/jobs/{id}/pause",
    tag = "jobs",
    summary = "Pause a job (leased units finish)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn pause_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.pause(id, now)).await
}

#[utoipa::path(
    post,
    path = "/api/v1/jobs/{id}/resume",
    tag = "jobs",
    summary = "Resume a paused job",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn resume_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.resume(id, now)).await
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PriorityBody {
    priority: i32,
}

#[utoipa::path(
    put,
    path = "/api/v1/jobs/{id}/priority",
    tag = "jobs",
    summary = "Change a job's priority (higher first)",
    params(("id" = u64, Path, description = "Job id")),
    request_body = crate::openapi::PriorityBody,
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 422, description = "Bad body", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn set_priority(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<impl IntoResponse> {
    let p: PriorityBody = serde_json::from_slice(&body)
        .map_err(|e| ApiError::unprocessable("invalid_body", format!("expected {{\"priority\": N}}: {e}")))?;
    job_action(state, id, move |f, id, _| f.set_priority(id, p.priority)).await
}

#[utoipa::path(
    delete,
    path = "/api/v1/jobs/{id}",
    tag = "jobs",
    summary = "Delete a job and its images",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 204, description = "Deleted"), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn delete_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let id = parse_id("job", &id)?;
    state.farm.lock().delete(id)?;
    state.forget_job(id)?;
    state.delete_job_files(id);
    state.publish("job", id);
    Ok(StatusCode::NO_CONTENT)
}

/// Rows of the film resolved per hold of the farm lock.
const RESOLVE_BAND_ROWS: usize = 16;

/// Resolves a job's film a band of rows at a time, taking the farm lock once per band: a
/// 1024 x 1024 film takes ~200 ms to resolve, during which leases and merges would wait.
/// Each band copies its sums (splats included) under one lock, so every
/// pixel is consistent; bands may be a few units apart, as tiles are anyway.
pub fn resolve_banded(state: &AppState, id: JobId) -> ApiResult<ImageLayers> {
    resolve_film_banded(state, id, None)
}

/// The film of job `id` (`frame`: `None` the job's image, `Some(n)` frame `n`), given to `f`.
/// A sequence has no single image (409 pointing at the frame URLs); a frame not started or
/// already written and dropped is 409 too (a written frame is served from its file).
fn with_film<T>(
    farm: &crate::farm::Farm,
    id: JobId,
    frame: Option<i32>,
    f: impl FnOnce(&pathfarm_common::film::Film) -> T,
) -> ApiResult<T> {
    let job = farm.job(id)?;
    let conflict = |m: String| ApiError::new(StatusCode::CONFLICT, "no_image", m);
    match frame {
        None if job.sequence => Err(conflict(format!(
            "job {id} is a sequence of {} frames ({}): each frame has its own image at              {API}/jobs/{id}/frames/{{frame}}/image.exr and preview.png; {API}/jobs/{id}/frames lists them",
            job.frames.len(),
            job.frames.spec()
        ))),
        None => job.film().map(f).ok_or_else(|| conflict(format!("job {id} has no film"))),
        Some(n) if !job.sequence => {
            if job.frames.frames().first() == Some(&n) {
                job.film().map(f).ok_or_else(|| conflict(format!("job {id} has no film")))
            } else {
                Err(ApiError::not_found(format!("job {id} renders frame {} only, not frame {n}", job.settings.frame)))
            }
        }
        Some(n) => {
            let index = job.frame_index(n).ok_or_else(|| {
                ApiError::not_found(format!("frame {n} is not in job {id}'s frames {}", job.frames.spec()))
            })?;
            match job.frame_film(n) {
                Some(film) => Ok(f(&film)),
                None => {
                    let state = job.frame_info(index).map(|i| i.state);
                    Err(conflict(format!("frame {n} of job {id} has no image in memory (it is {state:?})")))
                }
            }
        }
    }
}

/// Resolves a film a band of rows at a time (see [`resolve_banded`]); `frame` as in `with_film`.
pub fn resolve_film_banded(state: &AppState, id: JobId, frame: Option<i32>) -> ApiResult<ImageLayers> {
    // A film's size never changes; a frame dropped between bands is refused by `with_film`.
    let (w, h) = {
        let farm = state.farm.lock();
        with_film(&farm, id, frame, |f| (f.width as usize, f.height as usize))?
    };
    let n = w * h;
    let mut out = ImageLayers {
        width: w as u32,
        height: h as u32,
        rgb: Vec::with_capacity(n),
        albedo: Vec::with_capacity(n),
        normal: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
        samples: Vec::with_capacity(n),
        variance: Vec::with_capacity(n),
        denoised: None,
    };
    let mut y0 = 0;
    while y0 < h {
        let y1 = (y0 + RESOLVE_BAND_ROWS).min(h);
        let band = {
            let farm = state.farm.lock();
            with_film(&farm, id, frame, |f| f.band(y0 as u32, y1 as u32))?
        };
        let r = band.resolve();
        out.rgb.extend(r.rgb);
        out.albedo.extend(r.albedo);
        out.normal.extend(r.normal);
        out.depth.extend(r.depth);
        out.samples.extend(r.samples);
        out.variance.extend(r.variance);
        y0 = y1;
    }
    Ok(out)
}

async fn resolve_job(state: &Arc<AppState>, id: &str) -> ApiResult<ImageLayers> {
    let id = parse_id("job", id)?;
    let st = state.clone();
    tokio::task::spawn_blocking(move || resolve_banded(&st, id))
        .await
        .map_err(|e| ApiError::internal(format!("resolve task: {e}")))?
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/image.exr",
    tag = "images",
    summary = "The image so far as multi-layer OpenEXR (RGB, albedo, normal, depth, samples, variance)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "OpenEXR file", body = Vec<u8>, content_type = "image/x-exr"), (status = 409, description = "The job is a sequence: each frame has its own image (`/jobs/{id}/frames/{frame}/image.exr`)", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn job_exr(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<Response> {
    let layers = resolve_job(&state, &id).await?;
    let bytes = tokio::task::spawn_blocking(move || layers.encode_exr())
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(|e| ApiError::internal(format!("EXR encoding: {e}")))?;
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], bytes).into_response())
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/preview.png",
    tag = "images",
    summary = "The image so far as an sRGB PNG preview",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "PNG file", body = Vec<u8>, content_type = "image/png"), (status = 409, description = "The job is a sequence: each frame has its own preview (`/jobs/{id}/frames/{frame}/preview.png`)", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn job_png(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<Response> {
    let layers = resolve_job(&state, &id).await?;
    let exposure = preview_exposure(&state, parse_id("job", &id)?)?;
    let (bytes, ev) = tokio::task::spawn_blocking(move || {
        let ev = layers.preview_ev(exposure);
        layers.encode_png(ev).map(|b| (b, ev))
    })
    .await
    .map_err(|e| ApiError::internal(e.to_string()))?
    .map_err(|e| ApiError::internal(format!("PNG encoding: {e}")))?;
    let mut resp = ([(header::CONTENT_TYPE, "image/png")], bytes).into_response();
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    insert_exposure_header(&mut resp, ev);
    Ok(resp)
}

/// The response header that says which exposure a PNG preview used (EV).
pub const EXPOSURE_HEADER: &str = "x-pathfarm-preview-ev";

fn insert_exposure_header(resp: &mut Response, ev: f32) {
    if let Ok(v) = HeaderValue::from_str(&format!("{ev:.3}")) {
        resp.headers_mut().insert(EXPOSURE_HEADER, v);
    }
}

/// How job `id`'s previews are exposed (its `exposure` and `auto_exposure` settings).
fn preview_exposure(state: &AppState, id: JobId) -> ApiResult<pathfarm_common::film::PreviewExposure> {
    let farm = state.farm.lock();
    Ok(pathfarm_common::film::PreviewExposure::of(&farm.job(id)?.settings))
}

// ------------------------------------------------------------------------------------ frames

/// Query of `GET /jobs/{id}/frames`: `?limit=N&after=INDEX`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct FramePageQuery {
    /// Frames per page: 1 to 1000, default 100.
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<usize>,
    /// Only frames after this position in the frame set: the last `index` of the previous page.
    pub after: Option<u32>,
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/frames",
    tag = "jobs",
    summary = "A job's frames with their state and progress, a page at a time",
    description = "Frames in the order of the job's frame set, at most `limit` (default 100, at most 1000) \
        with `index` above `after`. When more follow, the `Link` header holds the next page's URL. A \
        single-frame job lists its one frame.",
    params(("id" = u64, Path, description = "Job id"), FramePageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of frames", body = Vec<pathfarm_common::protocol::FrameInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more frames follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id, `limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn job_frames(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    Query(q): Query<FramePageQuery>,
) -> ApiResult<Response> {
    let id = parse_id("job", &id)?;
    let limit = PageQuery { limit: q.limit, after: None }.limit()?;
    let mut page = state.farm.lock().job(id)?.frames_page(q.after, limit + 1);
    let more = page.len() > limit;
    page.truncate(limit);
    let last = page.last().map(|f| u64::from(f.index));
    Ok(paged(Json(page), &format!("/jobs/{id}/frames"), limit, more, last))
}

/// Where a frame's image comes from.
enum FrameSource {
    /// Written: `frames/NNNN/` on disk.
    File(std::path::PathBuf),
    /// Rendering or being written: resolved from its film.
    Film,
}

fn frame_source(state: &AppState, id: &str, frame: &str) -> ApiResult<(JobId, i32, FrameSource)> {
    let id = parse_id("job", id)?;
    let n: i32 = frame.parse().map_err(|_| {
        ApiError::new(StatusCode::BAD_REQUEST, "bad_id", format!("frame {frame:?} is not a frame number"))
    })?;
    let farm = state.farm.lock();
    let job = farm.job(id)?;
    if job.sequence
        && let Some(index) = job.frame_index(n)
        && job.frame_info(index).is_some_and(|f| f.state == pathfarm_common::protocol::FrameState::Done)
    {
        return Ok((id, n, FrameSource::File(crate::store::frame_dir(&state.job_dir(id), n))));
    }
    Ok((id, n, FrameSource::Film))
}

async fn frame_image(state: Arc<AppState>, id: String, frame: String, png: bool) -> ApiResult<Response> {
    let (id, n, source) = frame_source(&state, &id, &frame)?;
    let bytes = match source {
        FrameSource::File(dir) => {
            let path = dir.join(if png { "preview.png" } else { "image.exr" });
            tokio::fs::read(&path).await.map_err(|e| {
                if e.kind() == std::io::ErrorKind::NotFound {
                    ApiError::not_found(format!("frame {n} of job {id} has no image on disk (its files were removed)"))
                } else {
                    crate::server::storage_error(&e, "the frame's image")
                }
            })?
        }
        FrameSource::Film => {
            let st = state.clone();
            let exposure = preview_exposure(&state, id)?;
            tokio::task::spawn_blocking(move || -> ApiResult<Vec<u8>> {
                let layers = resolve_film_banded(&st, id, Some(n))?;
                if png {
                    let ev = layers.preview_ev(exposure);
                    layers.encode_png(ev).map_err(|e| ApiError::internal(format!("PNG encoding: {e}")))
                } else {
                    layers.encode_exr().map_err(|e| ApiError::internal(format!("EXR encoding: {e}")))
                }
            })
            .await
            .map_err(|e| ApiError::internal(format!("resolve task: {e}")))??
        }
    };
    let mut resp = ([(header::CONTENT_TYPE, if png { "image/png" } else { "image/x-exr" })], bytes).into_response();
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    Ok(resp)
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/frames/{frame}/image.exr",
    tag = "images",
    summary = "One frame as multi-layer OpenEXR: the written file once the frame is done, its film so far before",
    params(("id" = u64, Path, description = "Job id"), ("frame" = i32, Path, description = "Frame number")),
    security(("client_token" = [])),
    responses((status = 200, description = "OpenEXR file", body = Vec<u8>, content_type = "image/x-exr"), (status = 409, description = "The frame has not started (or the job was cancelled before it finished)", body = ErrorBody), (status = 404, description = "No such job, or the frame is not in its frame set", body = ErrorBody), (status = 400, description = "The id or the frame is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn frame_exr(
    State(state): State<Arc<AppState>>,
    Path((id, frame)): Path<(String, String)>,
) -> ApiResult<Response> {
    frame_image(state, id, frame, false).await
}

#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/frames/{frame}/preview.png",
    tag = "images",
    summary = "One frame as an sRGB PNG preview (the dashboard's thumbnails)",
    params(("id" = u64, Path, description = "Job id"), ("frame" = i32, Path, description = "Frame number")),
    security(("client_token" = [])),
    responses((status = 200, description = "PNG file", body = Vec<u8>, content_type = "image/png"), (status = 409, description = "The frame has not started (or the job was cancelled before it finished)", body = ErrorBody), (status = 404, description = "No such job, or the frame is not in its frame set", body = ErrorBody), (status = 400, description = "The id or the frame is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn frame_png(
    State(state): State<Arc<AppState>>,
    Path((id, frame)): Path<(String, String)>,
) -> ApiResult<Response> {
    frame_image(state, id, frame, true).await
}

// ------------------------------------------------------------------------------------ workers

#[utoipa::path(
    get,
    path = "/api/v1/workers",
    tag = "workers",
    summary = "List workers, a page at a time",
    description = "Workers in id order, paged like `GET /jobs`: `limit` (default 100, at most 1000), `after`, \
        and a `Link` header to the next page.",
    params(PageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of registered workers", body = Vec<pathfarm_common::protocol::WorkerInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more workers follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 400, description = "`limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn list_workers(State(state): State<Arc<AppState>>, Query(q): Query<PageQuery>) -> ApiResult<Response> {
    let limit = q.limit()?;
    let mut page = state.farm.lock().workers(now_ms());
    page.retain(|w| q.after.is_none_or(|a| w.id > a));
    let more = page.len() > limit;
    page.truncate(limit);
    let last = page.last().map(|w| w.id);
    Ok(paged(Json(page), "/workers", limit, more, last))
}

#[utoipa::path(
    post,
    path = "/api/v1/workers/register",
    tag = "worker protocol",
    summary = "Register a worker",
    description = "The answer holds the worker's own secret (`worker_secret`): the lease, heartbeat, result \
        and release requests of this worker must carry it as `X-Pathfarm-Worker-Secret`. It lives in the \
        coordinator's memory only; after a coordinator restart workers register again. Registrations are rate-limited \
        per client address (token bucket); workers offline longer than --prune-workers-after-ms are forgotten.",
    request_body = RegisterRequest,
    security(("worker_token" = [])),
    responses((status = 200, description = "Registered", body = Registered), (status = 429, description = "Too many registrations from this address (--register-per-minute, --register-burst)", body = ErrorBody, headers(("retry-after" = u64, description = "Seconds to wait"))), (status = 422, description = "Bad body", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
async fn register(
    State(state): State<Arc<AppState>>,
    peer: Option<axum::Extension<axum::extract::ConnectInfo<std::net::SocketAddr>>>,
    body: Bytes,
) -> Result<Json<Registered>, Response> {
    if let Some(axum::Extension(axum::extract::ConnectInfo(addr))) = peer
        && let Err(wait) = state.register_limiter.check(addr.ip(), Instant::now())
    {
        let secs = wait.as_secs_f64().ceil().max(1.0) as u64;
        tracing::warn!(peer = %addr.ip(), retry_after_s = secs, "worker registrations from this address are rate-limited");
        let mut r = ApiError::new(
            StatusCode::TOO_MANY_REQUESTS,
            "rate_limited",
            format!(
                "too many worker registrations from {}: at most {} a minute (burst {}); retry after {secs} s",
                addr.ip(),
                state.config.register_per_minute,
                state.config.register_burst
            ),
        )
        .into_response();
        r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(secs));
        return Err(r);
    }
    register_worker(&state, &body).await.map_err(IntoResponse::into_response)
}

async fn register_worker(state: &Arc<AppState>, body: &[u8]) -> ApiResult<Json<Registered>> {
    let req: RegisterRequest = serde_json::from_slice(body)
        .map_err(|e| ApiError::unprocessable("invalid_body", format!("register body: {e}")))?;
    if !(1..=4096).contains(&req.threads) || req.name.is_empty() || req.name.len() > 256 {
        return Err(ApiError::unprocessable(
            "invalid_body",
            format!("register body: threads must be 1..=4096 (got {}) and name 1..=256 bytes", req.threads),
        ));
    }
    validate_tags(&req.tags, "register body: tags").map_err(|e| ApiError::unprocessable("invalid_body", e))?;
    let worker_secret = new_worker_secret()?;
    let reg = {
        let mut farm = state.farm.lock();
        let worker_id = farm.register_tagged(req.name.clone(), req.threads, worker_secret.clone(), req.tags, now_ms());
        Registered {
            worker_id,
            worker_secret,
            heartbeat_ms: farm.cfg.heartbeat_ms,
            lease_timeout_ms: farm.cfg.lease_timeout_ms,
        }
    };
    state.persist_worker(reg.worker_id, &req.name, req.threads);
    state.publish("worker", reg.worker_id);
    Ok(Json(reg))
}

#[utoipa::path(
    post,
    path = "/api/v1/workers/{id}/heartbeat",
    tag = "worker protocol",
    summary = "Heartbeat (renews the worker's leases)",
    params(("id" = u64, Path, description = "Worker id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    security(("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 204, description = "Noted"), (status = 404, description = "Unknown worker: register again", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
async fn heartbeat(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<StatusCode> {
    let id: WorkerId = parse_id("worker", &id)?;
    let mut farm = state.farm.lock();
    farm.check_worker(id, worker_secret(&headers))?;
    farm.heartbeat(id, now_ms())?;
    Ok(StatusCode::NO_CONTENT)
}

/// Longest long-poll a lease request may ask for (longer asks are cut to this).
const MAX_LEASE_WAIT_MS: u64 = 20_000;

#[derive(Deserialize)]
struct LeaseQuery {
    wait_ms: Option<u64>,
}

#[utoipa::path(
    post,
    path = "/api/v1/workers/{id}/lease",
    tag = "worker protocol",
    summary = "Lease a work unit (long poll)",
    params(("id" = u64, Path, description = "Worker id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register"), ("wait_ms" = Option<u64>, Query, description = "Wait up to this long for work (at most 20000)")),
    security(("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 200, description = "A unit to render", body = pathfarm_common::protocol::LeaseGrant), (status = 204, description = "No work"), (status = 404, description = "Unknown worker", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
async fn lease(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    Query(q): Query<LeaseQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let worker: WorkerId = parse_id("worker", &id)?;
    state.farm.lock().check_worker(worker, worker_secret(&headers))?;
    let wait = Duration::from_millis(q.wait_ms.unwrap_or(0).min(MAX_LEASE_WAIT_MS));
    let start = Instant::now();
    loop {
        let notified = state.work_ready.notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        let t0 = Instant::now();
        let grant = state.farm.lock().lease(worker, now_ms())?;
        state.metrics.observe_lease(t0.elapsed());
        if let Some(g) = grant {
            state.publish("worker", worker);
            return Ok(Json(g).into_response());
        }
        let left = wait.saturating_sub(start.elapsed());
        if left.is_zero() {
            return Ok(StatusCode::NO_CONTENT.into_response());
        }
        let _ = tokio::time::timeout(left, notified).await;
    }
}

#[utoipa::path(
    put,
    path = "/api/v1/leases/{id}/result",
    tag = "worker protocol",
    summary = "Upload a unit's result",
    description = "The token, the worker secret, the lease and the declared `Content-Length` are checked before \
        the body is read: a refusal (401/403/409/413) closes the connection without reading the body.",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "Binary frame: PFR2 magic, u32 header length, JSON header, the tile's 64-byte pixel sums (raw or lz4), sparse splats, CRC-32"),
    security(("worker_token" = [])),
    responses((status = 200, description = "Accepted", body = ResultAccepted), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 413, description = "The declared or actual body is larger than --max-upload-mb or than the largest result of the lease's tile (JSON header, lz4 worst case of the tile's sums and of an image-sized splat buffer); refused before the body is read", body = ErrorBody), (status = 409, description = "The lease is no longer held", body = ErrorBody), (status = 422, description = "Corrupt or mismatched frame", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
async fn upload_result(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<ResultAccepted>, Response> {
    let lease_id: LeaseId = parse_id("lease", &id).map_err(refuse_unread)?;
    let secret = worker_secret(&headers).map(str::to_string);
    // Everything that can refuse the result without its bytes is checked before a byte of the
    // body is read: the declared length against the upload limit, the sender's secret and the
    // lease, then the declared length against the largest result the lease's unit can have.
    let declared = declared_length(&headers);
    check_declared(declared, state.config.max_upload_bytes as u64, || "the upload limit".to_string())
        .map_err(refuse_unread)?;
    let bound = {
        let mut farm = state.farm.lock();
        let shape = farm.check_lease(lease_id, secret.as_deref()).map(|()| farm.lease_shape(lease_id));
        match shape {
            Ok(Some((tile, image))) => max_result_bytes(tile, image).min(state.config.max_upload_bytes as u64),
            Ok(None) | Err(_) => {
                farm.counters.results_rejected += 1;
                let e = shape.err().unwrap_or(FarmError::LeaseLost(lease_id));
                if matches!(e, FarmError::WrongWorker(_)) {
                    tracing::warn!(lease = lease_id, "result refused: {e}");
                }
                return Err(refuse_unread(e.into()));
            }
        }
    };
    check_declared(declared, bound, || format!("the largest result of lease {lease_id}'s tile"))
        .map_err(refuse_unread)?;
    let body = read_bounded(body, declared, bound, || format!("the largest result of lease {lease_id}'s tile"))
        .await
        .map_err(refuse_unread)?;
    state.metrics.bytes_received.fetch_add(body.len() as u64, Ordering::Relaxed);
    // Decoding (lz4, CRC, 850 KB of sums for a 64 px tile) and merging take a few hundred
    // microseconds: run them off the async threads, at most one per core at a time, so lease
    // requests are answered meanwhile and bodies waiting to be decoded stay compressed.
    let _permit = decode_slots().acquire().await.map_err(|e| ApiError::internal(e.to_string()).into_response())?;
    let st = state.clone();
    let t0 = Instant::now();
    let (job_id, outcome) =
        tokio::task::spawn_blocking(move || decode_and_accept(&st, lease_id, secret.as_deref(), &body))
            .await
            .map_err(|e| ApiError::internal(format!("result task: {e}")).into_response())?
            .map_err(IntoResponse::into_response)?;
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            // A refused result may have sent its unit back to pending.
            state.work_ready.notify_waiters();
            return Err(ApiError::from(e).into_response());
        }
    };
    state.metrics.observe_merge(t0.elapsed());
    if !outcome.passes_completed.is_empty() || outcome.job_completed {
        state.output_ready.notify_one();
    }
    state.publish("job", job_id);
    Ok(Json(ResultAccepted { merged: outcome.folded > 0 }))
}

/// An error answered before the request's body was read: the connection is closed after it, so
/// the unread body is never parsed as the next request (and a client cannot make us drain it).
fn refuse_unread(e: ApiError) -> Response {
    let mut r = e.into_response();
    r.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// The request's `Content-Length`, if it has one that parses.
fn declared_length(headers: &HeaderMap) -> Option<u64> {
    headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse().ok())
}

fn too_large(len: u64, limit: u64, what: impl FnOnce() -> String) -> ApiError {
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "payload_too_large",
        format!("request body of {len} bytes is larger than {} ({limit} bytes)", what()),
    )
}

/// 413 when the declared length is above `limit`.
fn check_declared(declared: Option<u64>, limit: u64, what: impl FnOnce() -> String) -> ApiResult<()> {
    match declared {
        Some(len) if len > limit => Err(too_large(len, limit, what)),
        _ => Ok(()),
    }
}

/// Reads a body of at most `limit` bytes (413 as soon as more arrive), never buffering more.
async fn read_bounded(
    body: Body,
    declared: Option<u64>,
    limit: u64,
    what: impl FnOnce() -> String,
) -> ApiResult<Bytes> {
    use futures_util::StreamExt;
    let mut stream = body.into_data_stream();
    let mut buf = Vec::with_capacity(declared.unwrap_or(0).min(limit) as usize);
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| {
            ApiError::new(StatusCode::BAD_REQUEST, "bad_body", format!("reading the request body: {e}"))
        })?;
        let len = (buf.len() + chunk.len()) as u64;
        if len > limit {
            return Err(too_large(len, limit, what));
        }
        buf.extend_from_slice(&chunk);
    }
    Ok(Bytes::from(buf))
}

/// Refuses a request whose declared `Content-Length` is above the upload limit before its body
/// is read (scene uploads; the body is then read with the same limit).
async fn declared_length_within_limit(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    let limit = state.config.max_upload_bytes as u64;
    match check_declared(declared_length(req.headers()), limit, || "the upload limit".to_string()) {
        Ok(()) => next.run(req).await,
        Err(e) => refuse_unread(e),
    }
}

/// Concurrent result decodes: one per core.
fn decode_slots() -> &'static tokio::sync::Semaphore {
    static SLOTS: std::sync::OnceLock<tokio::sync::Semaphore> = std::sync::OnceLock::new();
    SLOTS.get_or_init(|| tokio::sync::Semaphore::new(std::thread::available_parallelism().map_or(2, |n| n.get())))
}

/// Decodes a result body and merges it; an undecodable body is a 422 (and its unit pending
/// again), a refusal by the farm is returned as the inner error.
fn decode_and_accept(
    state: &AppState,
    lease_id: LeaseId,
    secret: Option<&str>,
    body: &[u8],
) -> ApiResult<(JobId, Result<crate::farm::MergeOutcome, FarmError>)> {
    // Refuse results for leases that are not held, or not held by the sender, before
    // decoding: duplicates and late results cost nothing, and a body from someone without a
    // lease cannot make the decoder allocate what its header declares (up to 4 GiB of sums).
    let (tile, image) = {
        let mut farm = state.farm.lock();
        if let Err(e) = farm.check_lease(lease_id, secret) {
            farm.counters.results_rejected += 1;
            if matches!(e, FarmError::WrongWorker(_)) {
                tracing::warn!(lease = lease_id, "result refused: {e}");
            }
            return Ok((0, Err(e)));
        }
        match farm.lease_shape(lease_id) {
            Some(shape) => shape,
            None => {
                farm.counters.results_rejected += 1;
                return Ok((0, Err(FarmError::LeaseLost(lease_id))));
            }
        }
    };
    let frame = match UnitResultFrame::decode_expecting(body, tile, image) {
        Ok(f) => f,
        Err(e) => {
            // The worker does not retry a refused body, so its unit would sit leased until the
            // lease expired: give it to someone else now (a lost lease stays lost).
            let requeued = {
                let mut farm = state.farm.lock();
                farm.counters.results_rejected += 1;
                farm.release(lease_id, false, "", now_ms()).is_ok()
            };
            if requeued {
                state.work_ready.notify_waiters();
            }
            return Err(ApiError::unprocessable("bad_result", e.to_string()));
        }
    };
    let job_id = frame.job_id;
    let mut farm = state.farm.lock();
    let r = farm.accept(lease_id, frame, now_ms());
    if r.is_err() {
        farm.counters.results_rejected += 1;
    }
    Ok((job_id, r))
}

#[utoipa::path(
    post,
    path = "/api/v1/leases/{id}/release",
    tag = "worker protocol",
    summary = "Give a unit back, or report that it failed",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    request_body = ReleaseRequest,
    security(("worker_token" = [])),
    responses((status = 204, description = "Released"), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 422, description = "Bad body", body = ErrorBody), (status = 409, description = "The lease is no longer held", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
async fn release(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<StatusCode> {
    let lease_id: LeaseId = parse_id("lease", &id)?;
    let req: ReleaseRequest = serde_json::from_slice(&body)
        .map_err(|e| ApiError::unprocessable("invalid_body", format!("release body: {e}")))?;
    {
        let mut farm = state.farm.lock();
        if let Err(e) = farm.check_lease(lease_id, worker_secret(&headers)) {
            if matches!(e, FarmError::WrongWorker(_)) {
                tracing::warn!(lease = lease_id, "release refused: {e}");
            }
            return Err(e.into());
        }
        farm.release(lease_id, req.failed, &req.reason, now_ms())?;
    }
    state.work_ready.notify_waiters();
    Ok(StatusCode::NO_CONTENT)
}

// ------------------------------------------------------------------------------------ metrics

#[utoipa::path(
    get,
    path = "/metrics",
    tag = "service",
    summary = "Prometheus metrics",
    description = "Open unless the coordinator runs with `--metrics-token`; then it takes only that token \
        (`Authorization: Bearer`), not the client or worker token.",
    security((), ("metrics_token" = [])),
    responses((status = 200, description = "Prometheus text exposition", body = String, content_type = "text/plain; version=0.0.4"), (status = 401, description = "`--metrics-token` is set and the request does not carry it", body = ErrorBody)),
)]
async fn metrics(State(state): State<Arc<AppState>>, headers: HeaderMap) -> ApiResult<Response> {
    if let Some(expected) = state.config.metrics_token.as_deref() {
        match bearer(&headers) {
            Some(t) if token_matches(t, expected) => {}
            Some(t) if !t.is_empty() => {
                return Err(ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", "invalid metrics token"));
            }
            _ => {
                return Err(ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    "missing bearer token: /metrics needs the metrics token",
                ));
            }
        }
    }
    let text = state.metrics_text();
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::ServerConfig;
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
        assert!(crate::server::collect_scenes(&server.state, now_ms() - 60_000).is_empty());
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
        let e = crate::server::database_error(&anyhow::Error::from(full), "job 7");
        assert_eq!(e.status, StatusCode::INSUFFICIENT_STORAGE);
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
        assert_eq!(info["frames"]["current"][0]["frame"], 10);
        let (_, link, page) = get(&app, &format!("/api/v1/jobs/{id}/frames?limit=2")).await;
        let frames = |v: &serde_json::Value| -> Vec<i64> {
            v.as_array().expect("array").iter().map(|f| f["frame"].as_i64().expect("frame")).collect()
        };
        assert_eq!(frames(&page), vec![10, 11]);
        assert_eq!(link.as_deref(), Some(format!("</api/v1/jobs/{id}/frames?limit=2&after=1>; rel=\"next\"").as_str()));
        let (_, link, page) = get(&app, &format!("/api/v1/jobs/{id}/frames?limit=2&after=3")).await;
        assert_eq!((frames(&page), link), (vec![14], None));
        assert_eq!(page[0]["state"], "pending");
        // Frame 10 is rendering (its film exists): served; frame 14 has not started: 409.
        assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/10/preview.png")).await, StatusCode::OK);
        assert_eq!(
            status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/14/image.exr")).await,
            StatusCode::CONFLICT
        );
        assert_eq!(
            status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/9/image.exr")).await,
            StatusCode::NOT_FOUND
        );
        assert_eq!(
            status_of(&app, "GET", &format!("/api/v1/jobs/{id}/frames/x/image.exr")).await,
            StatusCode::BAD_REQUEST
        );
        assert_eq!(status_of(&app, "GET", &format!("/api/v1/jobs/{id}/image.exr")).await, StatusCode::CONFLICT);
        // A single-frame job serves its one frame under the frame route too.
        let single = submit(&app, &scene).await;
        assert_eq!(
            status_of(&app, "GET", &format!("/api/v1/jobs/{single}/frames/0/preview.png")).await,
            StatusCode::OK
        );
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
        let e = crate::events::authorize_client(&auth, &HeaderMap::new(), Some("")).expect_err("?token=");
        assert_eq!(e.status, StatusCode::UNAUTHORIZED);
        let mut h = HeaderMap::new();
        h.insert(header::AUTHORIZATION, HeaderValue::from_static("Bearer "));
        let e = crate::events::authorize_client(&auth, &h, None).expect_err("Bearer with nothing");
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
            let film = farm.job_mut(id).expect("job").film_mut().expect("film");
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
        assert!(matches!(resolve_banded(&state, id + 1), Err(e) if e.status == StatusCode::NOT_FOUND));
    }
}
