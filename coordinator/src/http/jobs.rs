//! Job routes: submit, list, inspect, actions, priority, delete, the job's images.

use super::*;
use pathfarm_common::routes;

#[utoipa::path(
    post,
    path = routes::JOBS,
    context_path = API,
    tag = "jobs",
    summary = "Submit a job",
    request_body = crate::http::openapi::JobRequestBody,
    security(("client_token" = [])),
    responses((status = 201, description = "Queued", body = JobCreated), (status = 400, description = "Not JSON", body = ErrorBody), (status = 422, description = "Invalid settings, `notify` or unknown scene", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn create_job(
    State(state): State<Arc<AppState>>,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<JobCreated>)> {
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
    let (submitted, changes) = state.locked(|farm| -> ApiResult<JobId> {
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
        Ok(id)
    });
    let applied = state.apply(changes);
    let id = submitted?;
    if let Err(e) = applied {
        // Not durable, so not accepted: the job goes away again.
        state.farm.lock().withdraw(id);
        return Err(e.into());
    }
    tracing::info!(job = id, "job submitted");
    for w in &warnings {
        tracing::warn!(job = id, "{w}");
    }
    Ok((StatusCode::CREATED, Json(JobCreated { id, warnings })))
}

#[utoipa::path(
    get,
    path = routes::JOBS,
    context_path = API,
    tag = "jobs",
    summary = "List jobs with their progress, a page at a time",
    description = "Jobs in id order, at most `limit` (default 100, at most 1000) with ids above `after`. \
        When more follow, the `Link` header holds the next page's URL (`rel=\"next\"`); a page shorter \
        than `limit` is the last.",
    params(PageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of jobs", body = Vec<pathfarm_common::protocol::JobInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more jobs follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 400, description = "`limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn list_jobs(State(state): State<Arc<AppState>>, Query(q): Query<PageQuery>) -> ApiResult<Response> {
    let limit = q.limit()?;
    let mut page: Vec<JobInfo> = {
        let farm = state.farm.lock();
        let now = now_ms();
        farm.jobs_after(q.after).take(limit + 1).map(|j| j.info(now)).collect()
    };
    let more = page.len() > limit;
    page.truncate(limit);
    let last = page.last().map(|j| j.id);
    Ok(paged(Json(page), routes::JOBS, limit, more, last))
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
    pub(crate) fn limit(&self) -> ApiResult<usize> {
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
pub(crate) fn paged(body: impl IntoResponse, path: &str, limit: usize, more: bool, last: Option<u64>) -> Response {
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
    path = routes::JOB,
    context_path = API,
    tag = "jobs",
    summary = "A job's state and progress",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job", body = pathfarm_common::protocol::JobInfo), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn get_job(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    Ok(Json(farm.job(id)?.info(now_ms())))
}

#[utoipa::path(
    get,
    path = routes::JOB_LOG,
    context_path = API,
    tag = "jobs",
    summary = "A job's log (retries, failures, blocklists), oldest first",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "Log lines", body = Vec<String>), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn job_log(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    Ok(Json(farm.job(id)?.log.clone()))
}

#[utoipa::path(
    get,
    path = routes::JOB_TILES,
    context_path = API,
    tag = "jobs",
    summary = "Per-tile progress (the tile map)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "Tiles and passes merged per tile", body = crate::http::openapi::TileProgress), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn job_tiles(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    let farm = state.farm.lock();
    let job = farm.job(id)?;
    Ok(Json(serde_json::json!({
        "tiles": job.plan.tiles,
        "passes_merged": job.tile_passes(),
        "passes_total": job.plan.passes.len(),
    })))
}

pub(crate) async fn job_action(
    state: Arc<AppState>,
    id: String,
    action: impl FnOnce(&mut crate::farm::Farm, JobId, u64) -> Result<(), FarmError>,
) -> ApiResult<impl IntoResponse> {
    let id = parse_id("job", &id)?;
    // The change is in effect; if it could not be saved, say so (the checkpoint loop retries).
    let info = state.act(|farm| {
        action(farm, id, now_ms())?;
        Ok(farm.job(id)?.info(now_ms()))
    })?;
    Ok(Json(info))
}

#[utoipa::path(
    post,
    path = routes::JOB_CANCEL,
    context_path = API,
    tag = "jobs",
    summary = "Cancel a job",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn cancel_job(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.cancel(id, now)).await
}

#[utoipa::path(
    post,
    path = routes::JOB_PAUSE,
    context_path = API,
    tag = "jobs",
    summary = "Pause a job (leased units finish)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn pause_job(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.pause(id, now)).await
}

#[utoipa::path(
    post,
    path = routes::JOB_RESUME,
    context_path = API,
    tag = "jobs",
    summary = "Resume a paused job",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 409, description = "Not possible in the job's state", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn resume_job(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<impl IntoResponse> {
    job_action(state, id, |f, id, now| f.resume(id, now)).await
}

#[utoipa::path(
    put,
    path = routes::JOB_PRIORITY,
    context_path = API,
    tag = "jobs",
    summary = "Change a job's priority (higher first)",
    params(("id" = u64, Path, description = "Job id")),
    request_body = crate::http::openapi::PriorityBody,
    security(("client_token" = [])),
    responses((status = 200, description = "The job after the change", body = pathfarm_common::protocol::JobInfo), (status = 422, description = "Bad body", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn set_priority(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<impl IntoResponse> {
    let p: crate::http::openapi::PriorityBody = serde_json::from_slice(&body)
        .map_err(|e| ApiError::unprocessable("invalid_body", format!("expected {{\"priority\": N}}: {e}")))?;
    job_action(state, id, move |f, id, _| f.set_priority(id, p.priority)).await
}

#[utoipa::path(
    delete,
    path = routes::JOB,
    context_path = API,
    tag = "jobs",
    summary = "Delete a job and its images",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 204, description = "Deleted"), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn delete_job(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let id = parse_id("job", &id)?;
    state.act(|farm| farm.delete(id).map(drop))?;
    Ok(StatusCode::NO_CONTENT)
}

pub(crate) async fn resolve_job(state: &Arc<AppState>, id: &str) -> ApiResult<ImageLayers> {
    let id = parse_id("job", id)?;
    let st = state.clone();
    tokio::task::spawn_blocking(move || resolve_banded(&st, id))
        .await
        .map_err(|e| ApiError::internal(format!("resolve task: {e}")))?
        .map_err(ApiError::from)
}

#[utoipa::path(
    get,
    path = routes::JOB_EXR,
    context_path = API,
    tag = "images",
    summary = "The image so far as multi-layer OpenEXR (RGB, albedo, normal, depth, samples, variance)",
    params(("id" = u64, Path, description = "Job id")),
    security(("client_token" = [])),
    responses((status = 200, description = "OpenEXR file", body = Vec<u8>, content_type = "image/x-exr"), (status = 409, description = "The job is a sequence: each frame has its own image (`/jobs/{id}/frames/{frame}/image.exr`)", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn job_exr(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<Response> {
    let layers = match film_or_file(&state, &id, "image.exr").await? {
        Ok(layers) => layers,
        Err((bytes, _)) => return Ok(([(header::CONTENT_TYPE, "image/x-exr")], bytes).into_response()),
    };
    let bytes = tokio::task::spawn_blocking(move || layers.encode_exr())
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(|e| ApiError::internal(format!("EXR encoding: {e}")))?;
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], bytes).into_response())
}

#[utoipa::path(
    get,
    path = routes::JOB_PNG,
    context_path = API,
    tag = "images",
    summary = "The image so far as an sRGB PNG preview",
    description = "Shows the denoised layer when the job has one (`denoise`), else the noisy colour; `layer` picks one.",
    params(("id" = u64, Path, description = "Job id"), ("layer" = Option<String>, Query, description = "`noisy` or `denoised` (409 `no_denoised` while there is none)")),
    security(("client_token" = [])),
    responses((status = 200, description = "PNG file", body = Vec<u8>, content_type = "image/png", headers(("x-pathfarm-preview-layer" = String, description = "`denoised` or `noisy`: the layer shown"))), (status = 409, description = "The job is a sequence: each frame has its own preview (`/jobs/{id}/frames/{frame}/preview.png`); or `layer=denoised` and no denoised layer yet", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn job_png(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    Query(q): Query<PreviewQuery>,
) -> ApiResult<Response> {
    // A film on disk: the written preview (the noisy one beside it for `?layer=noisy`).
    // A written preview shows the denoised layer when the noisy one was written beside it.
    let has_denoised_file = state.job_dir(parse_id("job", &id)?).join(crate::service::NOISY_PREVIEW).is_file();
    let noisy = q.layer == Some(PreviewLayer::Noisy);
    let file = if noisy && has_denoised_file { crate::service::NOISY_PREVIEW } else { "preview.png" };
    let (bytes, ev, denoised) = match film_or_file(&state, &id, file).await? {
        Err((bytes, ev)) => {
            if q.layer == Some(PreviewLayer::Denoised) && !has_denoised_file {
                return Err(no_denoised());
            }
            (bytes, ev, Some(has_denoised_file && !noisy))
        }
        Ok(layers) => {
            let layers = q.select(layers)?;
            let denoised = layers.denoised.is_some();
            let exposure = preview_exposure(&state, parse_id("job", &id)?)?;
            let (bytes, ev) = tokio::task::spawn_blocking(move || {
                let ev = layers.preview_ev(exposure);
                layers.encode_png(ev).map(|b| (b, ev))
            })
            .await
            .map_err(|e| ApiError::internal(e.to_string()))?
            .map_err(|e| ApiError::internal(format!("PNG encoding: {e}")))?;
            (bytes, Some(ev), Some(denoised))
        }
    };
    let mut resp = ([(header::CONTENT_TYPE, "image/png")], bytes).into_response();
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    if let Some(ev) = ev {
        insert_exposure_header(&mut resp, ev);
    }
    if let Some(denoised) = denoised {
        insert_layer_header(&mut resp, denoised);
    }
    Ok(resp)
}

/// The job's image resolved from its film, or (`Err`) its written file `name` with the
/// preview's EV when its film is not in memory (also when it was dropped during the resolve).
async fn film_or_file(
    state: &Arc<AppState>,
    id: &str,
    name: &str,
) -> ApiResult<Result<ImageLayers, (Vec<u8>, Option<f32>)>> {
    if let Some(written) = written_image(state, id, name).await? {
        return Ok(Err(written));
    }
    match resolve_job(state, id).await {
        Ok(layers) => Ok(Ok(layers)),
        Err(e) => match written_image(state, id, name).await? {
            Some(written) => Ok(Err(written)),
            None => Err(e),
        },
    }
}

/// A single-frame job whose film is not in memory (finished and written, or on disk for now):
/// its written file `name` (`image.exr`, `preview.png`, as of its last completed pass) and the
/// preview's EV when known; `None` while the job's film is in memory (resolved from it).
async fn written_image(state: &AppState, id: &str, name: &str) -> ApiResult<Option<(Vec<u8>, Option<f32>)>> {
    let id = parse_id("job", id)?;
    let ev = {
        let farm = state.farm.lock();
        let job = farm.job(id)?;
        match job.image_on_disk() {
            Some(ev) => ev,
            None if !job.sequence
                && job.film().is_none()
                && job.passes_done() > 0
                && state.job_dir(id).join(name).is_file() =>
            {
                None
            }
            None => return Ok(None),
        }
    };
    let bytes = tokio::fs::read(state.job_dir(id).join(name)).await.map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            ApiError::not_found(format!("job {id} has no {name} on disk (its files were removed)"))
        } else {
            crate::service::storage_error(&e, "the job's image").into()
        }
    })?;
    Ok(Some((bytes, ev)))
}

/// The response header that says which layer a PNG preview shows: `denoised` or `noisy`.
pub const LAYER_HEADER: &str = "x-pathfarm-preview-layer";

pub(crate) fn insert_layer_header(resp: &mut Response, denoised: bool) {
    resp.headers_mut().insert(LAYER_HEADER, HeaderValue::from_static(if denoised { "denoised" } else { "noisy" }));
}

/// `?layer=noisy|denoised` of the PNG previews (absent: denoised when there is a denoised layer).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PreviewQuery {
    pub(crate) layer: Option<PreviewLayer>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub(crate) enum PreviewLayer {
    Noisy,
    Denoised,
}

impl PreviewQuery {
    /// The layers a preview shows: without the denoised layer for `noisy`; 409 for `denoised`
    /// while there is none.
    pub(crate) fn select(&self, layers: ImageLayers) -> ApiResult<ImageLayers> {
        match self.layer {
            Some(PreviewLayer::Noisy) => Ok(ImageLayers { denoised: None, ..layers }),
            Some(PreviewLayer::Denoised) if layers.denoised.is_none() => Err(no_denoised()),
            _ => Ok(layers),
        }
    }
}

pub(crate) fn no_denoised() -> ApiError {
    ApiError::new(
        StatusCode::CONFLICT,
        "no_denoised",
        "no denoised layer (yet): the job has no `denoise`, its denoise step has not run, or no worker could denoise \
         (see the job's log)",
    )
}

/// The response header that says which exposure a PNG preview used (EV).
pub const EXPOSURE_HEADER: &str = "x-pathfarm-preview-ev";

pub(crate) fn insert_exposure_header(resp: &mut Response, ev: f32) {
    if let Ok(v) = HeaderValue::from_str(&format!("{ev:.3}")) {
        resp.headers_mut().insert(EXPOSURE_HEADER, v);
    }
}

/// How job `id`'s previews are exposed (its `exposure` and `auto_exposure` settings).
pub(crate) fn preview_exposure(state: &AppState, id: JobId) -> ApiResult<pathfarm_common::film::PreviewExposure> {
    let farm = state.farm.lock();
    Ok(pathfarm_common::film::PreviewExposure::of(&farm.job(id)?.settings))
}
