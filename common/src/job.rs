//! Job settings and the work-unit plan: a job is split into tiles x passes (sample ranges).
//!
//! The plan is a pure function of the settings, so the coordinator, the worker and a local render
//! agree on it without talking.

use serde::{Deserialize, Serialize};
use std::ops::Range;

/// How light samples and BSDF samples are combined in direct lighting.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum MisHeuristic {
    Balance,
    #[default]
    Power,
    /// Light sampling only (a single strategy).
    Light,
    /// BSDF sampling only (a single strategy).
    Bsdf,
}

/// How area lights are sampled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum LightSampling {
    /// Uniform by area, converted to solid angle.
    Area,
    /// Uniform over the spherical triangle's solid angle (Arvo).
    #[default]
    SolidAngle,
}

/// Which sampler addresses the random numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum SamplerKind {
    /// Owen-scrambled Sobol, padded per dimension pair (pbrt-v4's PaddedSobolSampler).
    #[default]
    Sobol,
    /// Counter-based hash: independent uniform numbers.
    Independent,
}

fn default_max_depth() -> u32 {
    8
}
fn default_rr_depth() -> u32 {
    3
}
fn default_vpls() -> u32 {
    64
}
fn default_vpl_sets() -> u32 {
    4
}
fn default_g_limit() -> f32 {
    10.0
}

/// Integrator and its parameters (JSON: `{"type": "path", "max_depth": 8, ...}`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum IntegratorSettings {
    /// Emitted plus direct lighting, one light and one BSDF sample with MIS.
    Direct {
        #[serde(default)]
        mis: MisHeuristic,
        #[serde(default)]
        light_sampling: LightSampling,
    },
    /// Path tracing with next-event estimation, MIS and Russian roulette.
    /// `max_depth` counts path segments as Mitsuba does (1 = emitters only, 2 = direct); 0 = no limit.
    Path {
        #[serde(default = "default_max_depth")]
        max_depth: u32,
        #[serde(default = "default_rr_depth")]
        rr_depth: u32,
        #[serde(default)]
        mis: MisHeuristic,
        #[serde(default)]
        light_sampling: LightSampling,
    },
    /// Bidirectional path tracing. `mis` must be `balance` or `power`.
    Bdpt {
        #[serde(default = "default_max_depth")]
        max_depth: u32,
        #[serde(default)]
        mis: MisHeuristic,
        /// Scatterings per subpath before Russian roulette starts.
        #[serde(default = "default_rr_depth")]
        rr_depth: u32,
        /// Debugging and teaching: only the MIS-weighted contribution of strategy `[s, t]`
        /// (`s` light vertices, `t` camera vertices).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        strategy: Option<[u32; 2]>,
    },
    /// Instant global illumination with virtual point lights.
    Igi {
        #[serde(default = "default_vpls")]
        vpls: u32,
        #[serde(default = "default_vpl_sets")]
        vpl_sets: u32,
        #[serde(default = "default_g_limit")]
        g_limit: f32,
        #[serde(default)]
        bias_compensation: bool,
        #[serde(default = "default_max_depth")]
        max_depth: u32,
    },
}

impl Default for IntegratorSettings {
    fn default() -> Self {
        IntegratorSettings::Path {
            max_depth: default_max_depth(),
            rr_depth: default_rr_depth(),
            mis: MisHeuristic::default(),
            light_sampling: LightSampling::default(),
        }
    }
}

/// How the sample budget is cut into passes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum PassSchedule {
    /// First pass of `first` spp, then each pass doubles, capped at `max` spp per pass.
    Doubling { first: u32, max: u32 },
    /// Every pass has `spp` samples (the last may be shorter).
    Fixed { spp: u32 },
}

impl Default for PassSchedule {
    fn default() -> Self {
        PassSchedule::Doubling { first: 1, max: 64 }
    }
}

fn default_tile_size() -> u32 {
    64
}

