//! The wavefront path integrator: the `path` (and `direct`) integrator run on batches of camera
//! samples, stage by stage, instead of one path at a time.
//!
//! A batch holds up to [`BATCH`] paths. The camera stage makes their camera rays (a pinhole
//! camera's 8 lanes at a time in AVX2: [`Sampler::pixel_2d_many`],
//! [`super::wide::Avx2::pinhole_directions`]). Then each bounce runs these stages over the paths
//! still alive: closest hits for all their rays (one batched BVH query); arrival (emission
//! found, the environment, the depth limit); the bounce's random numbers for every path that
//! goes on, drawn at once ([`Sampler::bounce_draws_many`]: 8-wide Owen scrambles where the CPU
//! has AVX2), and their diffuse directions ([`cosine_hemisphere_many`], 8 lanes); where every
//! light is a static triangle, their light samples, 8 lanes at a time
//! ([`RenderScene::sample_light_at_many`]: by area, a square root and two divisions per sample,
//! which one path at a time left waiting; by solid angle, [`super::spherical`]'s arcsines and
//! sines); shading, light sampling and BSDF sampling with Russian
//! roulette (which queue a shadow ray and the next ray);
//! one batched any-hit query for the queued shadow rays. Dead paths leave the list of live ones
//! (compaction), so later stages touch only live paths.
//!
//! Measured on the Cornell box (area light sampling, max depth 8): 11.5k instructions per
//! sample against 12.2k one path at a time (callgrind, the bench's `tiny`), and about 1.2x the
//! samples per CPU-second: the stages run long loops over warm code and data. The lane-wise
//! camera and diffuse stages (with `render::math`) took it to 10.8k; the lane-wise triangle
//! tests and packets (`accel`) trade it back up to 11.3k for less time; per-sample costs (the
//! pixel hash, paths reset in place, seeds shared by a pixel's samples, the Sobol kernels'
//! bit reversal and conversions in lanes) took it to 10.9k, the ray-origin offset in SSE2
//! lanes to 10.6k, the light samples in lanes to 10.5k and the bounce draws' transpose to
//! 10.2k (0.058 to 0.051 s over the session that made these last steps); the plain Lambertian
//! bounces in lanes ([`super::lambert`]) took it to 8.9k (0.766 to 0.718 s on `tiny long`), and
//! small scenes' rays in sorted packets (`accel`) to 8.3k (0.658 s). By solid angle (the jobs'
//! default), the light samples in lanes took `tiny solid long` from 1.41 s to 0.75 s. Later, on
//! another machine (AMD EPYC with AVX-512): hits on meshes with only positions and normals
//! built without the general case's checks, Lambertian lanes filled as the shading stage meets
//! them (light samples read from the lanes they were made in), one packet stack per batch, and
//! a tile's rows traced in groups of at least a batch (`Renderer::render_tile`: a 1-spp pass
//! left a row's batches at 64 paths) took `tiny` from 8.35k to 7.89k instructions per sample
//! (`tiny long` 0.855 to 0.821 s, min of 7 interleaved); the light sample's point by area drawn
//! in the light kernel's lanes, and the film's fixed-point rounding in lanes, to 7.73k; vectors
//! kept as [`super::wide::Vec3Lanes`] and transposed inside the kernels, and a packet's node
//! visiting only the children its rays hit, to 7.54k (`tiny long` 0.792 to 0.764 s), and no
//! material lookup for the transmittance of scenes where nothing attenuates, to 7.46k; batches
//! of 1,024 paths where rays go in sorted packets ([`batch_len`]) and emission looked up inline,
//! to 7.21k (`tiny long` 0.775 to 0.727 s over these last three steps, min of 7 interleaved).
//! On an AVX2-only AMD EPYC (Zen 3): each static triangle's geometric normal made once at
//! build, the light kernel's samples written in place, and packets that read their rays by
//! reference and write their hits in place, to 7.03k (472.3M to 460.8M instructions; `tiny
//! long` within this machine's noise, 0.91-0.93 s). Lane triangle tests that leave after the
//! edge functions, a packet's closest hits kept in lanes, the bench built as the `dist`
//! profile ships (fat LTO) and a batch's surfaces made in one loop, to 6.67k (437.1M). On an
//! AMD EPYC with AVX-512 (Zen 5): a sorted class's rays ordered by the octant of their origin
//! (`accel`), to 6.53k (427.8M). On an Intel Xeon with AVX-512: the light kernel's inputs
//! reused from chunk to chunk, to 6.50k (425.9M); the camera stage's pinhole directions made in
//! one kernel for the whole batch (`PinholeRays`: one call per 8 paths had left each call's
//! chain of divisions and square roots waiting on the last), `tiny` 426.2M -> 425.5M and the
//! 130k-triangle scene, where 85% of camera rays miss, `tiny large` 1,391.5M -> 1,382.2M
//! instructions, `tiny large long` 0.944x and 0.959x the time (medians of 11 interleaved pairs,
//! quartiles 0.904-0.968 and 0.855-0.986; `tiny long` 1.007x: noise). The same for the
//! Sobol draws of the pixel offsets and of each bounce (one kernel for the batch, not one call
//! per 8 samplers): `tiny` 422.4M, `tiny large` 1,381.8M, `tiny large long` 0.903x and 0.962x
//! (11 pairs each, quartiles 0.843-0.992 and 0.900-0.985), `tiny long` 1.003x. Tried the same
//! way and dropped: the cosine directions and the light samples in one kernel each: `tiny`
//! 422.4M -> 420.7M, `tiny solid` 458.9M -> 456.6M instructions, but `tiny long` 0.922x and
//! 0.990x, `tiny solid long` 1.026x and 1.018x (9 to 15 pairs): no gain in time (each call of
//! these kernels has work enough of its own to overlap). The paths' sample values kept out of
//! their state (192 -> 160 bytes a path) and written in place into the caller's values: `tiny
//! large` 1,381.8M -> 1,374.3M instructions, `tiny large long` 1.002x then 0.932x the time
//! (medians of 11 interleaved pairs, quartiles 0.948-1.024 and 0.914-0.951), `tiny long` 0.971x.
//! The batch's rays kept as an array of their own in the order of the live paths, written
//! where a path starts or bounces (not a ray in each path, gathered into the query each
//! bounce; 160 -> 128 bytes a path): `tiny` 422.6M -> 418.4M, `tiny solid` 459.0M -> 454.8M,
//! `tiny large` 1,374.3M -> 1,360.1M instructions; `tiny large long` 0.933x the time, `tiny
//! long` 1.012x and 0.993x, `tiny solid long` 1.026x (11 interleaved pairs each: noise).
//!
//! Bit identity with [`super::integrator::li_path`]: every path does exactly the f32 operations
//! of the scalar integrator in the same order, with the same shared functions
//! ([`nee_sample`], [`sample_scatter_ahead`], `emission_weight`, [`shade`]); its sampler draws the
//! same dimensions (the samplers are addressed by (seed, pixel, sample index, dimension), so a
//! path's numbers never depend on its neighbours); its radiance sums its terms in the scalar
//! order (a shadow ray's contribution is added in the shadow stage, before the next bounce adds
//! anything). Nothing crosses lanes: a sample's value is the same whatever batch it is in, so
//! images stay deterministic and split-invariant. The tests render whole tiles both ways and
//! compare bits.
//!
//! Tried on an AMD EPYC with AVX-512 (Zen 4) and dropped: the stages from arrival to shading
//! run over the live paths a chunk at a time (arrival, the bounce's numbers, the diffuse
//! directions, the light samples and shading for 64 paths, then the next 64), so that a chunk's
//! paths and surfaces stay in the L1 cache between stages (perf puts many of the stage loops'
//! cycles on their first reads of a path or surface). `tiny` 425.9M -> 429.0M instructions
//! (chunks of 8: 447.6M; 32: 432.5M; 128: 427.4M; 256: 426.7M), `tiny long` 1.038x the time with
//! chunks of 64 (median of 9 interleaved pairs), 0.991x (quartiles 0.935-1.009) with 128 and
//! 1.003x with 256 (15 pairs each): within the machine's noise at best.
//!
//! Tried on an Intel Xeon with AVX-512 and dropped: the stages' glue (`trace_batch`, 21% of
//! `tiny long`'s time in perf, compiled for the baseline x86-64) run as a kernel compiled for
//! the CPU's level (`wide::V3Kernel`): `tiny` 426.2M -> 425.0M instructions, `tiny long`
//! 0.964x then 1.001x the time, `tiny large long` 1.058x then 1.033x (medians of 9 and 11
//! interleaved pairs): no gain.
//!
//! Tried on an AVX2-only AMD EPYC (Zen 3) and dropped: the paths prefetched 8 ahead in the
//! arrival and shadow stages (which reach them through lists of indices; perf put their first
//! reads among the glue's hottest instructions): `tiny` 415.7M -> 420.2M instructions, `tiny
//! long` 1.002x the time (median of 15 interleaved pairs), 1.031x by the fastest of each.

