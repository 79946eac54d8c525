//! Instant global illumination (Keller 1997) with virtual point lights, the clamped geometry
//! term and Kollig and Keller's bias compensation (2004).
//!
//! For every sample index, `vpl_sets` independent sets of `vpls` light paths are traced; every
//! non-specular surface vertex of a light path becomes a virtual point light (VPL) carrying the
//! path's throughput divided by the number of paths of its set. Pixel `(x, y)` uses set
//! `(x + 2 y) mod vpl_sets` of its sample index (interleaved sampling, Keller and Heidrich 2001),
//! so neighbouring pixels see different VPLs and the structured error becomes noise. The VPLs
//! depend only on (job seed, sample index), not on the tile or on how samples are cut into
//! passes: every tile sees the same ones (no seams), and a render split into units is
//! bit-identical to one rendered whole. Each unit builds the sets of its samples once
//! ([`VplCache`]); tracing them costs `spp x vpl_sets x vpls` light paths per job, little
//! beside the shading.
//!
//! At the first non-specular camera hit `x`, radiance is direct lighting (one light sample,
//! the `direct` estimator's light-sampling half) plus the sum over VPLs of
//! `f(x) f(vpl) beta_vpl min(G, g_limit) V`. Clamping `G` removes the bright splotches near VPLs
//! but loses the energy `integral of f max(G - g_limit, 0) L`. Bias compensation adds it back
//! with a BSDF-sampled ray from `x` to `y`, weighted by `max(1 - g_limit / G(x, y), 0)`, and the
//! radiance leaving `y` estimated by the same estimator recursively (direct + clamped VPLs +
//! compensation), so that `a = min(a, b) + max(a - b, 0)` holds in expectation: the compensated
//! estimator is consistent for diffuse and glossy transport. Caustics seen directly (light
//! focused by specular surfaces onto the point the camera sees) are beyond VPLs; the VPLs that
//! such light paths leave do light other surfaces.
//!
//! The VPL terms of a point are computed for all of its set's VPLs, and their shadow rays wait:
//! a row's samples are recorded ([`IgiScratch`]: each sample's radiance as the sequence of
//! additions it makes, each VPL term's conditional on its ray) until their rays fill a batch of
//! [`IGI_BATCH_RAYS`], answered in one query, and the sums are then replayed in their order
//! (the same f32 operations: the digests of `tests/wavefront.rs` did not move). One point's 64
//! rays spread over the BVH's 24 ray classes, mostly too few per class to trace as a packet;
//! the rays of a batch fill them. Measured on an Intel Xeon (AVX-512): `tiny igi long`
//! 0.887x-0.900x the time (medians of 9 and 7 interleaved pairs), with the same instructions
//! (713.8M -> 718.6M on `tiny igi`); the scratch made once per rayon job with room for a
//! batch, 0.941x more (691.4M).
//! Where the point and every VPL of the set are bare Lambertian (the
//! Cornell box), the terms are computed 8 VPLs at a time in AVX2 lanes ([`vpl_terms`], written
//! once over [`Real`], the scalar bits): 21% fewer instructions on the bench's `tiny igi`.

use super::accel::RayQuery;
use super::bdpt::{Subpaths, VertexKind, light_subpath};
use super::bsdf::{Bsdf, Bxdf};
use super::camera::Camera;
use super::geometry::{Ray, offset_ray_origin, shadow_segment};
use super::integrator::{PathParams, sample_ld, sample_scatter};
use super::material::{Shading, shade};
use super::math::Real;
use super::sampler::{AnySampler, Sampler, hash_u64};
use super::scene::RenderScene;
use glam::{UVec2, Vec3A};
use pathfarm_common::film::SampleValue;
use pathfarm_common::job::{LightSampling, MisHeuristic, Pass, SamplerKind};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Why igi cannot render a material of the scene, naming it, or `None`. igi gathers at the first
/// non-specular surface a camera path meets, over the side its viewer is on: a rough
/// transmitting surface (KHR_materials_transmission with roughness, solid or thin-walled) would
/// lose what it lets through from the other side, and a glossy layer (sheen, rough clearcoat)
/// over a smooth base mixes a delta lobe into a non-delta BSDF, whose delta part the gather
/// cannot see. Rather than render those wrongly, igi refuses them.
pub fn unsupported_material(materials: &[pathfarm_common::scene::Material]) -> Option<String> {
    use super::microfacet::SMOOTH_ALPHA;
    use pathfarm_common::scene::MaterialModel;
    for m in materials.iter().filter(|m| m.model == MaterialModel::Gltf && !m.unlit) {
        // Textures only scale the factors down: the factors bound what a hit can see.
        let rough = m.roughness * m.roughness >= SMOOTH_ALPHA;
        if m.transmission > 0.0 && rough {
            return Some(format!(
                "igi cannot gather light through rough transmission (material \"{}\": transmission with roughness {}): \
                 use the path or bdpt integrator",
                m.name, m.roughness
            ));
        }
        let glossy_layer = m.sheen_color.max_element() > 0.0
            || m.clearcoat > 0.0 && m.clearcoat_roughness * m.clearcoat_roughness >= SMOOTH_ALPHA;
        let smooth_somewhere = !rough || m.metallic_roughness_texture.is_some();
        if glossy_layer && smooth_somewhere {
            return Some(format!(
                "igi cannot render a sheen or rough clearcoat over a smooth surface (material \"{}\"): use the path or \
                 bdpt integrator",
                m.name
            ));
        }
    }
    None
}

