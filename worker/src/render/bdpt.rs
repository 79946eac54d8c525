//! Bidirectional path tracing (Veach 1997, ch. 10; pbrt-v4's `BDPTIntegrator`).
//!
//! Each camera sample traces a camera subpath and a light subpath and combines every prefix pair
//! `(s, t)` (`s` light vertices, `t` camera vertices): `s = 0` (the camera path hits an emitter),
//! `s = 1` (a fresh light sample, next-event estimation), `t = 1` (light tracing: the light
//! vertex is connected to the camera and splatted onto the pixel it lands on) and all inner
//! connections through a visibility ray. Multiple importance sampling weighs the strategies with
//! the balance or power heuristic, computed with pbrt-v4's ratio recurrence over the vertices'
//! forward and reverse area densities; delta BSDFs and delta lights drop out of the sums.
//!
//! Path lengths count segments as elsewhere (Mitsuba's convention): a path of `s + t` vertices
//! has `s + t - 1` segments. Both random walks use Russian roulette after `rr_depth` scatterings;
//! the MIS weights ignore roulette, which keeps them a partition of unity, so the estimator stays
//! unbiased.

use super::accel::RayQuery;
use super::bsdf::Bsdf;
use super::camera::Camera;
use super::geometry::{Ray, offset_ray_origin, shadow_segment};
use super::integrator::sample_scatter;
use super::light::{Light, LightSampleContext};
use super::material::shade;
use super::sampler::Sampler;
use super::scene::{RenderScene, SurfaceInteraction};
use glam::{UVec2, Vec2, Vec3A};
use pathfarm_common::film::SampleValue;
use pathfarm_common::job::LightSampling;
use std::f32::consts::PI;

/// Parameters of the BDPT integrator.
#[derive(Clone, Copy, Debug)]
pub struct BdptParams {
    /// Path segments (1 = emitters seen directly); 0 = no limit but `UNLIMITED_VERTICES`.
    pub max_depth: u32,
    /// Scatterings per subpath before Russian roulette starts.
    pub rr_depth: u32,
    /// Exponent of the MIS heuristic: 1 = balance, 2 = power.
    pub mis_exponent: u32,
    /// Only this strategy `(s, t)`, with its MIS weight (debugging and teaching).
    pub strategy: Option<(u32, u32)>,
}

