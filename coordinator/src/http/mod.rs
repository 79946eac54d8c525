//! The REST API (axum): clients' routes, workers' routes, images, health and metrics.
//!
//! Every error is JSON `{"error": {"code", "message"}}` with a 4xx/5xx status; a panic inside a
//! handler becomes a 500 and the server keeps serving.

pub mod auth;
pub mod conn;
pub mod dashboard;
pub mod error;
pub mod events;
pub mod frames;
pub mod jobs;
pub mod openapi;
pub mod scenes;
pub mod workers;

use crate::farm::FarmError;
use crate::service::{AppState, Auth, now_ms, resolve_banded, resolve_film_banded};
pub use auth::*;
use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put};
use axum::{Json, Router};
pub use error::*;
use frames::*;
use jobs::*;
use pathfarm_common::film::ImageLayers;
use pathfarm_common::protocol::{
    API, DEFAULT_PAGE_LIMIT, DenoiseInput, ErrorBody, ErrorDetail, JobCreated, JobId, JobInfo, JobRequest, LeaseId,
    MAX_PAGE_LIMIT, RegisterRequest, Registered, ReleaseRequest, ResultAccepted, SceneCreated, UnitResultFrame,
    WORKER_SECRET_HEADER, WorkerId, decode_denoised, max_denoised_bytes, max_result_bytes, validate_tags,
};
use pathfarm_common::routes;
use pathfarm_common::scene::bundle::is_scene_id;
use scenes::*;
use serde::Deserialize;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use workers::*;

pub(crate) fn parse_id(kind: &str, raw: &str) -> ApiResult<u64> {
    raw.parse()
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "bad_id", format!("{kind} id {raw:?} is not a number")))
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
            routes::SCENES,
            post(upload_scene)
                .layer(DefaultBodyLimit::max(upload_limit))
                .layer(middleware::from_fn_with_state(state.clone(), declared_length_within_limit)),
        )
        .route(routes::SCENE, delete(delete_scene))
        .route(routes::JOBS, post(create_job).get(list_jobs))
        .route(routes::JOB, get(get_job).delete(delete_job))
        .route(routes::JOB_CANCEL, post(cancel_job))
        .route(routes::JOB_PAUSE, post(pause_job))
        .route(routes::JOB_RESUME, post(resume_job))
        .route(routes::JOB_PRIORITY, put(set_priority))
        .route(routes::JOB_LOG, get(job_log))
        .route(routes::JOB_TILES, get(job_tiles))
        .route(routes::JOB_EXR, get(job_exr))
        .route(routes::JOB_PNG, get(job_png))
        .route(routes::JOB_FRAMES, get(job_frames))
        .route(routes::FRAME_EXR, get(frame_exr))
        .route(routes::FRAME_PNG, get(frame_png))
        .route(routes::WORKERS, get(list_workers))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_client));
    let worker = Router::new()
        .route(routes::WORKER_REGISTER, post(register))
        .route(routes::WORKER_HEARTBEAT, post(heartbeat))
        .route(routes::WORKER_LEASE, post(lease))
        // The result handler reads its body itself, bounded by the lease's tile.
        .route(routes::LEASE_RESULT, put(upload_result))
        .route(routes::LEASE_RELEASE, post(release))
        // Denoise steps (`farm/denoise.rs`): the frame's input, and the layer, read bounded.
        .route(routes::LEASE_DENOISE_INPUT, get(denoise_input))
        .route(routes::LEASE_DENOISED, put(upload_denoised))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_worker));
    let shared = Router::new()
        .route(routes::SCENE, get(download_scene))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_any));
    // Own auth (the token may come as `?token=`, for EventSource), and the public API document.
    let live = Router::new()
        .route(routes::EVENTS, get(crate::http::events::events))
        .route(routes::OPENAPI, get(crate::http::openapi::openapi_json));
    let api = Router::new().merge(client).merge(worker).merge(shared).merge(live);
    Router::new()
        .nest(API, api)
        .route(routes::HEALTHZ, get(|| async { "ok" }))
        .route(routes::METRICS, get(metrics))
        .merge(crate::http::dashboard::routes(&state))
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

// ------------------------------------------------------------------------------------ metrics

#[utoipa::path(
    get,
    path = routes::METRICS,
    tag = "service",
    summary = "Prometheus metrics",
    description = "Open unless the coordinator runs with `--metrics-token`; then it takes only that token \
        (`Authorization: Bearer`), not the client or worker token.",
    security((), ("metrics_token" = [])),
    responses((status = 200, description = "OpenMetrics text exposition (Prometheus scrapes it), with the standard `process_*` metrics on Linux", body = String, content_type = "application/openmetrics-text; version=1.0.0; charset=utf-8"), (status = 401, description = "`--metrics-token` is set and the request does not carry it", body = ErrorBody)),
)]
pub(crate) async fn metrics(State(state): State<Arc<AppState>>, headers: HeaderMap) -> ApiResult<Response> {
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
    Ok(([(header::CONTENT_TYPE, crate::service::METRICS_CONTENT_TYPE)], text).into_response())
}

#[cfg(test)]
mod tests;