/// Everything that determines a render's pixels. Two renders with equal settings (and the same
/// scene) produce the same bits, whatever machine, thread count or work order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    #[serde(default)]
    pub seed: u64,
    /// Scene camera index; `None` = camera 0, or a default camera framing the scene.
    #[serde(default)]
    pub camera: Option<usize>,
    #[serde(default)]
    pub integrator: IntegratorSettings,
    #[serde(default)]
    pub sampler: SamplerKind,
    #[serde(default = "default_tile_size")]
    pub tile_size: u32,
    #[serde(default)]
    pub passes: PassSchedule,
    /// Animation frame to render: the scene is posed at time `frame / fps` seconds (the
    /// convention of Blender's glTF exporter). A still scene looks the same at every frame.
    #[serde(default)]
    pub frame: i32,
    /// Frames per second: converts frame numbers to animation time.
    #[serde(default = "default_fps")]
    pub fps: f32,
    /// Motion blur: the shutter stays open this fraction of a frame from the frame's time
    /// (0 = off, 1 = the whole frame). Each camera sample gets its own time in the interval.
    #[serde(default)]
    pub shutter: f32,
    /// Names of the glTF animations that play; `None` = all of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub animations: Option<Vec<String>>,
    /// Preview exposure in EV (stops): the PNG previews are scaled by 2^exposure. The EXR always
    /// holds the true radiance.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub exposure: f32,
    /// Previews expose automatically (log-average luminance to middle grey 0.18), `exposure`
    /// then adds to the automatic EV. The EXR is never affected.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub auto_exposure: bool,
    /// Light arriving from infinitely far away in every direction: an equirectangular image
    /// in the scene bundle or a constant colour. `None` = black.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<EnvironmentSettings>,
    /// Thin lens (depth of field): radius of the lens aperture in scene units (metres in glTF);
    /// 0 = pinhole. glTF cameras have no aperture, so the job sets it. An f-number N of a lens
    /// of focal length f is `aperture_radius = f / (2 N)`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub aperture_radius: f32,
    /// Distance from the camera to the plane in focus, along the view axis, in scene units;
    /// required when `aperture_radius` > 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focus_distance: Option<f32>,
    /// Adaptive sampling: after each pass (once `min_spp` is reached) 8 x 8 pixel blocks whose
    /// relative error is at most `threshold` get no more samples (`crate::adaptive`). `None` =
    /// every pixel gets `spp` samples.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<crate::adaptive::AdaptiveSettings>,
    /// Also produce a `denoised` layer (Intel Open Image Denoise, from the colour with albedo and
    /// normal). A request: a farm without a worker that can denoise finishes without the layer.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub denoise: bool,
    /// With `denoise`, on a farm: also denoise each frame after every completed pass, for the
    /// preview (the final frame's `denoised` layer is the same either way; a preview never
    /// holds a frame back). A local render denoises the final frame only.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub denoise_preview: bool,
}

fn is_zero(v: &f32) -> bool {
    *v == 0.0
}

/// An environment light (JSON: `{"file": "sky.exr", "intensity": 1, "rotation_deg": 0}` or
/// `{"color": [0.5, 0.6, 0.8]}`).
///
/// The image is equirectangular (latitude-longitude, 2:1), linear RGB in `.exr` or `.hdr`, a
/// path relative to the folder of the bundle's `.gltf`/`.glb` file (as glTF's own URIs are).
/// Its top row is straight up (+Y, glTF's up axis), and its centre column looks along -X, as
/// in Blender's world texture once glTF's axes are mapped to Blender's. Radiance = texel (or
/// `color`) x `intensity`, in the scene's radiance units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct EnvironmentSettings {
    /// Equirectangular `.exr` or `.hdr` image in the scene bundle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    /// Constant linear RGB radiance (instead of `file`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color: Option<[f32; 3]>,
    /// Multiplies the image or the colour (default 1).
    #[serde(default = "default_intensity")]
    pub intensity: f32,
    /// Turns the environment about the up axis (+Y), counter-clockwise seen from above.
    #[serde(default)]
    pub rotation_deg: f32,
}

fn default_intensity() -> f32 {
    1.0
}

/// Largest accepted length of an environment file name, in bytes.
pub const MAX_ENVIRONMENT_PATH: usize = 256;