/// Subpath length cap when the depth is unlimited (roulette ends paths long before).
const UNLIMITED_VERTICES: usize = 256;
/// Survival probability cap of Russian roulette, as in the path tracer.
const RR_MAX_SURVIVAL: f32 = 0.95;
/// First sampler dimension of the light subpath and of the light samples of `s = 1`.
const LIGHT_DIM: u32 = 1 << 12;
const CONNECT_DIM: u32 = 1 << 13;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransportMode {
    Radiance,
    Importance,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VertexKind {
    Camera,
    Light,
    Surface,
}

/// A subpath vertex (pbrt's `Vertex`). Densities are per unit area at this vertex (or per unit
/// solid angle after an infinite light).
#[derive(Clone, Debug)]
pub struct Vertex {
    pub(crate) kind: VertexKind,
    pub(crate) p: Vec3A,
    /// Geometric normal (zero for point-like vertices: cameras, point lights).
    pub(crate) ng: Vec3A,
    /// Shading normal for cosines.
    pub(crate) ns: Vec3A,
    /// Geometric normal turned to the side light may leave a reflecting surface.
    pub(crate) ng_side: Vec3A,
    /// Surface vertices: direction toward the previous vertex, the BSDF, the hit.
    pub(crate) wo: Vec3A,
    pub(crate) bsdf: Option<Bsdf>,
    pub(crate) si: Option<SurfaceInteraction>,
    /// Light vertices: the light.
    pub(crate) light: Option<usize>,
    pub(crate) beta: Vec3A,
    pub(crate) delta: bool,
    pub(crate) pdf_fwd: f32,
    pub(crate) pdf_rev: f32,
    /// A light-subpath vertex: its BSDF carries importance (the adjoint), which a refraction
    /// does not scale by 1 / eta'^2 as radiance's does.
    pub(crate) importance: bool,
    /// Shutter time in [0, 1] of the path this vertex is on (0 without motion blur).
    pub(crate) time: f32,
}

impl Vertex {
    fn camera(p: Vec3A, beta: Vec3A) -> Self {
        Self {
            kind: VertexKind::Camera,
            p,
            ng: Vec3A::ZERO,
            ns: Vec3A::ZERO,
            ng_side: Vec3A::ZERO,
            wo: Vec3A::ZERO,
            bsdf: None,
            si: None,
            light: None,
            beta,
            delta: false,
            pdf_fwd: 0.0,
            pdf_rev: 0.0,
            importance: false,
            time: 0.0,
        }
    }

    fn light(index: usize, p: Vec3A, n: Option<Vec3A>, beta: Vec3A, pdf_fwd: f32) -> Self {
        let n = n.unwrap_or(Vec3A::ZERO);
        Self { kind: VertexKind::Light, ng: n, ns: n, ng_side: n, light: Some(index), pdf_fwd, ..Self::camera(p, beta) }
    }

    fn on_surface(&self) -> bool {
        self.ng != Vec3A::ZERO
    }

    fn is_infinite_light(&self, scene: &RenderScene) -> bool {
        self.kind == VertexKind::Light && self.light.is_some_and(|l| scene.lights[l].is_infinite())
    }

    fn is_delta_light(&self, scene: &RenderScene) -> bool {
        self.kind == VertexKind::Light && self.light.is_some_and(|l| scene.lights[l].is_delta())
    }

    /// The light this vertex is on: a light vertex's, or an emissive surface's.
    fn light_index(&self, scene: &RenderScene) -> Option<usize> {
        match self.kind {
            VertexKind::Light => self.light,
            VertexKind::Surface => self.si.and_then(|si| scene.light_of_prim(si.prim)),
            VertexKind::Camera => None,
        }
    }

    /// Whether a connection can end here: not at a purely specular surface or a light with a
    /// delta direction.
    pub(crate) fn is_connectible(&self, scene: &RenderScene) -> bool {
        match self.kind {
            VertexKind::Camera => true,
            VertexKind::Light => !self.is_infinite_light(scene),
            VertexKind::Surface => self.bsdf.is_some_and(|b| !b.is_delta()),
        }
    }

    /// Radiance emitted from this surface toward `prev`.
    fn le(&self, scene: &RenderScene, prev: &Vertex) -> Vec3A {
        match (self.kind, self.si) {
            (VertexKind::Surface, Some(si)) => {
                let w = (prev.p - self.p).normalize_or_zero();
                scene.emitted_at(&si, w, self.time)
            }
            // A camera path that left the scene ends at the environment.
            (VertexKind::Light, _) if self.is_infinite_light(scene) => {
                scene.environment_le((self.p - prev.p).normalize_or_zero())
            }
            _ => Vec3A::ZERO,
        }
    }

    /// BSDF value toward `next` (reflection only to the side light may leave).
    fn f(&self, next: &Vertex) -> Vec3A {
        let Some(bsdf) = &self.bsdf else { return Vec3A::ZERO };
        let wi = (next.p - self.p).normalize_or_zero();
        if !has_transmission(bsdf) && wi.dot(self.ng_side) <= 0.0 {
            return Vec3A::ZERO;
        }
        let f = bsdf.f(self.wo, wi);
        if self.importance { f * bsdf.importance_scale(self.wo, wi) } else { f }
    }

    /// Converts a solid-angle density at this vertex to an area density at `next` (kept per
    /// solid angle toward a light at infinity).
    fn convert_density(&self, scene: &RenderScene, pdf: f32, next: &Vertex) -> f32 {
        if next.is_infinite_light(scene) {
            return pdf;
        }
        let w = next.p - self.p;
        let d2 = w.length_squared();
        if !(d2 > 0.0) {
            return 0.0;
        }
        let inv_d2 = 1.0 / d2;
        let mut pdf = pdf * inv_d2;
        if next.on_surface() {
            pdf *= next.ng.dot(w * inv_d2.sqrt()).abs();
        }
        pdf
    }

    /// Area density at `next` of sampling it from this vertex, arriving from `prev`.
    fn pdf(&self, scene: &RenderScene, camera: &Camera, prev: Option<&Vertex>, next: &Vertex) -> f32 {
        if self.kind == VertexKind::Light {
            return self.pdf_light(scene, next);
        }
        let wn = (next.p - self.p).normalize_or_zero();
        let pdf = match self.kind {
            VertexKind::Camera => camera.pdf_we(wn),
            _ => {
                let (Some(bsdf), Some(prev)) = (&self.bsdf, prev) else { return 0.0 };
                let wp = (prev.p - self.p).normalize_or_zero();
                bsdf.pdf(wp, wn)
            }
        };
        self.convert_density(scene, pdf, next)
    }

    /// Area density at `v` of a ray emitted from this light vertex (or emissive surface).
    fn pdf_light(&self, scene: &RenderScene, v: &Vertex) -> f32 {
        let Some(l) = self.light_index(scene) else { return 0.0 };
        let w = v.p - self.p;
        let d2 = w.length_squared();
        if !(d2 > 0.0) {
            return 0.0;
        }
        let w = w / d2.sqrt();
        let light = scene.light_at(l, self.time);
        let mut pdf = if light.is_infinite() {
            // Directional: the disk covering the scene, per unit area.
            1.0 / (PI * scene.radius * scene.radius)
        } else {
            light.pdf_le(w).1 / d2
        };
        if v.on_surface() {
            pdf *= v.ng.dot(w).abs();
        }
        pdf
    }

    /// Area density of choosing this point as a light path's origin (light selection included).
    fn pdf_light_origin(&self, scene: &RenderScene, v: &Vertex) -> f32 {
        let Some(l) = self.light_index(scene) else { return 0.0 };
        let light = scene.light_at(l, self.time);
        let w = (v.p - self.p).normalize_or_zero();
        if light.is_infinite() {
            // Per solid angle: the density of choosing the direction toward this light from
            // `v` (pbrt's `InfiniteLightDensity`); a directional light's is a delta, so 0.
            return match &*light {
                Light::Environment(env) => scene.light_pmf(l) * env.pdf_wi(-w),
                _ => 0.0,
            };
        }
        scene.light_pmf(l) * light.pdf_le(w).0
    }
}

/// Whether a BSDF can transmit (then connections may cross the surface).
fn has_transmission(bsdf: &Bsdf) -> bool {
    bsdf.bxdf.has_transmission()
}

/// pbrt's correction of the adjoint BSDF for shading normals (importance transport).
fn correct_shading_normal(ng: Vec3A, ns: Vec3A, wo: Vec3A, wi: Vec3A) -> f32 {
    let num = wo.dot(ns).abs() * wi.dot(ng).abs();
    let denom = wo.dot(ng).abs() * wi.dot(ns).abs();
    if denom == 0.0 { 0.0 } else { num / denom }
}

/// Reusable subpath storage (one per thread).
#[derive(Default)]
pub struct Subpaths {
    camera: Vec<Vertex>,
    light: Vec<Vertex>,
}

impl Subpaths {
    /// The light subpath storage (IGI traces its VPL paths into it).
    pub fn light_mut(&mut self) -> &mut Vec<Vertex> {
        &mut self.light
    }
}

/// Extends `path` (whose last vertex spawned `ray` with solid-angle density `pdf`) by a random
/// walk of at most `max_vertices` more vertices. Returns nothing; the vertices are in `path`.
#[allow(clippy::too_many_arguments)]
pub fn random_walk(
    scene: &RenderScene,
    mut ray: Ray,
    mut beta: Vec3A,
    pdf: f32,
    max_vertices: usize,
    rr_depth: u32,
    mode: TransportMode,
    sampler: &mut impl Sampler,
    path: &mut Vec<Vertex>,
    mut aov: Option<&mut SampleValue>,
) {
    let mut pdf_fwd = pdf;
    let mut bounces = 0usize;
    // The path's shutter time, from its first vertex.
    let time = path.first().map_or(0.0, |v| v.time);
    while bounces < max_vertices {
        let Some(si) = scene.intersect_at(ray.o, ray.d, f32::INFINITY, time) else {
            // A camera path that leaves the scene ends on the environment (pbrt's escaped-ray
            // light vertex), a unit beyond the last vertex along the ray.
            if let (TransportMode::Radiance, Some((index, _))) = (mode, scene.environment()) {
                let mut v = Vertex::light(index, ray.o + ray.d, None, beta, 0.0);
                v.time = time;
                if let Some(prev) = path.last() {
                    v.pdf_fwd = prev.convert_density(scene, pdf_fwd, &v);
                    path.push(v);
                }
            }
            break;
        };
        let wo = -ray.d;
        beta *= scene.transmittance(&si, ray.d);
        let sh = shade(scene, &si, wo, sampler.get_1d());
        if let Some(out) = aov.take() {
            out.depth = Some(si.t);
            out.albedo = sh.albedo.to_array();
            out.normal = sh.ns.to_array();
        }
        let ns = sh.bsdf.map_or(sh.ns, |b| b.frame.z);
        let mut v = Vertex {
            kind: VertexKind::Surface,
            p: si.p,
            ng: si.ng,
            ns,
            ng_side: sh.ng,
            wo,
            bsdf: sh.bsdf,
            si: Some(si),
            light: None,
            beta,
            delta: false,
            pdf_fwd: 0.0,
            pdf_rev: 0.0,
            importance: mode == TransportMode::Importance,
            time,
        };
        let Some(prev) = path.last() else { break };
        v.pdf_fwd = prev.convert_density(scene, pdf_fwd, &v);
        path.push(v);
        bounces += 1;
        if bounces >= max_vertices {
            break;
        }
        let Some(bsdf) = sh.bsdf else { break };
        let Some((bs, weight)) = sample_scatter(&bsdf, sh.ng, wo, sampler) else { break };
        beta *= weight;
        let mut pdf_rev;
        let n = path.len();
        if bs.is_specular() {
            path[n - 1].delta = true;
            pdf_fwd = 0.0;
            pdf_rev = 0.0;
        } else {
            pdf_fwd = bs.pdf;
            pdf_rev = bsdf.pdf(bs.wi, wo);
        }
        if mode == TransportMode::Importance {
            if bs.is_transmission() {
                // The dielectric scales radiance by 1 / eta'^2; importance is not scaled.
                beta *= bs.eta * bs.eta;
            }
            beta *= correct_shading_normal(si.ng, bsdf.frame.z, wo, bs.wi);
        }
        if !pdf_rev.is_finite() {
            pdf_rev = 0.0;
        }
        let rev = path[n - 1].convert_density(scene, pdf_rev, &path[n - 2]);
        path[n - 2].pdf_rev = rev;
        if !(beta.max_element() > 0.0) || !beta.is_finite() {
            break;
        }
        if bounces as u32 >= rr_depth {
            let q = beta.max_element().min(RR_MAX_SURVIVAL);
            if sampler.get_1d() >= q {
                break;
            }
            beta /= q;
        }
        ray = Ray::new(offset_ray_origin(si.p, sh.ng, bs.wi), bs.wi);
    }
}

/// Traces a light subpath into `path` (cleared first) at shutter time `time`: light chosen by
/// power, emission sampled by position and direction.
pub fn light_subpath(
    scene: &RenderScene,
    max_vertices: usize,
    rr_depth: u32,
    sampler: &mut impl Sampler,
    path: &mut Vec<Vertex>,
    time: f32,
) {
    path.clear();
    if max_vertices == 0 {
        return;
    }
    let u_light = sampler.get_1d();
    let u1 = sampler.get_2d();
    let u2 = sampler.get_2d();
    let Some((index, pmf)) = scene.pick_light(u_light) else { return };
    let Some(les) = scene.sample_le_at(index, u1, u2, time) else { return };
    let mut origin = Vertex::light(index, les.o, les.n, les.l, les.pdf_pos * pmf);
    origin.time = time;
    path.push(origin);
    let cos = les.n.map_or(1.0, |n| n.dot(les.d).abs());
    let beta = les.l * (cos / (pmf * les.pdf_pos * les.pdf_dir));
    let o = match les.n {
        Some(n) => offset_ray_origin(les.o, n, les.d),
        None => les.o,
    };
    random_walk(
        scene,
        Ray::new(o, les.d),
        beta,
        les.pdf_dir,
        max_vertices - 1,
        rr_depth,
        TransportMode::Importance,
        sampler,
        path,
        None,
    );
    if scene.lights[index].is_infinite() {
        if let Some(v) = path.get_mut(1) {
            v.pdf_fwd = les.pdf_pos;
            if v.on_surface() {
                v.pdf_fwd *= les.d.dot(v.ng).abs();
            }
        }
        // Per solid angle, as its reverse densities are (0 for a directional light).
        let origin = path[0].clone();
        path[0].pdf_fwd = path.get(1).map_or(0.0, |v| origin.pdf_light_origin(scene, v));
    }
}

/// Traces one BDPT sample through `pixel` at shutter time `time` (both subpaths and every
/// connection see the scene then; `camera` is the camera at that time): returns the camera-side
/// estimate and its AOVs and calls `splat(raster, value)` for every light-tracing (`t = 1`)
/// contribution. A batch of one sample ([`BdptBatch`]).
#[allow(clippy::too_many_arguments)]
pub fn li_bdpt(
    scene: &RenderScene,
    camera: &Camera,
    pixel: UVec2,
    sample_index: u32,
    sampler: &mut impl Sampler,
    params: &BdptParams,
    batch: &mut BdptBatch,
    splat: &mut impl FnMut(Vec2, Vec3A),
    time: f32,
) -> SampleValue {
    batch.clear();
    batch.push(scene, camera, pixel, sample_index, sampler, params, time);
    // The batch's own buffer for the value (no allocation per sample).
    let mut out = std::mem::take(&mut batch.one);
    out.clear();
    batch.finish(scene, camera, params, splat, &mut out);
    let value = out.pop().unwrap_or_default();
    batch.one = out;
    value
}

/// A strategy's contribution before its visibility ray is answered: unweighted, as if
/// unoccluded (zero where [`connect`] gives nothing), with its splat position (`t = 1`), the
/// vertex it sampled (`s = 1` or `t = 1`) and its visibility ray (an index into the batch's
/// rays; none where the contribution is zero or needs no ray).
struct Pending {
    s: usize,
    t: usize,
    l: Vec3A,
    raster: Option<Vec2>,
    sampled: Sampled,
    ray: Option<u32>,
}

impl Pending {
    fn nothing(s: usize, t: usize) -> Self {
        Self { s, t, l: Vec3A::ZERO, raster: None, sampled: Sampled::None, ray: None }
    }
}

/// The vertex a strategy sampled, by what makes it: 80 bytes, where a [`Vertex`] takes 432 (kept
/// whole in every strategy of a batch, with batches made anew per row, `tiny bdpt` took 746.8M
/// instructions against the one-ray-at-a-time 709.9M).
#[derive(Clone, Copy)]
enum Sampled {
    None,
    /// `t = 1`: the camera vertex.
    Camera {
        p: Vec3A,
        beta: Vec3A,
        time: f32,
    },
    /// `s = 1`: the light vertex, with its forward density.
    Light {
        index: usize,
        p: Vec3A,
        n: Option<Vec3A>,
        beta: Vec3A,
        pdf_fwd: f32,
        time: f32,
    },
}

impl Sampled {
    /// The vertex, as [`connect`] made it.
    fn vertex(self) -> Option<Vertex> {
        match self {
            Self::None => None,
            Self::Camera { p, beta, time } => {
                let mut v = Vertex::camera(p, beta);
                v.time = time;
                Some(v)
            }
            Self::Light { index, p, n, beta, pdf_fwd, time } => {
                let mut v = Vertex::light(index, p, n, beta, 0.0);
                v.time = time;
                v.pdf_fwd = pdf_fwd;
                Some(v)
            }
        }
    }
}

/// BDPT samples traced together: each sample's subpaths and strategies first
/// ([`BdptBatch::push`]), then the visibility rays of every strategy of the batch answered in
/// one batched query ([`RenderScene::occluded_many`]: sorted packets where the scene sorts its
/// rays, one SIMD dispatch either way) instead of one query per connection, then each sample's
/// MIS weights and sums ([`BdptBatch::finish`]). Each sample's value is exactly what one sample
/// at a time gives (the same operations in the same order; a ray's answer does not depend on
/// its batch), so images stay split-invariant; splats come in sample order.
///
/// The subpaths' random walks were tried batched the same way (bounce by bounce, every walk's
/// ray in one [`RenderScene::intersect_many`], each walk with its own copy of the sampler): the
/// walks cost as much as one ray at a time (258M instructions of `tiny bdpt` either way: their
/// incoherent rays make few full packets) and the batch's bookkeeping more, `tiny bdpt` 706.3M
/// -> 720.7M with 64 samples a batch, 735.2M with 256. Tried again and timed, as IGI's batched
/// shadow rays had run faster at equal instructions (on an Intel Xeon with AVX-512; each walk a
/// `Walk` stepped from one query of all live walks' rays, camera and light walks together):
/// 699.4M -> 711.4M instructions, `tiny bdpt long` 1.055x the time (median of 9 interleaved
/// pairs, quartiles 0.931-1.155), then 0.986x (15 pairs, quartiles 0.934-1.024): no gain
/// beyond the noise. They stay one ray at a time.
#[derive(Default)]
pub struct BdptBatch {
    /// The batch's samples: their subpaths (kept for the MIS weights), reused.
    paths: Vec<Subpaths>,
    /// Per sample: its strategies' range in `pending` and its AOVs.
    samples: Vec<(std::ops::Range<usize>, SampleValue)>,
    pending: Vec<Pending>,
    rays: Vec<RayQuery>,
    blocked: Vec<bool>,
    /// [`li_bdpt`]'s value of its one sample.
    one: Vec<SampleValue>,
}

impl BdptBatch {
    /// Samples in the batch.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether the batch holds no sample.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// An empty batch with room for `samples` samples' strategies (`strategies` each, the
    /// usual count; more grow): a batch grown from nothing copied its strategies and their rays
    /// at each doubling (912 reallocations in the bench's `tiny bdpt`, 1.1% of its
    /// instructions), and every rayon job of a tile starts a batch.
    pub fn with_capacity(samples: usize, strategies: usize) -> Self {
        Self {
            paths: Vec::with_capacity(samples),
            samples: Vec::with_capacity(samples),
            pending: Vec::with_capacity(samples * strategies),
            rays: Vec::with_capacity(samples * strategies),
            blocked: Vec::with_capacity(samples * strategies),
            ..Self::default()
        }
    }

    /// Empties the batch (its buffers are kept).
    pub fn clear(&mut self) {
        self.samples.clear();
        self.pending.clear();
        self.rays.clear();
    }

    /// Traces both subpaths of sample `sample_index` through `pixel` at shutter time `time` and
    /// its strategies up to their visibility rays (all its random numbers are drawn here).
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        scene: &RenderScene,
        camera: &Camera,
        pixel: UVec2,
        sample_index: u32,
        sampler: &mut impl Sampler,
        params: &BdptParams,
        time: f32,
    ) {
        let k = self.samples.len();
        let (max_camera, max_light) = if params.max_depth == 0 {
            (UNLIMITED_VERTICES, UNLIMITED_VERTICES)
        } else {
            (params.max_depth as usize + 1, params.max_depth as usize)
        };
        if self.paths.len() <= k {
            // A new slot's subpaths sized for the longest walks (up to 16 vertices; longer ones
            // grow): grown from nothing, their walks reallocated them 4,207 times in `tiny
            // bdpt`.
            self.paths.resize_with(k + 1, || Subpaths {
                camera: Vec::with_capacity(max_camera.min(15) + 1),
                light: Vec::with_capacity(max_light.min(15) + 1),
            });
        }
        let paths = &mut self.paths[k];
        let mut out = SampleValue::default();
        // Camera subpath.
        sampler.start_pixel_sample(pixel, sample_index, 0);
        let ray = camera.sample_ray(pixel, sampler);
        paths.camera.clear();
        let mut origin = Vertex::camera(ray.o, Vec3A::ONE);
        origin.time = time;
        paths.camera.push(origin);
        random_walk(
            scene,
            ray,
            Vec3A::ONE,
            camera.pdf_we(ray.d),
            max_camera - 1,
            params.rr_depth,
            TransportMode::Radiance,
            sampler,
            &mut paths.camera,
            Some(&mut out),
        );
        // Light subpath.
        sampler.start_pixel_sample(pixel, sample_index, LIGHT_DIM);
        light_subpath(scene, max_light, params.rr_depth, sampler, &mut paths.light, time);

        let max_vertices = if params.max_depth == 0 { usize::MAX } else { params.max_depth as usize + 1 };
        let (cam, light) = (&paths.camera, &paths.light);
        let first = self.pending.len();
        for t in 1..=cam.len() {
            // s = 1 takes a fresh light sample: it does not need the light subpath, which may be
            // empty (a zero emission texture at its origin).
            for s in 0..=light.len().max(1) {
                if (s == 1 && t == 1) || s + t < 2 || s + t > max_vertices {
                    continue;
                }
                if params.strategy.is_some_and(|(ws, wt)| (ws as usize, wt as usize) != (s, t)) {
                    continue;
                }
                if s == 1 {
                    sampler.start_pixel_sample(pixel, sample_index, CONNECT_DIM + 3 * t as u32);
                }
                self.pending.push(connect(scene, camera, light, cam, s, t, sampler, &mut self.rays));
            }
        }
        self.samples.push((first..self.pending.len(), out));
    }

    /// Answers the batch's visibility rays, then appends each sample's value to `out` in order
    /// (calling `splat(raster, value)` for its light-tracing contributions) and empties the
    /// batch. `camera` is the camera every sample was pushed with.
    pub fn finish(
        &mut self,
        scene: &RenderScene,
        camera: &Camera,
        params: &BdptParams,
        splat: &mut impl FnMut(Vec2, Vec3A),
        out: &mut Vec<SampleValue>,
    ) {
        self.blocked.clear();
        if !self.rays.is_empty() {
            scene.occluded_many(&self.rays, &mut self.blocked);
        }
        for ((range, value), paths) in self.samples.iter().zip(&self.paths) {
            let mut l = Vec3A::ZERO;
            for p in &self.pending[range.clone()] {
                let blocked = p.ray.is_some_and(|k| self.blocked.get(k as usize).copied().unwrap_or(true));
                let c = if blocked { Vec3A::ZERO } else { p.l };
                let c = if c == Vec3A::ZERO {
                    c
                } else {
                    let (light, cam) = (&paths.light, &paths.camera);
                    let sampled = p.sampled.vertex();
                    c * mis_weight(scene, camera, light, cam, sampled.as_ref(), p.s, p.t, params.mis_exponent)
                };
                if !c.is_finite() {
                    continue;
                }
                match p.raster {
                    Some(r) if c != Vec3A::ZERO => splat(r, c),
                    Some(_) => {}
                    None => l += c,
                }
            }
            let mut value = *value;
            value.radiance = l.to_array();
            out.push(value);
        }
        self.clear();
    }
}

