//! Scene routes: upload, download, delete.

use super::*;
use pathfarm_common::routes;

#[utoipa::path(
    post,
    path = routes::SCENES,
    context_path = API,
    tag = "scenes",
    summary = "Upload a scene (.glb, .gltf or tar bundle); content-addressed by SHA-256",
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "A .glb, a self-contained .gltf, or a tar of a .gltf with its files"),
    security(("client_token" = [])),
    responses((status = 201, description = "Stored (or already stored)", body = SceneCreated), (status = 422, description = "Not a loadable scene, or over a limit", body = ErrorBody), (status = 413, description = "Body larger than --max-upload-mb (a declared `Content-Length` above it is refused before the body is read)", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn upload_scene(
    State(state): State<Arc<AppState>>,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<SceneCreated>)> {
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
    path = routes::SCENE,
    context_path = API,
    tag = "scenes",
    summary = "Download a scene bundle (workers and clients)",
    params(("id" = String, Path, description = "Scene id (SHA-256, hex)")),
    security(("client_token" = []), ("worker_token" = [])),
    responses((status = 400, description = "Bad id", body = ErrorBody), (status = 200, description = "The bundle bytes", body = Vec<u8>, content_type = "application/octet-stream"), (status = 404, description = "No such scene", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn download_scene(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<Response> {
    if !is_scene_id(&id) {
        return Err(ApiError::not_found(format!("scene {id:?} does not exist")));
    }
    let path = state.scenes.bundle_path(&id);
    let bytes = tokio::fs::read(&path).await.map_err(|_| ApiError::not_found(format!("scene {id} does not exist")))?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

#[utoipa::path(
    delete,
    path = routes::SCENE,
    context_path = API,
    tag = "scenes",
    summary = "Delete a scene bundle that no unfinished job uses (finished jobs keep their images)",
    params(("id" = String, Path, description = "Scene id (SHA-256, hex)")),
    security(("client_token" = [])),
    responses((status = 204, description = "Deleted"), (status = 409, description = "Queued, running or paused jobs use the scene (named in the message)", body = ErrorBody), (status = 404, description = "No such scene", body = ErrorBody), (status = 400, description = "The id is not a scene id (64 lowercase hex digits)", body = ErrorBody), (status = 401, description = "Missing or invalid token", body = ErrorBody), (status = 403, description = "Wrong role for the token", body = ErrorBody)),
)]
pub(crate) async fn delete_scene(State(state): State<Arc<AppState>>, Path(id): Path<String>) -> ApiResult<StatusCode> {
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
    let removed = state.scenes.remove(&id).map_err(|e| crate::service::storage_error(&e, "the scene's deletion"))?;
    drop(farm);
    if removed { Ok(StatusCode::NO_CONTENT) } else { Err(ApiError::not_found(format!("scene {id} does not exist"))) }
}
