//! The OpenAPI 3 document, generated from the code with utoipa: `GET /api/v1/openapi.json`.
//!
//! Handlers carry `#[utoipa::path]` attributes where they are defined (api.rs); routes served by
//! closures or by other modules are described by the stubs below. `coordinator/tests/openapi.rs`
//! fails when a route registered in the router is missing here.

use crate::http::dashboard::{Convergence, ConvergencePoint};
use crate::http::events::{FrameWritten, IdOnly, Snapshot};
use axum::http::header;
use axum::response::IntoResponse;
use pathfarm_common::job::{
    EnvironmentSettings, IntegratorSettings, LightSampling, MisHeuristic, Pass, PassSchedule, RenderSettings,
    SamplerKind, TileRect, UnitKey,
};
use pathfarm_common::protocol::API;
use pathfarm_common::protocol::{
    ErrorBody, ErrorDetail, FrameInfo, FrameOrder, FrameState, FramesSummary, JobCreated, JobInfo, JobState,
    LeaseGrant, Notify, NotifyEvent, RegisterRequest, Registered, ReleaseRequest, ResultAccepted, SceneCreated,
    WorkerInfo, WorkerState,
};
use pathfarm_common::routes;
use serde::{Deserialize, Serialize};
use std::sync::OnceLock;
use utoipa::OpenApi;
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityScheme};

/// `POST /jobs` body: the job's own fields plus every [`RenderSettings`] field at the top level.
#[derive(Debug, Serialize, Deserialize, utoipa::ToSchema)]
#[schema(example = json!({"scene_id": "3f2a...", "name": "cornell", "priority": 0, "width": 256, "height": 256, "spp": 64, "integrator": {"type": "path", "max_depth": 8}}))]
pub struct JobRequestBody {
    /// Id returned by `POST /scenes`.
    pub scene_id: String,
    /// At most 256 bytes (UTF-8).
    #[schema(max_length = 256)]
    pub name: Option<String>,
    /// Higher runs first; equal priorities share the workers.
    #[serde(default)]
    pub priority: i32,
    /// Tags a worker must have, all of them, to be leased this job's units (at most 16, each
    /// 1 to 32 characters of `[a-z0-9_-]`). While no live worker has them the job stays queued
    /// and its `waiting` says so. Workers report `cpu`, `avx2` or `avx512f` (the level of
    /// their renderer's kernels), `denoise`, and their `--tags`.
    #[serde(default)]
    #[schema(max_items = 16)]
    pub requires: Vec<String>,
    /// Webhook: when the job reaches one of `events` the coordinator POSTs `{"event", "job":
    /// <JobInfo>, "sent_ms"}` to `url` with `X-Pathfarm-Event` and `X-Pathfarm-Signature:
    /// sha256=<hex HMAC-SHA256 of the body keyed by --webhook-secret>` (5 s per attempt, 5
    /// attempts with exponential backoff; outcomes in the job's log). Refused (422) when the
    /// coordinator has no `--webhook-secret`.
    #[serde(default)]
    pub notify: Option<pathfarm_common::protocol::Notify>,
    // The RenderSettings fields, spelled out: a flattened struct that refuses unknown fields
    // becomes an `allOf` that no object can satisfy.
    #[schema(minimum = 1)]
    pub width: u32,
    #[schema(minimum = 1)]
    pub height: u32,
    #[schema(minimum = 1)]
    pub spp: u32,
    #[serde(default)]
    pub seed: u64,
    /// Scene camera index; absent = camera 0 or a camera framing the scene.
    pub camera: Option<usize>,
    #[serde(default)]
    pub integrator: Option<pathfarm_common::job::IntegratorSettings>,
    #[serde(default)]
    pub sampler: Option<pathfarm_common::job::SamplerKind>,
    #[schema(minimum = 8, maximum = 1024)]
    pub tile_size: Option<u32>,
    #[serde(default)]
    pub passes: Option<pathfarm_common::job::PassSchedule>,
    /// Animation frame: the scene is posed at `frame / fps` seconds.
    #[serde(default)]
    pub frame: i32,
    /// Frames per second (default 24).
    #[schema(exclusive_minimum = 0.0, maximum = 10000.0)]
    pub fps: Option<f32>,
    /// Motion blur: shutter open for this fraction of a frame (default 0 = off).
    #[schema(minimum = 0.0, maximum = 1.0)]
    pub shutter: Option<f32>,
    /// glTF animations that play (by name); absent = all.
    pub animations: Option<Vec<String>>,
    /// Preview (PNG) exposure in EV, default 0; the EXR always holds the true radiance.
    #[schema(minimum = -32.0, maximum = 32.0)]
    pub exposure: Option<f32>,
    /// Previews expose automatically (log-average luminance to middle grey); `exposure` adds to
    /// it. The EV used is in the PNG's `x-pathfarm-preview-ev` header.
    pub auto_exposure: Option<bool>,
    /// A sequence: the frames to render, `"1-100"`, `"1-100x5"` (every 5th) or `"1,5,10-20"`
    /// (at most 100,000; frames x tiles x passes count against the unit limit). Each frame is
    /// rendered with `frame` set to it and written to `frames/NNNN/image.exr` and
    /// `preview.png`; the job's own `image.exr` is then 409. Absent: the one frame `frame`.
    pub frames: Option<String>,
    /// `frame` (default): frame by frame, memory bounded by the frames in progress;
    /// `sequence_preview`: every frame's first pass before any frame's second (every frame's
    /// film at once: refused when they do not fit `--film-memory-mb`).
    pub order: Option<pathfarm_common::protocol::FrameOrder>,
    /// Environment light: `{"file": "sky.exr", "intensity": 1, "rotation_deg": 0}` (an
    /// equirectangular `.exr`/`.hdr` beside the bundle's `.gltf`/`.glb`) or `{"color": [r, g, b]}`.
    pub environment: Option<pathfarm_common::job::EnvironmentSettings>,
    /// Thin lens: aperture radius in scene units (0 = pinhole; f-number N at focal length f:
    /// f / (2 N)). Not with bdpt.
    #[schema(minimum = 0.0, maximum = 1000000.0)]
    pub aperture_radius: Option<f32>,
    /// Adaptive sampling `{"threshold": 0.1, "min_spp": 16}`: after each pass (from `min_spp`
    /// samples on) 8x8 pixel blocks whose relative error is at most `threshold` get no more
    /// samples; `samples.Y` shows the per-pixel count. Not with bdpt.
    pub adaptive: Option<pathfarm_common::adaptive::AdaptiveSettings>,
    /// Also a `denoised` layer (OIDN) in the EXR, shown by the preview, made by a worker with the
    /// tag `denoise` after each frame's last pass; a farm without one (for `--denoise-grace-ms`)
    /// finishes without the layer and the job's log says why.
    pub denoise: Option<bool>,
    /// With `denoise`: also denoise after every completed pass (the preview; never holds a frame
    /// back).
    pub denoise_preview: Option<bool>,
    /// Distance in focus along the view axis (scene units); required with an aperture.
    #[schema(exclusive_minimum = 0.0)]
    pub focus_distance: Option<f32>,
}

