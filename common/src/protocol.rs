//! Wire protocol between clients, the coordinator and workers: the JSON bodies of the REST API
//! and the binary format of a unit's result.
//!
//! JSON is for control (small, debuggable); results are binary: a 64 x 64 tile is 4096 pixels of
//! 64-byte sums (256 KiB), parsed straight into the tile accumulator, and BDPT's splats travel
//! as sparse entries (only the pixels a unit's light paths reached).

use crate::film::{PIXEL_BYTES, PixelSums, SplatBuffer, TileAccum};
use crate::frames::FrameSet;
use crate::job::{Pass, RenderSettings, TileRect, UnitKey};
use serde::{Deserialize, Serialize};

/// API path prefix.
pub const API: &str = "/api/v1";

/// Longest job name, in bytes (UTF-8).
pub const MAX_JOB_NAME_BYTES: usize = 256;

/// Items per page of the list routes (`GET /jobs`, `GET /workers`) when `limit` is not given.
pub const DEFAULT_PAGE_LIMIT: usize = 100;
/// Largest `limit` of the list routes.
pub const MAX_PAGE_LIMIT: usize = 1000;

/// Header carrying a worker's own secret (returned by `POST /workers/register`) on the lease,
/// heartbeat, result and release requests: a lease is bound to the worker it was granted to.
pub const WORKER_SECRET_HEADER: &str = "x-pathfarm-worker-secret";

/// Job identifier (a decimal number in URLs).
pub type JobId = u64;
/// Worker identifier assigned at registration.
pub type WorkerId = u64;
/// Lease identifier; one per hand-out of a unit, never reused.
pub type LeaseId = u64;

/// Every error body: `{"error": {"code": "...", "message": "..."}}`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct ErrorDetail {
    /// Stable machine-readable code, e.g. `invalid_scene`, `lease_lost`, `not_found`.
    pub code: String,
    pub message: String,
}

/// `POST /scenes` answer.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct SceneCreated {
    /// SHA-256 of the uploaded bundle, lower-case hex.
    pub scene_id: String,
    pub triangles: usize,
    /// Loader warnings (e.g. a dangling texture that was dropped).
    pub warnings: Vec<String>,
}

/// Lifecycle of a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    Paused,
    Completed,
    Failed,
    Cancelled,
}

impl JobState {
    /// No more work will be done.
    pub fn is_finished(self) -> bool {
        matches!(self, JobState::Completed | JobState::Failed | JobState::Cancelled)
    }
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Paused => "paused",
            JobState::Completed => "completed",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
}

/// Tags a worker may report or a job require, at most.
pub const MAX_TAGS: usize = 16;
/// Longest tag, in bytes.
pub const MAX_TAG_LEN: usize = 32;

/// Checks a list of worker tags or required tags: at most [`MAX_TAGS`], each 1 to
/// [`MAX_TAG_LEN`] characters of `[a-z0-9_-]`, no duplicates. `what` names the field in errors.
pub fn validate_tags(tags: &[String], what: &str) -> Result<(), String> {
    if tags.len() > MAX_TAGS {
        return Err(format!("{what} has {} tags; at most {MAX_TAGS} are allowed", tags.len()));
    }
    for (i, t) in tags.iter().enumerate() {
        let ok = !t.is_empty()
            && t.len() <= MAX_TAG_LEN
            && t.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_' || b == b'-');
        if !ok {
            let shown: String = t.chars().take(MAX_TAG_LEN + 1).collect();
            return Err(format!("{what}: tag {shown:?} is not 1 to {MAX_TAG_LEN} characters of a-z, 0-9, '_' and '-'"));
        }
        if tags[..i].contains(t) {
            return Err(format!("{what}: tag {t:?} is given twice"));
        }
    }
    Ok(())
}

/// A job state a webhook may be sent for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum NotifyEvent {
    /// The first unit was leased.
    Started,
    Completed,
    Failed,
    Cancelled,
}

impl NotifyEvent {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Started => "started",
            Self::Completed => "completed",
            Self::Failed => "failed",
            Self::Cancelled => "cancelled",
        }
    }
}

/// Longest webhook URL accepted.
pub const MAX_NOTIFY_URL_LEN: usize = 2048;

/// A job's webhook: the coordinator POSTs to `url` when the job reaches one of `events`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Notify {
    /// An `http://` or `https://` URL of at most 2048 characters.
    #[schema(max_length = 2048)]
    pub url: String,
    /// A non-empty subset of `started`, `completed`, `failed`, `cancelled`.
    #[schema(min_items = 1, max_items = 4)]
    pub events: Vec<NotifyEvent>,
}

impl Notify {
    /// Parses and checks the `notify` field of a job body.
    pub fn from_json(v: serde_json::Value) -> Result<Self, String> {
        let n: Notify = serde_json::from_value(v).map_err(|e| format!("notify: {e}"))?;
        n.validate()?;
        Ok(n)
    }

    /// The URL is http or https with a host and at most [`MAX_NOTIFY_URL_LEN`] characters;
    /// the events are a non-empty set.
    pub fn validate(&self) -> Result<(), String> {
        let len = self.url.chars().count();
        if len > MAX_NOTIFY_URL_LEN {
            return Err(format!("notify.url is {len} characters long; the limit is {MAX_NOTIFY_URL_LEN}"));
        }
        let rest = self.url.strip_prefix("http://").or_else(|| self.url.strip_prefix("https://"));
        let host = rest.map(|r| r.split(['/', '?', '#']).next().unwrap_or_default());
        let bad_char = self.url.chars().any(|c| c.is_whitespace() || c.is_control());
        if host.is_none_or(|h| h.is_empty() || h.starts_with(':')) || bad_char {
            let shown: String = self.url.chars().take(80).collect();
            return Err(format!("notify.url {shown:?} is not an http:// or https:// URL with a host"));
        }
        if self.events.is_empty() {
            return Err("notify.events is empty: give some of started, completed, failed, cancelled".into());
        }
        for (i, e) in self.events.iter().enumerate() {
            if self.events[..i].contains(e) {
                return Err(format!("notify.events: {:?} is given twice", e.as_str()));
            }
        }
        Ok(())
    }

    pub fn wants(&self, event: NotifyEvent) -> bool {
        self.events.contains(&event)
    }
}

/// `POST /jobs` body: the job's own fields plus every field of [`RenderSettings`] at the top
/// level, e.g. `{"scene_id": "...", "name": "cornell", "priority": 0, "width": 256, ...}`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct JobRequest {
    pub scene_id: String,
    pub name: Option<String>,
    pub priority: i32,
    /// Tags a worker must have (every one) to be leased this job's units.
    pub requires: Vec<String>,
    /// Webhook to call when the job reaches some states.
    #[serde(default)]
    pub notify: Option<Notify>,
    /// The frames to render (`"1-100"`, `"1-100x5"`, `"1,5,10-20"`); `None`: the one frame
    /// `settings.frame`.
    #[serde(default)]
    pub frames: Option<FrameSet>,
    /// In which order a multi-frame job's units are handed out.
    #[serde(default)]
    pub order: FrameOrder,
    pub settings: RenderSettings,
}

/// In which order a multi-frame job's units are handed out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FrameOrder {
    /// Frame by frame: a frame's units (pass-major) before the next frame's. Frames in
    /// progress at once are bounded (film memory), so coordinator memory does not grow with the
    /// sequence's length.
    #[default]
    Frame,
    /// Every frame gets its first pass before any frame gets its second (a rough preview of the
    /// whole shot early). Every frame's film is held at once: the job must fit the film budget.
    SequencePreview,
}

impl FrameOrder {
    pub fn as_str(self) -> &'static str {
        match self {
            FrameOrder::Frame => "frame",
            FrameOrder::SequencePreview => "sequence_preview",
        }
    }
}

/// Where one frame of a job stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FrameState {
    /// Not started: no film, no units yet.
    Pending,
    /// Its film exists and units are handed out or merging.
    Rendering,
    /// Every unit is merged; its image is being written.
    Writing,
    /// Written to `frames/NNNN/image.exr` and `preview.png`; its film is dropped.
    Done,
}

/// One frame of a job (`GET /jobs/{id}/frames`, and the frames in progress in `JobInfo`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct FrameInfo {
    /// Position in the job's frame set (0-based): the `after` cursor of the paged list.
    pub index: u32,
    /// The frame number.
    pub frame: i32,
    pub state: FrameState,
    /// Passes merged for every tile of the frame.
    pub passes_done: u32,
}