impl EnvironmentSettings {
    /// Checks the fields: exactly one of `file` and `color`, finite non-negative numbers, a
    /// relative `.exr`/`.hdr` path that stays inside the bundle.
    pub fn validate(&self) -> Result<(), SettingsError> {
        let bad = |m: String| Err(SettingsError::Invalid(format!("environment.{m}")));
        match (&self.file, &self.color) {
            (Some(_), Some(_)) => return bad("file and environment.color exclude each other: give one".into()),
            (None, None) => return bad("file or environment.color is required".into()),
            (Some(f), None) => {
                if f.len() > MAX_ENVIRONMENT_PATH {
                    return bad(format!("file is {} bytes long; the limit is {MAX_ENVIRONMENT_PATH}", f.len()));
                }
                let path = std::path::Path::new(f);
                let inside = !f.is_empty()
                    && !f.contains('\\')
                    && path.components().all(|c| matches!(c, std::path::Component::Normal(_)));
                if !inside {
                    return bad(format!(
                        "file {f:?} must be a relative path inside the scene bundle (no '..', no leading '/')"
                    ));
                }
                let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
                if !matches!(ext.as_deref(), Some("exr" | "hdr")) {
                    return bad(format!("file {f:?} must be an .exr or .hdr image"));
                }
            }
            (None, Some(c)) => {
                if !c.iter().all(|v| v.is_finite() && *v >= 0.0) {
                    return bad(format!("color must be three finite numbers >= 0, got {c:?}"));
                }
            }
        }
        if !(self.intensity.is_finite() && self.intensity >= 0.0) {
            return bad(format!("intensity must be a finite number >= 0, got {}", self.intensity));
        }
        if !(self.rotation_deg.is_finite() && self.rotation_deg.abs() <= 360_000.0) {
            return bad(format!("rotation_deg must be a finite number of degrees, got {}", self.rotation_deg));
        }
        Ok(())
    }
}

fn default_fps() -> f32 {
    24.0
}

/// Largest accepted |frame| number.
pub const MAX_FRAME: i32 = 10_000_000;

/// Errors in settings, each naming the offending field.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SettingsError {
    #[error("{field} must be at least {min}, got {value}")]
    TooSmall { field: &'static str, min: u64, value: u64 },
    #[error("{field} must be at most {max}, got {value}")]
    TooLarge { field: &'static str, max: u64, value: u64 },
    #[error("{0}")]
    Invalid(String),
}

/// Limits a service enforces on settings (configurable on the coordinator).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    pub max_pixels: u64,
    pub max_dimension: u32,
    pub max_spp: u32,
    pub max_depth: u32,
    /// Most work units (tiles x passes) of one job: the coordinator keeps a state per unit.
    pub max_units: u64,
}

impl Limits {
    /// No service limit: [`RenderSettings::validate`] against it checks only that the settings
    /// make sense (and fit the film's fixed-point sums). The renderer uses it: the coordinator
    /// has already applied its configured limits, which may be above [`Limits::default`].
    pub const UNBOUNDED: Limits = Limits {
        max_pixels: u64::MAX,
        max_dimension: u32::MAX,
        max_spp: u32::MAX,
        max_depth: u32::MAX,
        max_units: u64::MAX,
    };
}

impl Default for Limits {
    fn default() -> Self {
        Self { max_pixels: 8192 * 8192, max_dimension: 16384, max_spp: 1 << 20, max_depth: 1024, max_units: 1 << 22 }
    }
}

impl RenderSettings {
    /// Tiles of the plan, without building it.
    pub fn tile_count(&self) -> u64 {
        let ts = u64::from(self.tile_size.max(1));
        u64::from(self.width).div_ceil(ts) * u64::from(self.height).div_ceil(ts)
    }

    /// Passes of the plan, without building it (the schedule of [`Plan::new`]).
    pub fn pass_count(&self) -> u64 {
        match self.passes {
            PassSchedule::Fixed { spp } => u64::from(self.spp).div_ceil(u64::from(spp.max(1))),
            PassSchedule::Doubling { first, max } => {
                let (mut s0, mut next, mut n) = (0u64, u64::from(first.max(1)), 0u64);
                while s0 < u64::from(self.spp) {
                    s0 += next;
                    n += 1;
                    next = (next * 2).min(u64::from(max.max(1)));
                    if next == u64::from(max.max(1)) {
                        // Constant from here on: the rest is a division.
                        return n + (u64::from(self.spp).saturating_sub(s0)).div_ceil(next);
                    }
                }
                n
            }
        }
    }