use super::accel::{Hit, RayQuery};
use super::camera::Camera;
use super::geometry::{Ray, offset_ray_origin};
use super::integrator::{
    PathParams, RR_MAX_SURVIVAL, emission_weight, nee_sample, nee_with_light, sample_scatter_ahead,
};
use super::lambert::LambertLanes;
use super::light::LightSampleContext;
use super::material::shade;
use super::sampler::{BounceDraws, Replay, Sampler};
use super::sampling::{CosineSample, cosine_hemisphere_many};
use super::scene::{LightBatch, RenderScene, SurfaceInteraction};
use super::wide::{Avx2, SimdLevel};
use glam::{UVec2, Vec2, Vec3A};
use pathfarm_common::film::SampleValue;
use pathfarm_common::job::MisHeuristic;

/// Paths per batch: enough that a stage's loop runs long over warm code and data, few enough
/// that the batch's state (128 bytes a path, beside its ray and its sample value) stays in the
/// L2 cache. 512 measured no better on the 130k-triangle scene (Intel Xeon, `tiny large long` 0.967x and 0.995x the time,
/// medians of 11 interleaved pairs).
pub const BATCH: usize = 256;

/// The batch size for `scene`: the largest batch the BVH sorts into packets
/// (`accel::SORTED_BATCH`, 2,048 paths) where the scene's rays go in sorted packets
/// ([`RenderScene::sorts_rays`]) and it has no textures, else [`BATCH`]. Either way every
/// sample's value is the same (nothing crosses lanes).
///
/// More rays of each octant and dominant axis make fuller packets. Measured with 1,024 paths
/// wherever rays are sorted, against 256: the Cornell box (36 triangles, `tiny`) 489.0M ->
/// 474.4M instructions (512 paths: 479.2M; 2048: 473.9M), `tiny long` 0.762 -> 0.722 s (min of
/// 7 interleaved), the bench's paired rounds 0.70 -> 0.77 of Mitsuba's llvm_ad_rgb;
/// cornellBox_nvpro (16.7k triangles, sorted while it pays) 2,072M -> 2,023M instructions
/// (128x128x8), 1.81 -> 1.73 s (`pathfarm-worker render`, 256x256x32, 2 threads). But
/// MixedLighting (41k triangles) and GlassHurricane (4.1k), both textured and sorted, rendered
/// 9-10% slower (min of 11 interleaved) with the same instruction counts: the cost is in the
/// memory system (likely the larger batch's state evicting the texels their shading reads), so
/// textured scenes keep [`BATCH`]. The sorted batch later went to 2,048 (with the sort's origin
/// cells); 1,024 again, measured on an Intel Xeon (AVX-512): `tiny` 417.9M -> 423.9M
/// instructions, one pass of the Cornell box on 2 threads (`tiny long onepass threads2`)
/// 1.036x the time (median of 15 interleaved pairs, quartiles 1.006-1.056). On an AVX2-only
/// AMD EPYC (Zen 3, 512 KB of L2 cache a core, where 2,048 paths' state does not fit), 1,024
/// and 512 paths measured no faster: `tiny long` 0.989x and 1.039x the time (the fastest of 15
/// interleaved runs each). 4,096 (batches whose later bounces stay fuller, about what
/// refilling a batch's dead paths with new camera samples could give) took `tiny` from 417.9M
/// to 413.9M instructions only: refilling was not built.
pub fn batch_len(scene: &RenderScene) -> usize {
    if scene.textures.is_empty() && scene.sorts_rays() { super::accel::SORTED_BATCH } else { BATCH }
}