/// A job's frames, summarized (bounded whatever the frame count).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct FramesSummary {
    /// The job was submitted with `frames`: each frame has its own image
    /// (`/jobs/{id}/frames/{frame}/image.exr`); otherwise the job's image is `/jobs/{id}/image.exr`.
    pub sequence: bool,
    /// The frame set as submitted (`"7"` for a single-frame job).
    pub spec: String,
    pub order: FrameOrder,
    pub total: u32,
    pub done: u32,
    /// Frames whose film exists (rendering or writing).
    pub in_progress: u32,
    /// The first frames in progress (at most 64); every frame: `GET /jobs/{id}/frames`.
    pub current: Vec<FrameInfo>,
}

impl JobRequest {
    /// The JSON body as the API takes it (settings flattened to the top level).
    pub fn to_json(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(&self.settings).unwrap_or_default();
        if let Some(o) = v.as_object_mut() {
            o.insert("scene_id".into(), self.scene_id.clone().into());
            if let Some(n) = &self.name {
                o.insert("name".into(), n.clone().into());
            }
            o.insert("priority".into(), self.priority.into());
            if !self.requires.is_empty() {
                o.insert("requires".into(), self.requires.clone().into());
            }
            if let Some(n) = &self.notify {
                o.insert("notify".into(), serde_json::to_value(n).unwrap_or_default());
            }
            if let Some(f) = &self.frames {
                o.insert("frames".into(), f.spec().into());
            }
            if self.order != FrameOrder::Frame {
                o.insert("order".into(), self.order.as_str().into());
            }
        }
        v
    }

    /// Parses the API body; unknown fields are refused with a message that names them.
    pub fn from_json(mut v: serde_json::Value) -> Result<Self, String> {
        let o = v.as_object_mut().ok_or("the job must be a JSON object")?;
        let scene_id = match o.remove("scene_id") {
            Some(serde_json::Value::String(s)) => s,
            Some(_) => return Err("scene_id must be a string".into()),
            None => return Err("missing field `scene_id`".into()),
        };
        let name = match o.remove("name") {
            None | Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(s)) if s.len() > MAX_JOB_NAME_BYTES => {
                return Err(format!("name is {} bytes long; the limit is {MAX_JOB_NAME_BYTES} bytes", s.len()));
            }
            Some(serde_json::Value::String(s)) => Some(s),
            Some(_) => return Err("name must be a string".into()),
        };
        let priority = match o.remove("priority") {
            None | Some(serde_json::Value::Null) => 0,
            Some(p) => p
                .as_i64()
                .and_then(|p| i32::try_from(p).ok())
                .ok_or("priority must be an integer between -2^31 and 2^31-1")?,
        };
        let requires = match o.remove("requires") {
            None | Some(serde_json::Value::Null) => Vec::new(),
            Some(serde_json::Value::Array(a)) if a.len() > MAX_TAGS => {
                return Err(format!("requires has {} tags; at most {MAX_TAGS} are allowed", a.len()));
            }
            Some(serde_json::Value::Array(a)) => a
                .into_iter()
                .map(|t| match t {
                    serde_json::Value::String(s) => Ok(s),
                    _ => Err("requires must be an array of strings".to_string()),
                })
                .collect::<Result<Vec<_>, _>>()?,
            Some(_) => return Err("requires must be an array of strings".into()),
        };
        validate_tags(&requires, "requires")?;
        let notify = match o.remove("notify") {
            None | Some(serde_json::Value::Null) => None,
            Some(n) => Some(Notify::from_json(n)?),
        };
        let frames = match o.remove("frames") {
            None | Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(s)) => Some(FrameSet::parse(&s).map_err(|e| e.to_string())?),
            Some(serde_json::Value::Number(n)) => Some(FrameSet::parse(&n.to_string()).map_err(|e| e.to_string())?),
            Some(_) => return Err("frames must be a string such as \"1-100\", \"1-100x5\" or \"1,5,10-20\"".into()),
        };
        let order = match o.remove("order") {
            None | Some(serde_json::Value::Null) => FrameOrder::Frame,
            Some(serde_json::Value::String(s)) if s == "frame" => FrameOrder::Frame,
            Some(serde_json::Value::String(s)) if s == "sequence_preview" => FrameOrder::SequencePreview,
            Some(other) => return Err(format!("order must be \"frame\" or \"sequence_preview\", got {other}")),
        };
        let settings: RenderSettings = serde_json::from_value(v).map_err(|e| e.to_string())?;
        Ok(Self { scene_id, name, priority, requires, notify, frames, order, settings })
    }
}

/// `POST /jobs` answer (201).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct JobCreated {
    pub id: JobId,
    /// What the job will look like that the submitter may not expect (also in the job's log),
    /// e.g. a scene without lights and a job without an environment renders black.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// `GET /jobs/{id}`: a job's state and progress.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct JobInfo {
    pub id: JobId,
    pub name: String,
    pub scene_id: String,
    pub state: JobState,
    pub priority: i32,
    pub settings: RenderSettings,
    pub tiles: u32,
    pub passes_total: u32,
    /// Passes merged for every tile.
    pub passes_done: u32,
    pub units_total: u64,
    pub units_merged: u64,
    /// Samples per pixel merged for the whole image (the last complete pass's end).
    pub spp_done: u32,
    /// Pixel samples merged so far (over all tiles).
    pub samples_done: u64,
    pub samples_total: u64,
    /// `samples_done / samples_total`.
    pub progress: f64,
    /// Pixel samples per second over the job's running time.
    pub samples_per_sec: f64,
    pub eta_secs: Option<f64>,
    pub elapsed_secs: f64,
    /// Unix time in milliseconds.
    pub created_ms: u64,
    pub finished_ms: Option<u64>,
    /// Why the job failed.
    pub error: Option<String>,
    /// Workers refused for this job after repeated failures.
    pub blocklist: Vec<WorkerId>,
    /// Tags a worker must have to render this job.
    #[serde(default)]
    pub requires: Vec<String>,
    /// Why no unit is being handed out although some are pending (e.g. `no live worker has tags
    /// [highmem]`); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub waiting: Option<String>,
    /// The job's frames: counts and the frames in progress. Progress fields above
    /// (`passes_done`, `units_*`, `samples_*`) count over every frame.
    #[serde(default)]
    pub frames: FramesSummary,
}

/// Worker states as the coordinator sees them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum WorkerState {
    Idle,
    Busy,
    Offline,
}

/// `GET /workers` entry.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct WorkerInfo {
    pub id: WorkerId,
    pub name: String,
    pub threads: u32,
    pub state: WorkerState,
    /// `(job, pass, tile)` of the unit it holds.
    pub current: Option<(JobId, UnitKey)>,
    pub units_done: u64,
    pub samples_done: u64,
    pub samples_per_sec: f64,
    pub last_seen_ms: u64,
    /// What it reported at registration (`cpu`, SIMD level, `denoise`, and `--tags`).
    #[serde(default)]
    pub tags: Vec<String>,
}

/// `POST /workers/register` body.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RegisterRequest {
    #[schema(min_length = 1, max_length = 256)]
    pub name: String,
    #[schema(minimum = 1, maximum = 4096)]
    pub threads: u32,
    /// What the worker offers (at most 16 tags of `[a-z0-9_-]`, 1 to 32 characters each); jobs
    /// that `require` tags are leased only to workers having all of them.
    #[serde(default)]
    pub tags: Vec<String>,
}

/// `POST /workers/register` answer.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct Registered {
    pub worker_id: WorkerId,
    /// This worker's own secret (64 hex digits): send it as the `X-Pathfarm-Worker-Secret`
    /// header on every lease, heartbeat, result and release request. Kept in the coordinator's
    /// memory only: after a coordinator restart the worker registers again and gets a new one.
    pub worker_secret: String,
    /// Send a heartbeat at least this often.
    pub heartbeat_ms: u64,
    /// A lease not renewed by a heartbeat for this long expires.
    pub lease_timeout_ms: u64,
}

/// What a lease asks the worker to do.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq, Eq, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum LeaseKind {
    /// Render the unit (`unit`, `tile`, `pass`, `mask`) and `PUT /leases/{id}/result`.
    #[default]
    Render,
    /// Denoise frame `unit.frame` as merged through pass `unit.pass` (`tile` is the whole
    /// image): `GET /leases/{id}/denoise-input`, denoise, `PUT /leases/{id}/denoised`. Only
    /// workers that registered the tag `denoise` are given these.
    Denoise,
}

impl LeaseKind {
    pub fn is_render(&self) -> bool {
        *self == LeaseKind::Render
    }
}