/// `PUT /jobs/{id}/priority` body (the one definition: the handler reads it, the document
/// shows it).
#[derive(Debug, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PriorityBody {
    pub priority: i32,
}

/// `GET /jobs/{id}/tiles` answer.
#[derive(Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TileProgress {
    /// The job's tiles, row-major.
    pub tiles: Vec<TileRect>,
    /// Per tile, the passes merged so far.
    pub passes_merged: Vec<u32>,
    pub passes_total: usize,
}

#[utoipa::path(
    get,
    path = routes::HEALTHZ,
    tag = "service",
    summary = "Liveness probe",
    responses((status = 200, description = "`ok`", body = String, content_type = "text/plain"))
)]
#[allow(dead_code)]
fn healthz() {}

#[utoipa::path(
    get,
    path = routes::OPENAPI,
    context_path = API,
    tag = "service",
    summary = "This document",
    responses((status = 200, description = "OpenAPI 3.1 document", body = Object))
)]
#[allow(dead_code)]
fn openapi_doc() {}

#[utoipa::path(
    get,
    path = routes::EVENTS,
    context_path = API,
    tag = "events",
    summary = "Live events (server-sent events)",
    description = "A `text/event-stream`. Messages (SSE `event:` name, JSON `data:`): `snapshot` \
        (first: `{jobs, workers}`), `job` (a JobInfo), `job_deleted` (`{id}`), `workers` (the \
        WorkerInfo list; on changes and every 2 s), `image` (`{id}`: new preview/EXR), `resync` \
        (`{}`: messages were dropped, fetch again). Bursts are coalesced to at most one message \
        per job every 250 ms; a comment line every 15 s keeps the connection open. The client \
        token may be passed as `?token=` because EventSource cannot set headers.",
    params(crate::http::events::EventsQuery),
    security(("client_token" = [])),
    responses(
        (status = 200, description = "Event stream; `snapshot` data shown", body = Snapshot, content_type = "text/event-stream"),
        (status = 401, description = "Missing or invalid token", body = ErrorBody),
        (status = 403, description = "Wrong role for the token", body = ErrorBody),
    )
)]
#[allow(dead_code)]
fn events() {}