/// Which implementation renders `path` and `direct` units (their images are bit-identical).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum PathKernel {
    /// One path at a time ([`super::integrator::li_path`]).
    Scalar,
    /// Batches of paths, stage by stage ([`Wavefront`]).
    #[default]
    Wavefront,
}

/// One path of a batch: the loop state of the scalar integrator, but its ray (the batch's
/// rays are an array of their own, in the order of the live paths: see [`Wavefront::trace`]).
struct PathState<S> {
    sampler: S,
    /// Shutter time of the path's camera sample (0 without motion blur).
    time: f32,
    l: Vec3A,
    beta: Vec3A,
    eta_scale: f32,
    specular_bounce: bool,
    prev_bsdf_pdf: f32,
    prev_ctx: LightSampleContext,
    depth: u32,
}

impl<S> PathState<S> {
    /// A path at its camera ray (from `origin`), before its first bounce.
    fn new(sampler: S, origin: Vec3A, time: f32) -> Self {
        Self {
            sampler,
            time,
            l: Vec3A::ZERO,
            beta: Vec3A::ONE,
            eta_scale: 1.0,
            specular_bounce: true,
            prev_bsdf_pdf: 0.0,
            prev_ctx: LightSampleContext { p: origin, n: Vec3A::ZERO },
            depth: 0,
        }
    }

    /// Makes this path [`PathState::new`]'s, field by field in place (a new value would be
    /// built apart and copied: about 30 instructions a path).
    #[inline(always)]
    fn reset(&mut self, sampler: S, origin: Vec3A, time: f32) {
        self.sampler = sampler;
        self.time = time;
        self.l = Vec3A::ZERO;
        self.beta = Vec3A::ONE;
        self.eta_scale = 1.0;
        self.specular_bounce = true;
        self.prev_bsdf_pdf = 0.0;
        self.prev_ctx = LightSampleContext { p: origin, n: Vec3A::ZERO };
        self.depth = 0;
    }
}

