//! The renderer. Pure: no async, no I/O, no global state. Everything a unit computes is a
//! function of (scene, settings, tile, sample range).

pub mod accel;
pub mod bdpt;
pub mod bsdf;
pub mod camera;
#[cfg(test)]
pub mod chi2;
pub mod geometry;
pub mod igi;
pub mod integrator;
pub mod lambert;
pub mod light;
pub mod material;
pub mod math;
pub mod microfacet;
pub mod sampler;
pub mod sampling;
pub mod scene;
pub mod spherical;
mod vec3;
pub mod wavefront;
pub mod wide;

use bdpt::{BdptBatch, BdptParams, li_bdpt};
use camera::Camera;
use glam::{UVec2, Vec2, Vec3A};
use igi::{IgiParams, IgiScratch, VplCache};
use integrator::{PathParams, li_path};
use pathfarm_common::adaptive::BlockMask;
use pathfarm_common::assembly::FilmAssembly;
use pathfarm_common::film::{self, Film, SplatBuffer, TileAccum};
use pathfarm_common::job::{IntegratorSettings, MisHeuristic, Pass, RenderSettings, TileRect, UnitKey};
use pathfarm_common::scene::{self as scene_model, EnvironmentImage, Scene};
use rayon::prelude::*;
use sampler::{AnySampler, Sampler};
use scene::{EnvironmentSpec, RenderScene};
use wavefront::{PathKernel, Wavefront};

/// Errors preparing a scene for rendering.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error("scene: {0}")]
    Scene(String),
}

/// What one work unit (tile x pass) produces.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnitResult {
    pub accum: TileAccum,
    /// Light-tracing splats anywhere on the image (BDPT only).
    pub splats: Option<SplatBuffer>,
}

/// The integrator of a job with its parameters (one match per sample; the sampler is the
/// monomorphized part).
#[derive(Clone, Copy, Debug)]
enum Integrator {
    Path(PathParams),
    Bdpt(BdptParams),
    Igi(IgiParams),
}

/// A scene prepared for rendering (BVH, lights, materials, camera) with fixed settings.
pub struct Renderer {
    settings: RenderSettings,
    scene: RenderScene,
    camera: Camera,
    /// Motion blur: the scene cameras at shutter open and close; each camera sample draws a
    /// time in [0, 1] of the shutter and sees the camera and the geometry at that time.
    /// `None` without blur (no shutter, or a still scene: nothing can move).
    shutter_cameras: Option<(scene_model::Camera, scene_model::Camera)>,
    integrator: Integrator,
    /// IGI: the virtual point lights of each sample index, built on first use.
    vpls: VplCache,
    /// How `path` and `direct` units are traced (bit-identical either way).
    path_kernel: PathKernel,
}

/// The sample dimension of a bdpt sample's shutter time (beyond its camera and light subpaths'
/// dimensions, below the lens's).
const BDPT_TIME_DIM: u32 = 1 << 14;

/// A light-tracing contribution at a raster position.
type Splat = (Vec2, Vec3A);

impl Renderer {
    /// Prepares `scene` for rendering with `settings` (builds the BVH: do it once per job).
    ///
    /// An animated scene is posed at the settings' frame time (`frame / fps`) with the named
    /// animations playing (all by default); a still scene is used as it is. A job whose
    /// environment names an image needs [`Renderer::with_environment`].
    pub fn new(scene: &Scene, settings: &RenderSettings) -> Result<Self, RenderError> {
        Self::with_environment(scene, settings, None)
    }