/// Parameters of the IGI integrator.
#[derive(Clone, Copy, Debug)]
pub struct IgiParams {
    /// Light paths per VPL set.
    pub vpls: u32,
    pub vpl_sets: u32,
    pub g_limit: f32,
    pub bias_compensation: bool,
    /// Path segments (0 = no limit).
    pub max_depth: u32,
}

/// Russian roulette starts after this many light-path scatterings; compensation recursion too.
const RR_DEPTH: u32 = 3;
/// Caps when the depth is unlimited.
const UNLIMITED_VERTICES: usize = 256;
const MAX_SPECULAR_CHAIN: u32 = 64;
/// Separates the VPL sampler's seed from the camera sampler's.
const VPL_SEED_TAG: u64 = 0x1617_0001;
/// Bytes of VPLs kept in the cache (`VplSets::bytes`: about 290 bytes a VPL, 380 with its
/// lanes); the oldest sample indices go first. Units arrive pass by pass, so the cache mostly
/// serves the tiles of the current pass.
const CACHED_VPL_BYTES: usize = 512 << 20;

/// A virtual point light: a light-path vertex on a non-specular surface.
#[derive(Clone, Debug)]
pub struct Vpl {
    pub p: Vec3A,
    /// Geometric normal (for ray offsets), shading normal (for cosines), and the side light
    /// leaves from.
    ng: Vec3A,
    ns: Vec3A,
    ng_side: Vec3A,
    /// Direction toward the previous light-path vertex, and the BSDF there.
    wo: Vec3A,
    bsdf: Bsdf,
    /// Throughput of the light path at this vertex divided by the set's path count.
    pub beta: Vec3A,
    /// Light-path segments from the light to this vertex.
    segments: u32,
}

/// The VPL sets of one sample index.
#[derive(Clone, Debug, Default)]
pub struct VplSets {
    pub sets: Vec<VplSet>,
}

impl VplSets {
    /// The memory the sets hold: their VPLs and lanes.
    fn bytes(&self) -> usize {
        let set = |s: &VplSet| {
            s.vpls.len() * std::mem::size_of::<Vpl>()
                + s.lanes.as_ref().map_or(0, |l| l.len() * std::mem::size_of::<VplLanes>())
        };
        self.sets.iter().map(set).sum()
    }
}

/// One VPL set, and its VPLs in lanes of 8 where every one of them is plain Lambertian: a
/// shading point on a plain Lambertian surface then evaluates them 8 at a time ([`vpl_terms`]).
#[derive(Clone, Debug, Default)]
pub struct VplSet {
    pub vpls: Vec<Vpl>,
    lanes: Option<Vec<VplLanes>>,
}

/// Up to 8 VPLs as lanes (lane `i` is VPL `i` of the chunk; lanes past `count` are zeros):
/// what [`vpl_terms`] reads of each.
#[derive(Clone, Debug, Default)]
pub struct VplLanes {
    pub p: [[f32; 8]; 3],
    pub ng: [[f32; 8]; 3],
    pub ns: [[f32; 8]; 3],
    pub ng_side: [[f32; 8]; 3],
    /// The VPL's BSDF frame's normal, `wo` in that frame (its z), and `f` (`r / pi`).
    pub z: [[f32; 8]; 3],
    pub wo_z: [f32; 8],
    pub f: [[f32; 8]; 3],
    pub beta: [[f32; 8]; 3],
    segments: [u32; 8],
    count: usize,
}

/// Writes `v` into lane `lane` of `a` (a VPL's vectors kept as 3 lanes of components: they are
/// set once per VPL set and read by every shading point).
#[inline(always)]
fn set3(a: &mut [[f32; 8]; 3], lane: usize, v: Vec3A) {
    a[0][lane] = v.x;
    a[1][lane] = v.y;
    a[2][lane] = v.z;
}