/// The camera stage of the wavefront (see [`Wavefront::trace`]): fresh samplers, the camera,
/// and the camera at a shutter time where there is motion blur.
pub struct CameraStage<'a, F> {
    pub new_sampler: F,
    pub camera: &'a Camera,
    pub shutter: Option<&'a dyn Fn(f32) -> Camera>,
}

/// A path in a lane of [`Wavefront::lambert_lanes`]: its index and its bounce's first
/// dimension.
#[derive(Clone, Copy, Default)]
struct LambertPath {
    path: u32,
    base: u32,
}

/// What the lanes of [`super::lambert`] write back to: the paths, and the stage's shadow rays
/// and next live paths and their rays.
struct LambertSink<'a, S> {
    paths: &'a mut [PathState<S>],
    /// The paths' sample values (the AOVs of their first hits).
    values: &'a mut [SampleValue],
    shadows: &'a mut Vec<PendingShadow>,
    shadow_rays: &'a mut Vec<RayQuery>,
    next_live: &'a mut Vec<u32>,
    next_rays: &'a mut Vec<RayQuery>,
}

/// A shadow ray's pending contribution: `beta * contribution` is added to the path's radiance
/// if the ray is unoccluded, `beta * 0` if it is not (as the scalar integrator adds).
struct PendingShadow {
    path: u32,
    beta: Vec3A,
    contribution: Vec3A,
}

/// The buffers of the wavefront integrator, reused from batch to batch (one per thread).
pub struct Wavefront<S> {
    paths: Vec<PathState<S>>,
    live: Vec<u32>,
    next_live: Vec<u32>,
    /// Positions in `live` of the paths that shade this bounce, and their numbers.
    shading: Vec<u32>,
    draws: Vec<BounceDraws>,
    /// The camera stage's pixel offsets.
    pixel_us: Vec<Vec2>,
    /// The diffuse direction of each shading path, computed 8 lanes at a time from its
    /// direction number (`draws[k].d2[1]`), and those numbers.
    cosines: Vec<CosineSample>,
    cosine_us: Vec<Vec2>,
    /// The live paths' rays (`rays[k]`: path `live[k]`'s), and the next bounce's (in the order
    /// of `next_live`): written where a ray is made, not gathered from the paths each bounce.
    rays: Vec<RayQuery>,
    next_rays: Vec<RayQuery>,
    hits: Vec<Option<Hit>>,
    surfaces: Vec<Option<SurfaceInteraction>>,
    /// The shading paths' light samples, where they are sampled ahead in lanes.
    light_samples: LightBatch,
    shadows: Vec<PendingShadow>,
    shadow_rays: Vec<RayQuery>,
    blocked: Vec<bool>,
    /// The shading paths at plain Lambertian hits, bounced 8 at a time in lanes
    /// ([`super::lambert`]): the lanes' inputs, filled as the shading stage meets them (reused:
    /// lanes past a short chunk's end keep old values, and their results are dropped), and
    /// their paths.
    lambert_lanes: Box<LambertLanes>,
    lambert: [LambertPath; 8],
}

impl<S: Sampler> Default for Wavefront<S> {
    fn default() -> Self {
        Self::with_batch(BATCH)
    }
}

impl<S: Sampler> Wavefront<S> {
    /// Buffers for batches of `batch` paths ([`batch_len`]), made once (growing them batch by
    /// batch was a `realloc` and copy per buffer and rayon job).
    pub fn with_batch(batch: usize) -> Self {
        Self {
            paths: Vec::with_capacity(batch),
            live: Vec::with_capacity(batch),
            next_live: Vec::with_capacity(batch),
            shading: Vec::with_capacity(batch),
            draws: Vec::with_capacity(batch),
            pixel_us: Vec::with_capacity(batch),
            cosines: Vec::with_capacity(batch),
            cosine_us: Vec::with_capacity(batch),
            rays: Vec::with_capacity(batch),
            next_rays: Vec::with_capacity(batch),
            hits: Vec::with_capacity(batch),
            surfaces: Vec::with_capacity(batch),
            light_samples: LightBatch::with_capacity(batch),
            shadows: Vec::with_capacity(batch),
            shadow_rays: Vec::with_capacity(batch),
            blocked: Vec::with_capacity(batch),
            lambert_lanes: Box::default(),
            lambert: [LambertPath::default(); 8],
        }
    }
}