#[utoipa::path(
    get,
    path = routes::JOB_CONVERGENCE,
    context_path = API,
    tag = "jobs",
    summary = "Estimated image noise after each completed pass",
    description = "Measured from the film's variance layer (variance of each pixel's mean) when \
        a pass completes: `rmse` is the root mean square standard error of pixel luminance. \
        Takes `?token=` like /events.",
    params(("id" = u64, Path, description = "Job id"), crate::http::events::EventsQuery),
    security(("client_token" = [])),
    responses(
        (status = 200, description = "Noise per pass", body = Convergence),
        (status = 400, description = "Bad id", body = ErrorBody),
        (status = 404, description = "No such job", body = ErrorBody),
        (status = 401, description = "Missing or invalid token", body = ErrorBody),
    )
)]
#[allow(dead_code)]
fn convergence() {}

#[utoipa::path(get, path = routes::DASHBOARD, tag = "dashboard", summary = "The web dashboard (HTML)",
    responses((status = 200, description = "HTML page", body = String, content_type = "text/html")))]
#[allow(dead_code)]
fn dashboard_page() {}

#[utoipa::path(get, path = routes::DASHBOARD_SCRIPT, tag = "dashboard", summary = "Dashboard script",
    responses((status = 200, description = "JavaScript", body = String, content_type = "text/javascript")))]
#[allow(dead_code)]
fn dashboard_script() {}

#[utoipa::path(get, path = routes::DASHBOARD_STYLE, tag = "dashboard", summary = "Dashboard stylesheet",
    responses((status = 200, description = "CSS", body = String, content_type = "text/css")))]
#[allow(dead_code)]
fn dashboard_style() {}

#[utoipa::path(get, path = routes::DASHBOARD_ICON, tag = "dashboard", summary = "Dashboard icon",
    responses((status = 200, description = "SVG", body = String, content_type = "image/svg+xml")))]
#[allow(dead_code)]
fn dashboard_icon() {}

struct SecuritySchemes;

impl utoipa::Modify for SecuritySchemes {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        for name in ["client_token", "worker_token", "metrics_token"] {
            components.add_security_scheme(name, SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)));
        }
    }
}

/// Binary bodies (scene bundles, result frames, EXR and PNG images) as OpenAPI types them:
/// `{"type": "string", "format": "binary", "contentMediaType": ...}`. utoipa writes `Vec<u8>` as an
/// array of integers, which generated clients then try to send and parse as JSON.
struct BinaryBodies;

fn is_binary_media_type(media_type: &str) -> bool {
    media_type == "application/octet-stream" || media_type.starts_with("image/")
}

fn binary_schema(media_type: &str) -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, SchemaFormat, Type};
    ObjectBuilder::new()
        .schema_type(Type::String)
        .format(Some(SchemaFormat::KnownFormat(KnownFormat::Binary)))
        .content_media_type(media_type)
        .into()
}

fn type_binary_content<'a>(content: impl IntoIterator<Item = (&'a String, &'a mut utoipa::openapi::content::Content)>) {
    for (media_type, c) in content {
        if is_binary_media_type(media_type) {
            c.schema = Some(binary_schema(media_type));
        }
    }
}

impl utoipa::Modify for BinaryBodies {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        for item in openapi.paths.paths.values_mut() {
            let operations = [
                &mut item.get,
                &mut item.put,
                &mut item.post,
                &mut item.delete,
                &mut item.options,
                &mut item.head,
                &mut item.patch,
                &mut item.trace,
            ];
            for op in operations.into_iter().flatten() {
                if let Some(body) = &mut op.request_body {
                    type_binary_content(body.content.iter_mut());
                }
                for response in op.responses.responses.values_mut() {
                    if let utoipa::openapi::RefOr::T(r) = response {
                        type_binary_content(r.content.iter_mut());
                    }
                }
            }
        }
    }
}