    /// A settings value with defaults for everything but the size and the sample count.
    pub fn new(width: u32, height: u32, spp: u32) -> Self {
        Self {
            width,
            height,
            spp,
            seed: 0,
            camera: None,
            integrator: IntegratorSettings::default(),
            sampler: SamplerKind::default(),
            tile_size: default_tile_size(),
            passes: PassSchedule::default(),
            frame: 0,
            fps: default_fps(),
            shutter: 0.0,
            animations: None,
            exposure: 0.0,
            auto_exposure: false,
            environment: None,
            aperture_radius: 0.0,
            focus_distance: None,
            adaptive: None,
            denoise: false,
            denoise_preview: false,
        }
    }

    /// Checks the settings against `limits`.
    pub fn validate(&self, limits: &Limits) -> Result<(), SettingsError> {
        fn at_least(field: &'static str, value: u64, min: u64) -> Result<(), SettingsError> {
            if value < min { Err(SettingsError::TooSmall { field, min, value }) } else { Ok(()) }
        }
        fn at_most(field: &'static str, value: u64, max: u64) -> Result<(), SettingsError> {
            if value > max { Err(SettingsError::TooLarge { field, max, value }) } else { Ok(()) }
        }
        at_least("width", self.width.into(), 1)?;
        at_least("height", self.height.into(), 1)?;
        at_most("width", self.width.into(), limits.max_dimension.into())?;
        at_most("height", self.height.into(), limits.max_dimension.into())?;
        at_most("width x height", u64::from(self.width) * u64::from(self.height), limits.max_pixels)?;
        at_least("spp", self.spp.into(), 1)?;
        at_most("spp", self.spp.into(), limits.max_spp.into())?;
        // Whatever the configured limit: the film's fixed-point sums are sized for this many.
        at_most("spp", self.spp.into(), crate::film::MAX_EXACT_SPP.into())?;
        at_least("tile_size", self.tile_size.into(), 8)?;
        at_most("tile_size", self.tile_size.into(), 1024)?;
        match self.passes {
            PassSchedule::Doubling { first, max } => {
                at_least("passes.first", first.into(), 1)?;
                at_least("passes.max", max.into(), first.into())?;
            }
            PassSchedule::Fixed { spp } => at_least("passes.spp", spp.into(), 1)?,
        }
        if self.frame.unsigned_abs() > MAX_FRAME.unsigned_abs() {
            return Err(SettingsError::Invalid(format!(
                "frame must be between -{MAX_FRAME} and {MAX_FRAME}, got {}",
                self.frame
            )));
        }
        if !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 10_000.0) {
            return Err(SettingsError::Invalid(format!("fps must be a number in (0, 10000], got {}", self.fps)));
        }
        if !(self.shutter.is_finite() && (0.0..=1.0).contains(&self.shutter)) {
            return Err(SettingsError::Invalid(format!(
                "shutter must be a fraction of a frame in [0, 1], got {}",
                self.shutter
            )));
        }
        if !(self.exposure.is_finite() && self.exposure.abs() <= 32.0) {
            return Err(SettingsError::Invalid(format!(
                "exposure must be between -32 and 32 EV, got {}",
                self.exposure
            )));
        }
        if let Some(names) = &self.animations {
            at_most("animations (count)", names.len() as u64, 1024)?;
            if let Some(n) = names.iter().find(|n| n.len() > 256) {
                return Err(SettingsError::Invalid(format!(
                    "animation name {:?}... is {} bytes long; the limit is 256",
                    n.chars().take(32).collect::<String>(),
                    n.len()
                )));
            }
        }
        if let Some(env) = &self.environment {
            env.validate()?;
        }
        if !(self.aperture_radius.is_finite() && (0.0..=1e6).contains(&self.aperture_radius)) {
            return Err(SettingsError::Invalid(format!(
                "aperture_radius must be a number in [0, 1e6] (scene units; 0 = pinhole), got {}",
                self.aperture_radius
            )));
        }
        match self.focus_distance {
            Some(f) if !(f.is_finite() && f > 0.0 && f <= 1e7) => {
                return Err(SettingsError::Invalid(format!(
                    "focus_distance must be a positive distance in scene units, got {f}"
                )));
            }
            None if self.aperture_radius > 0.0 => {
                return Err(SettingsError::Invalid(
                    "focus_distance is required when aperture_radius > 0 (the distance in focus)".into(),
                ));
            }
            _ => {}
        }
        // Counted, not built: 8192^2 in 8-px tiles with 1-spp passes of 2^20 spp would be 10^12.
        at_most("units (tiles x passes)", self.tile_count().saturating_mul(self.pass_count()), limits.max_units)?;
        match &self.integrator {
            IntegratorSettings::Path { max_depth, .. }
            | IntegratorSettings::Bdpt { max_depth, .. }
            | IntegratorSettings::Igi { max_depth, .. } => {
                at_most("integrator.max_depth", (*max_depth).into(), limits.max_depth.into())?;
            }
            IntegratorSettings::Direct { .. } => {}
        }
        if let IntegratorSettings::Bdpt { mis, strategy, .. } = &self.integrator {
            if matches!(mis, MisHeuristic::Light | MisHeuristic::Bsdf) {
                return Err(SettingsError::Invalid(format!(
                    "integrator.mis must be balance or power for bdpt, got {mis:?}"
                )));
            }
            // Checked: [u32::MAX, u32::MAX] must not wrap around to a sum that passes.
            if let Some([s, t]) = strategy
                && (*t < 1 || s.checked_add(*t).is_none_or(|n| n < 2))
            {
                return Err(SettingsError::Invalid(format!(
                    "integrator.strategy [{s}, {t}] does not exist: t >= 1 and s + t >= 2"
                )));
            }
        }
        if self.denoise_preview && !self.denoise {
            return Err(SettingsError::Invalid(
                "denoise_preview needs denoise: a denoised preview is of a job that asks for the denoised layer".into(),
            ));
        }
        if let Some(adaptive) = &self.adaptive {
            adaptive.validate(self.spp)?;
            if matches!(self.integrator, IntegratorSettings::Bdpt { .. }) {
                // Light-tracing splats land anywhere on the image, outside the tile sums the
                // error is estimated from, and are normalized by a per-pixel sample count that
                // adaptive sampling makes uneven.
                return Err(SettingsError::Invalid(
                    "adaptive sampling is not available with the bdpt integrator (its light-tracing splats \
                     are not in the per-pixel error estimate): use path, direct or igi, or drop adaptive"
                        .into(),
                ));
            }
        }
        if let IntegratorSettings::Igi { vpls, vpl_sets, g_limit, .. } = &self.integrator {
            at_least("integrator.vpls", (*vpls).into(), 1)?;
            at_most("integrator.vpls", (*vpls).into(), 1 << 16)?;
            at_least("integrator.vpl_sets", (*vpl_sets).into(), 1)?;
            at_most("integrator.vpl_sets", (*vpl_sets).into(), 1024)?;
            // Every sample index traces vpls x vpl_sets light paths.
            at_most("integrator.vpls x vpl_sets", u64::from(*vpls) * u64::from(*vpl_sets), 1 << 18)?;
            if !(g_limit.is_finite() && *g_limit > 0.0) {
                return Err(SettingsError::Invalid(format!(
                    "integrator.g_limit must be a positive number, got {g_limit}"
                )));
            }
        }
        Ok(())
    }

    /// Animation time of the frame's shutter opening, in seconds.
    pub fn frame_time(&self) -> f32 {
        self.frame as f32 / self.fps
    }

    /// Animation time of the shutter's closing, in seconds (= [`Self::frame_time`] without blur).
    pub fn shutter_close_time(&self) -> f32 {
        (self.frame as f32 + self.shutter) / self.fps
    }

    /// The work-unit plan of these settings.
    pub fn plan(&self) -> Plan {
        Plan::new(self)
    }
}