impl<S: Sampler + Clone> Wavefront<S> {
    /// Traces one camera sample per entry of `samples` (pixel, sample index) and appends each
    /// one's value to `out`, in order. `camera` is the camera stage: a fresh sampler positioned
    /// at the sample (`start_pixel_sample(pixel, index, 0)`), what the camera draws from it, the
    /// camera ray and the shutter time, as the scalar renderer does before calling `li_path`.
    pub fn trace(
        &mut self,
        scene: &RenderScene,
        params: &PathParams,
        samples: &[(UVec2, u32)],
        camera: &CameraStage<'_, impl Fn() -> S>,
        out: &mut Vec<SampleValue>,
    ) {
        for chunk in samples.chunks(batch_len(scene)) {
            // The batch's values are written in place: a path's state holds none (its reset and
            // the copy out touched them path by path).
            let start = out.len();
            out.resize(start + chunk.len(), SampleValue::default());
            self.trace_batch(scene, params, chunk, camera, &mut out[start..]);
        }
    }

    /// The camera stage: one path per sample. A pinhole camera without motion blur draws the
    /// batch's pixel offsets and makes its rays 8 lanes at a time where the CPU has AVX2 (the
    /// scalar bits); other cameras one path at a time ([`camera_sample`]).
    // Out of line: once per batch, and the stages' code stays apart (the optimizer's choices
    // in the bounce loop do not move with it).
    #[inline(never)]
    fn start_paths(&mut self, samples: &[(UVec2, u32)], camera: &CameraStage<'_, impl Fn() -> S>, level: SimdLevel) {
        let lanes = Avx2::at(level).filter(|_| camera.shutter.is_none() && camera.camera.is_pinhole());
        // Each path's sampler is a copy of one positioned at its sample: a pixel's samples follow
        // one another, and a sampler keeps what depends on the pixel alone (Sobol's pixel hash)
        // from one sample to the next (the same state as a fresh sampler positioned there).
        let mut proto = (camera.new_sampler)();
        // The batch's paths are those of the last batch, reset in place.
        self.paths.truncate(samples.len());
        while self.paths.len() < samples.len() {
            self.paths.push(PathState::new(proto.clone(), Vec3A::ZERO, 0.0));
        }
        self.rays.clear();
        let Some(avx2) = lanes else {
            for (p, &(pixel, index)) in self.paths.iter_mut().zip(samples) {
                proto.start_pixel_sample(pixel, index, 0);
                let (sampler, ray, time) = camera_sample(proto.clone(), pixel, index, camera.camera, camera.shutter);
                p.reset(sampler, ray.o, time);
                self.rays.push(RayQuery::unbounded(ray.o, ray.d, time));
            }
            return;
        };
        let origin = camera.camera.position();
        for (p, &(pixel, index)) in self.paths.iter_mut().zip(samples) {
            proto.start_pixel_sample(pixel, index, 0);
            p.reset(proto.clone(), origin, 0.0);
        }
        // Their directions are the kernel's.
        self.rays.resize(samples.len(), RayQuery::unbounded(origin, Vec3A::Z, 0.0));
        self.pixel_us.clear();
        S::pixel_2d_many(self.paths.iter_mut().map(|p| &mut p.sampler), level, &mut self.pixel_us);
        let kernel = PinholeRays { avx2, camera: camera.camera, rays: &mut self.rays, us: &self.pixel_us, samples };
        avx2.run_kernel(kernel);
    }