impl VplLanes {
    /// `set` in chunks of 8, or `None` if some VPL's BSDF is not a bare Lambertian.
    fn of(set: &[Vpl]) -> Option<Vec<Self>> {
        set.chunks(8)
            .map(|chunk| {
                let mut l = Self { count: chunk.len(), ..Self::default() };
                for (j, v) in chunk.iter().enumerate() {
                    let r = lambert_reflectance(&v.bsdf)?;
                    set3(&mut l.p, j, v.p);
                    set3(&mut l.ng, j, v.ng);
                    set3(&mut l.ns, j, v.ns);
                    set3(&mut l.ng_side, j, v.ng_side);
                    set3(&mut l.z, j, v.bsdf.frame.z);
                    // `Bsdf::f`'s `to_local(wo).z` and `Bxdf::f`'s value.
                    l.wo_z[j] = v.wo.dot(v.bsdf.frame.z);
                    set3(&mut l.f, j, r * std::f32::consts::FRAC_1_PI);
                    set3(&mut l.beta, j, v.beta);
                    l.segments[j] = v.segments;
                }
                Some(l)
            })
            .collect()
    }
}

/// The reflectance of a BSDF that is a bare Lambertian (no layers), else `None`.
fn lambert_reflectance(b: &Bsdf) -> Option<Vec3A> {
    match (b.bxdf, &b.layers) {
        (Bxdf::Lambertian { r }, None) => Some(r),
        _ => None,
    }
}

/// The shading point of [`vpl_terms`]: position, geometric normal (toward the viewer), BSDF
/// frame normal, `wo` in that frame (its z), `f` (`r / pi`), and the clamp of `G`.
#[derive(Clone, Copy)]
pub struct VplPoint<R> {
    pub p: [R; 3],
    pub ng: [R; 3],
    pub z: [R; 3],
    pub wo_z: R,
    pub f: [R; 3],
    pub g_limit: R,
}

/// 8 (or 1) VPLs' terms at a plain Lambertian point `x`, written once over [`Real`]: where the
/// VPL lights `x` (`valid`, both on the right sides, `f` and the clamped `G` nonzero), its
/// contribution `f(x) f(vpl) beta min(G, g_limit)` and the shadow segment; the scalar loop of
/// `reflected` does the same f32 operations (glam's orders), so the lanes give its bits.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn vpl_terms<R: Real>(
    x: &VplPoint<R>,
    valid: R::Mask,
    p: [R; 3],
    ng: [R; 3],
    ns: [R; 3],
    ng_side: [R; 3],
    z: [R; 3],
    wo_z: R,
    f: [R; 3],
    beta: [R; 3],
) -> VplTerm<R> {
    use super::lambert::shadow_segment;
    use super::vec3::{dot, is_zero, neg};
    let zero = wo_z.splat(0.0);
    let d = [p[0] - x.p[0], p[1] - x.p[1], p[2] - x.p[2]];
    let d2 = dot(d, d);
    let len = d2.sqrt();
    let w = [d[0] / len, d[1] / len, d[2] / len];
    let sides = !dot(w, x.ng).le(zero) & !dot(neg(w), ng_side).le(zero);
    let wi_z = dot(w, x.z);
    let f_x = !x.wo_z.eq(zero) & (x.wo_z * wi_z).gt(zero);
    let wv_z = dot(neg(w), z);
    let f_v = !wo_z.eq(zero) & (wo_z * wv_z).gt(zero);
    let f = [
        R::select(f_x, x.f[0], zero) * R::select(f_v, f[0], zero) * beta[0],
        R::select(f_x, x.f[1], zero) * R::select(f_v, f[1], zero) * beta[1],
        R::select(f_x, x.f[2], zero) * R::select(f_v, f[2], zero) * beta[2],
    ];
    let g = wi_z.abs() * dot(w, ns).abs() / d2;
    // `f32::min`: the limit where `g` is NaN.
    let g = R::select(g.lt(x.g_limit), g, x.g_limit);
    let c = [f[0] * g, f[1] * g, f[2] * g];
    let lit = valid & d2.gt(zero) & sides & !is_zero(f) & !is_zero(c);
    let (o, d, t_max) = shadow_segment(x.p, x.ng, p, ng);
    VplTerm { lit, c, o, d, t_max }
}

/// One VPL's term (or 8 in lanes): whether it lights the point, its contribution and shadow
/// segment (origin, direction, max t).
pub struct VplTerm<R: Real> {
    pub lit: R::Mask,
    pub c: [R; 3],
    pub o: [R; 3],
    pub d: [R; 3],
    pub t_max: R,
}

/// What [`vpl_terms`] gives for 8 VPLs in lanes: where each lights the point (bits), and its
/// contribution and shadow segment.
pub struct VplTerms {
    pub lit: u32,
    pub c: [[f32; 8]; 3],
    pub o: [[f32; 8]; 3],
    pub d: [[f32; 8]; 3],
    pub t_max: [f32; 8],
}