    /// [`Renderer::new`] with the decoded image of the job's environment (the renderer does no
    /// I/O: the caller loads it with `pathfarm_common::scene::load_environment`).
    pub fn with_environment(
        scene: &Scene,
        settings: &RenderSettings,
        environment_image: Option<EnvironmentImage>,
    ) -> Result<Self, RenderError> {
        // The one settings check, without a service's limits: a coordinator may be configured
        // above the defaults and has applied its own (the CLI applies the defaults before this).
        settings
            .validate(&pathfarm_common::job::Limits::UNBOUNDED)
            .map_err(|e| RenderError::Settings(e.to_string()))?;
        let names = settings.animations.as_deref();
        if let Some(unknown) = names.and_then(|n| n.iter().find(|n| !scene.animation_names().contains(&n.as_str()))) {
            let clips = scene.animation.as_ref().map_or(&[][..], |a| a.clips());
            return Err(RenderError::Settings(pathfarm_common::scene::anim::unknown_animation(unknown, clips)));
        }
        // Motion blur needs something that can move: an animated scene.
        let blur = settings.shutter > 0.0 && scene.animation.is_some();
        if blur && matches!(settings.integrator, IntegratorSettings::Igi { .. }) {
            return Err(RenderError::Settings(
                "motion blur (shutter > 0) on an animated scene is implemented for the direct, path and \
                 bdpt integrators; igi (whose VPLs are shared by every pixel) needs shutter 0"
                    .into(),
            ));
        }
        let pose = |t: f32| scene.posed(t, names).map_err(|e| RenderError::Scene(e.to_string()));
        let posed;
        let close = if blur { Some(pose(settings.shutter_close_time())?) } else { None };
        let scene = match &scene.animation {
            Some(_) => {
                posed = pose(settings.frame_time())?;
                &posed
            }
            None => scene,
        };
        // The loader refuses such scenes; a Scene built another way must not reach the BVH.
        let limit = pathfarm_common::scene::MAX_COORDINATE;
        for m in scene.meshes.iter().chain(close.iter().flat_map(|c| &c.meshes)) {
            if let Some(p) = m.positions.iter().find(|p| !(p.is_finite() && p.abs().max_element() <= limit)) {
                return Err(RenderError::Scene(format!(
                    "mesh {:?}: vertex at {p}: coordinates must be finite and within +-{limit:e}",
                    m.name
                )));
            }
        }
        let aspect = settings.width as f32 / settings.height.max(1) as f32;
        let scene_camera = |s: &Scene| match settings.camera {
            Some(i) => s.cameras.get(i).cloned().ok_or_else(|| {
                RenderError::Settings(format!("camera {i} does not exist (the scene has {})", s.cameras.len()))
            }),
            None => Ok(s.cameras.first().cloned().unwrap_or_else(|| scene_model::default_camera(s, aspect))),
        };
        let open_camera = scene_camera(scene)?;
        let camera = Camera::new(&open_camera, settings.width, settings.height);
        let shutter_cameras = match &close {
            // Without scene cameras the framing camera stays where the open pose puts it.
            Some(c) if !c.cameras.is_empty() => Some((open_camera, scene_camera(c)?)),
            Some(_) => Some((open_camera.clone(), open_camera)),
            None => None,
        };
        let camera = match (settings.aperture_radius > 0.0, settings.focus_distance) {
            (true, Some(focus_distance)) => camera
                .with_lens(camera::Lens { radius: settings.aperture_radius, focus_distance })
                .ok_or_else(|| {
                    RenderError::Settings(
                        "aperture_radius needs a perspective camera (this one is orthographic)".into(),
                    )
                })?,
            _ => camera,
        };
        let integrator = match settings.integrator {
            IntegratorSettings::Direct { mis, light_sampling } => {
                Integrator::Path(PathParams { max_depth: 2, rr_depth: u32::MAX, mis, light_sampling })
            }
            IntegratorSettings::Path { max_depth, rr_depth, mis, light_sampling } => {
                Integrator::Path(PathParams { max_depth, rr_depth, mis, light_sampling })
            }
            IntegratorSettings::Bdpt { max_depth, mis, rr_depth, strategy } => {
                if camera.lens().is_some() {
                    return Err(RenderError::Settings(
                        "bdpt does not connect light paths to a thin lens yet: use aperture_radius 0, or the path or \
                         igi integrator for depth of field"
                            .into(),
                    ));
                }
                if !camera.is_pinhole() {
                    return Err(RenderError::Settings(
                        "bdpt needs a perspective (pinhole) camera: light paths cannot be connected to an \
                         orthographic one"
                            .into(),
                    ));
                }
                let mis_exponent = match mis {
                    MisHeuristic::Balance => 1,
                    MisHeuristic::Power => 2,
                    other => {
                        return Err(RenderError::Settings(format!(
                            "bdpt weighs its strategies with mis balance or power, not {other:?}"
                        )));
                    }
                };
                Integrator::Bdpt(BdptParams {
                    max_depth,
                    rr_depth,
                    mis_exponent,
                    strategy: strategy.map(|[s, t]| (s, t)),
                })
            }
            IntegratorSettings::Igi { vpls, vpl_sets, g_limit, bias_compensation, max_depth } => {
                if let Some(why) = igi::unsupported_material(&scene.materials) {
                    return Err(RenderError::Settings(why));
                }
                Integrator::Igi(IgiParams { vpls, vpl_sets, g_limit, bias_compensation, max_depth })
            }
        };
        let environment = environment_spec(settings, environment_image)?;
        let render_scene = match &close {
            Some(c) => RenderScene::new_moving(scene, c, environment).map_err(RenderError::Scene)?,
            None => RenderScene::with_environment(scene, environment),
        };
        Ok(Self {
            settings: settings.clone(),
            scene: render_scene,
            camera,
            shutter_cameras,
            integrator,
            vpls: VplCache::default(),
            path_kernel: PathKernel::default(),
        })
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// The camera at shutter time `time` (motion blur): interpolated between shutter open and
    /// close, with the job's thin lens (validated perspective at construction, so it holds).
    fn camera_at(&self, time: f32) -> Camera {
        let Some((open, close)) = &self.shutter_cameras else { return self.camera.clone() };
        let camera = Camera::interpolate(open, close, time, self.settings.width, self.settings.height);
        match self.camera.lens() {
            Some(lens) => camera.clone().with_lens(lens).unwrap_or(camera),
            None => camera,
        }
    }

    /// The SIMD level the renderer's kernels use on this CPU (workers report it).
    pub fn simd_level(&self) -> wide::SimdLevel {
        self.scene.simd_level()
    }

    /// Uses the best level up to `level` that the CPU supports: images are bit-identical at
    /// every level; for tests and measurements. Returns the level in use.
    pub fn set_simd_level(&mut self, level: wide::SimdLevel) -> wide::SimdLevel {
        self.scene.set_simd_level(level)
    }

    /// Traces `path` and `direct` units with `kernel` (the wavefront by default): images are
    /// bit-identical either way; for tests and measurements.
    pub fn set_path_kernel(&mut self, kernel: PathKernel) {
        self.path_kernel = kernel;
    }

    pub fn path_kernel(&self) -> PathKernel {
        self.path_kernel
    }

    pub fn scene(&self) -> &RenderScene {
        &self.scene
    }

    /// Renders the sample indices of `pass` for every pixel of `tile`, in parallel over rows on
    /// the current rayon pool. The result does not depend on the thread count.
    pub fn render_unit(&self, tile: TileRect, pass: Pass) -> UnitResult {
        self.render_tile_unit(tile, pass, None)
    }

    /// [`Renderer::render_unit`] for adaptive sampling: pixels in the converged blocks of `mask`
    /// get no samples (their sums stay zero, so merging the result adds nothing to them).
    /// `None`, or a mask with nothing converged, renders every pixel. Refused: a mask of another
    /// tile's block layout, and a mask with the bdpt integrator (whose splats adaptive sampling
    /// does not handle; settings validation refuses the pair too).
    pub fn render_unit_masked(
        &self,
        tile: TileRect,
        pass: Pass,
        mask: Option<&BlockMask>,
    ) -> Result<UnitResult, RenderError> {
        let mask = mask.filter(|m| !m.none());
        if let Some(m) = mask {
            if !m.fits(tile) {
                return Err(RenderError::Settings(format!(
                    "the block mask has {:?} blocks; tile {tile:?} has {:?}",
                    m.blocks(),
                    BlockMask::blocks_of(tile)
                )));
            }
            if matches!(self.integrator, Integrator::Bdpt(_)) {
                return Err(RenderError::Settings(
                    "adaptive sampling (a block mask) is not available with bdpt".into(),
                ));
            }
        }
        Ok(self.render_tile_unit(tile, pass, mask))
    }

    /// Builds what the units of `pass` share (igi's VPL sets of its samples), so that units
    /// rendered at once find it made rather than each making it.
    pub fn prepare_pass(&self, pass: Pass) {
        if let Integrator::Igi(p) = self.integrator {
            self.vpls.get(&self.scene, &p, self.settings.sampler, self.settings.seed, pass);
        }
    }

    fn render_tile_unit(&self, tile: TileRect, pass: Pass, mask: Option<&BlockMask>) -> UnitResult {
        // One match per unit: the per-sample loop is monomorphized for the concrete sampler.
        let seed = self.settings.seed;
        let (accum, splats) = match AnySampler::new(self.settings.sampler, seed) {
            AnySampler::Sobol(_) => self.render_tile(tile, pass, mask, || sampler::SobolSampler::new(seed)),
            AnySampler::Independent(_) => self.render_tile(tile, pass, mask, || sampler::IndependentSampler::new(seed)),
        };
        let splats = matches!(self.integrator, Integrator::Bdpt(_)).then(|| {
            let mut buf = SplatBuffer::new(self.settings.width, self.settings.height);
            for (raster, v) in splats {
                let p = raster.floor();
                if p.x >= 0.0 && p.y >= 0.0 {
                    buf.add(p.x as u32, p.y as u32, v.to_array());
                }
            }
            buf
        });
        UnitResult { accum, splats }
    }

    fn render_tile<S: Sampler + Clone>(
        &self,
        tile: TileRect,
        pass: Pass,
        mask: Option<&BlockMask>,
        new_sampler: impl Fn() -> S + Sync,
    ) -> (TileAccum, Vec<Splat>) {
        let vpls = match self.integrator {
            Integrator::Igi(p) => Some(self.vpls.get(&self.scene, &p, self.settings.sampler, self.settings.seed, pass)),
            _ => None,
        };
        // The wavefront's buffers are made once per rayon job, not per row (the bench's `tiny
        // large`: 0.125-0.126 s -> 0.123-0.125 s), and only for the wavefront; so are bdpt's
        // batches (their subpaths' vertices grown anew for each row cost more than the batched
        // rays saved), made with room for a batch's strategies and rays: a rayon job's batch
        // grown from nothing reallocated them 912 times in the bench's `tiny bdpt` (with the
        // subpaths' and splats' room below: 706.3M -> 699.3M instructions, `tiny bdpt long`
        // 0.980x the time, median of 11 interleaved pairs). So is igi's scratch, with room for
        // a batch (grown from nothing row by row, its growth was 3% of `tiny igi`'s
        // instructions).
        let no_wavefront = || {
            let bdpt = match &self.integrator {
                Integrator::Bdpt(_) => BdptBatch::with_capacity(BDPT_BATCH, BDPT_STRATEGIES),
                _ => BdptBatch::default(),
            };
            let igi = match &self.integrator {
                Integrator::Igi(_) => IgiScratch::with_capacity(igi::IGI_BATCH_RAYS),
                _ => IgiScratch::default(),
            };
            (None::<Wavefront<S>>, bdpt, igi)
        };
        let wavefront = match (&self.integrator, self.path_kernel) {
            (Integrator::Path(params), PathKernel::Wavefront) => Some(params),
            _ => None,
        };
        // The wavefront traces rows in groups with a full batch of samples or more (a pass of
        // few samples per pixel left a row's batches short: per-bounce stage costs spread over
        // fewer paths, and small scenes' sorted packets less full); the others row by row.
        let group = match wavefront {
            Some(_) => wavefront::batch_len(&self.scene)
                .div_ceil((tile.width() as usize * pass.spp() as usize).max(1))
                .max(1) as u32,
            None => 1,
        };
        let groups: Vec<(u32, u32)> =
            (tile.y0..tile.y1).step_by(group as usize).map(|y| (y, (y + group).min(tile.y1))).collect();
        // Each group's pixels are written in place into the tile's sums (row-major; a chunk
        // size of at least 1, as rayon needs, even for a tile without pixels).
        let width = tile.width() as usize;
        let mut accum = TileAccum { rect: tile, sums: vec![film::PixelSums::default(); tile.pixel_count()] };
        let splats: Vec<Vec<Splat>> = accum
            .sums
            .par_chunks_mut((width * group as usize).max(1))
            .zip(groups)
            .map_init(no_wavefront, |(wf, bdpt_batch, igi_scratch), (out, (y, y_end))| {
                if let Some(params) = wavefront {
                    let wf = wf.get_or_insert_with(|| Wavefront::with_batch(wavefront::batch_len(&self.scene)));
                    self.path_rows_wavefront(wf, tile, pass, mask, y..y_end, params, &new_sampler, out);
                    return Vec::new();
                }
                let mut sampler = new_sampler();
                let mut splats = Vec::new();
                if let (Integrator::Bdpt(params), None) = (&self.integrator, &self.shutter_cameras) {
                    // Room for a splat or two per sample from the start (grown from nothing,
                    // the row's splats were copied at each doubling), up to 2 MiB: a long pass
                    // of a scene the light paths seldom splat into grows only as it needs.
                    let samples = out.len() * pass.s1.saturating_sub(pass.s0) as usize;
                    splats.reserve((2 * samples).min(MAX_SPLATS_RESERVED));
                    let row = TileRow { tile, pass, mask, y };
                    self.bdpt_row(row, params, &mut sampler, bdpt_batch, &mut splats, out);
                    return splats;
                }
                if let Integrator::Igi(params) = &self.integrator {
                    let row = TileRow { tile, pass, mask, y };
                    self.igi_row(row, params, vpls.as_deref().unwrap_or_default(), &mut sampler, igi_scratch, out);
                    return splats;
                }
                for (x, pixel_out) in (tile.x0..tile.x1).zip(out.iter_mut()) {
                    if mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0)) {
                        // A converged block: no samples, nothing added by the merge (its sums
                        // stay zero).
                        continue;
                    }
                    // The unit's samples of this pixel, AOVs summed in f64, in sample order.
                    let mut acc = film::PixelAccum::default();
                    let pixel = UVec2::new(x, y);
                    for s in pass.samples() {
                        let v = match &self.integrator {
                            Integrator::Path(params) => {
                                sampler.start_pixel_sample(pixel, s, 0);
                                match &self.shutter_cameras {
                                    // The time is the sample's first dimension, so stills keep
                                    // their layout.
                                    Some(_) => {
                                        let time = sampler.get_1d();
                                        let camera = self.camera_at(time);
                                        li_path(&self.scene, &camera, pixel, &mut sampler, params, time)
                                    }
                                    None => li_path(&self.scene, &self.camera, pixel, &mut sampler, params, 0.0),
                                }
                            }
                            Integrator::Bdpt(params) => {
                                // bdpt addresses its own dimensions from 0: the time comes from
                                // a dimension of its own.
                                let (camera, time) = match &self.shutter_cameras {
                                    Some(_) => {
                                        sampler.start_pixel_sample(pixel, s, 0);
                                        let time = sampler.get_2d_at(BDPT_TIME_DIM).x;
                                        (std::borrow::Cow::Owned(self.camera_at(time)), time)
                                    }
                                    None => (std::borrow::Cow::Borrowed(&self.camera), 0.0),
                                };
                                li_bdpt(
                                    &self.scene,
                                    &camera,
                                    pixel,
                                    s,
                                    &mut sampler,
                                    params,
                                    bdpt_batch,
                                    &mut |raster, v| splats.push((raster, v)),
                                    time,
                                )
                            }
                            // Rendered by `igi_row` above.
                            Integrator::Igi(_) => film::SampleValue::default(),
                        };
                        acc.add(&v);
                    }
                    *pixel_out = acc.finish();
                }
                splats
            })
            .collect();
        // The rows' splats in row order, in one allocation (`flatten().collect()` grew its
        // `Vec` from nothing).
        let mut all = Vec::with_capacity(splats.iter().map(Vec::len).sum());
        for row in splats {
            all.extend(row);
        }
        (accum, all)
    }
}