/// `POST /workers/{id}/lease?wait_ms=N` answer (200; 204 when there is no work).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct LeaseGrant {
    /// `render` (absent: a render unit, as from coordinators before denoise steps) or `denoise`.
    #[serde(default, skip_serializing_if = "LeaseKind::is_render")]
    pub kind: LeaseKind,
    pub lease_id: LeaseId,
    pub job_id: JobId,
    pub scene_id: String,
    pub settings: RenderSettings,
    pub unit: UnitKey,
    pub tile: TileRect,
    pub pass: Pass,
    /// Adaptive sampling: the tile's blocks that have converged (no samples in this unit; their
    /// pixels hold empty sums in the result). Absent: every pixel gets the pass's samples.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<crate::adaptive::BlockMaskWire>)]
    pub mask: Option<crate::adaptive::BlockMask>,
}

/// `POST /leases/{id}/release` body: give a unit back (shutdown) or report its failure.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReleaseRequest {
    /// `true` if rendering failed (counts towards retries and the blocklist).
    pub failed: bool,
    pub reason: String,
}

/// `PUT /leases/{id}/result` answer.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct ResultAccepted {
    pub merged: bool,
}

// ---------------------------------------------------------------------------------------------
// Binary result format
// ---------------------------------------------------------------------------------------------

/// Magic bytes at the start of a result body (`PFR1`, 13 x 128-bit sums per pixel, is refused).
pub const RESULT_MAGIC: &[u8; 4] = b"PFR2";

/// A unit's result as it travels from worker to coordinator.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnitResultFrame {
    pub lease_id: LeaseId,
    pub job_id: JobId,
    pub unit: UnitKey,
    pub accum: TileAccum,
    pub splats: Option<SplatBuffer>,
}

/// Why a result body was refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DecodeError {
    #[error("result body is truncated ({0} bytes)")]
    Truncated(usize),
    #[error("result body does not start with the magic bytes PFR2 (PFR1 is the format of older workers)")]
    BadMagic,
    #[error("result checksum mismatch (body says {expected:08x}, computed {actual:08x})")]
    Checksum { expected: u32, actual: u32 },
    #[error("result header: {0}")]
    Header(String),
    #[error("result {section} section: {message}")]
    Section { section: &'static str, message: String },
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FrameHeader {
    lease_id: LeaseId,
    job_id: JobId,
    unit: UnitKey,
    tile: TileRect,
    /// Bytes per pixel of the sums section ([`PIXEL_BYTES`]).
    pixel_bytes: u32,
    splats: Option<(u32, u32)>,
}

/// How a section's bytes are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Codec {
    /// As they are: the decoder parses them in place, with no copy.
    Raw = 0,
    /// An lz4 block (`lz4_flex`, size-prepended).
    Lz4 = 1,
    /// Pixel sums with each field cut to the bytes its largest value in the section needs
    /// ([`push_pixels`]); other sections are stored raw. One unit's sums are far below their
    /// 64-bit range (a sample of radiance 1 is 2^24), so a 1-spp tile packs to about half.
    Packed = 2,
}

/// The codec results are sent with. Packed: the fields of a unit's sums cut to their bytes
/// (about half the bytes of raw for one sample per pixel), decoded about as fast as raw; lz4
/// (tried before raw was chosen) cost more CPU than it saved. Load tool (500 workers, 64 px
/// tiles, two jobs, 2 shared cores): the figures are in the commit that chose packed.
pub const RESULT_CODEC: Codec = Codec::Packed;

/// Bytes of [`PixelSums`]' fields in [`PixelSums::write_le`] order.
const FIELD_BYTES: [usize; PIXEL_FIELDS] = [8, 8, 8, 8, 8, 4, 4, 4, 2, 2, 2, 2, 2, 2];
/// Fields of [`PixelSums`].
const PIXEL_FIELDS: usize = 14;

/// A pixel's fields in [`PixelSums::write_le`] order, as unsigned integers.
#[inline]
fn pixel_fields(p: &PixelSums) -> [u64; PIXEL_FIELDS] {
    [
        p.rgb[0],
        p.rgb[1],
        p.rgb[2],
        p.lum,
        p.lum_sq,
        u64::from(p.weight),
        u64::from(p.hits),
        u64::from(p.depth),
        u64::from(p.albedo[0]),
        u64::from(p.albedo[1]),
        u64::from(p.albedo[2]),
        u64::from(p.normal[0] as u16),
        u64::from(p.normal[1] as u16),
        u64::from(p.normal[2] as u16),
    ]
}

/// Bytes of one sparse splat entry: u32 pixel index, 3 x u64 sums.
pub const SPLAT_ENTRY_BYTES: usize = 4 + 3 * 8;

/// Appends a section: u8 codec, u64 stored length, the stored bytes.
pub fn push_section(out: &mut Vec<u8>, raw: &[u8], codec: Codec) {
    // Packing applies to pixel sums ([`push_pixels`]); other sections are stored raw.
    let codec = if codec == Codec::Packed { Codec::Raw } else { codec };
    out.push(codec as u8);
    match codec {
        Codec::Raw | Codec::Packed => {
            out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
            out.extend_from_slice(raw);
        }
        Codec::Lz4 => {
            let packed = lz4_flex::compress_prepend_size(raw);
            out.extend_from_slice(&(packed.len() as u64).to_le_bytes());
            out.extend_from_slice(&packed);
        }
    }
}

/// Stored size of a section holding `raw` bytes at worst (lz4's worst case included).
pub fn max_section_bytes(raw: u64) -> u64 {
    // u8 codec + u64 length + u32 size prefix + lz4_flex's worst case (16 + 4 + 110 % of the input).
    1 + 8 + 4 + 20 + raw.saturating_mul(110) / 100 + 1
}

/// Takes a section's stored bytes (after its u8 codec and u64 length) from `rest`, refusing a
/// length beyond the bytes left or above `max_stored`.
fn read_section_bytes<'a>(
    rest: &mut &'a [u8],
    max_stored: usize,
    section: &'static str,
) -> Result<&'a [u8], DecodeError> {
    let err = |message: String| DecodeError::Section { section, message };
    let Some((head, tail)) = rest.split_first_chunk::<9>() else {
        return Err(err("missing codec and length".into()));
    };
    let mut len = [0u8; 8];
    len.copy_from_slice(&head[1..]);
    let len = u64::from_le_bytes(len);
    if len > tail.len() as u64 {
        return Err(err(format!("length {len} exceeds the {} bytes left", tail.len())));
    }
    if len > max_stored as u64 {
        return Err(err(format!("{len} bytes, at most {max_stored} expected")));
    }
    let (stored, tail) = tail.split_at(len as usize);
    *rest = tail;
    Ok(stored)
}

/// Reads a section written by [`push_section`]: raw bytes are borrowed from the body, lz4 ones
/// decompressed. A section declaring more than `max_raw` bytes is refused before anything is
/// allocated.
pub fn read_section<'a>(
    rest: &mut &'a [u8],
    max_raw: usize,
    section: &'static str,
) -> Result<std::borrow::Cow<'a, [u8]>, DecodeError> {
    let err = |message: String| DecodeError::Section { section, message };
    let codec = rest.first().copied();
    let stored = read_section_bytes(rest, usize::MAX, section)?;
    match codec.unwrap_or(u8::MAX) {
        0 if stored.len() > max_raw => Err(err(format!("{} bytes, at most {max_raw} expected", stored.len()))),
        0 => Ok(std::borrow::Cow::Borrowed(stored)),
        1 => {
            if stored.len() < 4 {
                return Err(err("lz4 block without its size".into()));
            }
            let raw = u32::from_le_bytes([stored[0], stored[1], stored[2], stored[3]]) as usize;
            if raw > max_raw {
                return Err(err(format!("declares {raw} bytes uncompressed, at most {max_raw} expected")));
            }
            let mut out = vec![0u8; raw];
            let n = lz4_flex::decompress_into(&stored[4..], &mut out).map_err(|e| err(format!("lz4: {e}")))?;
            if n != raw {
                return Err(err(format!("lz4 block holds {n} bytes, its size says {raw}")));
            }
            Ok(std::borrow::Cow::Owned(out))
        }
        c => Err(err(format!("unknown codec {c}"))),
    }
}

/// The little-endian bytes of pixel sums ([`PixelSums::write_le`]).
pub fn pixels_to_bytes(pixels: &[PixelSums]) -> Vec<u8> {
    let mut out = vec![0u8; pixels.len() * PIXEL_BYTES];
    for (p, chunk) in pixels.iter().zip(out.chunks_exact_mut(PIXEL_BYTES)) {
        if let Ok(c) = <&mut [u8; PIXEL_BYTES]>::try_from(chunk) {
            p.write_le(c);
        }
    }
    out
}