/// Tuples (`(JobId, UnitKey)`, `[u32; 2]`) as generators read them: utoipa writes
/// `"prefixItems": [...], "items": false`, and `"items": false` is refused by generators such as
/// openapi-python-client. Here `items` becomes `{}` with `minItems` = `maxItems` = the tuple's
/// length; `prefixItems` still types each position.
fn open_tuples(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(map) => {
            if map.get("items") == Some(&serde_json::Value::Bool(false))
                && let Some(n) = map.get("prefixItems").and_then(|p| p.as_array()).map(Vec::len)
            {
                map.insert("items".into(), serde_json::json!({}));
                map.insert("minItems".into(), n.into());
                map.insert("maxItems".into(), n.into());
            }
            map.values_mut().for_each(open_tuples);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(open_tuples),
        _ => {}
    }
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "pathfarm",
        description = "Distributed render farm: scenes, jobs, images, live events, and the worker protocol. \
            Every error is `{\"error\": {\"code\", \"message\"}}`. Bearer tokens (client, worker) are \
            required only when the coordinator is started with them."
    ),
    paths(
        crate::http::upload_scene,
        crate::http::download_scene,
        crate::http::delete_scene,
        crate::http::create_job,
        crate::http::list_jobs,
        crate::http::get_job,
        crate::http::delete_job,
        crate::http::cancel_job,
        crate::http::pause_job,
        crate::http::resume_job,
        crate::http::set_priority,
        crate::http::job_log,
        crate::http::job_tiles,
        crate::http::job_exr,
        crate::http::job_png,
        crate::http::job_frames,
        crate::http::frame_exr,
        crate::http::frame_png,
        crate::http::list_workers,
        crate::http::register,
        crate::http::heartbeat,
        crate::http::lease,
        crate::http::upload_result,
        crate::http::release,
        crate::http::denoise_input,
        crate::http::upload_denoised,
        crate::http::metrics,
        healthz,
        openapi_doc,
        events,
        convergence,
        dashboard_page,
        dashboard_script,
        dashboard_style,
        dashboard_icon,
    ),
    components(schemas(
        ErrorBody, ErrorDetail, SceneCreated, JobState, JobCreated, JobInfo, WorkerState, WorkerInfo,
        RegisterRequest, Registered, LeaseGrant, pathfarm_common::protocol::LeaseKind, ReleaseRequest, ResultAccepted, RenderSettings, EnvironmentSettings,
        IntegratorSettings, MisHeuristic, LightSampling, SamplerKind, PassSchedule, TileRect, Pass, UnitKey,
        JobRequestBody, FrameOrder, FrameState, FrameInfo, FramesSummary, Notify, NotifyEvent, PriorityBody, TileProgress, Snapshot, IdOnly, FrameWritten, Convergence, ConvergencePoint,
        pathfarm_common::adaptive::BlockMaskWire,
    )),
    modifiers(&SecuritySchemes, &BinaryBodies),
    tags(
        (name = "scenes", description = "Scene bundles, content-addressed"),
        (name = "jobs", description = "Render jobs and their progress"),
        (name = "images", description = "A job's image so far"),
        (name = "workers", description = "The worker list (clients)"),
        (name = "events", description = "Live updates"),
        (name = "worker protocol", description = "Routes the worker daemons use"),
        (name = "service", description = "Health, metrics, this document"),
        (name = "dashboard", description = "The web dashboard's files"),
    )
)]
pub struct ApiDoc;

/// The document.
pub fn document() -> utoipa::openapi::OpenApi {
    let mut doc = ApiDoc::openapi();
    doc.info.version = env!("CARGO_PKG_VERSION").to_string();
    doc
}

/// The document as served: [`document`] with tuples opened (see `open_tuples`).
pub fn document_json() -> serde_json::Value {
    let mut value = serde_json::to_value(document()).unwrap_or_else(|e| serde_json::json!({"error": e.to_string()}));
    open_tuples(&mut value);
    value
}

/// `GET /api/v1/openapi.json`.
pub async fn openapi_json() -> impl IntoResponse {
    static JSON: OnceLock<String> = OnceLock::new();
    let body = JSON.get_or_init(|| {
        serde_json::to_string_pretty(&document_json()).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    });
    ([(header::CONTENT_TYPE, "application/json")], body.as_str())
}