/// A rectangle of pixels `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TileRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl TileRect {
    pub fn width(&self) -> u32 {
        self.x1 - self.x0
    }
    pub fn height(&self) -> u32 {
        self.y1 - self.y0
    }
    pub fn pixel_count(&self) -> usize {
        self.width() as usize * self.height() as usize
    }
}

/// A pass: the sample index range `[s0, s1)` rendered for every pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Pass {
    pub index: u32,
    pub s0: u32,
    pub s1: u32,
}

impl Pass {
    pub fn samples(&self) -> Range<u32> {
        self.s0..self.s1
    }
    pub fn spp(&self) -> u32 {
        self.s1 - self.s0
    }
}

/// Address of a work unit inside a job: (frame, pass, tile). `frame` is the animation frame
/// number (`settings.frame` of the lease); a single-frame job's units all have its one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, utoipa::ToSchema)]
pub struct UnitKey {
    #[serde(default)]
    pub frame: i32,
    pub pass: u32,
    pub tile: u32,
}

/// Tiles (row-major) and passes of a job.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub tiles: Vec<TileRect>,
    pub passes: Vec<Pass>,
}

impl Plan {
    pub fn new(settings: &RenderSettings) -> Self {
        let ts = settings.tile_size.max(1);
        let mut tiles = Vec::new();
        for y0 in (0..settings.height).step_by(ts as usize) {
            for x0 in (0..settings.width).step_by(ts as usize) {
                tiles.push(TileRect { x0, y0, x1: (x0 + ts).min(settings.width), y1: (y0 + ts).min(settings.height) });
            }
        }
        let mut passes = Vec::new();
        let mut s0 = 0u32;
        let mut next = match settings.passes {
            PassSchedule::Doubling { first, .. } => first.max(1),
            PassSchedule::Fixed { spp } => spp.max(1),
        };
        while s0 < settings.spp {
            let s1 = s0.saturating_add(next).min(settings.spp);
            passes.push(Pass { index: passes.len() as u32, s0, s1 });
            s0 = s1;
            if let PassSchedule::Doubling { max, .. } = settings.passes {
                next = next.saturating_mul(2).min(max.max(1));
            }
        }
        Plan { tiles, passes }
    }

