//! Worker routes: register, heartbeat, lease, result upload, release; the bounded body reads.

use super::*;
use pathfarm_common::routes;

#[utoipa::path(
    get,
    path = routes::WORKERS,
    context_path = API,
    tag = "workers",
    summary = "List workers, a page at a time",
    description = "Workers in id order, paged like `GET /jobs`: `limit` (default 100, at most 1000), `after`, \
        and a `Link` header to the next page.",
    params(PageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of registered workers", body = Vec<pathfarm_common::protocol::WorkerInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more workers follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 400, description = "`limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn list_workers(
    State(state): State<Arc<AppState>>,
    Query(q): Query<PageQuery>,
) -> ApiResult<Response> {
    let limit = q.limit()?;
    let mut page = state.farm.lock().workers(now_ms());
    page.retain(|w| q.after.is_none_or(|a| w.id > a));
    let more = page.len() > limit;
    page.truncate(limit);
    let last = page.last().map(|w| w.id);
    Ok(paged(Json(page), routes::WORKERS, limit, more, last))
}

#[utoipa::path(
    post,
    path = routes::WORKER_REGISTER,
    context_path = API,
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
pub(crate) async fn register(
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

pub(crate) async fn register_worker(state: &Arc<AppState>, body: &[u8]) -> ApiResult<Json<Registered>> {
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
    let reg = state.act(|farm| {
        let worker_id = farm.register_tagged(req.name, req.threads, worker_secret.clone(), req.tags, now_ms());
        Ok(Registered {
            worker_id,
            worker_secret,
            heartbeat_ms: farm.cfg.heartbeat_ms,
            lease_timeout_ms: farm.cfg.lease_timeout_ms,
        })
    })?;
    Ok(Json(reg))
}

#[utoipa::path(
    post,
    path = routes::WORKER_HEARTBEAT,
    context_path = API,
    tag = "worker protocol",
    summary = "Heartbeat (renews the worker's leases)",
    params(("id" = u64, Path, description = "Worker id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    security(("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 204, description = "Noted"), (status = 404, description = "Unknown worker: register again", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn heartbeat(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<StatusCode> {
    let id: WorkerId = parse_id("worker", &id)?;
    state.act(|farm| {
        farm.check_worker(id, worker_secret(&headers))?;
        farm.heartbeat(id, now_ms())
    })?;
    Ok(StatusCode::NO_CONTENT)
}

/// Longest long-poll a lease request may ask for (longer asks are cut to this).
pub(crate) const MAX_LEASE_WAIT_MS: u64 = 20_000;

#[derive(Deserialize)]
pub(crate) struct LeaseQuery {
    wait_ms: Option<u64>,
}

#[utoipa::path(
    post,
    path = routes::WORKER_LEASE,
    context_path = API,
    tag = "worker protocol",
    summary = "Lease a work unit (long poll)",
    params(("id" = u64, Path, description = "Worker id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register"), ("wait_ms" = Option<u64>, Query, description = "Wait up to this long for work (at most 20000)")),
    security(("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 200, description = "A unit to render", body = pathfarm_common::protocol::LeaseGrant), (status = 204, description = "No work"), (status = 404, description = "Unknown worker", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn lease(
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
        let grant = state.act(|farm| farm.lease(worker, now_ms()))?;
        state.metrics.observe_lease(t0.elapsed());
        if let Some(g) = grant {
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
    path = routes::LEASE_RESULT,
    context_path = API,
    tag = "worker protocol",
    summary = "Upload a unit's result",
    description = "The token, the worker secret, the lease and the declared `Content-Length` are checked before \
        the body is read: a refusal (401/403/409/413) closes the connection without reading the body.",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "Binary frame: PFR2 magic, u32 header length, JSON header, the tile's 64-byte pixel sums (raw or lz4), sparse splats, CRC-32"),
    security(("worker_token" = [])),
    responses((status = 200, description = "Accepted", body = ResultAccepted), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 413, description = "The declared or actual body is larger than --max-upload-mb or than the largest result of the lease's tile (JSON header, lz4 worst case of the tile's sums and of an image-sized splat buffer); refused before the body is read", body = ErrorBody), (status = 409, description = "The lease is no longer held", body = ErrorBody), (status = 422, description = "Corrupt or mismatched frame", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn upload_result(
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
    let (shape, bound) = {
        let mut farm = state.farm.lock();
        let shape = farm.check_lease(lease_id, secret.as_deref()).map(|()| farm.lease_shape(lease_id));
        match shape {
            Ok(Some((tile, image))) => {
                ((tile, image), max_result_bytes(tile, image).min(state.config.max_upload_bytes as u64))
            }
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
    // Decoding (CRC, 256 KiB of sums for a 64 px tile) and folding take ~100 us: they run
    // right here, on the async thread, at most one fewer at a time than there are cores, so a
    // thread is always free to answer lease requests. (A hop to the blocking pool per result
    // cost ~13% more coordinator CPU per unit: load tool, 500 workers.)
    let _permit = decode_slots().acquire().await.map_err(|e| ApiError::internal(e.to_string()).into_response())?;
    let t0 = Instant::now();
    let outcome = decode_and_accept(&state, lease_id, shape, &body).map_err(IntoResponse::into_response)?;
    let outcome = outcome.map_err(|e| ApiError::from(e).into_response())?;
    state.metrics.observe_merge(t0.elapsed());
    Ok(Json(ResultAccepted { merged: outcome.folded > 0 }))
}

#[utoipa::path(
    get,
    path = routes::LEASE_DENOISE_INPUT,
    context_path = API,
    tag = "worker protocol",
    summary = "A denoise step's input: the frame's colour, albedo and normal",
    description = "For a lease of `kind` `denoise`: the frame's film resolved (the same resolve as a local render's), \
        as a binary body: `PFDI` magic, u32 width, u32 height, three sections (colour, albedo, normal: width x height \
        x 3 little-endian f32, each a u8 codec, u64 length and lz4 block), CRC-32.",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    security(("worker_token" = [])),
    responses((status = 200, description = "The input", body = Vec<u8>, content_type = "application/octet-stream"), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 409, description = "The lease is no longer held, or its frame's film is gone", body = ErrorBody), (status = 422, description = "A render lease, not a denoise lease", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn denoise_input(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let lease_id: LeaseId = parse_id("lease", &id)?;
    let (job, frame) = {
        let farm = state.farm.lock();
        farm.check_lease(lease_id, worker_secret(&headers))?;
        let (job, frame, _) = farm.denoise_lease(lease_id)?;
        (job, frame)
    };
    let st = state.clone();
    // Resolved band by band (the farm lock is never held for a whole film), then encoded.
    let body = tokio::task::spawn_blocking(move || -> ApiResult<Vec<u8>> {
        let layers = resolve_film_banded(&st, job, Some(frame))?;
        Ok(DenoiseInput::of(&layers).encode())
    })
    .await
    .map_err(|e| ApiError::internal(format!("denoise input task: {e}")))??;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], body).into_response())
}

#[utoipa::path(
    put,
    path = routes::LEASE_DENOISED,
    context_path = API,
    tag = "worker protocol",
    summary = "Upload a denoise step's layer",
    description = "The denoised colour of the lease's frame: `PFDO` magic, u32 width, u32 height, one section \
        (width x height x 3 little-endian f32, raw or lz4), CRC-32. The token, the worker secret, the lease and the \
        declared `Content-Length` (at most the lz4 worst case of the frame's layer) are checked before the body is \
        read. A layer of an earlier pass than the one stored is refused (409 `stale`): it never replaces a newer one.",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "PFDO body"),
    security(("worker_token" = [])),
    responses((status = 204, description = "Stored"), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 413, description = "Larger than the frame's layer can be, or than --max-upload-mb", body = ErrorBody), (status = 409, description = "The lease is no longer held (`lease_lost`), or a newer layer is stored (`stale`)", body = ErrorBody), (status = 422, description = "Corrupt body, another size than the frame's, or a render lease", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn upload_denoised(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<StatusCode, Response> {
    let lease_id: LeaseId = parse_id("lease", &id).map_err(refuse_unread)?;
    let secret = worker_secret(&headers).map(str::to_string);
    let declared = declared_length(&headers);
    check_declared(declared, state.config.max_upload_bytes as u64, || "the upload limit".to_string())
        .map_err(refuse_unread)?;
    let (w, h) = {
        let farm = state.farm.lock();
        let size = farm.check_lease(lease_id, secret.as_deref()).and_then(|()| farm.denoise_lease(lease_id));
        size.map(|(_, _, size)| size).map_err(|e| refuse_unread(e.into()))?
    };
    let bound = max_denoised_bytes(w, h).min(state.config.max_upload_bytes as u64);
    let what = || format!("the largest denoised layer of lease {lease_id}'s frame");
    check_declared(declared, bound, what).map_err(refuse_unread)?;
    let body = read_bounded(body, declared, bound, what).await.map_err(refuse_unread)?;
    state.metrics.bytes_received.fetch_add(body.len() as u64, Ordering::Relaxed);
    let rgb = match tokio::task::spawn_blocking(move || decode_denoised(&body, w, h)).await {
        Ok(Ok(rgb)) => rgb,
        Ok(Err(e)) => {
            // Counted as a failure of the step (retried, then given up), like a failed render.
            let _ = state.act(|farm| farm.release(lease_id, true, &format!("bad denoised layer: {e}"), now_ms()));
            return Err(ApiError::unprocessable("bad_denoised", e.to_string()).into_response());
        }
        Err(e) => return Err(ApiError::internal(format!("denoised layer task: {e}")).into_response()),
    };
    let outcome = state
        .act(|farm| {
            farm.check_lease(lease_id, secret.as_deref())?;
            farm.accept_denoised(lease_id, rgb, now_ms())
        })
        .map_err(|e| ApiError::from(e).into_response())?;
    tracing::debug!(job = outcome.job_id, frame = outcome.frame, last = outcome.last, "denoised layer stored");
    Ok(StatusCode::NO_CONTENT)
}

/// An error answered before the request's body was read: the connection is closed after it, so
/// the unread body is never parsed as the next request (and a client cannot make us drain it).
pub(crate) fn refuse_unread(e: ApiError) -> Response {
    let mut r = e.into_response();
    r.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// The request's `Content-Length`, if it has one that parses.
pub(crate) fn declared_length(headers: &HeaderMap) -> Option<u64> {
    headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse().ok())
}

pub(crate) fn too_large(len: u64, limit: u64, what: impl FnOnce() -> String) -> ApiError {
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "payload_too_large",
        format!("request body of {len} bytes is larger than {} ({limit} bytes)", what()),
    )
}

/// 413 when the declared length is above `limit`.
pub(crate) fn check_declared(declared: Option<u64>, limit: u64, what: impl FnOnce() -> String) -> ApiResult<()> {
    match declared {
        Some(len) if len > limit => Err(too_large(len, limit, what)),
        _ => Ok(()),
    }
}

/// Reads a body of at most `limit` bytes (413 as soon as more arrive), never buffering more.
pub(crate) async fn read_bounded(
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
pub(crate) async fn declared_length_within_limit(
    State(state): State<Arc<AppState>>,
    req: Request,
    next: Next,
) -> Response {
    let limit = state.config.max_upload_bytes as u64;
    match check_declared(declared_length(req.headers()), limit, || "the upload limit".to_string()) {
        Ok(()) => next.run(req).await,
        Err(e) => refuse_unread(e),
    }
}

/// Concurrent result decodes: one fewer than the cores (at least one), so that lease requests
/// always find an async thread.
pub(crate) fn decode_slots() -> &'static tokio::sync::Semaphore {
    static SLOTS: std::sync::OnceLock<tokio::sync::Semaphore> = std::sync::OnceLock::new();
    SLOTS.get_or_init(|| {
        tokio::sync::Semaphore::new(
            std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1).max(1)),
        )
    })
}

/// Decodes a result body for lease `lease_id`, whose holder and shape (`tile`, `image`) were
/// checked before its body was read, and merges it; an undecodable body is a 422 (and its unit
/// pending again), a refusal by the farm (e.g. the lease was lost meanwhile) is returned as the
/// inner error.
pub(crate) fn decode_and_accept(
    state: &AppState,
    lease_id: LeaseId,
    (tile, image): (pathfarm_common::job::TileRect, (u32, u32)),
    body: &[u8],
) -> ApiResult<Result<crate::farm::MergeOutcome, FarmError>> {
    // Packed sums stay in the body: they are read as they are merged.
    let frame = match UnitResultFrame::decode_view(body, tile, image) {
        Ok(f) => f,
        Err(e) => {
            // The worker does not retry a refused body, so its unit would sit leased until the
            // lease expired: give it to someone else now (a lost lease stays lost).
            let _ = state.act(|farm| {
                farm.counters.results_rejected += 1;
                farm.release(lease_id, false, "", now_ms())
            });
            return Err(ApiError::unprocessable("bad_result", e.to_string()));
        }
    };
    // Under the farm lock: check the result and take it from its lease. Then fold it under its
    // frame's lock alone (leases and other frames' merges go on), and record the fold under the
    // farm lock again (`farm/frame_run.rs`).
    let begun = {
        let mut farm = state.farm.lock();
        match farm.begin_accept(lease_id, frame, now_ms()) {
            Ok(fold) => Ok(fold),
            Err(e) => {
                farm.counters.results_rejected += 1;
                Err((e, farm.take_changes()))
            }
        }
    };
    let (r, changes) = match begun {
        Ok(fold) => {
            let folding = fold.fold();
            let (out, changes) = state.locked(|farm| farm.finish_accept(folding, now_ms()));
            (Ok(out), changes)
        }
        Err((e, changes)) => (Err(e), changes),
    };
    // A merged result is in effect whether or not a record could be saved (the checkpoint loop
    // saves it again); the worker is told it was merged.
    state.apply_logged(changes, &format!("lease {lease_id}'s result"));
    Ok(r)
}

#[utoipa::path(
    post,
    path = routes::LEASE_RELEASE,
    context_path = API,
    tag = "worker protocol",
    summary = "Give a unit back, or report that it failed",
    params(("id" = u64, Path, description = "Lease id"), ("X-Pathfarm-Worker-Secret" = String, Header, description = "The worker_secret returned by POST /workers/register")),
    request_body = ReleaseRequest,
    security(("worker_token" = [])),
    responses((status = 204, description = "Released"), (status = 400, description = "Bad lease id", body = ErrorBody), (status = 422, description = "Bad body", body = ErrorBody), (status = 409, description = "The lease is no longer held", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token, or the worker secret is missing or another worker's (code `wrong_worker`)", body = ErrorBody)),
)]
pub(crate) async fn release(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<StatusCode> {
    let lease_id: LeaseId = parse_id("lease", &id)?;
    let req: ReleaseRequest = serde_json::from_slice(&body)
        .map_err(|e| ApiError::unprocessable("invalid_body", format!("release body: {e}")))?;
    state.act(|farm| {
        if let Err(e) = farm.check_lease(lease_id, worker_secret(&headers)) {
            if matches!(e, FarmError::WrongWorker(_)) {
                tracing::warn!(lease = lease_id, "release refused: {e}");
            }
            return Err(e);
        }
        farm.release(lease_id, req.failed, &req.reason, now_ms())
    })?;
    Ok(StatusCode::NO_CONTENT)
}