/// [`vpl_terms`] of the chunk `v` in AVX2 lanes (called from [`super::wide::Avx2::vpl_terms`]).
/// No closures (see `accel::Sheared::new`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn lane_vpl_terms(avx2: super::wide::Avx2, x: &VplPoint<f32>, v: &VplLanes, valid: u32) -> VplTerms {
    use super::wide::F32x8;
    #[inline(always)]
    fn v3(avx2: super::wide::Avx2, a: &[[f32; 8]; 3]) -> [F32x8; 3] {
        [avx2.f32x8(&a[0]), avx2.f32x8(&a[1]), avx2.f32x8(&a[2])]
    }
    #[inline(always)]
    fn s3(l: F32x8, a: [f32; 3]) -> [F32x8; 3] {
        [l.splat(a[0]), l.splat(a[1]), l.splat(a[2])]
    }
    let zero = avx2.f32x8(&[0.0; 8]);
    let point = VplPoint {
        p: s3(zero, x.p),
        ng: s3(zero, x.ng),
        z: s3(zero, x.z),
        wo_z: zero.splat(x.wo_z),
        f: s3(zero, x.f),
        g_limit: zero.splat(x.g_limit),
    };
    let bits: [f32; 8] = std::array::from_fn(|i| if valid & (1 << i) != 0 { 1.0 } else { 0.0 });
    let VplTerm { lit, c, o, d, t_max } = vpl_terms(
        &point,
        avx2.f32x8(&bits).gt(zero),
        v3(avx2, &v.p),
        v3(avx2, &v.ng),
        v3(avx2, &v.ns),
        v3(avx2, &v.ng_side),
        v3(avx2, &v.z),
        avx2.f32x8(&v.wo_z),
        v3(avx2, &v.f),
        v3(avx2, &v.beta),
    );
    VplTerms {
        lit: lit.bits(),
        c: [c[0].to_array(), c[1].to_array(), c[2].to_array()],
        o: [o[0].to_array(), o[1].to_array(), o[2].to_array()],
        d: [d[0].to_array(), d[1].to_array(), d[2].to_array()],
        t_max: t_max.to_array(),
    }
}

/// VPL sets by sample index, built on first use; the tiles of a pass share them.
#[derive(Default)]
pub struct VplCache(Mutex<BTreeMap<u32, Arc<VplSets>>>);

impl VplCache {
    /// The VPL sets of each sample of `pass`, in sample order (a pure function of the
    /// settings and the sample index).
    pub fn get(
        &self,
        scene: &RenderScene,
        params: &IgiParams,
        sampler: SamplerKind,
        seed: u64,
        pass: Pass,
    ) -> Vec<Arc<VplSets>> {
        pass.samples()
            .map(|s| {
                if let Some(v) = self.0.lock().unwrap_or_else(|e| e.into_inner()).get(&s) {
                    return v.clone();
                }
                let built = Arc::new(trace_vpls(scene, params, sampler, seed, s));
                let mut map = self.0.lock().unwrap_or_else(|e| e.into_inner());
                let mut total: usize = map.values().map(|v| v.bytes()).sum::<usize>() + built.bytes();
                while total > CACHED_VPL_BYTES {
                    let Some((_, old)) = map.pop_first() else { break };
                    total -= old.bytes();
                }
                map.entry(s).or_insert(built).clone()
            })
            .collect()
    }
}

/// Traces the VPL sets of sample index `sample_index`.
pub fn trace_vpls(
    scene: &RenderScene,
    params: &IgiParams,
    sampler_kind: SamplerKind,
    seed: u64,
    sample_index: u32,
) -> VplSets {
    // A VPL at light vertex k (k segments from the light) lights a camera hit at c >= 1
    // segments through c + 1 + k segments: k <= max_depth - 2.
    let max_vertices =
        if params.max_depth == 0 { UNLIMITED_VERTICES } else { params.max_depth.saturating_sub(1) as usize };
    let mut sampler = AnySampler::new(sampler_kind, hash_u64(&[seed, VPL_SEED_TAG]));
    let mut paths = Subpaths::default();
    let scale = 1.0 / params.vpls.max(1) as f32;
    let sets = (0..params.vpl_sets)
        .map(|set| {
            let mut vpls = Vec::new();
            for k in 0..params.vpls {
                sampler.start_pixel_sample(UVec2::new(set, sample_index), k, 0);
                light_subpath(scene, max_vertices, RR_DEPTH, &mut sampler, paths.light_mut(), 0.0);
                for (segments, v) in paths.light_mut().iter().enumerate().skip(1) {
                    let Some(bsdf) = v.bsdf else { continue };
                    if v.kind != VertexKind::Surface || bsdf.is_delta() {
                        continue;
                    }
                    vpls.push(Vpl {
                        p: v.p,
                        ng: v.ng,
                        ns: v.ns,
                        ng_side: v.ng_side,
                        wo: v.wo,
                        bsdf,
                        beta: v.beta * scale,
                        segments: segments as u32,
                    });
                }
            }
            let lanes = VplLanes::of(&vpls);
            VplSet { vpls, lanes }
        })
        .collect();
    VplSets { sets }
}