/// Strategy `(s, t)` up to its visibility ray, which goes into `rays` where its contribution is
/// not zero (see [`Pending`]).
#[allow(clippy::too_many_arguments)]
fn connect(
    scene: &RenderScene,
    camera: &Camera,
    light: &[Vertex],
    cam: &[Vertex],
    s: usize,
    t: usize,
    sampler: &mut impl Sampler,
    rays: &mut Vec<RayQuery>,
) -> Pending {
    let pt = &cam[t - 1];
    // Both subpaths are at the camera sample's shutter time.
    let time = pt.time;
    let mut queue = |(o, d, t_max): (Vec3A, Vec3A, f32)| {
        rays.push(RayQuery { o, d, t_max, time });
        Some(rays.len() as u32 - 1)
    };
    if s == 0 {
        if t < 2 {
            return Pending::nothing(s, t);
        }
        let l = pt.beta * pt.le(scene, &cam[t - 2]);
        Pending { l, ..Pending::nothing(s, t) }
    } else if t == 1 {
        let qs = &light[s - 1];
        if !qs.is_connectible(scene) || qs.kind != VertexKind::Surface {
            return Pending::nothing(s, t);
        }
        let Some(cs) = camera.sample_wi(qs.p) else { return Pending::nothing(s, t) };
        let mut v = Vertex::camera(cs.p_camera, Vec3A::splat(cs.we / cs.pdf));
        v.time = time;
        let l = qs.beta * qs.f(&v) * v.beta * cs.wi.dot(qs.ns).abs();
        let ray = if l != Vec3A::ZERO { queue(shadow_segment(qs.p, qs.ng, cs.p_camera, None)) } else { None };
        let sampled = Sampled::Camera { p: v.p, beta: v.beta, time };
        Pending { s, t, l, raster: Some(cs.raster), sampled, ray }
    } else if s == 1 {
        if !pt.is_connectible(scene) || pt.kind != VertexKind::Surface {
            return Pending::nothing(s, t);
        }
        let u_select = sampler.get_1d();
        let u = sampler.get_2d();
        let ctx = LightSampleContext { p: pt.p, n: pt.ng };
        // Area sampling: the density the MIS weights assume for a light vertex.
        let Some((index, ls, pmf)) = scene.sample_light_at(&ctx, u_select, u, LightSampling::Area, time) else {
            return Pending::nothing(s, t);
        };
        let mut v = Vertex::light(index, ls.p_light, ls.n_light, ls.l / (ls.pdf * pmf), 0.0);
        v.time = time;
        v.pdf_fwd = v.pdf_light_origin(scene, pt);
        let l = pt.beta * pt.f(&v) * v.beta * ls.wi.dot(pt.ns).abs();
        let ray = if l != Vec3A::ZERO { queue(RenderScene::shadow_ray(pt.p, pt.ng, &ls)) } else { None };
        let sampled = Sampled::Light { index, p: ls.p_light, n: ls.n_light, beta: v.beta, pdf_fwd: v.pdf_fwd, time };
        Pending { s, t, l, raster: None, sampled, ray }
    } else {
        let qs = &light[s - 1];
        if !qs.is_connectible(scene) || !pt.is_connectible(scene) || qs.kind != VertexKind::Surface {
            return Pending::nothing(s, t);
        }
        let mut l = qs.beta * qs.f(pt) * pt.f(qs) * pt.beta;
        let mut ray = None;
        if l != Vec3A::ZERO {
            let d = pt.p - qs.p;
            let d2 = d.length_squared();
            if !(d2 > 0.0) {
                return Pending::nothing(s, t);
            }
            let w = d / d2.sqrt();
            l *= w.dot(qs.ns).abs() * w.dot(pt.ns).abs() / d2;
            // A connection inside an attenuating object (it reaches the back of pt's surface).
            if let Some(si) = &pt.si {
                let mut along = *si;
                along.t = d2.sqrt();
                l *= scene.transmittance(&along, w);
            }
            if l != Vec3A::ZERO {
                ray = queue(shadow_segment(qs.p, qs.ng, pt.p, Some(pt.ng)));
            }
        }
        Pending { l, ray, ..Pending::nothing(s, t) }
    }
}