/// A row of a tile's pass for [`Renderer::bdpt_row`] and [`Renderer::igi_row`].
#[derive(Clone, Copy)]
struct TileRow<'a> {
    tile: TileRect,
    pass: Pass,
    mask: Option<&'a BlockMask>,
    y: u32,
}

/// Samples per [`BdptBatch`] of a row: enough visibility rays (about 8 a sample in the Cornell
/// box at depth 8) that a batch's sorted packets fill.
/// 256 measured slower on an Intel Xeon (AVX-512): `tiny bdpt long` 1.048x the time (median of 9
/// interleaved pairs, quartiles 1.018-1.148).
const BDPT_BATCH: usize = 64;

/// The most splats a bdpt row's job makes room for before it has any (2 MiB).
const MAX_SPLATS_RESERVED: usize = 1 << 16;

/// The strategies (and visibility rays) a bdpt sample usually has, for which its batch makes
/// room at once ([`BdptBatch::with_capacity`]).
const BDPT_STRATEGIES: usize = 16;

impl Renderer {
    /// Row `row.y` of a tile for the `bdpt` integrator without motion blur: its samples (pixel by
    /// pixel, each pixel's in sample order) in batches of [`BDPT_BATCH`] ([`BdptBatch`]: each
    /// batch's visibility rays answered at once), each pixel's values folded in sample order as
    /// one sample at a time folds them, splats in sample order; the row's sums written to `out`
    /// (converged pixels left as they are).
    fn bdpt_row<S: Sampler>(
        &self,
        row: TileRow<'_>,
        params: &BdptParams,
        sampler: &mut S,
        batch: &mut BdptBatch,
        splats: &mut Vec<Splat>,
        out: &mut [film::PixelSums],
    ) {
        let TileRow { tile, pass, mask, y } = row;
        let mut values = Vec::with_capacity(BDPT_BATCH);
        // The pixels of the samples in the batch, and the pixel whose values are being folded.
        let mut owners: Vec<usize> = Vec::with_capacity(BDPT_BATCH);
        let mut acc: Option<(usize, film::PixelAccum)> = None;
        let mut flush = |batch: &mut BdptBatch, owners: &mut Vec<usize>, out: &mut [film::PixelSums]| {
            values.clear();
            batch.finish(&self.scene, &self.camera, params, &mut |raster, v| splats.push((raster, v)), &mut values);
            for (&owner, v) in owners.iter().zip(&values) {
                match &mut acc {
                    Some((o, a)) if *o == owner => a.add(v),
                    _ => {
                        if let Some((o, a)) = acc.take()
                            && let Some(slot) = out.get_mut(o)
                        {
                            *slot = a.finish();
                        }
                        let mut a = film::PixelAccum::default();
                        a.add(v);
                        acc = Some((owner, a));
                    }
                }
            }
            owners.clear();
        };
        for (k, x) in (tile.x0..tile.x1).enumerate() {
            if mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0)) {
                continue;
            }
            let pixel = UVec2::new(x, y);
            for s in pass.samples() {
                batch.push(&self.scene, &self.camera, pixel, s, sampler, params, 0.0);
                owners.push(k);
                if batch.len() >= BDPT_BATCH {
                    flush(batch, &mut owners, out);
                }
            }
        }
        if !batch.is_empty() {
            flush(batch, &mut owners, out);
        }
        if let Some((o, a)) = acc
            && let Some(slot) = out.get_mut(o)
        {
            *slot = a.finish();
        }
    }

    /// Row `row.y` of a tile for the `igi` integrator: its samples (pixel by pixel, each
    /// pixel's in sample order, with `vpls`, the pass's VPL sets by sample) recorded until
    /// their VPLs' shadow rays fill a batch ([`igi::IGI_BATCH_RAYS`]), the batch's rays
    /// answered at once ([`IgiScratch`]), each pixel's values folded in sample order; the row's
    /// sums written to `out` (converged pixels left as they are).
    fn igi_row<S: Sampler>(
        &self,
        row: TileRow<'_>,
        params: &IgiParams,
        vpls: &[std::sync::Arc<igi::VplSets>],
        sampler: &mut S,
        scratch: &mut IgiScratch,
        out: &mut [film::PixelSums],
    ) {
        let TileRow { tile, pass, mask, y } = row;
        let mut accs = vec![film::PixelAccum::default(); out.len()];
        let mut flush = |scratch: &mut IgiScratch| {
            scratch.resolve(&self.scene, |k, v| {
                if let Some(acc) = accs.get_mut(k) {
                    acc.add(v);
                }
            });
        };
        let converged = |x: u32| mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0));
        for (k, x) in (tile.x0..tile.x1).enumerate() {
            if converged(x) {
                continue;
            }
            let pixel = UVec2::new(x, y);
            for s in pass.samples() {
                sampler.start_pixel_sample(pixel, s, 0);
                let sets = vpls.get((s - pass.s0) as usize).map(|v| &**v);
                scratch.record(&self.scene, &self.camera, pixel, sampler, params, sets, k);
                if scratch.rays() >= igi::IGI_BATCH_RAYS {
                    flush(scratch);
                }
            }
        }
        flush(scratch);
        // A converged block: no samples, nothing added by the merge (its sums stay zero).
        for ((slot, acc), x) in out.iter_mut().zip(&accs).zip(tile.x0..tile.x1) {
            if !converged(x) {
                *slot = acc.finish();
            }
        }
    }

    /// Rows `ys` of `tile` for the `path` integrator with the wavefront kernel: their samples
    /// (row by row, pixel by pixel, each pixel's in sample order) in batches, each pixel's
    /// values folded in sample order as the scalar loop folds them; the rows' sums written to
    /// `out` (row-major; converged pixels left as they are). (A sample's value does not depend
    /// on its batch, so neither do the sums.)
    #[allow(clippy::too_many_arguments)]
    fn path_rows_wavefront<S: Sampler + Clone>(
        &self,
        wf: &mut Wavefront<S>,
        tile: TileRect,
        pass: Pass,
        mask: Option<&BlockMask>,
        ys: std::ops::Range<u32>,
        params: &PathParams,
        new_sampler: &(impl Fn() -> S + Sync),
        out: &mut [film::PixelSums],
    ) {
        let camera_at = |time: f32| self.camera_at(time);
        let shutter: Option<&dyn Fn(f32) -> Camera> = self.shutter_cameras.as_ref().map(|_| &camera_at as _);
        let start = wavefront::CameraStage { new_sampler, camera: &self.camera, shutter };
        let width = tile.width() as usize;
        let mut accs = vec![film::PixelAccum::default(); width * ys.len()];
        let batch_len = wavefront::batch_len(&self.scene);
        let mut batch: Vec<(UVec2, u32)> = Vec::with_capacity(batch_len);
        let mut values = Vec::with_capacity(batch_len);
        let origin = UVec2::new(tile.x0, ys.start);
        let mut flush = |batch: &mut Vec<(UVec2, u32)>, accs: &mut [film::PixelAccum]| {
            values.clear();
            wf.trace(&self.scene, params, batch, &start, &mut values);
            let accumulate = Accumulate { accs: &mut *accs, origin, width, batch, values: &values };
            match self.scene.avx2() {
                Some(avx2) => avx2.run_kernel(accumulate),
                None => wide::V3Kernel::call(accumulate),
            }
            batch.clear();
        };
        let converged = |x: u32, y: u32| mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0));
        for y in ys.clone() {
            for x in (tile.x0..tile.x1).filter(|&x| !converged(x, y)) {
                for s in pass.samples() {
                    batch.push((UVec2::new(x, y), s));
                    if batch.len() == batch_len {
                        flush(&mut batch, &mut accs);
                    }
                }
            }
        }
        if !batch.is_empty() {
            flush(&mut batch, &mut accs);
        }
        let finish = FinishPixels { accs: &accs, out, tile, ys, converged: &converged };
        match self.scene.avx2() {
            Some(avx2) => avx2.run_kernel(finish),
            None => wide::V3Kernel::call(finish),
        }
    }
}