/// One step of a sample's radiance sum, recorded while its VPLs' shadow rays wait for their
/// batch ([`IgiScratch::resolve`] replays them: the same f32 operations in the same order as
/// adding each term where it was found).
#[derive(Clone, Copy, Debug)]
enum SumOp {
    /// `l += v`.
    Add(Vec3A),
    /// `l += v` where shadow ray `ray` (of the batch) is unblocked.
    AddVisible(Vec3A, u32),
    /// A nested sum (the radiance reflected at a compensation's point) starts from zero.
    Begin,
    /// The nested sum ends: its parent's `l += beta * nested`.
    EndScaled(Vec3A),
}

/// IGI's samples recorded together so that their VPLs' shadow rays go in one batched query:
/// one point's 64 rays spread over the BVH's 24 ray classes, and their sorted packets were
/// mostly too small to trace as packets; the rays of many samples fill them. One per thread,
/// reused.
#[derive(Default)]
pub struct IgiScratch {
    ops: Vec<SumOp>,
    rays: Vec<RayQuery>,
    blocked: Vec<bool>,
    /// Per recorded sample: its owner (the caller's tag), its value (radiance to come) and the
    /// end of its ops.
    samples: Vec<(usize, SampleValue, usize)>,
    /// The sums' stack while replaying.
    stack: Vec<Vec3A>,
}

/// The shadow rays a batch of IGI samples gathers before its query (`IgiScratch::resolve`),
/// about 16 Cornell box points' VPLs. 2,048 (the most a query sorts at once) measured no
/// better: `tiny igi long` 1.025x the time of 1,024 (median of 9 interleaved pairs, quartiles
/// 0.976-1.041). Queried in the order of their VPLs (a stable counting sort, so that a packet
/// holds rays from the batch's points to one VPL, nearly parallel, rather than one point's rays
/// to several VPLs, which share their origin): `tiny igi` 691.3M -> 769.9M instructions,
/// `tiny igi long` 1.072x the time (7 pairs, Intel Xeon); not kept.
pub const IGI_BATCH_RAYS: usize = 1024;

impl IgiScratch {
    /// Room for a batch of `rays` shadow rays (and a sample's beyond them), their sums' ops
    /// and samples, made once for a thread's rows.
    pub fn with_capacity(rays: usize) -> Self {
        let room = rays + 256;
        Self {
            ops: Vec::with_capacity(2 * room),
            rays: Vec::with_capacity(room),
            blocked: Vec::with_capacity(room),
            samples: Vec::with_capacity(room / 16),
            stack: Vec::with_capacity(16),
        }
    }

    /// The shadow rays recorded so far.
    pub fn rays(&self) -> usize {
        self.rays.len()
    }

    /// Records one IGI camera sample through `pixel` (the sampler positioned at dimension 0)
    /// with the VPL sets of its sample index (`None`: no sets, a zero sample): its value
    /// comes from [`IgiScratch::resolve`], in recording order, with `owner`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &mut self,
        scene: &RenderScene,
        camera: &Camera,
        pixel: UVec2,
        sampler: &mut impl Sampler,
        params: &IgiParams,
        vpls: Option<&VplSets>,
        owner: usize,
    ) {
        let v = match vpls {
            Some(vpls) => record_igi(scene, camera, pixel, sampler, params, vpls, self),
            None => SampleValue::default(),
        };
        self.samples.push((owner, v, self.ops.len()));
    }

    /// The recorded samples' owners and values in recording order, passed to `each`: their
    /// shadow rays answered in one batch, their sums replayed. Leaves the scratch empty.
    pub fn resolve(&mut self, scene: &RenderScene, mut each: impl FnMut(usize, &SampleValue)) {
        if self.rays.len() <= super::accel::SORTED_BATCH {
            scene.occluded_many(&self.rays, &mut self.blocked);
        } else {
            // No more at once than a query sorts.
            self.blocked.clear();
            let mut blocked = Vec::new();
            for rays in self.rays.chunks(super::accel::SORTED_BATCH) {
                scene.occluded_many(rays, &mut blocked);
                self.blocked.extend_from_slice(&blocked);
            }
        }
        let mut start = 0;
        for (owner, v, end) in &mut self.samples {
            let mut l = Vec3A::ZERO;
            for op in &self.ops[start..*end] {
                match *op {
                    SumOp::Add(c) => l += c,
                    SumOp::AddVisible(c, ray) => {
                        if !self.blocked.get(ray as usize).copied().unwrap_or(true) {
                            l += c;
                        }
                    }
                    SumOp::Begin => {
                        self.stack.push(l);
                        l = Vec3A::ZERO;
                    }
                    SumOp::EndScaled(beta) => {
                        let nested = l;
                        l = self.stack.pop().unwrap_or(Vec3A::ZERO);
                        l += beta * nested;
                    }
                }
            }
            start = *end;
            v.radiance = l.to_array();
            each(*owner, v);
        }
        self.ops.clear();
        self.rays.clear();
        self.blocked.clear();
        self.samples.clear();
        self.stack.clear();
    }
}