/// The MIS weight of strategy `(s, t)` for the path it built (pbrt-v4's `MISWeight`, with the
/// ratios raised to `exponent`: 1 = balance heuristic, 2 = power heuristic).
#[allow(clippy::too_many_arguments)]
fn mis_weight(
    scene: &RenderScene,
    camera: &Camera,
    light: &[Vertex],
    cam: &[Vertex],
    sampled: Option<&Vertex>,
    s: usize,
    t: usize,
    exponent: u32,
) -> f32 {
    if s + t == 2 {
        return 1.0;
    }
    // The strategy's endpoints: a sampled vertex replaces the subpath's end for s = 1 or t = 1.
    let qs: Option<&Vertex> = match s {
        0 => None,
        1 => sampled,
        _ => light.get(s - 1),
    };
    let pt: Option<&Vertex> = if t == 1 { sampled } else { cam.get(t - 1) };
    let Some(pt) = pt else { return 0.0 };
    let qs_minus = if s > 1 { light.get(s - 2) } else { None };
    let pt_minus = if t > 1 { cam.get(t - 2) } else { None };

    // Reverse densities of this strategy's path (pbrt's scoped assignments).
    let pt_rev = match (qs, pt_minus) {
        (Some(qs), _) => qs.pdf(scene, camera, qs_minus, pt),
        (None, Some(pm)) => pt.pdf_light_origin(scene, pm),
        (None, None) => 0.0,
    };
    let pt_minus_rev = match (qs, pt_minus) {
        (Some(qs), Some(pm)) => pt.pdf(scene, camera, Some(qs), pm),
        (None, Some(pm)) => pt.pdf_light(scene, pm),
        _ => 0.0,
    };
    let qs_rev = qs.map_or(0.0, |qs| pt.pdf(scene, camera, pt_minus, qs));
    let qs_minus_rev = match (qs, qs_minus) {
        (Some(qs), Some(qm)) => qs.pdf(scene, camera, Some(pt), qm),
        _ => 0.0,
    };
    let remap = |f: f32| if f != 0.0 { f } else { 1.0 };
    let pow = |r: f32| if exponent == 2 { r * r } else { r };

    // Camera side: vertex i's (pdf_rev, pdf_fwd, delta) with this strategy's overrides.
    let cam_vertex = |i: usize| -> (f32, f32, bool) {
        if i == t - 1 {
            (pt_rev, pt.pdf_fwd, false)
        } else if i + 2 == t {
            (pt_minus_rev, cam[i].pdf_fwd, cam[i].delta)
        } else {
            (cam[i].pdf_rev, cam[i].pdf_fwd, cam[i].delta)
        }
    };
    let mut sum = 0.0f32;
    let mut ri = 1.0f32;
    for i in (1..t).rev() {
        let (rev, fwd, delta) = cam_vertex(i);
        ri *= remap(rev) / remap(fwd);
        if !delta && !cam_vertex(i - 1).2 {
            sum += pow(ri);
        }
    }
    if let Some(qs) = qs {
        let light_vertex = |i: usize| -> (f32, f32, bool) {
            if i == s - 1 {
                (qs_rev, qs.pdf_fwd, false)
            } else if i + 2 == s {
                (qs_minus_rev, light[i].pdf_fwd, light[i].delta)
            } else {
                (light[i].pdf_rev, light[i].pdf_fwd, light[i].delta)
            }
        };
        let mut ri = 1.0f32;
        for i in (0..s).rev() {
            let (rev, fwd, delta) = light_vertex(i);
            ri *= remap(rev) / remap(fwd);
            let delta_light = if i > 0 {
                light_vertex(i - 1).2
            } else if s == 1 {
                qs.is_delta_light(scene)
            } else {
                light[0].is_delta_light(scene)
            };
            if !delta && !delta_light {
                sum += pow(ri);
            }
        }
    }
    let w = 1.0 / (1.0 + sum);
    if w.is_finite() { w } else { 0.0 }
}