    fn trace_batch(
        &mut self,
        scene: &RenderScene,
        params: &PathParams,
        samples: &[(UVec2, u32)],
        camera: &CameraStage<'_, impl Fn() -> S>,
        values: &mut [SampleValue],
    ) {
        self.start_paths(samples, camera, scene.simd_level());
        self.live.clear();
        self.live.extend(0..self.paths.len() as u32);
        while !self.live.is_empty() {
            // Intersection stage (the rays were made where the paths were started or bounced).
            scene.intersect_many(&self.rays, &mut self.hits, &mut self.surfaces);
            // Arrival stage: emission, environment, depth limit.
            self.shading.clear();
            for (k, (&i, ray)) in self.live.iter().zip(&self.rays).enumerate() {
                let (path, value) = (&mut self.paths[i as usize], &mut values[i as usize]);
                if arrive(scene, params, path, value, ray.d, self.surfaces[k].as_ref()) {
                    self.shading.push(k as u32);
                }
            }
            // The random numbers of the bounce, for every shading path at once.
            self.draws.clear();
            let (paths, live) = (&self.paths, &self.live);
            S::bounce_draws_many(
                self.shading.iter().map(|&k| &paths[live[k as usize] as usize].sampler),
                scene.simd_level(),
                &mut self.draws,
            );
            // The cosine-hemisphere directions of diffuse lobes, for every shading path at once
            // (8 lanes, the scalar bits): from the number a non-delta vertex samples its
            // direction with (`BOUNCE_2D[1]`); a vertex that samples with another number
            // computes its own.
            self.cosine_us.clear();
            self.cosine_us.extend(self.draws.iter().map(|d| d.d2[1]));
            self.cosines.clear();
            cosine_hemisphere_many(&self.cosine_us, scene.simd_level(), &mut self.cosines);
            // The light samples of every shading path, 8 lanes at a time, where the scene's
            // lights allow (`RenderScene::samples_lights_in_lanes`): from the numbers a non-delta
            // vertex samples its light with (`BOUNCE_1D[1]`, `BOUNCE_2D[0]`) and the hit point
            // (all a light sample reads of the vertex).
            let ahead = scene.samples_lights_in_lanes(params.light_sampling);
            if ahead {
                let (paths, live, surfaces) = (&self.paths, &self.live, &self.surfaces);
                let queries = self.shading.iter().zip(&self.draws).map(|(&k, d)| {
                    let p = surfaces[k as usize].as_ref().map_or(Vec3A::ZERO, |si| si.p);
                    (p, d.d1[1], d.d2[0], paths[live[k as usize] as usize].time)
                });
                scene.sample_light_at_many(queries, params.light_sampling, &mut self.light_samples);
            }
            // Shading stage: BSDF, light sample, scattering, roulette. Paths at plain Lambertian
            // hits go 8 at a time in lanes where the light samples were taken ahead (the same
            // bits: `lambert` is written once for both); the others one at a time.
            self.shadows.clear();
            self.shadow_rays.clear();
            self.next_live.clear();
            self.next_rays.clear();
            let lanes = (ahead
                && scene.has_plain_lambert()
                && matches!(params.mis, MisHeuristic::Power | MisHeuristic::Balance))
            .then(|| scene.avx2())
            .flatten();
            let mut sink = LambertSink {
                paths: &mut self.paths,
                values: &mut *values,
                shadows: &mut self.shadows,
                shadow_rays: &mut self.shadow_rays,
                next_live: &mut self.next_live,
                next_rays: &mut self.next_rays,
            };
            let mut in_lanes = 0;
            for (n, ((&k, draws), cosine)) in self.shading.iter().zip(&self.draws).zip(&self.cosines).enumerate() {
                let i = self.live[k as usize];
                let Some(si) = self.surfaces[k as usize].as_ref() else { continue };
                let path = &mut sink.paths[i as usize];
                let d = self.rays[k as usize].d;
                if let Some(avx2) = lanes
                    && let Some(r) = scene.plain_lambert_at(si, -d)
                {
                    // Into the next lane; 8 full lanes bounce at once.
                    let lane_paths = &mut self.lambert;
                    let lanes = &mut *self.lambert_lanes;
                    lanes.p.set(in_lanes, si.p);
                    lanes.ng.set(in_lanes, si.ng);
                    lanes.ns.set(in_lanes, si.ns);
                    lanes.d.set(in_lanes, d);
                    lanes.r.set(in_lanes, r);
                    lanes.beta.set(in_lanes, path.beta);
                    lanes.eta_scale[in_lanes] = path.eta_scale;
                    // The light sample, taken ahead in lanes.
                    let light = self.light_samples.write_lane(scene, n, lanes, in_lanes);
                    lanes.light[in_lanes] = if light { 1.0 } else { 0.0 };
                    lanes.cosine.set(in_lanes, cosine.w);
                    lanes.roulette[in_lanes] = if path.depth + 1 >= params.rr_depth { 1.0 } else { 0.0 };
                    lanes.u_rr[in_lanes] = draws.d1[3];
                    lane_paths[in_lanes] = LambertPath { path: i, base: draws.base };
                    in_lanes += 1;
                    if in_lanes == 8 {
                        lambert_bounces(avx2, lanes, &lane_paths[..], params, &mut sink);
                        in_lanes = 0;
                    }
                    continue;
                }
                let light = ahead.then_some((&self.light_samples, n));
                let pending = scatter(scene, params, path, &mut sink.values[i as usize], d, si, draws, cosine, light);
                if let Some((ray, shadow)) = pending.shadow {
                    sink.shadow_rays.push(ray);
                    sink.shadows.push(PendingShadow { path: i, beta: shadow.0, contribution: shadow.1 });
                }
                if let Some(ray) = pending.next {
                    sink.next_live.push(i);
                    sink.next_rays.push(RayQuery::unbounded(ray.o, ray.d, path.time));
                }
            }
            if let Some(avx2) = lanes
                && in_lanes > 0
            {
                lambert_bounces(avx2, &self.lambert_lanes, &self.lambert[..in_lanes], params, &mut sink);
            }
            // Shadow stage.
            if !self.shadows.is_empty() {
                scene.occluded_many(&self.shadow_rays, &mut self.blocked);
                for (s, &blocked) in self.shadows.iter().zip(&self.blocked) {
                    let c = if blocked { Vec3A::ZERO } else { s.contribution };
                    self.paths[s.path as usize].l += s.beta * c;
                }
            }
            std::mem::swap(&mut self.live, &mut self.next_live);
            std::mem::swap(&mut self.rays, &mut self.next_rays);
        }
        for (p, v) in self.paths.iter().zip(values) {
            v.radiance = p.l.to_array();
        }
    }
}