/// Records one IGI camera sample (see [`IgiScratch::record`]): its AOVs, and its radiance as
/// ops in `scratch`.
fn record_igi(
    scene: &RenderScene,
    camera: &Camera,
    pixel: UVec2,
    sampler: &mut impl Sampler,
    params: &IgiParams,
    vpls: &VplSets,
    scratch: &mut IgiScratch,
) -> SampleValue {
    let mut out = SampleValue::default();
    let empty = VplSet::default();
    let set = if vpls.sets.is_empty() {
        &empty
    } else {
        let k = (u64::from(pixel.x) + 2 * u64::from(pixel.y)) % vpls.sets.len() as u64;
        &vpls.sets[k as usize]
    };
    let mut ray: Ray = camera.sample_ray(pixel, sampler);
    let mut beta = Vec3A::ONE;
    let mut segments = 0u32;
    loop {
        let Some(si) = scene.intersect(ray.o, ray.d, f32::INFINITY) else {
            // Seen from the camera or through specular surfaces, like emitters.
            scratch.ops.push(SumOp::Add(beta * scene.environment_le(ray.d)));
            break;
        };
        let wo = -ray.d;
        segments += 1;
        beta *= scene.transmittance(&si, ray.d);
        // Emitters seen from the camera or through specular surfaces count in full; after a
        // diffuse or glossy hit, direct lighting is the light sample's.
        scratch.ops.push(SumOp::Add(beta * scene.emitted(&si, wo)));
        let sh = shade(scene, &si, wo, sampler.get_1d());
        if segments == 1 {
            out.depth = Some(si.t);
            out.albedo = sh.albedo.to_array();
            out.normal = sh.ns.to_array();
        }
        if params.max_depth != 0 && segments >= params.max_depth {
            break;
        }
        let Some(bsdf) = &sh.bsdf else { break };
        if !bsdf.is_delta() {
            // `l += beta * reflected(..)`.
            scratch.ops.push(SumOp::Begin);
            reflected(scene, si.p, &sh, wo, segments, sampler, params, set, 0, scratch);
            scratch.ops.push(SumOp::EndScaled(beta));
            break;
        }
        let Some((bs, weight)) = sample_scatter(bsdf, sh.ng, wo, sampler) else { break };
        beta *= weight;
        if !(beta.max_element() > 0.0) || !beta.is_finite() || segments >= MAX_SPECULAR_CHAIN {
            break;
        }
        ray = Ray::new(offset_ray_origin(si.p, sh.ng, bs.wi), bs.wi);
    }
    out
}