/// The rows `ys` of `tile`: each pixel's sums from its accumulator (AOVs as means), written
/// to `out` but where `converged` (a converged block: no samples, nothing added by the merge,
/// its sums stay zero). Run compiled for x86-64-v3 where the CPU has it: the means' divisions
/// go in lanes (the same IEEE operations, so the same bits). The bench's `tiny large` (5
/// progressive passes) 1,360.1M -> 1,353.7M instructions (`finish` 37.6M -> about 25M), `tiny
/// large long` 0.993x the time (15 interleaved pairs: noise).
struct FinishPixels<'a, C> {
    accs: &'a [film::PixelAccum],
    out: &'a mut [film::PixelSums],
    tile: TileRect,
    ys: std::ops::Range<u32>,
    converged: &'a C,
}

impl<C: Fn(u32, u32) -> bool> wide::V3Kernel for FinishPixels<'_, C> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let tile = self.tile;
        let pixels = self.ys.flat_map(|y| (tile.x0..tile.x1).map(move |x| (x, y)));
        for (((x, y), a), o) in pixels.zip(self.accs).zip(self.out) {
            if !(self.converged)(x, y) {
                *o = a.finish();
            }
        }
    }
}

/// Adds a batch's sample values to their pixels' accumulators (each pixel's in sample order):
/// `accs` holds rows of `width` pixels from `origin`. Run compiled for x86-64-v3 where the CPU
/// has it: the optimizer then does the channels' conversions in AVX lanes (the same IEEE
/// operations, so the same sums).
///
/// Tried on an Intel Xeon with AVX-512 and dropped: each pixel's run of samples added into a
/// copy held in registers and written back once (no store and reload of the accumulator from
/// one sample to the next): this kernel is 11% of the 130k-triangle scene's time (`tiny large
/// long`, 256 samples a pixel), which took 0.984x then 0.996x the time (medians of 11 and 15
/// interleaved pairs, quartiles 0.956-1.025 the second time), `tiny long` 1.003x: noise.
struct Accumulate<'a> {
    accs: &'a mut [film::PixelAccum],
    origin: UVec2,
    width: usize,
    batch: &'a [(UVec2, u32)],
    values: &'a [film::SampleValue],
}