/// Appends a section of pixel sums.
pub fn push_pixels(out: &mut Vec<u8>, pixels: &[PixelSums], codec: Codec) {
    match codec {
        Codec::Raw => {
            // Written straight into the body: no intermediate buffer.
            out.push(Codec::Raw as u8);
            out.extend_from_slice(&((pixels.len() * PIXEL_BYTES) as u64).to_le_bytes());
            let at = out.len();
            out.resize(at + pixels.len() * PIXEL_BYTES, 0);
            for (p, chunk) in pixels.iter().zip(out[at..].chunks_exact_mut(PIXEL_BYTES)) {
                if let Ok(c) = <&mut [u8; PIXEL_BYTES]>::try_from(chunk) {
                    p.write_le(c);
                }
            }
        }
        Codec::Lz4 => push_section(out, &pixels_to_bytes(pixels), codec),
        Codec::Packed => {
            // The bytes each field needs: those of the OR of its values over the section.
            let mut or = [0u64; PIXEL_FIELDS];
            for p in pixels {
                for (o, v) in or.iter_mut().zip(pixel_fields(p)) {
                    *o |= v;
                }
            }
            let widths = or.map(|v| (u64::BITS - v.leading_zeros()).div_ceil(8) as usize);
            let stride: usize = widths.iter().sum();
            out.push(Codec::Packed as u8);
            out.extend_from_slice(&((PIXEL_FIELDS + pixels.len() * stride) as u64).to_le_bytes());
            out.extend(widths.map(|w| w as u8));
            out.reserve(pixels.len() * stride);
            for p in pixels {
                for (v, &w) in pixel_fields(p).iter().zip(&widths) {
                    out.extend_from_slice(&v.to_le_bytes()[..w]);
                }
            }
        }
    }
}

/// A packed section's pixels, read one at a time from its stored bytes (the field widths,
/// then `count` pixels, each its fields in [`PixelSums::write_le`] order cut to their widths).
#[derive(Clone, Copy, Debug)]
pub struct PackedPixels<'a> {
    data: &'a [u8],
    offsets: [usize; PIXEL_FIELDS],
    masks: [u64; PIXEL_FIELDS],
    stride: usize,
    count: usize,
}

impl<'a> PackedPixels<'a> {
    /// Checks a packed section's stored bytes for `count` pixels: widths above a field's size,
    /// or a length other than the widths give, are refused; any other bytes are some pixels.
    pub fn parse(stored: &'a [u8], count: usize, section: &'static str) -> Result<Self, DecodeError> {
        let err = |message: String| DecodeError::Section { section, message };
        let Some((widths, data)) = stored.split_first_chunk::<PIXEL_FIELDS>() else {
            return Err(err("packed section without its field widths".into()));
        };
        let mut offsets = [0usize; PIXEL_FIELDS];
        let mut masks = [0u64; PIXEL_FIELDS];
        let mut stride = 0;
        for f in 0..PIXEL_FIELDS {
            let w = usize::from(widths[f]);
            if w > FIELD_BYTES[f] {
                return Err(err(format!("field {f} packed in {w} bytes, it has {}", FIELD_BYTES[f])));
            }
            offsets[f] = stride;
            masks[f] = if w == 8 { u64::MAX } else { (1u64 << (8 * w)) - 1 };
            stride += w;
        }
        if Some(data.len()) != count.checked_mul(stride) {
            return Err(err(format!(
                "expected {count} pixels of {stride} packed bytes ({} bytes), got {} bytes",
                count.saturating_mul(stride),
                data.len()
            )));
        }
        Ok(Self { data, offsets, masks, stride, count })
    }

    /// Pixels in the section.
    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Pixel `i`'s sums (`i < len()`).
    #[inline(always)]
    pub fn get(&self, i: usize) -> PixelSums {
        // Each field is read as 8 bytes at its offset (at most 62) in a 72-byte window on the
        // pixel (the window has no bounds to check) and masked to its width; near the end of the
        // data the window is a zero-padded copy.
        let at = i * self.stride;
        match self.data.get(at..).and_then(|d| d.first_chunk::<{ PIXEL_BYTES + 8 }>()) {
            Some(window) => self.read(window),
            None => {
                let mut px = [0u8; PIXEL_BYTES + 8];
                let end = (at + self.stride).min(self.data.len());
                let part = self.data.get(at..end).unwrap_or_default();
                px[..part.len()].copy_from_slice(part);
                self.read(&px)
            }
        }
    }

    /// Pixel `i`'s sample weight and hit count (`i < len()`), its other fields unread.
    #[inline]
    pub fn weight_hits(&self, i: usize) -> (u32, u32) {
        let field = |f: usize| {
            let at = i * self.stride + self.offsets[f];
            let mut b = [0u8; 8];
            let part = self.data.get(at..(at + 8).min(self.data.len())).unwrap_or_default();
            b[..part.len()].copy_from_slice(part);
            // Masked to the field's size (4 bytes at most): the cast keeps every bit.
            (u64::from_le_bytes(b) & self.masks[f]) as u32
        };
        (field(5), field(6))
    }

    #[inline(always)]
    fn read(&self, px: &[u8; PIXEL_BYTES + 8]) -> PixelSums {
        let v = |f: usize| {
            let o = self.offsets[f] & (PIXEL_BYTES - 1);
            let mut b = [0u8; 8];
            b.copy_from_slice(&px[o..o + 8]);
            u64::from_le_bytes(b) & self.masks[f]
        };
        // Masked to the field's size: the casts keep every bit.
        PixelSums {
            rgb: [v(0), v(1), v(2)],
            lum: v(3),
            lum_sq: v(4),
            weight: v(5) as u32,
            hits: v(6) as u32,
            depth: v(7) as u32,
            albedo: [v(8) as u16, v(9) as u16, v(10) as u16],
            normal: [v(11) as u16 as i16, v(12) as u16 as i16, v(13) as u16 as i16],
        }
    }
}

/// The pixels of a packed section's stored bytes ([`PackedPixels`]).
fn unpack_pixels(stored: &[u8], count: usize, section: &'static str) -> Result<Vec<PixelSums>, DecodeError> {
    let packed = PackedPixels::parse(stored, count, section)?;
    Ok((0..count).map(|i| packed.get(i)).collect())
}

/// A packed sums section's pixels, read in place ([`PackedPixels`]); `None` when the section is
/// stored another way. Advances `rest` past the section.
pub fn read_packed_pixels<'a>(
    rest: &mut &'a [u8],
    count: usize,
    section: &'static str,
) -> Option<Result<PackedPixels<'a>, DecodeError>> {
    if rest.first() != Some(&(Codec::Packed as u8)) {
        return None;
    }
    let max = count.saturating_mul(PIXEL_BYTES).saturating_add(PIXEL_FIELDS);
    Some(read_section_bytes(rest, max, section).and_then(|stored| PackedPixels::parse(stored, count, section)))
}

/// Reads a section of exactly `count` pixels, parsed straight from the body (raw) or from the
/// decompressed block (lz4) into the returned vector.
pub fn read_pixels(rest: &mut &[u8], count: usize, section: &'static str) -> Result<Vec<PixelSums>, DecodeError> {
    let expected = count.saturating_mul(PIXEL_BYTES);
    if rest.first() == Some(&(Codec::Packed as u8)) {
        // Never longer than raw plus its widths.
        let stored = read_section_bytes(rest, expected.saturating_add(PIXEL_FIELDS), section)?;
        return unpack_pixels(stored, count, section);
    }
    let bytes = read_section(rest, expected, section)?;
    if bytes.len() != expected {
        return Err(DecodeError::Section {
            section,
            message: format!("expected {count} pixels ({expected} bytes), got {} bytes", bytes.len()),
        });
    }
    Ok(bytes
        .chunks_exact(PIXEL_BYTES)
        .map(|c| <&[u8; PIXEL_BYTES]>::try_from(c).map(PixelSums::read_le).unwrap_or_default())
        .collect())
}

