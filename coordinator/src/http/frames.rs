//! A sequence's frames: the list and each frame's images.

use super::*;
use pathfarm_common::routes;

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
    path = routes::JOB_FRAMES,
    context_path = API,
    tag = "jobs",
    summary = "A job's frames with their state and progress, a page at a time",
    description = "Frames in the order of the job's frame set, at most `limit` (default 100, at most 1000) \
        with `index` above `after`. When more follow, the `Link` header holds the next page's URL. A \
        single-frame job lists its one frame.",
    params(("id" = u64, Path, description = "Job id"), FramePageQuery),
    security(("client_token" = [])),
    responses((status = 200, description = "A page of frames", body = Vec<pathfarm_common::protocol::FrameInfo>, headers(("link" = String, description = "`<URL>; rel=\"next\"` when more frames follow"))), (status = 422, description = "`limit` out of range", body = ErrorBody), (status = 404, description = "No such job", body = ErrorBody), (status = 400, description = "The id, `limit` or `after` is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn job_frames(
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
    Ok(paged(Json(page), &routes::fill(routes::JOB_FRAMES, &[&id]), limit, more, last))
}

/// Where a frame's image comes from.
pub(crate) enum FrameSource {
    /// Written: `frames/NNNN/` on disk.
    File(std::path::PathBuf),
    /// Rendering or being written: resolved from its film.
    Film,
}

pub(crate) fn frame_source(state: &AppState, id: &str, frame: &str) -> ApiResult<(JobId, i32, FrameSource)> {
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
        return Ok((id, n, FrameSource::File(crate::service::store::frame_dir(&state.job_dir(id), n))));
    }
    Ok((id, n, FrameSource::Film))
}

pub(crate) async fn frame_image(
    state: Arc<AppState>,
    id: String,
    frame: String,
    png: bool,
    layer: PreviewQuery,
) -> ApiResult<Response> {
    let (id, n, source) = frame_source(&state, &id, &frame)?;
    let (bytes, denoised) = match source {
        FrameSource::File(dir) => {
            // A frame written with a denoised layer has its noisy preview beside.
            let noisy = dir.join(crate::service::NOISY_PREVIEW);
            let file = match layer.layer {
                _ if !png => "image.exr",
                Some(PreviewLayer::Noisy) if noisy.exists() => crate::service::NOISY_PREVIEW,
                Some(PreviewLayer::Denoised) if !noisy.exists() => return Err(no_denoised()),
                _ => "preview.png",
            };
            let path = dir.join(file);
            let denoised = file == "preview.png" && noisy.exists();
            let bytes = tokio::fs::read(&path).await.map_err(|e| {
                if e.kind() == std::io::ErrorKind::NotFound {
                    ApiError::not_found(format!("frame {n} of job {id} has no image on disk (its files were removed)"))
                } else {
                    crate::service::storage_error(&e, "the frame's image").into()
                }
            })?;
            (bytes, denoised)
        }
        FrameSource::Film => {
            let st = state.clone();
            let exposure = preview_exposure(&state, id)?;
            tokio::task::spawn_blocking(move || -> ApiResult<(Vec<u8>, bool)> {
                let layers = resolve_film_banded(&st, id, Some(n))?;
                if png {
                    let layers = layer.select(layers)?;
                    let ev = layers.preview_ev(exposure);
                    let png = layers.encode_png(ev).map_err(|e| ApiError::internal(format!("PNG encoding: {e}")))?;
                    Ok((png, layers.denoised.is_some()))
                } else {
                    let exr = layers.encode_exr().map_err(|e| ApiError::internal(format!("EXR encoding: {e}")))?;
                    Ok((exr, layers.denoised.is_some()))
                }
            })
            .await
            .map_err(|e| ApiError::internal(format!("resolve task: {e}")))??
        }
    };
    let mut resp = ([(header::CONTENT_TYPE, if png { "image/png" } else { "image/x-exr" })], bytes).into_response();
    resp.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    if png {
        insert_layer_header(&mut resp, denoised);
    }
    Ok(resp)
}

#[utoipa::path(
    get,
    path = routes::FRAME_EXR,
    context_path = API,
    tag = "images",
    summary = "One frame as multi-layer OpenEXR: the written file once the frame is done, its film so far before",
    params(("id" = u64, Path, description = "Job id"), ("frame" = i32, Path, description = "Frame number")),
    security(("client_token" = [])),
    responses((status = 200, description = "OpenEXR file", body = Vec<u8>, content_type = "image/x-exr"), (status = 409, description = "The frame has not started (or the job was cancelled before it finished)", body = ErrorBody), (status = 404, description = "No such job, or the frame is not in its frame set", body = ErrorBody), (status = 400, description = "The id or the frame is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn frame_exr(
    State(state): State<Arc<AppState>>,
    Path((id, frame)): Path<(String, String)>,
) -> ApiResult<Response> {
    frame_image(state, id, frame, false, PreviewQuery::default()).await
}

#[utoipa::path(
    get,
    path = routes::FRAME_PNG,
    context_path = API,
    tag = "images",
    summary = "One frame as an sRGB PNG preview (the dashboard's thumbnails)",
    description = "Shows the frame's denoised layer when it has one (`denoise`), else the noisy colour; `layer` picks one.",
    params(("id" = u64, Path, description = "Job id"), ("frame" = i32, Path, description = "Frame number"), ("layer" = Option<String>, Query, description = "`noisy` or `denoised` (409 `no_denoised` while there is none)")),
    security(("client_token" = [])),
    responses((status = 200, description = "PNG file", body = Vec<u8>, content_type = "image/png", headers(("x-pathfarm-preview-layer" = String, description = "`denoised` or `noisy`: the layer shown"))), (status = 409, description = "The frame has not started (or the job was cancelled before it finished)", body = ErrorBody), (status = 404, description = "No such job, or the frame is not in its frame set", body = ErrorBody), (status = 400, description = "The id or the frame is not a number", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn frame_png(
    State(state): State<Arc<AppState>>,
    Path((id, frame)): Path<(String, String)>,
    Query(q): Query<PreviewQuery>,
) -> ApiResult<Response> {
    frame_image(state, id, frame, true, q).await
}