/// Radiance reflected toward `wo` at the non-specular point `p` reached through `segments`
/// path segments: direct lighting + clamped VPLs (+ the compensation of the clamping), recorded
/// as the ops of a nested sum its caller began (the VPLs' terms wait for their shadow rays).
#[allow(clippy::too_many_arguments)]
fn reflected(
    scene: &RenderScene,
    p: Vec3A,
    sh: &Shading,
    wo: Vec3A,
    segments: u32,
    sampler: &mut impl Sampler,
    params: &IgiParams,
    set: &VplSet,
    recursion: u32,
    scratch: &mut IgiScratch,
) {
    let Some(bsdf) = &sh.bsdf else { return };
    let within = |n: u32| params.max_depth == 0 || n <= params.max_depth;
    if within(segments + 1) {
        let direct = PathParams {
            max_depth: 2,
            rr_depth: u32::MAX,
            mis: MisHeuristic::Light,
            light_sampling: LightSampling::SolidAngle,
        };
        // IGI refuses motion blur (see `Renderer::new`): the scene is at time 0.
        scratch.ops.push(SumOp::Add(sample_ld(scene, p, sh, wo, sampler, &direct, 0.0)));
    }
    let lanes = set.lanes.as_ref().zip(lambert_reflectance(bsdf)).zip(scene.avx2());
    if let Some(((chunks, r), avx2)) = lanes {
        // 8 VPLs at a time (the scalar loop's bits, in its order).
        let point = VplPoint {
            p: p.to_array(),
            ng: sh.ng.to_array(),
            z: bsdf.frame.z.to_array(),
            wo_z: wo.dot(bsdf.frame.z),
            f: (r * std::f32::consts::FRAC_1_PI).to_array(),
            g_limit: params.g_limit,
        };
        for chunk in chunks {
            let valid = (0..chunk.count)
                .filter(|&j| within(segments + 1 + chunk.segments[j]))
                .fold(0u32, |bits, j| bits | 1 << j);
            if valid == 0 {
                continue;
            }
            let t = avx2.vpl_terms(&point, chunk, valid);
            for j in (0..chunk.count).filter(|&j| t.lit & (1 << j) != 0) {
                let get = |a: &[[f32; 8]; 3]| Vec3A::new(a[0][j], a[1][j], a[2][j]);
                scratch.ops.push(SumOp::AddVisible(get(&t.c), scratch.rays.len() as u32));
                scratch.rays.push(RayQuery { o: get(&t.o), d: get(&t.d), t_max: t.t_max[j], time: 0.0 });
            }
        }
    }
    let one_by_one = if lanes.is_some() { &[][..] } else { &set.vpls[..] };
    for vpl in one_by_one {
        if !within(segments + 1 + vpl.segments) {
            continue;
        }
        let d = vpl.p - p;
        let d2 = d.length_squared();
        if !(d2 > 0.0) {
            continue;
        }
        let w = d / d2.sqrt();
        if w.dot(sh.ng) <= 0.0 || (-w).dot(vpl.ng_side) <= 0.0 {
            continue;
        }
        let f = bsdf.f(wo, w) * vpl.bsdf.f(vpl.wo, -w) * vpl.beta;
        if f == Vec3A::ZERO {
            continue;
        }
        let g = w.dot(bsdf.frame.z).abs() * w.dot(vpl.ns).abs() / d2;
        let c = f * g.min(params.g_limit);
        if c != Vec3A::ZERO {
            let (o, d, t_max) = shadow_segment(p, sh.ng, vpl.p, Some(vpl.ng));
            scratch.ops.push(SumOp::AddVisible(c, scratch.rays.len() as u32));
            scratch.rays.push(RayQuery { o, d, t_max, time: 0.0 });
        }
    }
    // The visible VPLs add up in the VPLs' order (their shadow rays answered in the batch).
    if params.bias_compensation && within(segments + 2) {
        compensation(scene, p, sh, bsdf, wo, segments, sampler, params, set, recursion, scratch);
    }
}

/// The clamped-away part `integral of f L max(G - g_limit, 0) dA`, as a BSDF-sampled ray from
/// `p` to `y` weighted by `max(1 - g_limit / G, 0)` times the radiance reflected at `y`
/// (estimated recursively; Russian roulette after [`RR_DEPTH`] levels), recorded as its
/// caller's `l += compensation`.
#[allow(clippy::too_many_arguments)]
fn compensation(
    scene: &RenderScene,
    p: Vec3A,
    sh: &Shading,
    bsdf: &Bsdf,
    wo: Vec3A,
    segments: u32,
    sampler: &mut impl Sampler,
    params: &IgiParams,
    set: &VplSet,
    recursion: u32,
    scratch: &mut IgiScratch,
) {
    match compensation_vertex(scene, p, sh, bsdf, wo, sampler, params, recursion) {
        // `l += 0`.
        None => scratch.ops.push(SumOp::Add(Vec3A::ZERO)),
        // `l += beta * reflected(y)`.
        Some((beta, y, sh_y, wo_y)) => {
            scratch.ops.push(SumOp::Begin);
            reflected(scene, y, &sh_y, wo_y, segments + 1, sampler, params, set, recursion + 1, scratch);
            scratch.ops.push(SumOp::EndScaled(beta));
        }
    }
}