impl wide::V3Kernel for Accumulate<'_> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        for ((pixel, _), v) in self.batch.iter().zip(self.values) {
            let (x, y) = (pixel.x.wrapping_sub(self.origin.x) as usize, pixel.y.wrapping_sub(self.origin.y) as usize);
            if x < self.width
                && let Some(acc) = self.accs.get_mut(y * self.width + x)
            {
                acc.add(v);
            }
        }
    }
}

/// The job's environment light from its settings and the image its `file` names.
fn environment_spec(
    settings: &RenderSettings,
    image: Option<EnvironmentImage>,
) -> Result<Option<EnvironmentSpec>, RenderError> {
    let Some(env) = &settings.environment else { return Ok(None) };
    let scale = Vec3A::from(env.color.unwrap_or([1.0; 3])) * env.intensity;
    let image = match (&env.file, image) {
        (Some(_), Some(img)) => Some(img),
        (Some(f), None) => {
            return Err(RenderError::Settings(format!(
                "environment.file {f:?}: the image was not loaded (Renderer::with_environment takes it)"
            )));
        }
        (None, _) => None,
    };
    Ok(Some(EnvironmentSpec { image, scale, rotation_deg: env.rotation_deg }))
}

/// The most memory `render_local`'s units in flight may hold at once (their tiles' sums, and
/// bdpt's whole-image splat buffers): at least one unit is always in flight.
const LOCAL_IN_FLIGHT_BYTES: usize = 64 << 20;