/// The camera stage's directions of a batch's paths (a pinhole camera), 8 lanes at a time in
/// one kernel: from each path's pixel and offset, written into its ray (of the batch's rays).
struct PinholeRays<'a> {
    avx2: Avx2,
    camera: &'a Camera,
    rays: &'a mut [RayQuery],
    us: &'a [Vec2],
    samples: &'a [(UVec2, u32)],
}

impl super::wide::V3Kernel for PinholeRays<'_> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let chunks = self.rays.chunks_mut(8).zip(self.us.chunks(8)).zip(self.samples.chunks(8));
        for ((rays, us), samples) in chunks {
            // A short chunk's missing lanes compute something harmless, and are dropped.
            let [mut px, mut py, mut ux, mut uy] = [[0.0f32; 8]; 4];
            for (i, (&(pixel, _), u)) in samples.iter().zip(us).enumerate().take(8) {
                (px[i], py[i], ux[i], uy[i]) = (pixel.x as f32, pixel.y as f32, u.x, u.y);
            }
            let lanes = |v: &[f32; 8]| self.avx2.f32x8(v);
            let Some((x, y, z)) = self.camera.pinhole_directions(lanes(&px), lanes(&py), lanes(&ux), lanes(&uy)) else {
                return;
            };
            let (x, y, z) = (x.to_array(), y.to_array(), z.to_array());
            for (i, r) in rays.iter_mut().enumerate() {
                r.d = Vec3A::new(x[i], y[i], z[i]);
            }
        }
    }
}

/// The shading stage of up to 8 paths at plain Lambertian hits, in the lanes of `lanes` (lane
/// `j`: `paths[j]`): [`scatter`]'s effects on each path, from [`super::lambert::bounce`] (the
/// same bits).
#[inline(never)]
fn lambert_bounces<S: Sampler>(
    avx2: Avx2,
    lanes: &LambertLanes,
    paths: &[LambertPath],
    params: &PathParams,
    sink: &mut LambertSink<'_, S>,
) {
    let out = avx2.lambert_bounces(lanes, params.mis == MisHeuristic::Power);
    for (j, l) in paths.iter().enumerate().take(8) {
        let i = l.path;
        let path = &mut sink.paths[i as usize];
        if path.depth == 0 {
            let value = &mut sink.values[i as usize];
            value.albedo = lanes.r.get(j).to_array();
            value.normal = out.ns.get(j).to_array();
        }
        if out.shadow & (1 << j) != 0 {
            let (o, d) = (out.shadow_o.get(j), out.shadow_d.get(j));
            sink.shadow_rays.push(RayQuery { o, d, t_max: out.shadow_t_max[j], time: path.time });
            sink.shadows.push(PendingShadow { path: i, beta: path.beta, contribution: out.contribution.get(j) });
        } else {
            path.l += path.beta * Vec3A::ZERO;
        }
        if out.alive & (1 << j) == 0 {
            continue;
        }
        // The numbers the bounce read: 7, and roulette's.
        let roulette = path.depth + 1 >= params.rr_depth;
        path.sampler.set_dimension(l.base + if roulette { 8 } else { 7 });
        path.beta = out.beta.get(j);
        path.specular_bounce = false;
        path.prev_bsdf_pdf = out.pdf[j];
        path.prev_ctx = LightSampleContext { p: lanes.p.get(j), n: out.ng.get(j) };
        path.depth += 1;
        sink.next_live.push(i);
        sink.next_rays.push(RayQuery::unbounded(out.ray_o.get(j), out.ray_d.get(j), path.time));
    }
}

/// What one bounce of a path left to do: a shadow ray with (throughput, contribution), and
/// the path's next ray where it goes on.
struct Bounce {
    shadow: Option<(RayQuery, (Vec3A, Vec3A))>,
    next: Option<Ray>,
}