    pub fn unit_count(&self) -> usize {
        self.tiles.len() * self.passes.len()
    }

    /// Units in canonical (pass-major) order.
    pub fn units(&self) -> impl Iterator<Item = UnitKey> + '_ {
        (0..self.passes.len() as u32)
            .flat_map(move |pass| (0..self.tiles.len() as u32).map(move |tile| UnitKey { frame: 0, pass, tile }))
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn unit_counts_match_the_plan_and_are_bounded() {
        for (w, h, spp, ts, passes) in [
            (100, 60, 256, 32, PassSchedule::Doubling { first: 1, max: 64 }),
            (64, 64, 1000, 8, PassSchedule::Doubling { first: 3, max: 7 }),
            (64, 64, 10, 64, PassSchedule::Doubling { first: 16, max: 8 }),
            (33, 17, 999, 16, PassSchedule::Fixed { spp: 10 }),
            (1, 1, 1, 8, PassSchedule::Fixed { spp: 1 }),
        ] {
            let mut s = RenderSettings::new(w, h, spp);
            s.tile_size = ts;
            s.passes = passes;
            let plan = Plan::new(&s);
            assert_eq!(s.tile_count(), plan.tiles.len() as u64, "{s:?}");
            assert_eq!(s.pass_count(), plan.passes.len() as u64, "{s:?}");
        }
        // 8192^2 in 8-px tiles, 2^20 spp in 1-spp passes: 10^12 units (the coordinator tried to
        // allocate 16 TiB). Refused before any plan is built.
        let mut s = RenderSettings::new(8192, 8192, 1 << 20);
        s.tile_size = 8;
        s.passes = PassSchedule::Fixed { spp: 1 };
        let e = s.validate(&Limits::default()).expect_err("too many units");
        assert!(e.to_string().contains("units (tiles x passes)"), "{e}");
    }

    use super::*;

    #[test]
    fn lens_settings_are_checked_by_name() {
        let mut s = RenderSettings::new(8, 8, 1);
        s.aperture_radius = 0.1;
        let e = s.validate(&Limits::default()).expect_err("no focus").to_string();
        assert!(e.contains("focus_distance is required"), "{e}");
        s.focus_distance = Some(2.0);
        assert_eq!(s.validate(&Limits::default()), Ok(()));
        s.focus_distance = Some(-1.0);
        assert!(s.validate(&Limits::default()).expect_err("negative").to_string().contains("focus_distance"));
        s.focus_distance = Some(2.0);
        s.aperture_radius = f32::NAN;
        assert!(s.validate(&Limits::default()).expect_err("nan").to_string().contains("aperture_radius"));
    }