/// The compensation's vertex: its weight `beta`, the point `y`, its shading and the direction
/// back to `p`; `None` where the compensation adds nothing.
#[allow(clippy::too_many_arguments)]
fn compensation_vertex(
    scene: &RenderScene,
    p: Vec3A,
    sh: &Shading,
    bsdf: &Bsdf,
    wo: Vec3A,
    sampler: &mut impl Sampler,
    params: &IgiParams,
    recursion: u32,
) -> Option<(Vec3A, Vec3A, Shading, Vec3A)> {
    let uc = sampler.get_1d();
    let u = sampler.get_2d();
    let u_lobe = sampler.get_1d();
    let u_rr = sampler.get_1d();
    let bs = bsdf.sample_f(wo, uc, u)?;
    if bs.is_transmission() || bs.wi.dot(sh.ng) <= 0.0 || bs.is_specular() {
        return None;
    }
    let y = scene.intersect(offset_ray_origin(p, sh.ng, bs.wi), bs.wi, f32::INFINITY)?;
    let wo_y = -bs.wi;
    let sh_y = shade(scene, &y, wo_y, u_lobe);
    let Some(bsdf_y) = &sh_y.bsdf else { return None };
    if bsdf_y.is_delta() {
        return None;
    }
    let d2 = (y.p - p).length_squared();
    let cos_x = bs.wi.dot(bsdf.frame.z).abs();
    let g = cos_x * bs.wi.dot(bsdf_y.frame.z).abs() / d2;
    if !(g > params.g_limit) {
        return None;
    }
    let mut beta = bs.f * (cos_x / bs.pdf) * (1.0 - params.g_limit / g);
    if recursion >= RR_DEPTH {
        let q = beta.max_element().min(0.95);
        if !(u_rr < q) {
            return None;
        }
        beta /= q;
    }
    if !beta.is_finite() {
        return None;
    }
    Some((beta, y.p, sh_y, wo_y))
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::render::wide::{Avx2, unit};

    /// The 8-lane VPL terms (AVX2) are the `f32` terms in every lane, on random points, normals
    /// and weights with zeros, NaN and infinities among them, VPLs at the point itself, and
    /// lanes left invalid. (The `f32` terms are the scalar loop's: the renders' digests and the
    /// baseline-against-AVX2 renders compare them.)
    #[test]
    fn lanes_are_the_scalar_vpl_terms() {
        let Some(avx2) = Avx2::new() else { return };
        let special = [0.0, -0.0, f32::NAN, f32::INFINITY, 1e-30, 1e30, 1.0, -1.0];
        let value = |i: u64, k: u64| {
            let u = unit(i * 61 + k);
            if u < 0.03 {
                special[(unit(i * 61 + k + 40) * special.len() as f32) as usize % special.len()]
            } else {
                u * 2.0 - 1.0
            }
        };
        let bits = |x: f32| if x.is_nan() { f32::NAN.to_bits() } else { x.to_bits() };
        let (mut compared, mut lit) = (0, 0);
        for case in 0..3000u64 {
            let v = |k: u64| value(case * 1000, k);
            let v3 = |k: u64| [v(k), v(k + 1), v(k + 2)];
            let up = if v(20) > -0.8 { [0.0, 0.0, 1.0] } else { v3(3) };
            let point = VplPoint {
                p: v3(0),
                ng: up,
                z: up,
                wo_z: v(9).abs(),
                f: v3(10).map(f32::abs),
                g_limit: v(13).abs() * 5.0,
            };
            let mut lanes = VplLanes { count: 8, ..VplLanes::default() };
            let valid = (unit(case) * 256.0) as u32 | 1;
            for j in 0..8 {
                let w = |k: u64| value(case * 1000 + 1 + j as u64, k);
                let w3 = |k: u64| glam::Vec3A::new(w(k), w(k + 1), w(k + 2));
                // Mostly above the point (its normals are +z) and facing it; now and then on
                // the point itself.
                let origin = glam::Vec3A::from_array(point.p);
                let above = glam::Vec3A::new(w(0), w(1), w(2).abs() + 0.1);
                let p = if w(30) > 0.95 { origin } else { origin + above };
                let facing = -above + w3(3) * 0.3;
                super::set3(&mut lanes.p, j, p);
                super::set3(&mut lanes.ng, j, facing);
                super::set3(&mut lanes.ns, j, w3(6));
                super::set3(&mut lanes.ng_side, j, if w(31) > -0.8 { facing } else { w3(9) });
                super::set3(&mut lanes.z, j, if w(32) > -0.8 { facing } else { w3(12) });
                lanes.wo_z[j] = if w(33) > -0.8 { w(15).abs() } else { w(15) };
                super::set3(&mut lanes.f, j, w3(16).abs());
                super::set3(&mut lanes.beta, j, w3(19).abs());
            }
            let got = avx2.vpl_terms(&point, &lanes, valid);
            for j in 0..8 {
                let l3 = |a: &[[f32; 8]; 3]| [a[0][j], a[1][j], a[2][j]];
                let want = vpl_terms(
                    &point,
                    valid & (1 << j) != 0,
                    l3(&lanes.p),
                    l3(&lanes.ng),
                    l3(&lanes.ns),
                    l3(&lanes.ng_side),
                    l3(&lanes.z),
                    lanes.wo_z[j],
                    l3(&lanes.f),
                    l3(&lanes.beta),
                );
                let at = format!("case {case} lane {j}");
                assert_eq!(got.lit & (1 << j) != 0, want.lit, "{at}: lit");
                if want.lit {
                    lit += 1;
                    assert_eq!(l3(&got.c).map(bits), want.c.map(bits), "{at}: contribution");
                    assert_eq!(l3(&got.o).map(bits), want.o.map(bits), "{at}: origin");
                    assert_eq!(l3(&got.d).map(bits), want.d.map(bits), "{at}: direction");
                    assert_eq!(bits(got.t_max[j]), bits(want.t_max), "{at}: t_max");
                }
                compared += 1;
            }
        }
        assert_eq!(compared, 24_000);
        // Enough of them light the point to compare the values too.
        assert!(lit > 5000, "{lit} lit");
    }
}