/// The first part of one iteration of `li_path`'s loop after its closest-hit query found `si`,
/// line for line: emission found, the environment, the depth limit. Whether the path goes on to
/// [`scatter`].
#[inline]
fn arrive<S: Sampler>(
    scene: &RenderScene,
    params: &PathParams,
    path: &mut PathState<S>,
    value: &mut SampleValue,
    d: Vec3A,
    si: Option<&SurfaceInteraction>,
) -> bool {
    let time = path.time;
    let Some(si) = si else {
        // The ray left the scene: the environment is its emitter.
        if let Some((i, env)) = scene.environment() {
            let le = env.le(d);
            if le != Vec3A::ZERO {
                path.l += path.beta
                    * le
                    * emission_weight(path.specular_bounce, params.mis, path.prev_bsdf_pdf, || {
                        scene.light_pmf(i) * env.pdf_wi(d)
                    });
            }
        }
        return false;
    };
    let wo = -d;
    if path.depth == 0 {
        value.depth = Some(si.t);
    }
    path.beta *= scene.transmittance(si, d);
    let le = scene.emitted_at(si, wo, time);
    if le != Vec3A::ZERO {
        let prev_ctx = path.prev_ctx;
        let w = emission_weight(path.specular_bounce, params.mis, path.prev_bsdf_pdf, || {
            scene.light_of_prim(si.prim).map_or(0.0, |i| {
                scene.light_pmf(i) * scene.light_at(i, time).pdf_li(&prev_ctx, si.p, params.light_sampling)
            })
        });
        path.l += path.beta * le * w;
    }
    // The next segment would exceed the depth limit.
    if params.max_depth != 0 && path.depth + 1 >= params.max_depth {
        if path.depth == 0 {
            let sh = shade(scene, si, wo, 0.5);
            value.albedo = sh.albedo.to_array();
            value.normal = sh.ns.to_array();
        }
        return false;
    }
    true
}

/// The rest of the iteration after [`arrive`], line for line: shading, the light sample (its
/// shadow ray queued), BSDF sampling and roulette, with the bounce's numbers drawn ahead.
#[inline]
#[allow(clippy::too_many_arguments)]
fn scatter<S: Sampler>(
    scene: &RenderScene,
    params: &PathParams,
    path: &mut PathState<S>,
    value: &mut SampleValue,
    d: Vec3A,
    si: &SurfaceInteraction,
    draws: &BounceDraws,
    cosine: &CosineSample,
    light: Option<(&LightBatch, usize)>,
) -> Bounce {
    let done = Bounce { shadow: None, next: None };
    let time = path.time;
    let wo = -d;
    let mut sampler = Replay { inner: &mut path.sampler, draws };
    let sh = shade(scene, si, wo, sampler.get_1d());
    if path.depth == 0 {
        value.albedo = sh.albedo.to_array();
        value.normal = sh.ns.to_array();
    }
    let Some(bsdf) = &sh.bsdf else { return done };
    let mut shadow = None;
    if !bsdf.is_delta() {
        let u_select = sampler.get_1d();
        let u = sampler.get_2d();
        let nee = match light {
            // Sampled ahead with these numbers.
            Some((batch, n)) => batch.get(scene, n).and_then(|light| nee_with_light(scene, &sh, wo, light, params)),
            None => nee_sample(scene, si.p, &sh, wo, u_select, u, params, time),
        };
        match nee {
            Some(nee) => {
                let (o, d, t_max) = RenderScene::shadow_ray(si.p, sh.ng, &nee.ls);
                let c = nee.contribution(params);
                shadow = Some((RayQuery { o, d, t_max, time }, (path.beta, c)));
            }
            None => path.l += path.beta * Vec3A::ZERO,
        }
    }
    let Some((bs, weight)) = sample_scatter_ahead(bsdf, sh.ng, wo, &mut sampler, Some(cosine)) else {
        return Bounce { shadow, next: None };
    };
    path.beta *= weight;
    path.specular_bounce = bs.is_specular();
    path.prev_bsdf_pdf = bs.pdf;
    path.prev_ctx = LightSampleContext { p: si.p, n: sh.ng };
    if bs.is_transmission() {
        path.eta_scale *= bs.eta * bs.eta;
    }
    path.depth += 1;
    if !(path.beta.max_element() > 0.0) || !path.beta.is_finite() {
        return Bounce { shadow, next: None };
    }
    if path.depth >= params.rr_depth {
        let u_rr = sampler.get_1d();
        let q = (path.beta.max_element() * path.eta_scale).min(RR_MAX_SURVIVAL);
        if u_rr >= q {
            return Bounce { shadow, next: None };
        }
        path.beta /= q;
    }
    Bounce { shadow, next: Some(Ray::new(offset_ray_origin(si.p, sh.ng, bs.wi), bs.wi)) }
}

/// The camera stage of the renderer for a path: a sampler positioned at (pixel, index), and the
/// camera ray and shutter time drawn from it.
#[inline]
pub fn camera_sample<S: Sampler>(
    mut sampler: S,
    pixel: UVec2,
    index: u32,
    camera: &Camera,
    camera_at: Option<&dyn Fn(f32) -> Camera>,
) -> (S, Ray, f32) {
    sampler.start_pixel_sample(pixel, index, 0);
    match camera_at {
        // The time is the sample's first dimension, so stills keep their layout.
        Some(camera_at) => {
            let time = sampler.get_1d();
            let ray = camera_at(time).sample_ray(pixel, &mut sampler);
            (sampler, ray, time)
        }
        None => {
            let ray = camera.sample_ray(pixel, &mut sampler);
            (sampler, ray, 0.0)
        }
    }
}