    #[test]
    fn environment_settings_are_checked_by_name() {
        let mut s = RenderSettings::new(8, 8, 1);
        let ok = |e: &str| -> EnvironmentSettings { serde_json::from_str(e).expect("parses") };
        for good in [
            r#"{"file": "sky.exr"}"#,
            r#"{"file": "env/Sky.HDR", "intensity": 2, "rotation_deg": -90}"#,
            r#"{"color": [0.5, 0.6, 0.8]}"#,
        ] {
            s.environment = Some(ok(good));
            assert_eq!(s.validate(&Limits::default()), Ok(()), "{good}");
        }
        for (bad, words) in [
            (r#"{}"#, "required"),
            (r#"{"file": "a.exr", "color": [1, 1, 1]}"#, "exclude"),
            (r#"{"file": "../a.exr"}"#, "inside the scene bundle"),
            (r#"{"file": "/etc/a.exr"}"#, "inside the scene bundle"),
            (r#"{"file": "sky.png"}"#, ".exr or .hdr"),
            (r#"{"color": [1, -1, 1]}"#, "color"),
            (r#"{"color": [1, 1, 1], "intensity": -2}"#, "intensity"),
        ] {
            s.environment = Some(ok(bad));
            let e = s.validate(&Limits::default()).expect_err(bad).to_string();
            assert!(e.contains("environment.") && e.contains(words), "{bad}: {e}");
        }
        assert!(serde_json::from_str::<EnvironmentSettings>(r#"{"colour": [1, 1, 1]}"#).is_err());
        // A job without an environment serializes as before.
        s.environment = None;
        assert!(!serde_json::to_string(&s).expect("json").contains("environment"));
    }

    #[test]
    fn plan_covers_every_pixel_and_sample_once() {
        let mut s = RenderSettings::new(130, 67, 100);
        s.tile_size = 32;
        let plan = s.plan();
        let mut hits = vec![0u32; 130 * 67];
        for t in &plan.tiles {
            for y in t.y0..t.y1 {
                for x in t.x0..t.x1 {
                    hits[(y * 130 + x) as usize] += 1;
                }
            }
        }
        assert!(hits.iter().all(|&h| h == 1));
        let spp: u32 = plan.passes.iter().map(Pass::spp).sum();
        assert_eq!(spp, 100);
        assert_eq!(plan.passes[0].s0, 0);
        for w in plan.passes.windows(2) {
            assert_eq!(w[0].s1, w[1].s0);
        }
        // Doubling 1, 2, 4, ... capped at 64.
        assert_eq!(plan.passes.iter().map(Pass::spp).collect::<Vec<_>>(), vec![1, 2, 4, 8, 16, 32, 37]);
    }

    #[test]
    fn settings_json_roundtrip_and_unknown_fields_rejected() {
        let s = RenderSettings::new(64, 32, 16);
        let json = serde_json::to_string(&s).expect("serialize");
        let back: RenderSettings = serde_json::from_str(&json).expect("parse");
        assert_eq!(s, back);
        let bad = r#"{"width": 4, "height": 4, "spp": 1, "bogus": 3}"#;
        assert!(serde_json::from_str::<RenderSettings>(bad).is_err());
        let p: RenderSettings =
            serde_json::from_str(r#"{"width":4,"height":4,"spp":1,"integrator":{"type":"direct","mis":"balance"}}"#)
                .expect("parse direct");
        assert_eq!(
            p.integrator,
            IntegratorSettings::Direct { mis: MisHeuristic::Balance, light_sampling: LightSampling::SolidAngle }
        );
    }

    #[test]
    fn bdpt_settings_default_and_validate() {
        let p: RenderSettings =
            serde_json::from_str(r#"{"width":4,"height":4,"spp":1,"integrator":{"type":"bdpt"}}"#).expect("parse");
        assert_eq!(
            p.integrator,
            IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 3, strategy: None }
        );
        assert!(p.validate(&Limits::default()).is_ok());
        let mut s = p.clone();
        s.integrator =
            IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 3, strategy: Some([0, 1]) };
        assert!(s.validate(&Limits::default()).expect_err("no (0, 1)").to_string().contains("strategy"));
        // The sum s + t overflows u32: refused, not wrapped around.
        for strategy in [[u32::MAX, u32::MAX], [u32::MAX, 1], [1, u32::MAX]] {
            s.integrator = IntegratorSettings::Bdpt {
                max_depth: 8,
                mis: MisHeuristic::Power,
                rr_depth: 3,
                strategy: Some(strategy),
            };
            let e = s.validate(&Limits::default()).expect_err("overflowing strategy");
            assert!(e.to_string().contains("strategy"), "{e}");
        }
        s.integrator =
            IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 3, strategy: Some([2, 1]) };
        assert!(s.validate(&Limits::default()).is_ok());
        s.integrator = IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Light, rr_depth: 3, strategy: None };
        assert!(s.validate(&Limits::default()).expect_err("light only").to_string().contains("mis"));
        let json = serde_json::to_string(&p).expect("serialize");
        assert!(!json.contains("strategy"), "{json}");
    }

    #[test]
    fn adaptive_and_denoise_default_off_parse_and_validate() {
        let s = RenderSettings::new(8, 8, 32);
        let json = serde_json::to_string(&s).expect("json");
        assert!(!json.contains("adaptive") && !json.contains("denoise"), "{json}");
        let p: RenderSettings = serde_json::from_str(
            r#"{"width":8,"height":8,"spp":32,"adaptive":{"threshold":0.02,"min_spp":8},"denoise":true}"#,
        )
        .expect("parse");
        assert_eq!(p.adaptive, Some(crate::adaptive::AdaptiveSettings { threshold: 0.02, min_spp: 8 }));
        assert!(p.denoise);
        assert_eq!(p.validate(&Limits::default()), Ok(()));
        let back: RenderSettings = serde_json::from_str(&serde_json::to_string(&p).expect("json")).expect("parse");
        assert_eq!(back, p);
        let mut bad = p.clone();
        bad.adaptive = Some(crate::adaptive::AdaptiveSettings { threshold: 0.02, min_spp: 64 });
        let e = bad.validate(&Limits::default()).expect_err("min_spp > spp").to_string();
        assert!(e.contains("adaptive.min_spp"), "{e}");
        bad = p.clone();
        bad.integrator =
            IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
        let e = bad.validate(&Limits::default()).expect_err("bdpt").to_string();
        assert!(e.contains("adaptive sampling is not available with the bdpt integrator"), "{e}");
        bad = p.clone();
        bad.denoise = false;
        bad.denoise_preview = true;
        let e = bad.validate(&Limits::default()).expect_err("preview without denoise").to_string();
        assert!(e.contains("denoise_preview needs denoise"), "{e}");
        bad.denoise = true;
        assert_eq!(bad.validate(&Limits::default()), Ok(()));
    }

    #[test]
    fn unbounded_limits_still_refuse_nonsense() {
        let mut deep = RenderSettings::new(16, 16, 4);
        deep.integrator = IntegratorSettings::Path {
            max_depth: 5000,
            rr_depth: 5,
            mis: MisHeuristic::default(),
            light_sampling: Default::default(),
        };
        assert!(
            deep.validate(&Limits::default()).expect_err("deeper than the default").to_string().contains("max_depth")
        );
        assert_eq!(deep.validate(&Limits::UNBOUNDED), Ok(()));
        let big = RenderSettings::new(16384, 16384, 4);
        assert!(big.validate(&Limits::default()).is_err());
        assert_eq!(big.validate(&Limits::UNBOUNDED), Ok(()));
        assert!(RenderSettings::new(16, 16, 0).validate(&Limits::UNBOUNDED).is_err());
        let over = RenderSettings::new(16, 16, crate::film::MAX_EXACT_SPP + 1);
        assert!(over.validate(&Limits::UNBOUNDED).is_err());
    }

    #[test]
    fn validate_names_the_limit() {
        let mut s = RenderSettings::new(100_000, 10, 1);
        let e = s.validate(&Limits::default()).expect_err("too wide");
        assert!(e.to_string().contains("width"), "{e}");
        s.width = 10;
        s.spp = 0;
        assert!(s.validate(&Limits::default()).expect_err("spp 0").to_string().contains("spp"));
    }
}