/// Appends a splat section: the nonzero pixels only, as (u32 index, 3 x u64) in index order.
pub fn push_splats(out: &mut Vec<u8>, splats: &SplatBuffer, codec: Codec) {
    let mut raw = Vec::new();
    for (i, s) in splats.sums.chunks_exact(3).enumerate() {
        if s.iter().any(|&v| v != 0) {
            raw.extend_from_slice(&(i as u32).to_le_bytes());
            for v in s {
                raw.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    push_section(out, &raw, codec);
}

/// Reads a splat section into a `width` x `height` buffer; indices must be increasing and
/// inside the image.
pub fn read_splats(
    rest: &mut &[u8],
    width: u32,
    height: u32,
    section: &'static str,
) -> Result<SplatBuffer, DecodeError> {
    let err = |message: String| DecodeError::Section { section, message };
    let n = width as usize * height as usize;
    let bytes = read_section(rest, n.saturating_mul(SPLAT_ENTRY_BYTES), section)?;
    if bytes.len() % SPLAT_ENTRY_BYTES != 0 {
        return Err(err(format!("{} bytes is not a whole number of {SPLAT_ENTRY_BYTES}-byte entries", bytes.len())));
    }
    let mut buf = SplatBuffer::new(width, height);
    let mut last: Option<usize> = None;
    for e in bytes.chunks_exact(SPLAT_ENTRY_BYTES) {
        let i = u32::from_le_bytes([e[0], e[1], e[2], e[3]]) as usize;
        if i >= n || last.is_some_and(|l| i <= l) {
            return Err(err(format!("entry for pixel {i}: outside the {width} x {height} image or out of order")));
        }
        last = Some(i);
        for c in 0..3 {
            let mut v = [0u8; 8];
            v.copy_from_slice(&e[4 + 8 * c..12 + 8 * c]);
            buf.sums[i * 3 + c] = u64::from_le_bytes(v);
        }
    }
    Ok(buf)
}

/// Largest JSON header of a result frame the coordinator reads (ours are about 200 bytes).
pub const MAX_RESULT_HEADER_BYTES: u64 = 4096;

/// The largest body a result for `tile` of an image of `image` (width, height) can be: magic,
/// header length, a header of at most [`MAX_RESULT_HEADER_BYTES`], the tile's sums and a splat
/// entry for every pixel of the image, both at lz4's worst case, and the CRC. The coordinator
/// refuses a declared `Content-Length` above it before reading the body.
pub fn max_result_bytes(tile: TileRect, image: (u32, u32)) -> u64 {
    let sums = max_section_bytes(tile.pixel_count() as u64 * PIXEL_BYTES as u64);
    let splats = max_section_bytes(u64::from(image.0) * u64::from(image.1) * SPLAT_ENTRY_BYTES as u64);
    (8 + MAX_RESULT_HEADER_BYTES + 4).saturating_add(sums).saturating_add(splats)
}

impl UnitResultFrame {
    /// Encodes with [`RESULT_CODEC`].
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(RESULT_CODEC)
    }

    /// Layout: magic, u32 header length, JSON header, sums section (the tile's pixels, row-major,
    /// [`PIXEL_BYTES`] each: [`PixelSums::write_le`]), optional splat section (sparse entries),
    /// CRC-32 of everything before it. A section is u8 codec, u64 length, the stored bytes.
    pub fn encode_with(&self, codec: Codec) -> Vec<u8> {
        let header = FrameHeader {
            lease_id: self.lease_id,
            job_id: self.job_id,
            unit: self.unit,
            tile: self.accum.rect,
            pixel_bytes: PIXEL_BYTES as u32,
            splats: self.splats.as_ref().map(|s| (s.width, s.height)),
        };
        let header = serde_json::to_vec(&header).unwrap_or_default();
        let mut out = Vec::with_capacity(8 + header.len() + 9 + self.accum.sums.len() * PIXEL_BYTES + 4);
        out.extend_from_slice(RESULT_MAGIC);
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        push_pixels(&mut out, &self.accum.sums, codec);
        if let Some(s) = &self.splats {
            push_splats(&mut out, s, codec);
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Parses and checks a body; never panics, whatever the bytes.
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        Self::decode_inner(bytes, None)
    }

    /// Like [`decode`](Self::decode), but refuses a header whose tile is not `tile` or whose
    /// splat buffer is not `image` (width, height) before decompressing anything, so a body
    /// cannot make the decoder allocate more than the lease's unit needs.
    pub fn decode_expecting(bytes: &[u8], tile: TileRect, image: (u32, u32)) -> Result<Self, DecodeError> {
        Self::decode_inner(bytes, Some((tile, image)))
    }

    /// Like [`decode_expecting`](Self::decode_expecting), but packed sums stay in the body,
    /// read as they are merged ([`TileSums::Packed`]): no tile of decoded pixels in between.
    pub fn decode_view(bytes: &[u8], tile: TileRect, image: (u32, u32)) -> Result<ResultView<'_>, DecodeError> {
        Self::parse(bytes, Some((tile, image)), true)
    }

    fn decode_inner(bytes: &[u8], expect: Option<(TileRect, (u32, u32))>) -> Result<Self, DecodeError> {
        let v = Self::parse(bytes, expect, false)?;
        // The sums were checked against the tile's size.
        let accum = TileAccum { rect: v.rect, sums: v.sums.into_pixels() };
        Ok(Self { lease_id: v.lease_id, job_id: v.job_id, unit: v.unit, accum, splats: v.splats })
    }

    /// Checks and parses a body; `in_place`: packed sums are read in place, not decoded.
    fn parse(
        bytes: &[u8],
        expect: Option<(TileRect, (u32, u32))>,
        in_place: bool,
    ) -> Result<ResultView<'_>, DecodeError> {
        if bytes.len() < 12 {
            return Err(DecodeError::Truncated(bytes.len()));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        if &body[..4] != RESULT_MAGIC {
            return Err(DecodeError::BadMagic);
        }
        let expected = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
        let actual = crc32fast::hash(body);
        if expected != actual {
            return Err(DecodeError::Checksum { expected, actual });
        }
        let hlen = u32::from_le_bytes([body[4], body[5], body[6], body[7]]) as usize;
        if hlen as u64 > MAX_RESULT_HEADER_BYTES || 8 + hlen > body.len() {
            return Err(DecodeError::Truncated(bytes.len()));
        }
        let header: FrameHeader =
            serde_json::from_slice(&body[8..8 + hlen]).map_err(|e| DecodeError::Header(e.to_string()))?;
        if header.pixel_bytes != PIXEL_BYTES as u32 {
            return Err(DecodeError::Header(format!("{} bytes per pixel, expected {PIXEL_BYTES}", header.pixel_bytes)));
        }
        let t = header.tile;
        if t.x1 <= t.x0 || t.y1 <= t.y0 || t.width() > 4096 || t.height() > 4096 {
            return Err(DecodeError::Header(format!("bad tile rectangle {t:?}")));
        }
        if let Some((w, h)) = header.splats
            && (w == 0 || h == 0 || w > 65536 || h > 65536)
        {
            return Err(DecodeError::Header(format!("bad splat buffer size {w} x {h}")));
        }
        if let Some((tile, image)) = expect {
            if t != tile {
                return Err(DecodeError::Header(format!("tile {t:?}, the lease is for {tile:?}")));
            }
            if let Some(dims) = header.splats
                && dims != image
            {
                return Err(DecodeError::Header(format!("splat buffer {dims:?}, the image is {image:?}")));
            }
        }
        let mut rest = &body[8 + hlen..];
        let packed = if in_place { read_packed_pixels(&mut rest, t.pixel_count(), "sums") } else { None };
        let sums = match packed {
            Some(packed) => TileSums::Packed(packed?),
            None => TileSums::Pixels(read_pixels(&mut rest, t.pixel_count(), "sums")?),
        };
        let splats = match header.splats {
            None => None,
            Some((w, h)) => Some(read_splats(&mut rest, w, h, "splats")?),
        };
        if !rest.is_empty() {
            return Err(DecodeError::Section { section: "trailer", message: format!("{} extra bytes", rest.len()) });
        }
        Ok(ResultView { lease_id: header.lease_id, job_id: header.job_id, unit: header.unit, rect: t, sums, splats })
    }
}

/// A tile's sums as a result holds them: decoded pixels, or a packed section read in place
/// from the body. Either way `len()` is the tile's pixel count (checked when decoded).
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)] // one per result, moved a few times: boxing would allocate
pub enum TileSums<'a> {
    Pixels(Vec<PixelSums>),
    Packed(PackedPixels<'a>),
}

impl TileSums<'_> {
    pub fn len(&self) -> usize {
        match self {
            Self::Pixels(p) => p.len(),
            Self::Packed(p) => p.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The decoded pixels (a packed section is decoded now).
    pub fn into_pixels(self) -> Vec<PixelSums> {
        match self {
            Self::Pixels(p) => p,
            Self::Packed(p) => (0..p.len()).map(|i| p.get(i)).collect(),
        }
    }

    /// Pixel `i`'s sample weight and hit count.
    #[inline]
    pub fn weight_hits(&self, i: usize) -> (u32, u32) {
        match self {
            Self::Pixels(p) => p.get(i).map_or((0, 0), |p| (p.weight, p.hits)),
            Self::Packed(p) => p.weight_hits(i),
        }
    }
}

/// A checked result body ([`UnitResultFrame::decode_view`]): the header's fields, the tile,
/// its sums (packed ones still in the body) and its splats.
#[derive(Clone, Debug)]
pub struct ResultView<'a> {
    pub lease_id: LeaseId,
    pub job_id: JobId,
    pub unit: UnitKey,
    pub rect: TileRect,
    pub sums: TileSums<'a>,
    pub splats: Option<SplatBuffer>,
}