/// Renders a whole job locally, folding its units in canonical order, exactly as the farm does.
/// `progress(done, total)` is called after each unit.
///
/// Consecutive units of one pass (each of its own tile) render at once on the rayon pool, up to
/// twice its threads and 64 MiB of results, and are folded in order when all are done:
/// one unit at a time, each unit's last rows left a thread idle, and so did each fold. Measured
/// on an Intel Xeon (2 threads, interleaved runs, ratios of wall time): progressive passes of
/// the Cornell box (256 x 256, 16 spp) 0.907x (9 pairs), of the 130k-triangle scene (64 spp)
/// 0.951x (25 pairs, quartiles 0.892-1.001); one pass of 64 spp, 1.004x (noise: its 16 units
/// are long). Each unit's result is the same whenever it renders, so the film is the same bits
/// as one unit at a time (`tests/local.rs`). Tried and dropped: a chunk folding while the next
/// renders (unless the next holds one of its tiles): on 2 threads (the bench's `tiny ...
/// threads2`), progressive passes of the 130k-triangle scene (256 spp) 0.992x the time (15
/// pairs), of the Cornell box (256 x 256, 16 spp) 0.967x then 0.998x (11 and 15 pairs): the
/// folds are about 100 instructions a pixel and pass, well under 1% of a render. Tried on an
/// Intel Xeon and dropped: a chunk's units (distinct tiles) merged into the film together, its
/// rows in parallel on the pool (the same bits): the 130k-triangle scene at 16 spp in 5 passes
/// (`tiny large threads2`, where passes cost the most: 0.066-0.073 s against 0.042-0.050 s in
/// one pass) 1.066x and 1.069x the time (11 and 15 runs each), `tiny long threads2` 0.966x (9).
///
/// With adaptive sampling the passes run in order and, after each pass, every tile's mask comes
/// from [`pathfarm_common::adaptive::converged_blocks`] of the film's merged sums of that tile; the next pass
/// renders with it, and a tile whose blocks have all converged is skipped (counted as done).
/// (A tile's mask depends only on its own earlier passes, which are folded before its next
/// unit renders.)
pub fn render_local(renderer: &Renderer, mut progress: impl FnMut(usize, usize)) -> Film {
    let settings = renderer.settings();
    let plan = settings.plan();
    // The farm's merge: the same assembly folds, judges blocks and drops converged tiles.
    let mut asm = FilmAssembly::new(&plan, settings.width, settings.height);
    let adaptive = settings.adaptive.as_ref().map(|a| (a, settings.spp));
    let total = plan.unit_count();
    let most_units = 2 * rayon::current_num_threads().max(1);
    let splat_bytes = match renderer.integrator {
        Integrator::Bdpt(_) => {
            settings.width as usize * settings.height as usize * 3 * std::mem::size_of::<film::Fixed>()
        }
        _ => 0,
    };
    let unit_bytes = |key: &UnitKey| {
        plan.tiles[key.tile as usize].pixel_count() * std::mem::size_of::<film::PixelSums>() + splat_bytes
    };
    let mut units = plan.units().peekable();
    let mut chunk = Vec::with_capacity(most_units);
    let mut done = 0;
    while let Some(first) = units.next() {
        chunk.clear();
        chunk.push(first);
        let mut bytes = unit_bytes(&first);
        while chunk.len() < most_units
            && let Some(next) = units.peek()
            && next.pass == first.pass
            && bytes + unit_bytes(next) <= LOCAL_IN_FLIGHT_BYTES
        {
            bytes += unit_bytes(next);
            chunk.extend(units.next());
        }
        let pass = plan.passes[first.pass as usize];
        // The pass's shared state (igi's VPL sets) built once, before its units look it up.
        renderer.prepare_pass(pass);
        let asm_now = &asm;
        let results: Vec<Option<UnitResult>> = chunk
            .par_iter()
            .map(|key| {
                // A tile whose every block converged left the schedule (its later passes count
                // as done).
                if asm_now.next_pass(key.tile as usize) != key.pass {
                    return None;
                }
                let tile = plan.tiles[key.tile as usize];
                let mask = asm_now.mask(key.tile as usize);
                Some(if mask.is_some() {
                    // The settings were validated (no bdpt) and the mask is of this tile.
                    renderer.render_unit_masked(tile, pass, mask).unwrap_or_else(|e| unreachable!("{e}"))
                } else {
                    renderer.render_unit(tile, pass)
                })
            })
            .collect();
        for (&key, r) in chunk.iter().zip(results) {
            if let Some(r) = r {
                asm.offer(&plan, adaptive, key, r.accum, r.splats);
            }
            done += 1;
            progress(done, total);
        }
    }
    asm.into_film().unwrap_or_else(|| unreachable!("render_local never takes the film away"))
}