impl From<UnitResultFrame> for ResultView<'static> {
    fn from(f: UnitResultFrame) -> Self {
        Self {
            lease_id: f.lease_id,
            job_id: f.job_id,
            unit: f.unit,
            rect: f.accum.rect,
            sums: TileSums::Pixels(f.accum.sums),
            splats: f.splats,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Denoise steps: the input and the output
// ---------------------------------------------------------------------------------------------

/// Magic bytes of a denoise input body (`GET /leases/{id}/denoise-input`).
pub const DENOISE_INPUT_MAGIC: &[u8; 4] = b"PFDI";
/// Magic bytes of a denoised layer body (`PUT /leases/{id}/denoised`).
pub const DENOISED_MAGIC: &[u8; 4] = b"PFDO";

/// What the denoiser reads of a frame: its resolved colour, albedo and normal (each
/// `width * height`, row-major). Built by [`DenoiseInput::of`] from a resolved film, the one
/// path by which both `pathfarm-worker render --denoise` and the farm's denoise steps make it,
/// so the same film gives the same input bits, hence the same denoised layer.
#[derive(Clone, Debug, PartialEq)]
pub struct DenoiseInput {
    pub width: u32,
    pub height: u32,
    pub color: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
}

impl DenoiseInput {
    /// The denoiser's input of a resolved image ([`crate::film::Film::resolve`]).
    pub fn of(img: &crate::film::ImageLayers) -> Self {
        Self {
            width: img.width,
            height: img.height,
            color: img.rgb.clone(),
            albedo: img.albedo.clone(),
            normal: img.normal.clone(),
        }
    }

    /// Layout: magic `PFDI`, u32 width, u32 height, three sections (colour, albedo, normal:
    /// `width * height` x 3 little-endian f32 each, lz4), CRC-32 of everything before it.
    pub fn encode(&self) -> Vec<u8> {
        encode_planes(DENOISE_INPUT_MAGIC, self.width, self.height, &[&self.color, &self.albedo, &self.normal])
    }

    /// Parses a body that must be of a `width` x `height` image (refused before anything is
    /// allocated otherwise); never panics, whatever the bytes.
    pub fn decode_expecting(bytes: &[u8], width: u32, height: u32) -> Result<Self, DecodeError> {
        let mut planes = decode_planes(bytes, DENOISE_INPUT_MAGIC, width, height, 3)?.into_iter();
        let mut next = || planes.next().unwrap_or_default();
        let (color, albedo, normal) = (next(), next(), next());
        Ok(Self { width, height, color, albedo, normal })
    }
}

/// A denoised layer's body: magic `PFDO`, u32 width, u32 height, one section (R, G, B
/// little-endian f32 per pixel, lz4), CRC-32.
pub fn encode_denoised(width: u32, height: u32, rgb: &[[f32; 3]]) -> Vec<u8> {
    encode_planes(DENOISED_MAGIC, width, height, &[rgb])
}

/// Parses a denoised layer of a `width` x `height` image (anything else is refused before it
/// is decompressed).
pub fn decode_denoised(bytes: &[u8], width: u32, height: u32) -> Result<Vec<[f32; 3]>, DecodeError> {
    Ok(decode_planes(bytes, DENOISED_MAGIC, width, height, 1)?.into_iter().next().unwrap_or_default())
}

/// The largest body a denoised layer of a `width` x `height` image can be (lz4's worst case).
pub fn max_denoised_bytes(width: u32, height: u32) -> u64 {
    (12 + 4u64).saturating_add(max_section_bytes(u64::from(width) * u64::from(height) * 12))
}

fn encode_planes(magic: &[u8; 4], width: u32, height: u32, planes: &[&[[f32; 3]]]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(magic);
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    for plane in planes {
        let raw: Vec<u8> = plane.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        push_section(&mut out, &raw, Codec::Lz4);
    }
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

fn decode_planes(
    bytes: &[u8],
    magic: &[u8; 4],
    width: u32,
    height: u32,
    count: usize,
) -> Result<Vec<Vec<[f32; 3]>>, DecodeError> {
    let section = "denoise";
    let err = |message: String| DecodeError::Section { section, message };
    if bytes.len() < 16 {
        return Err(err(format!("body is truncated ({} bytes)", bytes.len())));
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    if &body[..4] != magic {
        return Err(err(format!("body does not start with the magic bytes {}", String::from_utf8_lossy(magic))));
    }
    let expected = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let actual = crc32fast::hash(body);
    if expected != actual {
        return Err(DecodeError::Checksum { expected, actual });
    }
    let (w, h) = (
        u32::from_le_bytes([body[4], body[5], body[6], body[7]]),
        u32::from_le_bytes([body[8], body[9], body[10], body[11]]),
    );
    if (w, h) != (width, height) {
        return Err(DecodeError::Header(format!("image of {w} x {h}, the lease's frame is {width} x {height}")));
    }
    let n = width as usize * height as usize;
    let mut rest = &body[12..];
    let mut planes = Vec::with_capacity(count);
    for _ in 0..count {
        let raw = read_section(&mut rest, n.saturating_mul(12), section)?;
        if raw.len() != n * 12 {
            return Err(err(format!("expected {n} pixels ({} bytes), got {} bytes", n * 12, raw.len())));
        }
        let f = |c: &[u8]| f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        planes.push(raw.chunks_exact(12).map(|p| [f(&p[0..4]), f(&p[4..8]), f(&p[8..12])]).collect());
    }
    if !rest.is_empty() {
        return Err(err(format!("{} extra bytes", rest.len())));
    }
    Ok(planes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::film::{MAX_SAMPLE_VALUE, SampleValue, add_sample};

    #[test]
    fn denoise_bodies_round_trip_and_refuse_other_sizes() {
        let px = |i: usize| [i as f32 * 0.5, -(i as f32), f32::INFINITY];
        let input = DenoiseInput {
            width: 3,
            height: 2,
            color: (0..6).map(px).collect(),
            albedo: (6..12).map(px).collect(),
            normal: (12..18).map(px).collect(),
        };
        let body = input.encode();
        assert_eq!(DenoiseInput::decode_expecting(&body, 3, 2), Ok(input.clone()));
        let e = DenoiseInput::decode_expecting(&body, 2, 3).expect_err("other size").to_string();
        assert!(e.contains("3 x 2") && e.contains("2 x 3"), "{e}");
        let mut bad = body.clone();
        bad[20] ^= 1;
        assert!(matches!(DenoiseInput::decode_expecting(&bad, 3, 2), Err(DecodeError::Checksum { .. })));
        assert!(DenoiseInput::decode_expecting(&body[..10], 3, 2).is_err());
        // A denoised layer: its own magic, one plane; an input body is not one.
        let out = encode_denoised(3, 2, &input.color);
        assert!(out.len() as u64 <= max_denoised_bytes(3, 2));
        assert_eq!(decode_denoised(&out, 3, 2), Ok(input.color.clone()));
        assert!(decode_denoised(&body, 3, 2).expect_err("input body").to_string().contains("PFDO"));
        // A body declaring a huge section is refused before allocating.
        let mut huge = Vec::new();
        huge.extend_from_slice(DENOISED_MAGIC);
        huge.extend_from_slice(&3u32.to_le_bytes());
        huge.extend_from_slice(&2u32.to_le_bytes());
        huge.push(1);
        huge.extend_from_slice(&8u64.to_le_bytes());
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        huge.extend_from_slice(&[0; 4]);
        let crc = crc32fast::hash(&huge);
        huge.extend_from_slice(&crc.to_le_bytes());
        assert!(decode_denoised(&huge, 3, 2).expect_err("huge").to_string().contains("at most 72 expected"));
    }

    fn frame(splats: bool) -> UnitResultFrame {
        let rect = TileRect { x0: 8, y0: 16, x1: 24, y1: 20 };
        let mut accum = TileAccum::new(rect);
        for y in rect.y0..rect.y1 {
            for x in rect.x0..rect.x1 {
                let v = SampleValue { radiance: [x as f32 * 0.1, y as f32, 0.25], ..Default::default() };
                add_sample(accum.pixel_mut(x - rect.x0, y - rect.y0), &v);
            }
        }
        let splats = splats.then(|| {
            let mut s = SplatBuffer::new(32, 32);
            s.add(3, 4, [1.0, 2.0, 3.0]);
            s
        });
        UnitResultFrame { lease_id: 7, job_id: 3, unit: UnitKey { frame: 0, pass: 2, tile: 5 }, accum, splats }
    }

    #[test]
    fn roundtrip_with_and_without_splats() {
        for s in [false, true] {
            for codec in [Codec::Raw, Codec::Lz4, Codec::Packed] {
                let f = frame(s);
                let bytes = f.encode_with(codec);
                assert_eq!(UnitResultFrame::decode(&bytes).expect("decode"), f);
            }
        }
    }

    #[test]
    fn corruption_is_refused_not_panicking() {
        for codec in [Codec::Raw, Codec::Lz4, Codec::Packed] {
            let bytes = frame(true).encode_with(codec);
            // Every truncation.
            for n in 0..bytes.len() {
                assert!(UnitResultFrame::decode(&bytes[..n]).is_err(), "truncated at {n}");
            }
            // Every single-bit flip is caught (by the checksum, or the magic).
            for i in (0..bytes.len()).step_by(7) {
                let mut b = bytes.clone();
                b[i] ^= 0x10;
                assert!(UnitResultFrame::decode(&b).is_err(), "flip at {i}");
            }
        }
        // A PFR1 body (a worker of the old format) is refused by its magic.
        assert_eq!(UnitResultFrame::decode(b"PFR1\0\0\0\0\0\0\0\0\0\0"), Err(DecodeError::BadMagic));
    }

    #[test]
    fn a_64_px_tile_is_a_quarter_of_a_megabyte_and_splats_are_sparse() {
        let rect = TileRect { x0: 0, y0: 0, x1: 64, y1: 64 };
        let mut accum = TileAccum::new(rect);
        for p in &mut accum.sums {
            add_sample(p, &SampleValue { radiance: [0.5, 0.25, 2.0], depth: Some(3.0), ..Default::default() });
        }
        let mut splats = SplatBuffer::new(1024, 1024);
        for i in 0..100 {
            splats.add(i * 7, i * 3, [1.0, 2.0, 3.0]);
        }
        let f = UnitResultFrame {
            lease_id: 1,
            job_id: 2,
            unit: UnitKey { frame: 0, pass: 0, tile: 0 },
            accum,
            splats: Some(splats),
        };
        let raw = f.encode_with(Codec::Raw).len();
        // 4096 pixels x 64 bytes, 100 splat entries, a small header: was 850 KB (13 x 16 bytes x 4096
        // plus a full-frame lz4 splat section).
        assert!(raw < 4096 * 64 + 100 * SPLAT_ENTRY_BYTES + 400, "{raw}");
        assert_eq!(UnitResultFrame::decode(&f.encode_with(Codec::Lz4)).expect("lz4"), f);
    }

    /// A packed section cuts each field to the bytes its largest value needs: one sample per
    /// pixel of radiance below 1 packs to less than half of raw; a pixel of large sums widens
    /// only its fields, and every field at full width is raw's size plus the widths.
    #[test]
    fn packed_sums_take_the_bytes_their_values_need() {
        let rect = TileRect { x0: 0, y0: 0, x1: 64, y1: 64 };
        let mut accum = TileAccum::new(rect);
        for (i, p) in accum.sums.iter_mut().enumerate() {
            let v = (i % 97) as f32 / 100.0;
            add_sample(p, &SampleValue { radiance: [v, 0.5 * v, 0.25], depth: Some(3.0), ..Default::default() });
        }
        let frame = |accum: TileAccum| UnitResultFrame {
            lease_id: 1,
            job_id: 2,
            unit: UnitKey { frame: 0, pass: 0, tile: 0 },
            accum,
            splats: None,
        };
        let f = frame(accum.clone());
        let (raw, packed) = (f.encode_with(Codec::Raw), f.encode_with(Codec::Packed));
        assert!(packed.len() * 2 < raw.len(), "packed {} bytes, raw {}", packed.len(), raw.len());
        assert_eq!(UnitResultFrame::decode(&packed).expect("packed"), f);
        // One bright pixel widens the radiance fields (to 6 bytes: 2^19 * 2^24 < 2^48), no other.
        accum.sums[4095]
            .merge(&PixelSums::from_sample(&SampleValue { radiance: [MAX_SAMPLE_VALUE; 3], ..Default::default() }));
        let f = frame(accum.clone());
        let bright = f.encode_with(Codec::Packed);
        assert_eq!(UnitResultFrame::decode(&bright).expect("packed"), f);
        assert!(bright.len() < raw.len() * 3 / 4, "{} of raw {}", bright.len(), raw.len());
        // All ones: every field at full width.
        for p in &mut accum.sums {
            *p = PixelSums::read_le(&[0xFF; PIXEL_BYTES]);
        }
        let f = frame(accum);
        let full = f.encode_with(Codec::Packed);
        assert_eq!(full.len(), f.encode_with(Codec::Raw).len() + PIXEL_FIELDS);
        assert_eq!(UnitResultFrame::decode(&full).expect("packed"), f);
    }

    /// Packed sums read in place give the decoded pixels, every one (those at the end of the
    /// data read from a padded copy), and their weights and hits.
    #[test]
    fn packed_pixels_read_in_place_equal_the_decoded_ones() {
        for n in [1usize, 2, 3, 7, 64] {
            let pixels: Vec<PixelSums> = (0..n)
                .map(|i| {
                    let mut p = PixelSums::from_sample(&SampleValue {
                        radiance: [i as f32 * 0.3, 1.0, 2.0],
                        depth: Some(i as f32),
                        ..Default::default()
                    });
                    p.weight += i as u32;
                    p.hits = (i % 3) as u32;
                    p
                })
                .collect();
            let mut section = Vec::new();
            push_pixels(&mut section, &pixels, Codec::Packed);
            let mut rest = &section[..];
            let packed = read_packed_pixels(&mut rest, n, "sums").expect("packed").expect("valid");
            assert!(rest.is_empty());
            for (i, p) in pixels.iter().enumerate() {
                assert_eq!(packed.get(i), *p, "pixel {i} of {n}");
                assert_eq!(packed.weight_hits(i), (p.weight, p.hits), "pixel {i} of {n}");
            }
            assert_eq!(TileSums::Packed(packed).into_pixels(), pixels);
        }
        // Another codec is not read in place.
        let mut raw = Vec::new();
        push_pixels(&mut raw, &[PixelSums::default()], Codec::Raw);
        assert!(read_packed_pixels(&mut &raw[..], 1, "sums").is_none());
    }

    /// Packed sums whose field widths exceed a field's size, or whose length is not the pixel
    /// count times the widths' sum, are refused (with a valid checksum).
    #[test]
    fn packed_widths_and_lengths_are_checked() {
        let pixels = vec![PixelSums::from_sample(&SampleValue { radiance: [0.5; 3], ..Default::default() }); 6];
        let mut section = Vec::new();
        push_pixels(&mut section, &pixels, Codec::Packed);
        assert_eq!(read_pixels(&mut &section[..], 6, "sums").expect("valid"), pixels);
        // The first width (rgb[0], 8 bytes) at 9.
        let mut wide = section.clone();
        wide[9] = 9;
        let e = read_pixels(&mut &wide[..], 6, "sums").expect_err("width 9");
        assert!(e.to_string().contains("field 0 packed in 9 bytes"), "{e}");
        // Five pixels' bytes for six.
        let e = read_pixels(&mut &section[..], 7, "sums").expect_err("count");
        assert!(e.to_string().contains("expected 7 pixels"), "{e}");
        // A length field larger than raw plus the widths.
        let mut long = section.clone();
        long[1..9].copy_from_slice(&(6 * 64 + 15u64).to_le_bytes());
        long.resize(9 + 6 * 64 + 15, 0);
        assert!(read_pixels(&mut &long[..], 6, "sums").is_err());
        // Missing widths.
        let mut short = vec![Codec::Packed as u8];
        short.extend_from_slice(&3u64.to_le_bytes());
        short.extend_from_slice(&[1, 2, 3]);
        assert!(read_pixels(&mut &short[..], 0, "sums").is_err());
    }

    #[test]
    fn results_fit_their_size_bound() {
        for s in [false, true] {
            for codec in [Codec::Raw, Codec::Lz4, Codec::Packed] {
                let f = frame(s);
                let bound = max_result_bytes(f.accum.rect, (32, 32));
                assert!(f.encode_with(codec).len() as u64 <= bound, "{} > {bound}", f.encode_with(codec).len());
            }
        }
        // Incompressible sums and a splat on every pixel still fit: lz4's worst case is in the bound.
        let mut f = frame(true);
        let mut x: u64 = 0x1234_5678_9abc_def1;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x | 1
        };
        for p in f.accum.sums.iter_mut() {
            let mut b = [0u8; PIXEL_BYTES];
            for c in b.chunks_exact_mut(8) {
                c.copy_from_slice(&next().to_le_bytes());
            }
            *p = PixelSums::read_le(&b);
        }
        for v in f.splats.as_mut().map_or(&mut [][..], |s| &mut s.sums[..]) {
            *v = next();
        }
        let bound = max_result_bytes(f.accum.rect, (32, 32));
        for codec in [Codec::Raw, Codec::Lz4, Codec::Packed] {
            assert!(f.encode_with(codec).len() as u64 <= bound, "{} > {bound}", f.encode_with(codec).len());
            assert_eq!(UnitResultFrame::decode(&f.encode_with(codec)).expect("decode"), f);
        }
        assert!(bound < 2 * (16 * 4 * 64 + 32 * 32 * 28) + 8192, "{bound}");
    }

    #[test]
    fn wrong_size_with_valid_checksum_is_refused() {
        // A well-formed body whose sums section is the wrong length for its tile.
        for codec in [Codec::Raw, Codec::Lz4, Codec::Packed] {
            let mut f = frame(false);
            f.accum.sums.pop();
            let bytes = f.encode_with(codec);
            let e = UnitResultFrame::decode(&bytes).expect_err("wrong size");
            assert!(e.to_string().contains("sums"), "{e}");
        }
    }

    #[test]
    fn job_request_flattens_settings_and_names_unknown_fields() {
        let req = JobRequest {
            scene_id: "ab".into(),
            name: Some("n".into()),
            priority: 3,
            requires: vec!["highmem".into(), "gpu_2".into()],
            notify: Some(Notify { url: "https://example.com/hook".into(), events: vec![NotifyEvent::Completed] }),
            frames: Some(FrameSet::parse("1-3,7").expect("frames")),
            order: FrameOrder::SequencePreview,
            settings: RenderSettings::new(16, 8, 4),
        };
        let back = JobRequest::from_json(req.to_json()).expect("roundtrip");
        assert_eq!(back, req);
        let base = serde_json::json!({"scene_id": "x", "width": 4, "height": 4, "spp": 1});
        let with = |k: &str, v: serde_json::Value| {
            let mut b = base.clone();
            b[k] = v;
            JobRequest::from_json(b)
        };
        assert_eq!(
            with("frames", serde_json::json!(12)).expect("a number is one frame").frames.map(|f| f.frames().to_vec()),
            Some(vec![12])
        );
        for (k, v, needle) in [
            ("frames", serde_json::json!("5-1"), "backwards"),
            ("frames", serde_json::json!([1, 2]), "frames must be a string"),
            ("frames", serde_json::json!("1-200000"), "more than 100000 frames"),
            ("order", serde_json::json!("random"), "order must be"),
        ] {
            let e = with(k, v).expect_err("refused");
            assert!(e.contains(needle), "{e}");
        }
        let e =
            JobRequest::from_json(serde_json::json!({"scene_id": "x", "width": 4, "height": 4, "spp": 1, "wdth": 3}))
                .expect_err("unknown field");
        assert!(e.contains("wdth"), "{e}");
        let e = JobRequest::from_json(serde_json::json!({"width": 4})).expect_err("no scene");
        assert!(e.contains("scene_id"), "{e}");
    }

    #[test]
    fn notify_is_validated() {
        let job = |notify: serde_json::Value| {
            JobRequest::from_json(
                serde_json::json!({"scene_id": "x", "width": 4, "height": 4, "spp": 1, "notify": notify}),
            )
        };
        let ok = job(serde_json::json!({"url": "http://127.0.0.1:9/h?x=1", "events": ["completed", "started"]}))
            .expect("valid notify");
        assert_eq!(ok.notify.map(|n| n.events), Some(vec![NotifyEvent::Completed, NotifyEvent::Started]));
        for (bad, want) in [
            (serde_json::json!({"url": "ftp://h/x", "events": ["completed"]}), "not an http:// or https:// URL"),
            (serde_json::json!({"url": "https://", "events": ["completed"]}), "not an http:// or https:// URL"),
            (serde_json::json!({"url": "http://a b/", "events": ["completed"]}), "not an http:// or https:// URL"),
            (
                serde_json::json!({"url": format!("https://h/{}", "x".repeat(2100)), "events": ["failed"]}),
                "limit is 2048",
            ),
            (serde_json::json!({"url": "https://h/", "events": ["exploded"]}), "unknown variant `exploded`"),
            (serde_json::json!({"url": "https://h/", "events": []}), "notify.events is empty"),
            (serde_json::json!({"url": "https://h/", "events": ["failed", "failed"]}), "given twice"),
            (serde_json::json!({"url": "https://h/"}), "missing field `events`"),
            (serde_json::json!({"url": "https://h/", "events": ["failed"], "secret": 1}), "unknown field `secret`"),
            (serde_json::json!("https://h/"), "notify"),
        ] {
            let e = job(bad.clone()).expect_err("invalid notify");
            assert!(e.contains(want), "{bad}: {e}");
        }
    }

    #[test]
    fn job_names_are_bounded() {
        let job = |name: String| serde_json::json!({"scene_id": "x", "name": name, "width": 4, "height": 4, "spp": 1});
        let ok = JobRequest::from_json(job("é".repeat(MAX_JOB_NAME_BYTES / 2))).expect("256 bytes");
        assert_eq!(ok.name.map(|n| n.len()), Some(MAX_JOB_NAME_BYTES));
        let e = JobRequest::from_json(job("x".repeat(2 << 20))).expect_err("2 MB name");
        assert!(e.contains("name") && e.contains("256 bytes") && e.contains("2097152"), "{e}");
    }
}

/// Proptest targets: the decoder never panics on arbitrary bytes, on bodies with a valid magic
/// and checksum, or on valid results with bytes changed under a recomputed checksum; and every
/// encoded result decodes to itself.
#[cfg(test)]
mod fuzz {
    use super::*;
    use proptest::prelude::*;

    fn reseal(mut body: Vec<u8>) -> Vec<u8> {
        body.truncate(body.len().saturating_sub(4));
        let crc = crc32fast::hash(&body);
        body.extend_from_slice(&crc.to_le_bytes());
        body
    }

    fn result(w: u32, h: u32, seed: u64, splats: bool) -> UnitResultFrame {
        let rect = TileRect { x0: 1, y0: 2, x1: 1 + w, y1: 2 + h };
        let mut x = seed | 1;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let mut accum = TileAccum::new(rect);
        for p in &mut accum.sums {
            let v = (next() % 1000) as f32 / 10.0;
            crate::film::add_sample(
                p,
                &crate::film::SampleValue { radiance: [v, v * 0.5, 0.0], depth: Some(v), ..Default::default() },
            );
        }
        let splats = splats.then(|| {
            let mut s = SplatBuffer::new(16, 16);
            for _ in 0..(next() % 20) {
                s.add((next() % 16) as u32, (next() % 16) as u32, [1.0, 0.5, 0.25]);
            }
            s
        });
        UnitResultFrame { lease_id: next(), job_id: 4, unit: UnitKey { frame: 0, pass: 1, tile: 2 }, accum, splats }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, rng_seed: proptest::test_runner::RngSeed::Fixed(0x9f42), ..ProptestConfig::default() })]
        #[test]
        fn decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = UnitResultFrame::decode(&bytes);
        }

        #[test]
        fn decode_never_panics_with_valid_magic_and_crc(mut body in proptest::collection::vec(any::<u8>(), 8..512)) {
            body[..4].copy_from_slice(RESULT_MAGIC);
            let crc = crc32fast::hash(&body);
            body.extend_from_slice(&crc.to_le_bytes());
            let _ = UnitResultFrame::decode(&body);
        }

        /// A valid result with some bytes overwritten (then checksummed again) is decoded or
        /// refused, never a panic; unchanged it decodes to itself, with either codec.
        #[test]
        fn mutated_results_are_refused_or_decoded(
            w in 1u32..9, h in 1u32..9, seed in any::<u64>(), splats in any::<bool>(), codec in 0usize..3,
            edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
        ) {
            let f = result(w, h, seed, splats);
            let codec = [Codec::Raw, Codec::Lz4, Codec::Packed][codec];
            let bytes = f.encode_with(codec);
            let back = UnitResultFrame::decode(&bytes);
            prop_assert_eq!(back.as_ref(), Ok(&f));
            prop_assert!(bytes.len() as u64 <= max_result_bytes(f.accum.rect, (16, 16)));
            let mut m = bytes.clone();
            for (at, v) in &edits {
                let i = at % m.len();
                m[i] = *v;
            }
            let m = reseal(m);
            if let Ok(d) = UnitResultFrame::decode_expecting(&m, f.accum.rect, (16, 16)) {
                prop_assert_eq!(d.accum.sums.len(), f.accum.sums.len());
            }
        }
    }
}
