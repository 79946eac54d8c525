//! Ray-triangle acceleration: an obvhs compressed wide BVH (CWBVH) over all world-space
//! triangles, with closest-hit and shadow (any-hit) queries.
//!
//! Triangles are intersected with the watertight algorithm of Woop, Benthin and Wald (JCGT 2013,
//! as in pbrt-v4): rays through shared edges and vertices of a closed mesh never slip through.
//! Where the CPU has AVX2, the traversal tests a node's leaf triangles 8 at a time (its leaves'
//! triangles are consecutive BVH slots, stored also as structure of arrays): the same f32
//! operations in every lane as the one-at-a-time test (`Sheared` is written once, for `f32`
//! and for lanes), and the lanes' hits are taken in the one-at-a-time order with the `t_max`
//! then in force, so hits stay bit-identical. Measured with the bench's `tiny`: the closest-hit
//! and shadow queries use about 1.3 groups of 8 lanes for 3.4 triangles per ray on the Cornell
//! box, and render it about 2% faster though with 4% more instructions (lanes trade
//! instructions for branches); 130k-triangle diffuse rays gain about 6%.
//! Even the Cornell box's 36 triangles are traversed, not all tested at once: measured on the
//! bench's `tiny` (AMD EPYC, Zen 4), every query testing all 36 in triangle lanes (5 groups of 8
//! per ray, in one fixed order) took 425.9M -> 689.3M instructions, and sorted packets testing
//! all 36 for their rays in ray lanes (single rays through the tree), 515.5M.
//!
//! Coherent rays (up to 8 of one octant and dominant axis, within about 25 degrees: a pixel's
//! camera rays) go through the tree as a packet (`trace_packet`, from [`Accel::intersect_many`]).
//! A packet first tests the union of the root's children's boxes for all its rays at once, and
//! ends there when every ray misses it (rounding is monotone, so such a ray misses every
//! child: 80% of the 130k scene's camera packets). Then each node's 8 children are tested per
//! ray in lanes (the single-ray node test), the rays per child gathered by a bit transpose, and
//! each leaf triangle is tested for the rays that reached it, in lanes. Each ray still visits
//! its own nodes and triangles in its own order, so its hit is the single-ray hit. The bench's
//! primary rays of the 130k scene, 8 per pixel, one thread: 19.3 Mrays/s one by one, 36.3 in
//! packets (25.3 with each child tested for the packet's rays in lanes and no union test).
//!
//! The BVH build is single-threaded and deterministic, so every process that loads a scene gets
//! the same tree and breaks ties between equal distances the same way.

use super::math::Real;
#[cfg(target_arch = "x86_64")]
use super::wide::F32x8;
use super::wide::{Avx2, Baseline, NodeTest, SimdLevel, V3Kernel};
use glam::{UVec2, Vec3A};
use obvhs::faststack::FastStack;
use obvhs::{BvhBuildParams, aabb::Aabb, cwbvh::CwBvh, cwbvh::Traversal, cwbvh::builder::build_cwbvh, ray::Ray};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// A closest hit: distance, triangle index (as given to [`Accel::new`]) and barycentrics of
/// vertices 1 and 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub prim: u32,
    pub b1: f32,
    pub b2: f32,
}

/// One ray of a batched query: `o + t d` for `0 < t < t_max` at shutter time `time`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayQuery {
    pub o: Vec3A,
    pub d: Vec3A,
    pub t_max: f32,
    pub time: f32,
}

impl RayQuery {
    /// A ray without an end (a closest-hit query's: a path's next segment).
    #[inline(always)]
    pub fn unbounded(o: Vec3A, d: Vec3A, time: f32) -> Self {
        Self { o, d, t_max: f32::INFINITY, time }
    }
}

/// The BVH and its triangles, stored in BVH leaf order for locality.
pub struct Accel {
    bvh: Option<CwBvh>,
    /// Vertices of the triangle at each BVH primitive slot.
    tris: Vec<[Vec3A; 3]>,
    /// Original triangle index of each BVH primitive slot.
    prim_ids: Vec<u32>,
    /// Motion blur: each slot's vertices at shutter close (`tris` holds them at shutter open);
    /// a ray at time `u` in [0, 1] meets the triangle lerped between the two. The BVH is built
    /// over the swept boxes (both poses), so it bounds the triangle at every time.
    tris_close: Option<Vec<[Vec3A; 3]>>,
    /// Where the CPU has AVX2: the queries run the traversal compiled for it, with the 8-wide
    /// node test (bit-identical results; see [`super::wide`]).
    avx2: Option<Avx2>,
    /// Static triangles' vertices by BVH slot as structure of arrays: component `axis` of vertex
    /// `i` of slot `k` at `soa[3 * i + axis][k]`, padded with [`LANES`] zeros, so that 8
    /// consecutive slots (a node's leaves) load as lanes for the 8-wide triangle test. `None`
    /// with motion blur (moving triangles are tested one at a time).
    soa: Option<Box<[Vec<f32>; 9]>>,
    /// The union of the root's children's quantized boxes (per axis: lowest min, highest max;
    /// `None` where the root has no child): a packet tests it first (see `trace_packet`).
    root_union: Option<[[f32; 2]; 3]>,
    /// The sorted packets' triangle tests so far and the rays they tested (see
    /// [`Accel::sorted_packets`]).
    packet_tests: AtomicU64,
    packet_lanes: AtomicU64,
    /// The center of the triangles' bounds: sorted packets group a class's rays by the octant
    /// of their origin around it.
    sort_center: Vec3A,
}

/// What the packet traversals of a batch share ([`trace_packet`]): their triangle tests and the
/// rays they tested in all, counted where `count` is set (sorted packets on trial), and the
/// traversal stack (made once for the batch: a fresh one per packet cost a 768-byte `memset`,
/// 1% of the Cornell box's time).
#[derive(Clone, Copy)]
pub(super) struct PacketStats {
    count: bool,
    tests: u32,
    lanes: u32,
    stack: [(u32, u32); PACKET_STACK],
}

impl Default for PacketStats {
    fn default() -> Self {
        Self { count: false, tests: 0, lanes: 0, stack: [(0, 0); PACKET_STACK] }
    }
}

/// What the 8-wide triangle test needs: the proof of AVX2 and the triangles as lanes.
#[derive(Clone, Copy)]
struct TriangleLanes<'a> {
    avx2: Avx2,
    soa: &'a [Vec<f32>; 9],
}

/// Triangles per lane-wise test.
const LANES: usize = 8;

/// The triangle `v0` moving to `v1`, at time `u` in [0, 1] of the shutter.
#[inline(always)]
pub fn lerp_triangle(v0: &[Vec3A; 3], v1: &[Vec3A; 3], u: f32) -> [Vec3A; 3] {
    [v0[0].lerp(v1[0], u), v0[1].lerp(v1[1], u), v0[2].lerp(v1[2], u)]
}

/// Per-ray constants of the watertight test: the shear for the axis permutation `(KX, KY, KZ)`
/// (`KZ` = the ray's dominant axis). The permutation is a const parameter, so vertex components
/// are picked at compile time instead of by a runtime index into a SIMD register.
#[derive(Clone, Copy)]
pub(super) struct RayShear<const KX: usize, const KY: usize, const KZ: usize> {
    o: Vec3A,
    sx: f32,
    sy: f32,
    sz: f32,
}

/// The dominant axis of `d`.
///
/// Tried on an AVX2-only AMD EPYC (Zen 3) and dropped: without its branch on "z wins" (made a
/// conditional move with `std::hint::select_unpredictable`; written as arithmetic, the compiler
/// put the branch back), for the sort of a batch's random directions: cachegrind's simulated
/// mispredicts 1,449k -> 1,433k on `tiny`, `tiny long` 0.989x the time (median of 15 interleaved
/// pairs, quartiles 0.875-1.089): no measurable gain.
fn dominant_axis(d: Vec3A) -> usize {
    let ad = d.abs();
    if ad.x > ad.y {
        if ad.x > ad.z { 0 } else { 2 }
    } else if ad.y > ad.z {
        1
    } else {
        2
    }
}

impl<const KX: usize, const KY: usize, const KZ: usize> RayShear<KX, KY, KZ> {
    fn new(o: Vec3A, d: Vec3A) -> Self {
        let (dx, dy, dz) = (d[KX], d[KY], d[KZ]);
        Self { o, sx: -dx / dz, sy: -dy / dz, sz: 1.0 / dz }
    }

    /// Returns (t, b1, b2) of a hit with `0 < t < t_max`.
    #[inline(always)]
    fn intersect(&self, v: &[Vec3A; 3], t_max: f32) -> Option<(f32, f32, f32)> {
        let p =
            Sheared::new([self.o[KX], self.o[KY], self.o[KZ]], [self.sx, self.sy], v.map(|v| [v[KX], v[KY], v[KZ]]));
        let mut e = p.edges();
        // Fall back to double precision on an edge, so shared edges are decided consistently.
        if any_zero(e) {
            e = p.edges_f64();
        }
        // Most triangles fail here: leave before the rest (`candidate` checks it again).
        if (e[0] < 0.0 || e[1] < 0.0 || e[2] < 0.0) && (e[0] > 0.0 || e[1] > 0.0 || e[2] > 0.0) {
            return None;
        }
        let c = p.candidate(e, self.sz);
        (c.pass && c.within(t_max)).then_some((c.t, c.b1, c.b2))
    }
}

/// A triangle in the ray's sheared space (the watertight test's first step) for one ray and
/// triangle (`f32`) or 8 rays and triangles in lanes ([`super::wide::F32x8`]): the same f32
/// operations in the same order either way, so a lane gives the scalar test's bits.
#[derive(Clone, Copy)]
struct Sheared<R> {
    x: [R; 3],
    y: [R; 3],
    z: [R; 3],
}

/// The watertight test's outcome before the ray's `t_max` is known: `pass` holds where every
/// other test passes (edge signs, a nonzero determinant, the scaled distance on the right side,
/// and pbrt-v4's conservative lower bound on t).
#[derive(Clone, Copy)]
struct Candidate<R: Real> {
    pass: R::Mask,
    det: R,
    t_scaled: R,
    t: R,
    b1: R,
    b2: R,
}

impl<R: Real> Sheared<R> {
    /// Vertices `v` (components in the ray's (KX, KY, KZ) order) translated to the origin `o`
    /// and sheared by `s` (x and y).
    #[inline(always)]
    ///
    /// No closures here or below: the lane-wise form is inlined into a function compiled for
    /// AVX2, and a closure that is not inlined would be compiled (and call its intrinsics)
    /// without it.
    fn new(o: [R; 3], s: [R; 2], v: [[R; 3]; 3]) -> Self {
        let z = [v[0][2] - o[2], v[1][2] - o[2], v[2][2] - o[2]];
        Self {
            x: [(v[0][0] - o[0]) + s[0] * z[0], (v[1][0] - o[0]) + s[0] * z[1], (v[2][0] - o[0]) + s[0] * z[2]],
            y: [(v[0][1] - o[1]) + s[1] * z[0], (v[1][1] - o[1]) + s[1] * z[1], (v[2][1] - o[1]) + s[1] * z[2]],
            z,
        }
    }

    /// The three edge functions.
    #[inline(always)]
    fn edges(&self) -> [R; 3] {
        let (x, y) = (self.x, self.y);
        [x[1] * y[2] - y[1] * x[2], x[2] * y[0] - y[2] * x[0], x[0] * y[1] - y[0] * x[1]]
    }

    /// The rest of the test from the edge functions `e`, with `sz` the ray's z scale.
    ///
    /// Tried and dropped: the conservative bound on t (a third of these operations) made only
    /// where some lane still hits without it: `tiny` 417.9M -> 415.9M instructions, `tiny
    /// large` 1,353.7M -> 1,355.5M (most lanes inside the edges do hit).
    #[inline(always)]
    fn candidate(&self, e: [R; 3], sz: R) -> Candidate<R> {
        let zero = sz.splat(0.0);
        let any_negative = e[0].lt(zero) | e[1].lt(zero) | e[2].lt(zero);
        let any_positive = e[0].gt(zero) | e[1].gt(zero) | e[2].gt(zero);
        let det = e[0] + e[1] + e[2];
        let (x, y) = (self.x, self.y);
        let z = [self.z[0] * sz, self.z[1] * sz, self.z[2] * sz];
        let t_scaled = e[0] * z[0] + e[1] * z[1] + e[2] * z[2];
        let inv_det = sz.splat(1.0) / det;
        let t = t_scaled * inv_det;
        // Conservative lower bound on t (pbrt-v4 Triangle::Intersect): reject hits that may lie
        // behind the origin because of rounding.
        const GAMMA3: f32 = 3.0 * f32::EPSILON * 0.5 / (1.0 - 3.0 * f32::EPSILON * 0.5);
        const GAMMA5: f32 = 5.0 * f32::EPSILON * 0.5 / (1.0 - 5.0 * f32::EPSILON * 0.5);
        const GAMMA7: f32 = 7.0 * f32::EPSILON * 0.5 / (1.0 - 7.0 * f32::EPSILON * 0.5);
        let (gamma3, gamma5, gamma7) = (sz.splat(GAMMA3), sz.splat(GAMMA5), sz.splat(GAMMA7));
        let max_zt = max_abs(z);
        let delta_z = gamma3 * max_zt;
        let max_xt = max_abs(x);
        let max_yt = max_abs(y);
        let delta_x = gamma5 * (max_xt + max_zt);
        let delta_y = gamma5 * (max_yt + max_zt);
        let delta_e = sz.splat(2.0) * (gamma7 * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
        let max_e = max_abs(e);
        let delta_t = sz.splat(3.0) * (gamma3 * max_e * max_zt + delta_e * max_zt + delta_z * max_e) * inv_det.abs();
        let wrong_side = (det.lt(zero) & t_scaled.ge(zero)) | (det.gt(zero) & t_scaled.le(zero));
        let pass = !((any_negative & any_positive) | det.eq(zero) | wrong_side | t.le(delta_t));
        Candidate { pass, det, t_scaled, t, b1: e[1] * inv_det, b2: e[2] * inv_det }
    }
}

/// The largest magnitude of the three.
#[inline(always)]
fn max_abs<R: Real>(v: [R; 3]) -> R {
    v[0].abs().max(v[1].abs()).max(v[2].abs())
}

impl Sheared<f32> {
    /// The edge functions in double precision (the test's fallback where one is zero).
    fn edges_f64(&self) -> [f32; 3] {
        let f = f64::from;
        let (x, y) = (self.x, self.y);
        [
            (f(x[1]) * f(y[2]) - f(y[1]) * f(x[2])) as f32,
            (f(x[2]) * f(y[0]) - f(y[2]) * f(x[0])) as f32,
            (f(x[0]) * f(y[1]) - f(y[0]) * f(x[1])) as f32,
        ]
    }
}

impl<R: Real> Candidate<R> {
    /// The test's last part: the hit lies before `t_max` (on the scaled distance, as the
    /// watertight test compares it).
    #[inline(always)]
    fn within(&self, t_max: R) -> R::Mask {
        let (zero, limit) = (t_max.splat(0.0), t_max * self.det);
        !((self.det.lt(zero) & self.t_scaled.lt(limit)) | (self.det.gt(zero) & self.t_scaled.gt(limit)))
    }

    /// Where the whole test passes before `t_max`, and `t < t_max`: a hit the one-at-a-time
    /// test takes while its `t_max` is this one.
    #[inline(always)]
    fn hits_before(&self, t_max: R) -> R::Mask {
        self.pass & self.within(t_max) & self.t.lt(t_max)
    }
}

/// Where the edge functions do not have both signs (the ray may pass inside the triangle): the
/// first of `candidate`'s tests, the one most triangles fail.
#[inline(always)]
fn inside_edges<R: Real>(e: [R; 3]) -> R::Mask {
    let zero = e[0].splat(0.0);
    let any_negative = e[0].lt(zero) | e[1].lt(zero) | e[2].lt(zero);
    let any_positive = e[0].gt(zero) | e[1].gt(zero) | e[2].gt(zero);
    !(any_negative & any_positive)
}

/// Where an edge function is zero: the test's double-precision fallback decides there.
#[inline(always)]
fn any_zero<R: Real>(e: [R; 3]) -> R::Mask {
    let zero = e[0].splat(0.0);
    e[0].eq(zero) | e[1].eq(zero) | e[2].eq(zero)
}

/// [`Accel::intersect_at`] in AVX2: a kernel, not a closure given to `Avx2::run`, so that the
/// traversal is always compiled for AVX2 (a closure is inlined into the AVX2 function only
/// while the optimizer finds it small: when an unrelated change tipped it, `tiny bdpt` ran the
/// traversal compiled for the baseline, 3.7% more instructions).
struct IntersectOne<'a> {
    accel: &'a Accel,
    avx2: Avx2,
    ray: RayQuery,
}

impl V3Kernel for IntersectOne<'_> {
    type Output = Option<Hit>;
    #[inline(always)]
    fn call(self) -> Option<Hit> {
        let Self { accel, avx2, ray: r } = self;
        accel.intersect_dispatch(avx2, None, r.o, r.d, r.t_max, r.time)
    }
}

/// [`Accel::occluded_at`] in AVX2 (see [`IntersectOne`]).
struct OccludedOne<'a> {
    accel: &'a Accel,
    avx2: Avx2,
    ray: RayQuery,
}

impl V3Kernel for OccludedOne<'_> {
    type Output = bool;
    #[inline(always)]
    fn call(self) -> bool {
        let Self { accel, avx2, ray: r } = self;
        accel.occluded_dispatch(avx2, None, r.o, r.d, r.t_max, r.time)
    }
}

/// [`Accel::intersect_many`] in AVX2.
struct IntersectMany<'a> {
    accel: &'a Accel,
    avx2: Avx2,
    rays: &'a [RayQuery],
    hits: &'a mut Vec<Option<Hit>>,
}

impl V3Kernel for IntersectMany<'_> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let Self { accel, avx2, rays, hits } = self;
        // One traversal state for the batch, restarted per ray (see `restart`).
        let mut state = Traversal::default();
        if accel.sorted_packets(rays.len()) {
            accel.intersect_sorted::<false>(avx2, &mut state, rays, hits);
            return;
        }
        let mut i = 0;
        let mut stats = PacketStats::default();
        // Every hit is written in place (misses stay `None`).
        hits.resize(rays.len(), None);
        while i < rays.len() {
            // Coherent rays (a camera's, at the first bounce) go through the BVH as a packet; the
            // rest one by one. The hits are the same either way. (Small scenes sort them into
            // packets instead: above.)
            let n = accel.packet_len(&rays[i..]);
            if n >= MIN_PACKET {
                let mut packet = [&rays[i]; PACKET];
                for (j, r) in rays[i..i + n].iter().enumerate().take(PACKET) {
                    packet[j] = r;
                }
                let out = PacketOut { hits: &mut hits[i..], slots: &LANE_SLOTS[..n] };
                if accel.trace_packet::<false>(avx2, &packet[..n], out, &mut stats) {
                    i += n;
                    continue;
                }
            }
            // Too few for a packet: these rays one by one (without asking again from each).
            let end = i + n.max(1);
            for (r, hit) in rays[i..end].iter().zip(&mut hits[i..end]) {
                *hit = accel.intersect_dispatch(avx2, Some(&mut state), r.o, r.d, r.t_max, r.time);
            }
            i = end;
        }
    }
}

/// [`Accel::occluded_many`] in AVX2.
struct OccludedMany<'a> {
    accel: &'a Accel,
    avx2: Avx2,
    rays: &'a [RayQuery],
    blocked: &'a mut Vec<bool>,
}

impl V3Kernel for OccludedMany<'_> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let Self { accel, avx2, rays, blocked } = self;
        let mut state = Traversal::default();
        if accel.sorted_packets(rays.len()) {
            let mut hits = Vec::with_capacity(rays.len());
            accel.intersect_sorted::<true>(avx2, &mut state, rays, &mut hits);
            for h in &hits {
                blocked.push(h.is_some());
            }
            return;
        }
        // One by one: packets of shadow rays in the order they come saved 1.4% of the
        // instructions of the bench's `tiny` and cost `tiny igi` 3.5% (its rays to the VPLs
        // part at once; telling them apart cost more than it saved).
        for r in rays {
            blocked.push(accel.occluded_dispatch(avx2, Some(&mut state), r.o, r.d, r.t_max, r.time));
        }
    }
}

/// obvhs' `CwBvh::new_traversal(direction)`, made in `state` in place: its stack emptied, not
/// built anew (a new one is 256 bytes of zeros, written for every ray of a batch).
#[inline(always)]
fn restart(state: &mut Traversal, bvh: &CwBvh, direction: Vec3A) {
    state.stack.clear();
    state.current_group = if bvh.nodes.is_empty() { UVec2::ZERO } else { UVec2::new(0, 0x8000_0000) };
    state.primitive_group = UVec2::ZERO;
    // obvhs' `ray_get_octant_inv4`.
    state.oct_inv4 = (if direction.x < 0.0 { 0 } else { 0x0404_0404 })
        | (if direction.y < 0.0 { 0 } else { 0x0202_0202 })
        | (if direction.z < 0.0 { 0 } else { 0x0101_0101 });
    state.traversal_direction = direction;
    state.primitive_id = 0;
    state.hitmask = 0;
}

/// `tris` as structure of arrays ([`Accel::soa`]).
fn soa_of(tris: &[[Vec3A; 3]]) -> [Vec<f32>; 9] {
    std::array::from_fn(|k| {
        let (vertex, axis) = (k / 3, k % 3);
        tris.iter().map(|t| t[vertex][axis]).chain([0.0; LANES]).collect()
    })
}

/// The union of a node's children's quantized boxes: per axis the lowest `child_min` and the
/// highest `child_max` over its children (as f32, exact); `None` without children.
fn quantized_union(node: &obvhs::cwbvh::node::CwBvhNode) -> Option<[[f32; 2]; 3]> {
    let children = (0..8).filter(|&c| node.child_meta[c] != 0);
    let planes = [
        (&node.child_min_x, &node.child_max_x),
        (&node.child_min_y, &node.child_max_y),
        (&node.child_min_z, &node.child_max_z),
    ];
    let mut union = [[0.0f32; 2]; 3];
    for (u, (lo, hi)) in union.iter_mut().zip(planes) {
        let min = children.clone().map(|c| lo[c]).min()?;
        let max = children.clone().map(|c| hi[c]).max()?;
        *u = [f32::from(min), f32::from(max)];
    }
    Some(union)
}

/// The direction given to obvhs: negative zeros made positive (`-0.0 + 0.0 = +0.0`, every other
/// value unchanged). obvhs orders a node's slabs by `d < 0.0` (false for -0.0) but inverts -0.0
/// to a large negative number, so a ray with a -0.0 component (an orthographic camera's
/// axis-aligned rays) had swapped slabs and missed everything.
#[inline(always)]
fn bvh_direction(d: Vec3A) -> Vec3A {
    d + Vec3A::ZERO
}

/// The box the BVH is built over for a triangle with bounds `b`: `b` padded by 1e-5 of its
/// largest coordinate. The node test is exact arithmetic on quantized boxes, and a ray through a
/// box's edge (a mesh edge on the box boundary) can otherwise miss a node whose triangle the
/// watertight test would hit.
fn build_box(b: Aabb) -> Aabb {
    let pad = Vec3A::splat(build_pad(&b));
    Aabb { min: b.min - pad, max: b.max + pad }
}

fn build_pad(b: &Aabb) -> f32 {
    b.min.abs().max(b.max.abs()).max_element() * 1e-5 + 1e-20
}

/// Above this many triangles every build box is spread ([`spread_box`]), tied or not: ties
/// between distinct boxes (triangles evenly spaced in a row, with equal pads) made PLOC pair
/// about one node per pass, 16,000 of them built in 5 s and 32,000 in 19 s (0.05 s spread).
/// Smaller scenes keep their trees (only coincident boxes spread): 4,000 such triangles still
/// build in 0.5 s, and ties broken toward the right give the Cornell box's quads a good tree.
/// Measured on the 130k-triangle scene (`tiny large onepass`): build 450.8M -> 436.2M
/// instructions (no search for coincident boxes), render 689.4M -> 694.3M (+0.7%).
const SPREAD_ALL_ABOVE: usize = 4096;

/// The most build boxes that may coincide exactly before [`spread_coincident`] moves them apart.
const MAX_COINCIDENT: usize = 8;

/// Grows each build box that more than [`MAX_COINCIDENT`] triangles share exactly, on each of
/// its six sides by up to its pad again, by a hash of (its index, side): no two stay alike.
///
/// obvhs' PLOC pairs each node with the neighbour whose union with it has the least area and
/// breaks ties toward the rightmost, so among coincident boxes (all costs tied) only the last two
/// pair in each pass: 70,000 copies of one triangle (a degenerate scene; a mesh scaled to nothing)
/// made a chain 70,000 deep, whose conversion to the wide BVH overflowed the thread's stack after
/// minutes of build. Spread apart, 130,000 copies build in 0.22 s, 20 levels deep. Only such
/// groups move: every other scene keeps the tree that ties broken toward the
/// right give it (the Cornell box's quads are pairs of coincident boxes; spreading every box
/// cost `tiny` 472M -> 489M-504M instructions, by the hash). Boxes only grow, so every hit is
/// the same.
///
/// Ties between distinct boxes are as bad: triangles evenly spaced in a row, each box's union
/// with its left and right neighbours of exactly equal area, pair about one node per pass. So
/// above [`SPREAD_ALL_ABOVE`] triangles every box is spread instead.
fn spread_coincident(boxes: &mut [Aabb]) {
    // Boxes compared by a 64-bit hash of their bits (FxHash's step per 32-bit word: rotate, xor,
    // multiply): equal boxes hash alike, and a collision would only spread a few boxes more.
    // Sorted hashes, not a hash map: 4 ms for 130,000 boxes (with a full mix per word) against
    // 30-40 ms.
    let hash = |b: &Aabb| {
        let (min, max) = (b.min.to_array(), b.max.to_array());
        [min[0], min[1], min[2], max[0], max[1], max[2]]
            .iter()
            .fold(0u64, |h, x| (h.rotate_left(5) ^ u64::from(x.to_bits())).wrapping_mul(0x517c_c1b7_2722_0a95))
    };
    let mut hashes: Vec<u64> = boxes.iter().map(hash).collect();
    hashes.sort_unstable();
    let crowded: Vec<u64> =
        hashes.chunk_by(|a, b| a == b).filter(|run| run.len() > MAX_COINCIDENT).map(|run| run[0]).collect();
    if crowded.is_empty() {
        return;
    }
    for (i, b) in boxes.iter_mut().enumerate() {
        if crowded.binary_search(&hash(b)).is_ok() {
            spread_box(i, b);
        }
    }
}

/// Grows build box `i` on each of its six sides by up to its pad again, by a hash of (`i`,
/// side).
fn spread_box(i: usize, b: &mut Aabb) {
    let pad = build_pad(b);
    let bits = super::sampler::mix_bits(i as u64);
    // Six factors in [0, 1), 10 bits each.
    let f = |side: u32| ((bits >> (10 * side)) & 1023) as f32 / 1024.0;
    b.min -= pad * Vec3A::new(f(0), f(1), f(2));
    b.max += pad * Vec3A::new(f(3), f(4), f(5));
}

impl Accel {
    /// Builds the BVH over `tris` (world space).
    pub fn new(tris: &[[Vec3A; 3]]) -> Self {
        Self::build(tris, None)
    }

    /// Builds the BVH over triangles moving linearly from `open` to `close` during the shutter
    /// (same count and order; `close` falls back to `open` where it is shorter).
    pub fn new_moving(open: &[[Vec3A; 3]], close: &[[Vec3A; 3]]) -> Self {
        Self::build(open, Some(close))
    }

    fn build(tris: &[[Vec3A; 3]], close: Option<&[[Vec3A; 3]]>) -> Self {
        if tris.is_empty() {
            return Self {
                bvh: None,
                tris: Vec::new(),
                prim_ids: Vec::new(),
                tris_close: None,
                avx2: Avx2::new(),
                soa: None,
                root_union: None,
                packet_tests: AtomicU64::new(0),
                packet_lanes: AtomicU64::new(0),
                sort_center: Vec3A::ZERO,
            };
        }
        let close_of = |i: usize| close.and_then(|c| c.get(i)).copied();
        let mut boxes: Vec<Aabb> = tris
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let mut b = Aabb::from_points(t);
                if let Some(c) = close_of(i) {
                    let bc = Aabb::from_points(&c);
                    b = Aabb { min: b.min.min(bc.min), max: b.max.max(bc.max) };
                }
                build_box(b)
            })
            .collect();
        if boxes.len() > SPREAD_ALL_ABOVE {
            for (i, b) in boxes.iter_mut().enumerate() {
                spread_box(i, b);
            }
        } else {
            spread_coincident(&mut boxes);
        }
        // The build's quality hardly matters to the small scenes whose rays go in packets:
        // measured on the bench's `tiny` (the Cornell box, 36 triangles), obvhs' fastest-but-one,
        // fast, medium, slow and very slow builds trace it in 429.8M, 425.9M, 425.9M, 426.0M
        // and 426.1M instructions. Leaves of at most 1 triangle (obvhs' `max_prims_per_leaf`;
        // CWBVH leaves hold up to 3): `tiny` 417.9M -> 452.0M (more node visits than the
        // triangle tests they save); at most 2: 417.9M, the same. (`build_cwbvh` over boxes
        // ignores the slow builds' `pre_split`.) Large triangles' boxes split in parts
        // (obvhs' `split_aabbs_precise`, the build boxes padded after): the Cornell box split
        // none, even at a quarter of the preset's area threshold, its walls' boxes being thin
        // already (a ray enters one only where it meets the wall); not kept.
        let bvh = build_cwbvh(&boxes, BvhBuildParams::medium_build(), &mut Duration::default());
        let prim_ids = bvh.primitive_indices.clone();
        let ordered: Vec<[Vec3A; 3]> = prim_ids.iter().map(|&i| tris[i as usize]).collect();
        let tris_close =
            close.map(|_| prim_ids.iter().map(|&i| close_of(i as usize).unwrap_or(tris[i as usize])).collect());
        let soa = tris_close.is_none().then(|| Box::new(soa_of(&ordered)));
        let root_union = bvh.nodes.first().and_then(quantized_union);
        let (lo, hi) =
            tris.iter().flatten().fold((Vec3A::INFINITY, Vec3A::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        let sort_center = (lo + hi) * 0.5;
        Self {
            bvh: Some(bvh),
            tris: ordered,
            prim_ids,
            tris_close,
            avx2: Avx2::new(),
            soa,
            root_union,
            packet_tests: AtomicU64::new(0),
            packet_lanes: AtomicU64::new(0),
            sort_center,
        }
    }

    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// Closest hit along `o + t d` with `0 < t < t_max` (at shutter open).
    pub fn intersect(&self, o: Vec3A, d: Vec3A, t_max: f32) -> Option<Hit> {
        self.intersect_at(o, d, t_max, 0.0)
    }

    /// The SIMD level the queries use ([`SimdLevel::detect`] at construction).
    pub fn simd_level(&self) -> SimdLevel {
        self.avx2.map_or(SimdLevel::Baseline, Avx2::level)
    }

    /// Uses the best level up to `level` that the CPU supports for the queries: for tests and
    /// measurements that compare the kernels. Returns the level in use.
    pub fn set_simd_level(&mut self, level: SimdLevel) -> SimdLevel {
        self.avx2 = Avx2::at(level);
        self.simd_level()
    }

    /// Closest hit at time `time` in [0, 1] of the shutter (moving triangles lerped).
    #[inline]
    pub fn intersect_at(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> Option<Hit> {
        match self.avx2 {
            Some(avx2) => avx2.run_kernel(IntersectOne { accel: self, avx2, ray: RayQuery { o, d, t_max, time } }),
            None => self.intersect_baseline(o, d, t_max, time),
        }
    }

    /// [`Accel::intersect_at`] without SIMD, out of line: the callers inline only the dispatch
    /// (with the baseline traversal inside, the optimizer left the query itself out of line in
    /// some callers, as the codegen units fell).
    #[inline(never)]
    fn intersect_baseline(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> Option<Hit> {
        self.intersect_dispatch(Baseline, None, o, d, t_max, time)
    }

    #[inline(always)]
    fn intersect_dispatch<N: NodeTest>(
        &self,
        nodes: N,
        state: Option<&mut Traversal>,
        o: Vec3A,
        d: Vec3A,
        t_max: f32,
        time: f32,
    ) -> Option<Hit> {
        match dominant_axis(d) {
            0 => self.intersect_with(nodes, state, RayShear::<1, 2, 0>::new(o, d), o, d, t_max, time),
            1 => self.intersect_with(nodes, state, RayShear::<2, 0, 1>::new(o, d), o, d, t_max, time),
            _ => self.intersect_with(nodes, state, RayShear::<0, 1, 2>::new(o, d), o, d, t_max, time),
        }
    }

    /// The watertight test against the triangle in BVH slot `slot` at `time` (static triangles
    /// are tested in place, as without motion blur).
    #[inline(always)]
    fn test_slot<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        shear: &RayShear<KX, KY, KZ>,
        slot: usize,
        t_max: f32,
        time: f32,
    ) -> Option<(f32, f32, f32)> {
        match &self.tris_close {
            None => shear.intersect(&self.tris[slot], t_max),
            Some(close) => shear.intersect(&lerp_triangle(&self.tris[slot], &close[slot], time), t_max),
        }
    }

    /// Closest-hit traversal (obvhs' `CwBvh::ray_traverse`, with the node test `nodes`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn intersect_with<N: NodeTest, const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        nodes: N,
        state: Option<&mut Traversal>,
        shear: RayShear<KX, KY, KZ>,
        o: Vec3A,
        d: Vec3A,
        t_max: f32,
        time: f32,
    ) -> Option<Hit> {
        let bvh = self.bvh.as_ref()?;
        let mut ray = Ray::new(o, bvh_direction(d), 0.0, t_max);
        // A batch's state restarted in place, or a fresh one for a single ray.
        let mut fresh;
        let state = match state {
            Some(state) => {
                restart(state, bvh, ray.direction);
                state
            }
            None => {
                fresh = bvh.new_traversal(ray.direction);
                &mut fresh
            }
        };
        let mut node;
        let mut hit: Option<u32> = None;
        let mut best = (0.0f32, 0.0f32);
        let lanes = nodes.lanes().zip(self.soa.as_deref()).map(|(avx2, soa)| TriangleLanes { avx2, soa });
        obvhs::traverse!(bvh, node, state, nodes.hits(node, &ray, state.oct_inv4), {
            if let Some(lanes) = lanes {
                // The node's whole group of leaf triangles at once: this one and those left.
                let base = state.primitive_group.x;
                let group = state.primitive_group.y | (1 << (state.primitive_id - base));
                state.primitive_group.y = 0;
                if let Some((slot, t, b1, b2)) = self.closest_in_group(lanes, &shear, base, group, ray.tmax) {
                    best = (b1, b2);
                    hit = Some(slot);
                    ray.tmax = t;
                }
            // `primitive_id` indexes primitive_indices; tris is stored in that order.
            } else if let Some((t, b1, b2)) = self.test_slot(&shear, state.primitive_id as usize, ray.tmax, time)
                && t < ray.tmax
            {
                best = (b1, b2);
                hit = Some(state.primitive_id);
                ray.tmax = t;
            }
        });
        // The triangle test also passes t == tmax (a tie on a shared edge): such a hit loses to
        // the earlier one, barycentrics included.
        hit.map(|slot| Hit { t: ray.tmax, prim: self.prim_ids[slot as usize], b1: best.0, b2: best.1 })
    }

    /// The closest hits of a batch of rays, in order (a wavefront's intersection stage): each
    /// exactly [`Accel::intersect_at`] of its ray, with one SIMD dispatch for the batch.
    pub fn intersect_many(&self, rays: &[RayQuery], hits: &mut Vec<Option<Hit>>) {
        hits.clear();
        // Plain loops, not iterator adapters: their code stays inside the function compiled for
        // AVX2 (an adapter's `fold` is a function of its own, compiled for the baseline, which
        // cannot inline the AVX2 node test).
        match self.avx2 {
            Some(avx2) => avx2.run_kernel(IntersectMany { accel: self, avx2, rays, hits }),
            None => {
                let mut state = Traversal::default();
                for r in rays {
                    hits.push(self.intersect_dispatch(Baseline, Some(&mut state), r.o, r.d, r.t_max, r.time));
                }
            }
        }
    }

    /// How many of the first rays of `rays` (at most 8) can go through the BVH as a packet: the
    /// rays that share the first one's octant and dominant axis (which the packet needs) and
    /// run within about 25 degrees of it (what makes a packet pay: rays that part soon visit
    /// nodes apart, and the packet tests each node for them all). Static triangles only.
    #[inline(always)]
    fn packet_len(&self, rays: &[RayQuery]) -> usize {
        if self.tris_close.is_some() {
            return 0;
        }
        let Some(first) = rays.first() else { return 0 };
        // The octant as obvhs takes it (`d + 0 < 0`, and -0 is not below 0 either way).
        let (d0, octant, axis) = (first.d, first.d.cmplt(Vec3A::ZERO).bitmask(), dominant_axis(first.d));
        let len0 = d0.length_squared();
        let mut n = 1;
        for r in rays.iter().take(PACKET).skip(1) {
            let cos = r.d.dot(d0);
            let joins = r.d.cmplt(Vec3A::ZERO).bitmask() == octant
                && cos > 0.0
                && cos * cos >= 0.8 * r.d.length_squared() * len0
                && dominant_axis(r.d) == axis;
            if !joins {
                break;
            }
            n += 1;
        }
        n
    }

    /// Whether a batch of `n` rays goes through the BVH in packets of rays sorted by octant and
    /// dominant axis, however incoherent: where the rays of a packet visit mostly the same
    /// leaves, a packet tests each leaf triangle for several of them at once. Always in small
    /// scenes (see [`SORTED_PACKET_TRIANGLES`]); in larger ones (up to
    /// [`SORTED_ADAPTIVE_TRIANGLES`]) while the packets' triangle tests so far serve enough rays
    /// each ([`sorting_pays`]). Either way every ray gets its single-ray hit, so the choice
    /// (which depends on the order the threads traced their batches) changes no bit of an image.
    #[inline(always)]
    fn sorted_packets(&self, n: usize) -> bool {
        if self.tris_close.is_some() || n > SORTED_BATCH || self.tris.len() > SORTED_ADAPTIVE_TRIANGLES {
            return false;
        }
        let (tests, lanes) = (self.packet_tests.load(Relaxed), self.packet_lanes.load(Relaxed));
        sorting_pays(self.tris.len(), tests, lanes)
    }

    /// Whether batches of rays (up to `SORTED_BATCH`) go through the BVH in sorted packets
    /// now: always in small scenes, in larger ones while the packets pay (the wavefront then
    /// makes its batches that large where the scene has no textures: `wavefront::batch_len`).
    pub fn sorts_rays(&self) -> bool {
        self.sorted_packets(SORTED_BATCH)
    }

    /// The hits of `rays` (at most [`SORTED_BATCH`]), each in its place, traced in packets of
    /// rays that share their octant and dominant axis (what a packet needs): the rays' indices
    /// sorted by class (a counting sort; above [`SMALL_SORTED_BATCH`] rays, within a class by
    /// the octant of their origin, [`ORIGIN_CELLS`]), each class in packets of 8; a class's last few rays
    /// (fewer than [`MIN_PACKET`]) and any packet whose stack would overflow go one by one.
    /// Each ray's hit is its single-ray hit whatever its packet (see [`trace_packet`]), so the
    /// sort changes no bit of any image. `ANY`: shadow rays, `Some` where blocked.
    #[inline(always)]
    fn intersect_sorted<const ANY: bool>(
        &self,
        avx2: Avx2,
        state: &mut Traversal,
        rays: &[RayQuery],
        hits: &mut Vec<Option<Hit>>,
    ) {
        // The sort's arrays sized for the batch: a small batch (an IGI point's rays to its VPLs)
        // does not zero those of the largest.
        if rays.len() <= SMALL_SORTED_BATCH {
            self.intersect_sorted_in::<ANY, SMALL_SORTED_BATCH, 1>(avx2, state, rays, hits);
        } else {
            self.intersect_sorted_in::<ANY, SORTED_BATCH, ORIGIN_CELLS>(avx2, state, rays, hits);
        }
    }

    /// [`Accel::intersect_sorted`] of at most `CAP` rays (a power of two).
    ///
    /// The rays' classes were tried 8 at a time in lanes (their directions and origins
    /// transposed, octant, dominant axis and cell as lane selects): on the bench's `tiny` the
    /// sort's own instructions fell from 16.8M to 15.6M, and the transposes and conversions
    /// took as many back (425.9M -> 425.8M in all); not kept.
    #[inline(always)]
    fn intersect_sorted_in<const ANY: bool, const CAP: usize, const CELLS: usize>(
        &self,
        avx2: Avx2,
        state: &mut Traversal,
        rays: &[RayQuery],
        hits: &mut Vec<Option<Hit>>,
    ) {
        let mut class = [0u8; CAP];
        let mut start = [0u16; BUCKETS + 1];
        let center = self.sort_center;
        for (i, r) in rays.iter().enumerate() {
            let d = r.d + Vec3A::ZERO;
            let c = d.cmplt(Vec3A::ZERO).bitmask() as usize * 3 + dominant_axis(d);
            let cell = if CELLS > 1 { r.o.cmplt(center).bitmask() as usize } else { 0 };
            let b = (c * CELLS + cell).min(BUCKETS - 1);
            class[i & (CAP - 1)] = b as u8;
            start[b + 1] += 1;
        }
        for b in 0..(24 * CELLS).min(BUCKETS) {
            start[b + 1] += start[b];
        }
        let mut order = [0u16; CAP];
        for i in 0..rays.len() {
            let b = usize::from(class[i & (CAP - 1)]).min(BUCKETS - 1);
            order[usize::from(start[b]) & (CAP - 1)] = i as u16;
            start[b] += 1;
        }
        // `start[b]` is now the end of bucket `b`; a class ends with its last bucket.
        hits.clear();
        hits.resize(rays.len(), None);
        let mut slots = [0u32; PACKET];
        // Counted only while on trial: then the counts are final, and so is the choice.
        let count = self.tris.len() > SORTED_PACKET_TRIANGLES && self.packet_tests.load(Relaxed) < SORTED_TRIAL_TESTS;
        let mut stats = PacketStats { count, ..PacketStats::default() };
        let mut begin = 0usize;
        for c in 0..24 {
            let end = usize::from(start[(c * CELLS + CELLS - 1).min(BUCKETS - 1)]);
            let mut k = begin;
            while k < end {
                let n = (end - k).min(PACKET);
                let idx = &order[k..k + n];
                if n >= MIN_PACKET {
                    // The packet's rays by reference, its hits written in place.
                    let first = &rays[0];
                    let mut packet = [first; PACKET];
                    for (j, &i) in idx.iter().enumerate().take(PACKET) {
                        packet[j] = rays.get(usize::from(i)).unwrap_or(first);
                        slots[j] = u32::from(i);
                    }
                    let out = PacketOut { hits: &mut hits[..], slots: &slots[..n] };
                    if self.trace_packet::<ANY>(avx2, &packet[..n], out, &mut stats) {
                        k += n;
                        continue;
                    }
                }
                for &i in idx {
                    let r = &rays[usize::from(i)];
                    hits[usize::from(i)] = if ANY {
                        self.occluded_dispatch(avx2, Some(state), r.o, r.d, r.t_max, r.time).then_some(BLOCKED)
                    } else {
                        self.intersect_dispatch(avx2, Some(state), r.o, r.d, r.t_max, r.time)
                    };
                }
                k += n;
            }
            begin = end;
        }
        // Once per batch (the counters are shared by the threads).
        if count {
            self.packet_tests.fetch_add(u64::from(stats.tests), Relaxed);
            self.packet_lanes.fetch_add(u64::from(stats.lanes), Relaxed);
        }
    }

    /// [`trace_packet`] for the packet's dominant axis; `false` where it did not trace them.
    /// `ANY`: shadow rays (see [`trace_packet`]).
    #[inline(always)]
    fn trace_packet<const ANY: bool>(
        &self,
        avx2: Avx2,
        rays: &[&RayQuery],
        hits: PacketOut<'_>,
        stats: &mut PacketStats,
    ) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match rays.first().map(|r| dominant_axis(r.d)) {
                Some(0) => avx2.trace_packet::<ANY, 1, 2, 0>(self, rays, hits, stats),
                Some(1) => avx2.trace_packet::<ANY, 2, 0, 1>(self, rays, hits, stats),
                Some(_) => avx2.trace_packet::<ANY, 0, 1, 2>(self, rays, hits, stats),
                None => true,
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (avx2, rays, hits, stats);
            false
        }
    }

    /// Whether each ray of a batch is blocked, in order (a wavefront's shadow-ray stage): each
    /// exactly [`Accel::occluded_at`] of its ray, with one SIMD dispatch for the batch.
    pub fn occluded_many(&self, rays: &[RayQuery], blocked: &mut Vec<bool>) {
        blocked.clear();
        // Plain loops: see `intersect_many`.
        match self.avx2 {
            Some(avx2) => avx2.run_kernel(OccludedMany { accel: self, avx2, rays, blocked }),
            None => {
                let mut state = Traversal::default();
                for r in rays {
                    blocked.push(self.occluded_dispatch(Baseline, Some(&mut state), r.o, r.d, r.t_max, r.time));
                }
            }
        }
    }

    /// Whether anything blocks `o + t d` for `0 < t < t_max` (at shutter open).
    pub fn occluded(&self, o: Vec3A, d: Vec3A, t_max: f32) -> bool {
        self.occluded_at(o, d, t_max, 0.0)
    }

    /// Whether anything blocks the segment at time `time` in [0, 1] of the shutter.
    #[inline]
    pub fn occluded_at(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> bool {
        match self.avx2 {
            Some(avx2) => avx2.run_kernel(OccludedOne { accel: self, avx2, ray: RayQuery { o, d, t_max, time } }),
            None => self.occluded_baseline(o, d, t_max, time),
        }
    }

    /// [`Accel::occluded_at`] without SIMD, out of line (see [`Accel::intersect_baseline`]).
    #[inline(never)]
    fn occluded_baseline(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> bool {
        self.occluded_dispatch(Baseline, None, o, d, t_max, time)
    }

    #[inline(always)]
    fn occluded_dispatch<N: NodeTest>(
        &self,
        nodes: N,
        state: Option<&mut Traversal>,
        o: Vec3A,
        d: Vec3A,
        t_max: f32,
        time: f32,
    ) -> bool {
        match dominant_axis(d) {
            0 => self.occluded_with(nodes, state, RayShear::<1, 2, 0>::new(o, d), o, d, t_max, time),
            1 => self.occluded_with(nodes, state, RayShear::<2, 0, 1>::new(o, d), o, d, t_max, time),
            _ => self.occluded_with(nodes, state, RayShear::<0, 1, 2>::new(o, d), o, d, t_max, time),
        }
    }

    /// Any-hit traversal (obvhs' `CwBvh::ray_traverse_miss`, with the node test `nodes`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn occluded_with<N: NodeTest, const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        nodes: N,
        state: Option<&mut Traversal>,
        shear: RayShear<KX, KY, KZ>,
        o: Vec3A,
        d: Vec3A,
        t_max: f32,
        time: f32,
    ) -> bool {
        let Some(bvh) = self.bvh.as_ref() else { return false };
        let ray = Ray::new(o, bvh_direction(d), 0.0, t_max);
        // A batch's state restarted in place, or a fresh one for a single ray.
        let mut fresh;
        let state = match state {
            Some(state) => {
                restart(state, bvh, ray.direction);
                state
            }
            None => {
                fresh = bvh.new_traversal(ray.direction);
                &mut fresh
            }
        };
        let mut node;
        let mut blocked = false;
        let lanes = nodes.lanes().zip(self.soa.as_deref()).map(|(avx2, soa)| TriangleLanes { avx2, soa });
        'traversal: {
            obvhs::traverse!(bvh, node, state, nodes.hits(node, &ray, state.oct_inv4), {
                if let Some(lanes) = lanes {
                    let base = state.primitive_group.x;
                    let group = state.primitive_group.y | (1 << (state.primitive_id - base));
                    state.primitive_group.y = 0;
                    if self.any_in_group(lanes, &shear, base, group, ray.tmax) {
                        blocked = true;
                        break 'traversal;
                    }
                } else if self
                    .test_slot(&shear, state.primitive_id as usize, ray.tmax, time)
                    .is_some_and(|h| h.0 < ray.tmax)
                {
                    blocked = true;
                    break 'traversal;
                }
            });
        }
        blocked
    }
}

/// The outcome of the watertight test for 8 consecutive BVH slots: `hits` and `redo` as lane
/// bits (`hits`: the ray meets the lane's triangle before the `t_max` it was given; `redo`: an
/// edge function is zero, so the lane's triangle must take the scalar test's double-precision
/// fallback, and is not in `hits`), the lanes' values as arrays.
pub(super) struct LaneCandidates {
    hits: u32,
    redo: u32,
    det: [f32; LANES],
    t_scaled: [f32; LANES],
    t: [f32; LANES],
    b1: [f32; LANES],
    b2: [f32; LANES],
}

impl LaneCandidates {
    /// No lane hits, none needs the fallback.
    const NONE: Self = Self {
        hits: 0,
        redo: 0,
        det: [0.0; LANES],
        t_scaled: [0.0; LANES],
        t: [0.0; LANES],
        b1: [0.0; LANES],
        b2: [0.0; LANES],
    };

    /// Lane `i`'s candidate.
    #[inline(always)]
    fn get(&self, i: usize) -> Candidate<f32> {
        Candidate {
            pass: true,
            det: self.det[i],
            t_scaled: self.t_scaled[i],
            t: self.t[i],
            b1: self.b1[i],
            b2: self.b2[i],
        }
    }
}

/// The watertight test of slots `first..first + 8` (static triangles), lane-wise (called from
/// [`Avx2::watertight8`], compiled for AVX2).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn lane_candidates<const KX: usize, const KY: usize, const KZ: usize>(
    avx2: Avx2,
    soa: &[Vec<f32>; 9],
    shear: &RayShear<KX, KY, KZ>,
    first: usize,
    t_max: f32,
) -> LaneCandidates {
    // No closures: see `Sheared::new`.
    let v = [
        [load8(avx2, soa, KX, first), load8(avx2, soa, KY, first), load8(avx2, soa, KZ, first)],
        [load8(avx2, soa, 3 + KX, first), load8(avx2, soa, 3 + KY, first), load8(avx2, soa, 3 + KZ, first)],
        [load8(avx2, soa, 6 + KX, first), load8(avx2, soa, 6 + KY, first), load8(avx2, soa, 6 + KZ, first)],
    ];
    let l = v[0][0];
    let p = Sheared::new(
        [l.splat(shear.o[KX]), l.splat(shear.o[KY]), l.splat(shear.o[KZ])],
        [l.splat(shear.sx), l.splat(shear.sy)],
        v,
    );
    let e = p.edges();
    let redo = any_zero(e).bits();
    // Every lane outside an edge (most groups): no candidates, without the rest of the test.
    if redo == 0 && inside_edges(e).bits() == 0 {
        return LaneCandidates::NONE;
    }
    let c = p.candidate(e, l.splat(shear.sz));
    // The hits before the `t_max` at the group's start: the lanes that can still hit (the
    // one-at-a-time test's `t_max` only shrinks from there).
    let hits = c.hits_before(l.splat(t_max)).bits() & !redo;
    LaneCandidates {
        hits,
        redo,
        det: c.det.to_array(),
        t_scaled: c.t_scaled.to_array(),
        t: c.t.to_array(),
        b1: c.b1.to_array(),
        b2: c.b2.to_array(),
    }
}

/// Lanes `first..first + 8` of the structure-of-arrays component `k`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn load8(avx2: Avx2, soa: &[Vec<f32>; 9], k: usize, first: usize) -> super::wide::F32x8 {
    match soa[k].get(first..first + LANES).and_then(|s| <&[f32; LANES]>::try_from(s).ok()) {
        Some(lanes) => avx2.f32x8(lanes),
        // Unreachable: the arrays are padded by LANES and `first` is a slot.
        None => avx2.f32x8(&[0.0; LANES]),
    }
}

impl Accel {
    /// The watertight test of the slots `first..first + 8`, lane-wise where this target has the
    /// lanes (else one by one: the same values).
    #[inline(always)]
    fn candidates<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        lanes: TriangleLanes<'_>,
        shear: &RayShear<KX, KY, KZ>,
        first: usize,
        t_max: f32,
    ) -> LaneCandidates {
        #[cfg(target_arch = "x86_64")]
        {
            let _ = self;
            lanes.avx2.watertight8(lanes.soa, shear, first, t_max)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = lanes;
            let mut out = LaneCandidates::NONE;
            for i in 0..LANES.min(self.tris.len().saturating_sub(first)) {
                let v = &self.tris[first + i];
                let p = Sheared::new(
                    [shear.o[KX], shear.o[KY], shear.o[KZ]],
                    [shear.sx, shear.sy],
                    v.map(|v| [v[KX], v[KY], v[KZ]]),
                );
                let e = p.edges();
                let c = p.candidate(e, shear.sz);
                let redo = any_zero(e);
                out.redo |= u32::from(redo) << i;
                out.hits |= u32::from(!redo && c.hits_before(t_max)) << i;
                (out.det[i], out.t_scaled[i], out.t[i], out.b1[i], out.b2[i]) = (c.det, c.t_scaled, c.t, c.b1, c.b2);
            }
            out
        }
    }

    /// Calls `f(slot, hit)` for each slot of `group` (bits relative to `base`, a node's leaf
    /// triangles) that the ray hits before the `t_max` that `f` returns, highest slot first, as
    /// obvhs' traversal visits them one at a time. The triangles are tested 8 at a time; `f`
    /// sees exactly the hits (and the `t_max` in force) of the one-at-a-time test. `f` returns
    /// `None` to stop.
    #[inline(always)]
    fn hits_in_group<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        lanes: TriangleLanes<'_>,
        shear: &RayShear<KX, KY, KZ>,
        base: u32,
        mut group: u32,
        mut t_max: f32,
        mut f: impl FnMut(u32, (f32, f32, f32)) -> Option<f32>,
    ) {
        while group != 0 {
            let top = 31 - group.leading_zeros();
            let start = top.saturating_sub(LANES as u32 - 1);
            let in_group = (group >> start) & 0xff;
            group &= !(0xff << start);
            let first = (base + start) as usize;
            let c = self.candidates(lanes, shear, first, t_max);
            let mut todo = (c.hits | c.redo) & in_group;
            while todo != 0 {
                let lane = 31 - todo.leading_zeros();
                todo &= !(1 << lane);
                let slot = base + start + lane;
                let hit = if c.redo & (1 << lane) != 0 {
                    self.test_slot(shear, slot as usize, t_max, 0.0)
                } else {
                    let c = c.get(lane as usize);
                    c.within(t_max).then_some((c.t, c.b1, c.b2))
                };
                if let Some(hit) = hit
                    && hit.0 < t_max
                {
                    match f(slot, hit) {
                        Some(t) => t_max = t,
                        None => return,
                    }
                }
            }
        }
    }

    /// The closest hit among `group`'s triangles before `t_max` (see [`Accel::hits_in_group`]):
    /// slot, t and barycentrics. On a tie the first visited wins, as in the one-at-a-time test.
    #[inline(always)]
    fn closest_in_group<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        lanes: TriangleLanes<'_>,
        shear: &RayShear<KX, KY, KZ>,
        base: u32,
        group: u32,
        t_max: f32,
    ) -> Option<(u32, f32, f32, f32)> {
        let mut best = None;
        self.hits_in_group(lanes, shear, base, group, t_max, |slot, (t, b1, b2)| {
            best = Some((slot, t, b1, b2));
            Some(t)
        });
        best
    }

    /// Whether any of `group`'s triangles is hit before `t_max`.
    #[inline(always)]
    fn any_in_group<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        lanes: TriangleLanes<'_>,
        shear: &RayShear<KX, KY, KZ>,
        base: u32,
        group: u32,
        t_max: f32,
    ) -> bool {
        let mut any = false;
        self.hits_in_group(lanes, shear, base, group, t_max, |_, _| {
            any = true;
            None
        });
        any
    }
}

/// Rays per packet of the coherent closest-hit traversal.
const PACKET: usize = 8;

/// What [`Accel::intersect_sorted`] records for a blocked shadow ray (only `is_some` is read).
const BLOCKED: Hit = Hit { t: 0.0, prim: u32::MAX, b1: 0.0, b2: 0.0 };

/// The most triangles for which a batch's rays go through the BVH in sorted packets. Measured
/// (`pathfarm-worker render`, 128x128x32, 1 thread): the Cornell box (36 triangles) 1.7% faster
/// in the CLI's settings and 3.4% in the bench's `tiny long` (4.8% fewer instructions); the
/// Cornell box with spheres (2,572 triangles) 2% slower, its packets' rays parting too soon.
const SORTED_PACKET_TRIANGLES: usize = 256;

/// The most triangles for which a batch's rays may go through the BVH in sorted packets, while
/// they pay ([`sorting_pays`]).
const SORTED_ADAPTIVE_TRIANGLES: usize = 65_536;

/// The sorted packets' triangle tests after which [`sorting_pays`] judges them.
const SORTED_TRIAL_TESTS: u64 = 1 << 16;

/// The fewest rays per triangle test (in tenths) with which sorted packets pay above
/// [`SORTED_PACKET_TRIANGLES`]. Measured (`pathfarm-worker render`, 256x256x32, 2 threads): the
/// Cornell box with spheres (2,572 triangles) tests 2.41 rays per packet triangle test and
/// renders 2-3% slower in sorted packets; the corpus' `cornellBox_nvpro` (16.7k) tests 2.78 and
/// renders 7% faster (1.61-1.65 -> 1.49-1.51 s); the Mitsuba Cornell box tests 3.20.
const SORTED_MIN_LANES_X10: u64 = 26;

/// Whether sorted packets pay in a scene of `tris` triangles whose packets made `tests` triangle
/// tests for `lanes` rays in all (counted while on trial, a little beyond it as the threads'
/// batches end): always in small scenes, else while on trial or where each test served enough
/// rays.
fn sorting_pays(tris: usize, tests: u64, lanes: u64) -> bool {
    tris <= SORTED_PACKET_TRIANGLES || tests < SORTED_TRIAL_TESTS || lanes * 10 >= tests * SORTED_MIN_LANES_X10
}

/// The largest batch traced in sorted packets (a power of two), and the wavefront's batch size
/// where the scene sorts its rays (`wavefront::batch_len`).
pub(super) const SORTED_BATCH: usize = 2048;

/// Batches up to this size are sorted in arrays of this size (a power of two).
const SMALL_SORTED_BATCH: usize = 256;

/// The fewest coherent rays traced as a packet. 2 measured no better on an Intel Xeon (AVX-512):
/// `tiny long` 1.002x the time (median of 15 interleaved pairs), `tiny` 426.2M -> 427.0M
/// instructions.
const MIN_PACKET: usize = 4;

/// Origin cells of a sorted class: a class's rays are ordered by the octant of their origin
/// around the scene's center (`Accel::sort_center`), so that its packets hold rays that start
/// near one another (packets still span cells: only a class ends one). Batches of up to
/// [`SMALL_SORTED_BATCH`] rays are sorted by class alone: with cells there too, `tiny igi`
/// took 711.9M -> 721.2M instructions when it queried each point's rays to its VPLs (which
/// share their origin) apart; it now queries many points' at once (`igi::IgiScratch`).
/// Measured on the Cornell box (the bench's callgrind runs): `tiny` 437.1M -> 427.8M, `tiny
/// solid` 473.6M -> 464.2M, `tiny igi` 711.9M -> 712.2M; cells everywhere 434.0M; 64 cells
/// (a 4^3 grid) 446.3M, 27 cells 442.5M (the sort's own cost).
/// In time (Intel Xeon, AVX-512): without cells, `tiny long` 1.034x (median of 9 interleaved
/// pairs, quartiles 0.960-1.063). Tried on an AVX2-only AMD EPYC (Zen 3) and dropped: cells on
/// the plane across the class's dominant axis (a grid over the scene's bounds there: rays of one
/// direction class that start near one another across their travel), `tiny` 415.6M -> 423.4M
/// instructions with 4 x 4 cells, 429.4M with 2 x 2 (`tiny solid` 459.8M and 465.8M).
const ORIGIN_CELLS: usize = 8;

/// Buckets of the sort: 24 classes (octant and dominant axis) of [`ORIGIN_CELLS`] cells each.
const BUCKETS: usize = 24 * ORIGIN_CELLS;

/// Where a packet's hits go: lane `j`'s into `hits[slots[j]]`, which holds `None` before (a
/// miss writes nothing). Written in place: a packet's rays copied out and its hits copied back
/// cost 1% of the Cornell box's instructions.
pub(super) struct PacketOut<'a> {
    pub(super) hits: &'a mut [Option<Hit>],
    pub(super) slots: &'a [u32],
}

/// Slots 0 to 7: a packet of consecutive rays' hits, in order.
const LANE_SLOTS: [u32; PACKET] = [0, 1, 2, 3, 4, 5, 6, 7];

/// A packet's rays in lanes: what obvhs' node test and the watertight test read of each ray.
#[cfg(target_arch = "x86_64")]
struct PacketRays<'a, const KX: usize, const KY: usize, const KZ: usize> {
    /// obvhs' ray origin and inverse direction, per axis.
    origin: [super::wide::F32x8; 3],
    inv_direction: [super::wide::F32x8; 3],
    /// The watertight test's origin (in (KX, KY, KZ) order) and shear.
    shear_o: [super::wide::F32x8; 3],
    shear_s: [super::wide::F32x8; 2],
    shear_sz: super::wide::F32x8,
    /// The rays, one per lane up to their number (each one's scalar shear is made from it for
    /// the double-precision fallback).
    rays: &'a [&'a RayQuery],
    /// The direction's sign per axis (the same in every lane: one octant).
    negative: [bool; 3],
    oct_inv4: u32,
}

/// The closest hits of up to 8 rays that share their octant and dominant axis (`KZ`), traced
/// together through the BVH (static triangles): each node's children are tested against all
/// the packet's rays that reached the node, in lanes, and each leaf triangle against the rays
/// that hit its leaf. Every ray visits exactly the nodes, and tests exactly the triangles in
/// exactly the order, of its single-ray traversal (nodes in the same priority order, each
/// child's box tested with the ray's `t_max` when its parent is visited, a node's leaf
/// triangles before its inner children, highest slot first), with the same f32 operations in
/// its lane: so its hit is the single-ray hit, bit for bit. Returns `false` (and leaves `out`
/// alone) where the packet's stack would overflow; the caller then traces the rays one by one.
///
/// `ANY`: shadow rays. A lane stops at its first hit before its `t_max`, which is then some hit,
/// not the closest: whether there is one is exactly the single-ray [`Accel::occluded_at`]'s
/// answer, which tests each box with the same fixed `t_max` (so reaches the same leaves,
/// whatever the order) and each of their triangles with the same operations. So a node's
/// inner children are visited in the order they come, not sorted.
///
/// Tried on an Intel Xeon and dropped: in scenes of up to 64 triangles, every packet testing
/// every triangle in slot order (no node tests; a flat list, as some tracers keep for tiny
/// scenes): the Cornell box's `tiny` 417.9M -> 486.2M instructions, `tiny solid` 454.3M ->
/// 522.6M: the node tests cull more triangle tests than they cost.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn trace_packet<const ANY: bool, const KX: usize, const KY: usize, const KZ: usize>(
    avx2: Avx2,
    accel: &Accel,
    rays: &[&RayQuery],
    out: PacketOut<'_>,
    stats: &mut PacketStats,
) -> bool {
    let PacketOut { hits, slots } = out;
    // The slots hold `None` already: a miss writes nothing.
    let Some(bvh) = accel.bvh.as_ref() else { return true };
    let Some(&ray0) = rays.first() else { return true };
    let n = rays.len().min(PACKET);
    let active = (1u32 << n) - 1;
    // Lanes past `n` repeat the first ray (their results are dropped). The rays' origins and
    // directions turned into lanes; no closures (see `Sheared::new`).
    let (mut origins, mut directions) = ([&ray0.o; PACKET], [&ray0.d; PACKET]);
    let mut t_max = [0.0f32; PACKET];
    for i in 0..PACKET {
        let r = rays.get(i).copied().unwrap_or(ray0);
        (origins[i], directions[i]) = (&r.o, &r.d);
        t_max[i] = r.t_max;
    }
    let o = avx2.vec3_lanes_of(origins);
    let d = avx2.vec3_lanes_of(directions);
    // obvhs' `Ray::new(o, bvh_direction(d), ..)`: `safe_inverse` of `d + 0` in lanes (the same
    // bits: 1 / x, or signum(x) / EPSILON where |x| <= EPSILON).
    let zero = o[0].splat(0.0);
    let mut inv_direction = o;
    for a in 0..3 {
        let x = d[a] + zero;
        let signum = zero.splat(1.0).xor_bits(x.sign_bit());
        inv_direction[a] =
            F32x8::select(x.abs().le(zero.splat(f32::EPSILON)), signum / zero.splat(f32::EPSILON), zero.splat(1.0) / x);
    }
    let first = ray0.d + Vec3A::ZERO;
    let negative = [first.x < 0.0, first.y < 0.0, first.z < 0.0];
    // Rays that miss the union of the root's children's boxes miss every child: with the node
    // test's operations (`q * dir_inv + origin`, the same max/min, `<=`) on the union's planes,
    // and IEEE rounding monotone, the union's interval holds each child's for every ray. Most
    // camera packets of a small object miss it all: they end here, without the rest of the
    // setup or the root's test per ray, with the same (no) hits.
    if let (Some(root), Some(union)) = (bvh.nodes.first(), accel.root_union) {
        let extent = root.compute_extent();
        let root_p = Vec3A::from(root.p);
        let mut near = [zero; 3];
        let mut far = [zero; 3];
        for a in 0..3 {
            let dir_inv = zero.splat(extent[a]) * inv_direction[a];
            let origin = (zero.splat(root_p[a]) - o[a]) * inv_direction[a];
            let [lo, hi] = union[a];
            let (n, f) = if negative[a] { (hi, lo) } else { (lo, hi) };
            near[a] = zero.splat(n) * dir_inv + origin;
            far[a] = zero.splat(f) * dir_inv + origin;
        }
        if avx2.box_hits(&near, &far, avx2.f32x8(&t_max)) & active == 0 {
            return true;
        }
    }
    // `RayShear::new(o, d)`.
    let (dx, dy, dz) = (d[KX], d[KY], d[KZ]);
    let p = PacketRays::<KX, KY, KZ> {
        origin: o,
        inv_direction,
        shear_o: [o[KX], o[KY], o[KZ]],
        shear_s: [-dx / dz, -dy / dz],
        shear_sz: zero.splat(1.0) / dz,
        rays,
        negative,
        // obvhs' `ray_get_octant_inv4`, low byte.
        oct_inv4: u32::from(!(first.x < 0.0)) << 2 | u32::from(!(first.y < 0.0)) << 1 | u32::from(!(first.z < 0.0)),
    };
    let mut best = PacketBest { t: avx2.f32x8(&t_max), b1: zero, b2: zero, slot: zero, found: 0 };
    // The counting traversal is a copy of its own: the other counts nothing, at no cost.
    let traced = if stats.count {
        packet_traverse::<ANY, true, KX, KY, KZ>(avx2, accel, bvh, &p, active, &mut t_max, &mut best, stats)
    } else {
        packet_traverse::<ANY, false, KX, KY, KZ>(avx2, accel, bvh, &p, active, &mut t_max, &mut best, stats)
    };
    if !traced {
        return false;
    }
    if best.found == 0 {
        return true;
    }
    let (b1, b2, tri) = (best.b1.to_array(), best.b2.to_array(), best.slot.to_array());
    for (i, &slot) in slots.iter().enumerate().take(n) {
        if best.found & (1 << i) != 0
            && let Some(h) = hits.get_mut(slot as usize)
        {
            // `ANY`: only whether there is a hit is read (its lanes keep no best).
            *h = Some(if ANY {
                BLOCKED
            } else {
                Hit { t: t_max[i], prim: accel.prim_ids[tri[i].to_bits() as usize], b1: b1[i], b2: b2[i] }
            });
        }
    }
    true
}

/// A packet's closest hits so far, in lanes: each lane's `t_max` (its hit's distance where it
/// has one), barycentrics and triangle slot (as bits), and the lanes that have a hit. Updated
/// by blends: lane values written one at a time and read back as lanes wait on the stores.
#[cfg(target_arch = "x86_64")]
struct PacketBest {
    t: super::wide::F32x8,
    b1: super::wide::F32x8,
    b2: super::wide::F32x8,
    slot: super::wide::F32x8,
    found: u32,
}

/// Transposes the 8 x 8 bit matrix whose row `r` is byte `r` of `x` (column `c`: bit `c` of the
/// byte): byte `c` of the result holds bit `c` of every row, row `r` as bit `r` (Hacker's
/// Delight's `transpose8`, three rounds of block swaps).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn transpose_bits8(mut x: u64) -> u64 {
    let t = (x ^ (x >> 7)) & 0x00AA_00AA_00AA_00AA;
    x ^= t ^ (t << 7);
    let t = (x ^ (x >> 14)) & 0x0000_CCCC_0000_CCCC;
    x ^= t ^ (t << 14);
    let t = (x ^ (x >> 28)) & 0x0000_0000_F0F0_F0F0;
    x ^ t ^ (t << 28)
}

/// Bit `c` set where byte `c` of `x` is not zero: each byte's bits folded onto its lowest, then
/// the 8 lowest bits gathered into the top byte by one multiplication (every partial product
/// lands on a bit of its own, so nothing carries).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn nonzero_bytes(x: u64) -> u32 {
    let mut any = x | (x >> 4);
    any |= any >> 2;
    any |= any >> 1;
    ((any & 0x0101_0101_0101_0101).wrapping_mul(0x0102_0408_1020_4080) >> 56) as u32
}

/// Entries of a packet's traversal stack: a node and the packet's rays that visit it.
const PACKET_STACK: usize = 96;

/// The traversal of [`trace_packet`]: updates each lane's `t_max` and best hit (slot and
/// barycentrics); `ANY`: a lane leaves the packet at its first hit. No closures inside (see
/// `Sheared::new`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn packet_traverse<const ANY: bool, const COUNT: bool, const KX: usize, const KY: usize, const KZ: usize>(
    avx2: Avx2,
    accel: &Accel,
    bvh: &CwBvh,
    p: &PacketRays<'_, KX, KY, KZ>,
    active: u32,
    t_max: &mut [f32; PACKET],
    best: &mut PacketBest,
    stats: &mut PacketStats,
) -> bool {
    let l = p.shear_sz;
    let oct = p.oct_inv4 & 0x7;
    let stack = &mut stats.stack;
    // The root is visited by every ray (obvhs tests no box for it).
    stack[0] = (0, active);
    let mut len = 1;
    // `ANY`: the lanes that met something (each stops there).
    let mut done = 0u32;
    while len > 0 {
        len -= 1;
        let (index, rays) = stack[len];
        let rays = rays & !done;
        if rays == 0 {
            continue;
        }
        let Some(node) = bvh.nodes.get(index as usize) else { continue };
        let extent = node.compute_extent();
        let node_p = Vec3A::from(node.p);
        // Each ray's `extent * inv_direction` and `(p - origin) * inv_direction`, as the
        // single-ray node test makes them, computed in lanes.
        let mut dir_inv = [[0.0f32; PACKET]; 3];
        let mut origin = [[0.0f32; PACKET]; 3];
        for a in 0..3 {
            dir_inv[a] = (l.splat(extent[a]) * p.inv_direction[a]).to_array();
            origin[a] = ((l.splat(node_p[a]) - p.origin[a]) * p.inv_direction[a]).to_array();
        }
        let q = [
            (avx2.bytes_f32x8(&node.child_min_x), avx2.bytes_f32x8(&node.child_max_x)),
            (avx2.bytes_f32x8(&node.child_min_y), avx2.bytes_f32x8(&node.child_max_y)),
            (avx2.bytes_f32x8(&node.child_min_z), avx2.bytes_f32x8(&node.child_max_z)),
        ];
        let mut near = [l; 3];
        let mut far = [l; 3];
        for a in 0..3 {
            (near[a], far[a]) = if p.negative[a] { (q[a].1, q[a].0) } else { (q[a].0, q[a].1) };
        }
        // The single-ray node test for each ray that reached the node (its 8 children in lanes,
        // the same bits): row `r` (byte `r`) holds the children ray `r` hits; transposed, byte
        // `c` holds the rays that hit child `c`.
        let mut rows = 0u64;
        let mut todo = rays & 0xff;
        while todo != 0 {
            let r = todo.trailing_zeros() as usize & (PACKET - 1);
            todo &= todo - 1;
            let d = [dir_inv[0][r], dir_inv[1][r], dir_inv[2][r]];
            let o = [origin[0][r], origin[1][r], origin[2][r]];
            rows |= u64::from(avx2.child_box_hits(&near, &far, d, o, t_max[r])) << (8 * r);
        }
        let by_child = transpose_bits8(rows);
        // Rays per leaf triangle (by offset from the node's first primitive) and inner children
        // (priority, node index, rays).
        let mut prim_rays = [0u8; 24];
        let mut prims = 0u32;
        let mut inner = [(0u32, 0u32, 0u32); 8];
        let mut inner_len = 0;
        // Only the children some ray hits.
        let mut hit_children = nonzero_bytes(by_child);
        while hit_children != 0 {
            let child = hit_children.trailing_zeros() as usize & 7;
            hit_children &= hit_children - 1;
            let meta = node.child_meta[child];
            if meta == 0 {
                continue;
            }
            let hit = (by_child >> (8 * child)) as u32 & 0xff;
            if node.imask & (1 << child) == 0 {
                let first = usize::from(meta & 0b1_1111);
                for k in 0..(meta >> 5).count_ones() as usize {
                    if let Some(r) = prim_rays.get_mut(first + k) {
                        *r |= hit as u8;
                        prims |= 1 << (first + k);
                    }
                }
            } else {
                let slot = u32::from(meta & 0b1_1111).wrapping_sub(24) & 0x7;
                let below = u32::from(node.imask) & ((1 << slot) - 1);
                inner[inner_len] = (slot ^ oct, node.child_base_idx + below.count_ones(), hit);
                inner_len += 1;
            }
        }
        // The node's leaf triangles, highest slot first.
        while prims != 0 {
            let offset = 31 - prims.leading_zeros() as usize;
            prims &= !(1 << offset);
            let rays = u32::from(prim_rays[offset]) & !done;
            if rays == 0 {
                continue;
            }
            let slot = node.primitive_base_idx + offset as u32;
            if COUNT {
                stats.tests += 1;
                stats.lanes += rays.count_ones();
            }
            let changed = packet_triangle::<ANY, KX, KY, KZ>(avx2, accel, p, slot, rays, t_max, best);
            if ANY {
                done |= changed;
                if done == active {
                    return true;
                }
            }
        }
        // Inner children: the highest priority is visited next (pushed last). `ANY`: in any
        // order (whether a ray meets something before its fixed `t_max` does not depend on it).
        if !ANY {
            inner[..inner_len].sort_unstable_by_key(|c| c.0);
        }
        if len + inner_len > PACKET_STACK {
            return false;
        }
        for &(_, child, rays) in &inner[..inner_len] {
            stack[len] = (child, rays);
            len += 1;
        }
    }
    true
}

/// The watertight test of the triangle in `slot` against the packet's `rays` (lane bits): each
/// hit before its lane's `t_max` becomes the lane's best and its `t_max` (in `best`, and in
/// `t_max`, which the node tests read per ray). Returns the lanes hit. `ANY`: a hit lane is
/// done, so its best is not kept (nor, in the traversal, the order of a node's inner children,
/// nor its hit's triangle at the end): on an AVX2-only AMD EPYC (Zen 3), `tiny` 415.6M ->
/// 414.4M instructions, `tiny long` 0.993x the time (median of 15 interleaved pairs).
///
/// Tried there and dropped: lanes inside the edges compared with their `t_max` on the scaled
/// distance (no division) before the rest of the test, which then ran only where some lane was
/// still before its `t_max`: `tiny` 414.4M -> 417.6M instructions, `tiny long` 1.003x (11
/// pairs). In the Cornell box most lanes inside a triangle's edges do hit it before their
/// `t_max` (the packets tested 3.1 rays per triangle test, 3.9 triangle tests per ray).
///
/// Tried on an Intel Xeon with AVX-512 and dropped: a node's leaf triangles two at a time in
/// 16 lanes (an `F32x16` over `math::Real`: lanes 0..8 the first triangle against the packet's
/// rays, 8..16 the next; the test reads no `t_max`, so each half is this test's candidate, the
/// first's hits taken before the second's). The Cornell box's packets make 8.2 triangle tests
/// each (0.76 packets, 6.2 tests per sample), most of which pair up, but `tiny long` took 1.017x
/// the time (median of 11 interleaved pairs, quartiles 1.012-1.019), `tiny large long` 0.998x
/// (7 pairs): on this CPU 512-bit operations issue on two ports where 256-bit ones have three,
/// and a 16-lane division costs two 8-lane ones, so the halved instruction count bought no
/// time.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn packet_triangle<const ANY: bool, const KX: usize, const KY: usize, const KZ: usize>(
    avx2: Avx2,
    accel: &Accel,
    p: &PacketRays<'_, KX, KY, KZ>,
    slot: u32,
    rays: u32,
    t_max: &mut [f32; PACKET],
    best: &mut PacketBest,
) -> u32 {
    let Some(v) = accel.tris.get(slot as usize) else { return 0 };
    let l = p.shear_sz;
    let splat = [
        [l.splat(v[0][KX]), l.splat(v[0][KY]), l.splat(v[0][KZ])],
        [l.splat(v[1][KX]), l.splat(v[1][KY]), l.splat(v[1][KZ])],
        [l.splat(v[2][KX]), l.splat(v[2][KY]), l.splat(v[2][KZ])],
    ];
    let s = Sheared::new(p.shear_o, p.shear_s, splat);
    let e = s.edges();
    let redo = any_zero(e).bits() & rays;
    // Most tests end here, every lane outside an edge: before the rest of the test (its
    // division and error bounds), which `candidate` makes only where some lane may pass.
    if redo == 0 && inside_edges(e).bits() & rays == 0 {
        return 0;
    }
    let c = s.candidate(e, p.shear_sz);
    // `hits_before` holds `t < t_max`: each such lane's hit is its new best.
    let hit_lanes = c.hits_before(best.t) & l.mask_of_bits(rays & !redo);
    let hits = hit_lanes.bits();
    if hits | redo == 0 {
        return 0;
    }
    // `ANY`: a lane hit is done (only `found` is read of its best).
    if ANY && redo == 0 {
        best.found |= hits;
        return hits;
    }
    if hits != 0 {
        let slot_lanes = F32x8::from_bits(l.int(slot as i32));
        best.t = F32x8::select(hit_lanes, c.t, best.t);
        best.b1 = F32x8::select(hit_lanes, c.b1, best.b1);
        best.b2 = F32x8::select(hit_lanes, c.b2, best.b2);
        best.slot = F32x8::select(hit_lanes, slot_lanes, best.slot);
        best.found |= hits;
        *t_max = best.t.to_array();
    }
    if redo == 0 {
        return hits;
    }
    // Lanes on an edge take the scalar test's double-precision fallback, one at a time (rare).
    let (mut b1, mut b2, mut tri) = (best.b1.to_array(), best.b2.to_array(), best.slot.to_array());
    let mut todo = redo;
    let mut changed = hits;
    while todo != 0 {
        let lane = todo.trailing_zeros() as usize & (PACKET - 1);
        todo &= todo - 1;
        // A lane in `rays` has a ray of its own.
        let Some(r) = p.rays.get(lane) else { continue };
        let shear = RayShear::<KX, KY, KZ>::new(r.o, r.d);
        if let Some((t, hb1, hb2)) = accel.test_slot(&shear, slot as usize, t_max[lane], 0.0)
            && t < t_max[lane]
        {
            (t_max[lane], b1[lane], b2[lane], tri[lane]) = (t, hb1, hb2, f32::from_bits(slot));
            changed |= 1 << lane;
        }
    }
    (best.t, best.b1, best.b2, best.slot) = (avx2.f32x8(t_max), avx2.f32x8(&b1), avx2.f32x8(&b2), avx2.f32x8(&tri));
    best.found |= changed;
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A state restarted in place (after a traversal left it anywhere) is obvhs' fresh one,
    /// for directions of every octant, with zeros of both signs.
    #[test]
    fn a_restarted_traversal_is_a_fresh_one() {
        let accel = Accel::new(&cube());
        let bvh = accel.bvh.as_ref().expect("a BVH");
        let mut state = Traversal::default();
        for &x in &[1.0f32, -1.0, 0.0, -0.0] {
            for &y in &[0.5f32, -0.5, 0.0, -0.0] {
                for &z in &[2.0f32, -2.0, 0.0, -0.0] {
                    let d = Vec3A::new(x, y, z);
                    // Leave the state dirty, as a traversal ended early does.
                    state.stack.push(UVec2::new(7, 9));
                    state.current_group = UVec2::new(3, 0x0100_0000);
                    state.primitive_group = UVec2::new(5, 6);
                    state.primitive_id = 11;
                    state.hitmask = 12;
                    restart(&mut state, bvh, d);
                    let fresh = bvh.new_traversal(d);
                    assert!(state.stack.is_empty(), "{d}");
                    assert_eq!(state.current_group, fresh.current_group, "{d}");
                    assert_eq!(state.primitive_group, fresh.primitive_group, "{d}");
                    assert_eq!(state.oct_inv4, fresh.oct_inv4, "{d}");
                    assert_eq!(
                        state.traversal_direction.to_array().map(f32::to_bits),
                        fresh.traversal_direction.to_array().map(f32::to_bits)
                    );
                    assert_eq!((state.primitive_id, state.hitmask), (fresh.primitive_id, fresh.hitmask), "{d}");
                }
            }
        }
    }

    /// `nonzero_bytes` sets exactly the bits of the bytes that hold a bit.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn nonzero_bytes_finds_each_byte_with_a_bit() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..100_000 {
            x = x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            // Random bytes, many of them zero, and single high or low bits.
            let v = x & (x >> 7) & (x >> 13);
            for v in [v, v & 0x8080_8080_8080_8080, v & 0x0101_0101_0101_0101, x] {
                let want = (0..8).fold(0u32, |m, c| m | (u32::from((v >> (8 * c)) & 0xff != 0) << c));
                assert_eq!(nonzero_bytes(v), want, "{v:#018x}");
            }
        }
        assert_eq!(nonzero_bytes(0), 0);
        assert_eq!(nonzero_bytes(u64::MAX), 0xff);
    }

    /// `transpose_bits8` moves bit `c` of byte `r` to bit `r` of byte `c`, for every bit.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn bit_matrix_transpose_moves_each_bit() {
        for r in 0..8 {
            for c in 0..8 {
                assert_eq!(transpose_bits8(1 << (8 * r + c)), 1 << (8 * c + r), "row {r} column {c}");
            }
        }
        let x = 0x0123_4567_89ab_cdefu64;
        assert_eq!(transpose_bits8(transpose_bits8(x)), x);
    }

    /// A closed cube [-1, 1]^3 of 12 triangles.
    fn cube() -> Vec<[Vec3A; 3]> {
        let v = |x: f32, y: f32, z: f32| Vec3A::new(x, y, z);
        let c = [
            v(-1., -1., -1.),
            v(1., -1., -1.),
            v(1., 1., -1.),
            v(-1., 1., -1.),
            v(-1., -1., 1.),
            v(1., -1., 1.),
            v(1., 1., 1.),
            v(-1., 1., 1.),
        ];
        let quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [3, 7, 6, 2], [0, 4, 7, 3], [1, 2, 6, 5]];
        quads.iter().flat_map(|q| [[c[q[0]], c[q[1]], c[q[2]]], [c[q[0]], c[q[2]], c[q[3]]]]).collect()
    }

    /// The number of levels of the wide BVH (1 for a root alone), counted without recursion.
    fn bvh_depth(accel: &Accel) -> usize {
        let Some(bvh) = &accel.bvh else { return 0 };
        let mut deepest = 0;
        let mut stack = vec![(0usize, 1usize)];
        while let Some((i, depth)) = stack.pop() {
            deepest = deepest.max(depth);
            let node = &bvh.nodes[i];
            for ch in 0..8 {
                if node.imask & (1 << ch) != 0 {
                    stack.push((node.child_node_index(ch) as usize, depth + 1));
                }
            }
        }
        deepest
    }

    /// 70,000 copies of one triangle: every box tied in PLOC's costs, which once chained them
    /// 70,000 deep (minutes of build, then a stack overflow converting the chain: a worker
    /// killed by a degenerate scene). The build's boxes, padded apart, make a shallow tree.
    #[test]
    fn coincident_triangles_build_a_shallow_bvh() {
        let t = [Vec3A::new(-1.0, -1.0, 2.0), Vec3A::new(1.0, -1.0, 2.0), Vec3A::new(0.0, 1.0, 2.0)];
        let accel = Accel::new(&vec![t; 70_000]);
        let depth = bvh_depth(&accel);
        assert!(depth <= 32, "depth {depth}");
        let hit = accel.intersect(Vec3A::ZERO, Vec3A::Z, f32::INFINITY).expect("a hit");
        assert_eq!(hit.t, 2.0);
        assert!(hit.prim < 70_000);
        assert!(accel.occluded(Vec3A::ZERO, Vec3A::Z, 3.0));
        // A mesh scaled to nothing: 70,000 triangles collapsed onto one point, boxes of no size.
        let point = [Vec3A::new(0.5, 0.5, 0.5); 3];
        let depth = bvh_depth(&Accel::new(&vec![point; 70_000]));
        assert!(depth <= 32, "depth {depth}");
    }

    /// 100,000 triangles evenly spaced in a row, all with the same build pad (their largest
    /// coordinate is the same z), build in well under a minute. Each build box's union with its
    /// left and right neighbour then had exactly the same area, and PLOC (ties broken toward
    /// the rightmost) paired about one node per pass: 16,000 such triangles took 5 s, 32,000
    /// 19 s, 50,000 over 20 s (a hung worker for a large scene). With every box spread, 32,000
    /// take 0.05 s.
    #[test]
    fn triangles_evenly_spaced_in_a_row_build_quickly() {
        let (n, spacing, z) = (100_000, 0.0625, 8192.0);
        let tris: Vec<[Vec3A; 3]> = (0..n)
            .map(|i| {
                let x = i as f32 * spacing;
                [Vec3A::new(x, 0.0, z), Vec3A::new(x + 0.5 * spacing, 0.0, z), Vec3A::new(x, 1.0, z)]
            })
            .collect();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let accel = Accel::new(&tris);
            let hit = accel.intersect(Vec3A::new(1000.0 * spacing + 0.01, 0.1, z + 1.0), -Vec3A::Z, f32::INFINITY);
            tx.send(hit.map(|h| (h.prim, h.t))).ok();
        });
        // A hang guard, not a performance target: the build takes well under a second.
        let hit = rx.recv_timeout(std::time::Duration::from_secs(60)).expect("the build finishes within 60 s");
        assert_eq!(hit, Some((1000, 1.0)));
    }

    #[test]
    fn closest_hit_and_barycentrics() {
        let accel = Accel::new(&cube());
        let hit = accel.intersect(Vec3A::new(0.25, 0.5, 5.0), Vec3A::new(0.0, 0.0, -1.0), f32::INFINITY).expect("hit");
        assert!((hit.t - 4.0).abs() < 1e-5, "{hit:?}");
        let tri = cube()[hit.prim as usize];
        let p = tri[0] * (1.0 - hit.b1 - hit.b2) + tri[1] * hit.b1 + tri[2] * hit.b2;
        assert!((p - Vec3A::new(0.25, 0.5, 1.0)).length() < 1e-5, "{p}");
        assert!(accel.intersect(Vec3A::new(3.0, 0.0, 5.0), Vec3A::new(0.0, 0.0, -1.0), f32::INFINITY).is_none());
        assert!(accel.intersect(Vec3A::new(0.0, 0.0, 5.0), Vec3A::new(0.0, 0.0, -1.0), 3.9).is_none());
    }

    /// A ray through the edge two triangles share hits both at the same t: the reported
    /// triangle's barycentrics are its own (they were the other one's when it was tested
    /// second), at every SIMD level and in the reference traversal.
    #[test]
    fn a_tie_on_a_shared_edge_keeps_the_winners_barycentrics() {
        let tris = vec![
            [Vec3A::new(0.0, 0.0, 0.0), Vec3A::new(1.0, 0.0, 0.0), Vec3A::new(0.0, 1.0, 0.0)],
            [Vec3A::new(1.0, 0.0, 0.0), Vec3A::new(1.0, 1.0, 0.0), Vec3A::new(0.0, 1.0, 0.0)],
        ];
        let mut accel = Accel::new(&tris);
        for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
            accel.set_simd_level(level);
            for k in 1..16 {
                let target = tris[0][1].lerp(tris[0][2], k as f32 / 16.0);
                let (o, d) = (target + Vec3A::Z, -Vec3A::Z);
                for hit in [accel.intersect(o, d, f32::INFINITY), reference_intersect(&accel, o, d, f32::INFINITY)] {
                    let hit = hit.expect("hit");
                    let tri = tris[hit.prim as usize];
                    let p = tri[0] * (1.0 - hit.b1 - hit.b2) + tri[1] * hit.b1 + tri[2] * hit.b2;
                    assert!((p - target).length() < 1e-5, "{level:?} k {k}: {hit:?} gives {p}, the ray hits {target}");
                }
            }
        }
    }

    #[test]
    fn rays_through_edges_and_vertices_never_slip_through() {
        // From inside the closed cube, every ray must hit it: aim at every vertex, at points along
        // every edge (including the diagonals shared by the two triangles of a face) from many
        // origins.
        let tris = cube();
        let accel = Accel::new(&tris);
        let mut targets = Vec::new();
        for t in &tris {
            for i in 0..3 {
                let (a, b) = (t[i], t[(i + 1) % 3]);
                for k in 0..=16 {
                    targets.push(a.lerp(b, k as f32 / 16.0));
                }
            }
        }
        let origins = [
            Vec3A::ZERO,
            Vec3A::new(0.3, -0.2, 0.1),
            Vec3A::new(-0.9, 0.9, -0.9),
            Vec3A::new(0.123, 0.456, -0.789),
            Vec3A::new(1e-3, 0.0, 0.999),
        ];
        let mut rays = 0;
        for o in origins {
            for &p in &targets {
                let d = (p - o).normalize();
                assert!(accel.intersect(o, d, f32::INFINITY).is_some(), "ray from {o} to {p} slipped through");
                assert!(accel.occluded(o, d, f32::INFINITY));
                rays += 1;
            }
        }
        assert!(rays > 1000);
    }

    #[test]
    fn shadow_rays_respect_t_max() {
        let accel = Accel::new(&cube());
        let o = Vec3A::ZERO;
        let d = Vec3A::X;
        assert!(accel.occluded(o, d, 1.5));
        assert!(!accel.occluded(o, d, 0.5));
        assert!(!Accel::new(&[]).occluded(o, d, 10.0));
    }

    /// Axis-aligned rays whose other components are -0.0 (what an orthographic camera looking
    /// down -Z makes) hit, like those with +0.0: they used to miss everything.
    #[test]
    fn axis_aligned_rays_with_negative_zeros_hit() {
        let accel = Accel::new(&cube());
        for d in [Vec3A::new(-0.0, -0.0, -1.0), Vec3A::new(0.0, 0.0, -1.0), Vec3A::new(-1.0, -0.0, 0.0)] {
            // From 5 units back through (0.3, 0.2, 0.1) to the face of [-1, 1]^3 it meets.
            let p = Vec3A::new(0.3, 0.2, 0.1);
            let o = p - d * 5.0;
            let expected = 5.0 - (1.0 + p.dot(d));
            let hit = accel.intersect(o, d, f32::INFINITY).map(|h| h.t);
            assert!(hit.is_some_and(|t| (t - expected).abs() < 1e-5), "{d}: {hit:?}, expected {expected}");
            assert!(accel.occluded(o, d, 10.0), "{d}");
        }
    }

    /// A triangle sweeping from x in [-1, 0] to x in [2, 3] during the shutter: rays at its
    /// place at time u hit, at its place at other times miss (the swept BVH box is not a hit).
    #[test]
    fn moving_triangles_are_hit_where_they_are_at_the_ray_time() {
        let v = |x: f32, y: f32| Vec3A::new(x, y, 0.0);
        let open = [[v(-1.0, 0.0), v(0.0, 0.0), v(-1.0, 1.0)]];
        let close = [[v(2.0, 0.0), v(3.0, 0.0), v(2.0, 1.0)]];
        let accel = Accel::new_moving(&open, &close);
        let d = Vec3A::new(0.0, 0.0, -1.0);
        for u in [0.0f32, 0.25, 0.5, 1.0] {
            let x = -0.75 + 3.0 * u;
            let o = Vec3A::new(x, 0.2, 5.0);
            assert!(accel.intersect_at(o, d, f32::INFINITY, u).is_some_and(|h| (h.t - 5.0).abs() < 1e-5), "u {u}");
            assert!(accel.occluded_at(o, d, 10.0, u), "u {u}");
            let other = if u < 0.5 { u + 0.5 } else { u - 0.5 };
            assert!(accel.intersect_at(o, d, f32::INFINITY, other).is_none(), "u {u} at time {other}");
        }
    }

    /// A soup of random triangles in [-2, 2]^3 and the cube, static or moving.
    fn soup(n: u64, seed: u64) -> Vec<[Vec3A; 3]> {
        use crate::render::wide::unit;
        let mut tris = cube();
        for i in 0..n {
            let r = |k: u64| unit((seed * 1_000_003 + i) * 16 + k);
            let c = Vec3A::new(r(0), r(1), r(2)) * 4.0 - 2.0;
            let e = |k: u64| Vec3A::new(r(k) - 0.5, r(k + 1) - 0.5, r(k + 2) - 0.5) * 0.6;
            tris.push([c, c + e(3), c + e(6)]);
        }
        tris
    }

    /// The old query (obvhs' own `ray_traverse`): the kernels must give its hits exactly, so
    /// images stay what they were.
    fn reference_intersect(accel: &Accel, o: Vec3A, d: Vec3A, t_max: f32) -> Option<Hit> {
        let bvh = accel.bvh.as_ref()?;
        let shear = RayShear::<0, 1, 2>::new(o, d);
        let run = |shear: &dyn Fn(usize, f32) -> Option<(f32, f32, f32)>| {
            let mut hit = obvhs::ray::RayHit::none();
            let mut best = (0.0f32, 0.0f32);
            let found = bvh.ray_traverse(Ray::new(o, bvh_direction(d), 0.0, t_max), &mut hit, |r, slot| {
                match shear(slot, r.tmax) {
                    Some((t, b1, b2)) if t < r.tmax => {
                        best = (b1, b2);
                        t
                    }
                    _ => f32::INFINITY,
                }
            });
            found.then(|| Hit { t: hit.t, prim: accel.prim_ids[hit.primitive_id as usize], b1: best.0, b2: best.1 })
        };
        match dominant_axis(d) {
            0 => {
                let s = RayShear::<1, 2, 0>::new(o, d);
                run(&|slot, t| accel.test_slot(&s, slot, t, 0.0))
            }
            1 => {
                let s = RayShear::<2, 0, 1>::new(o, d);
                run(&|slot, t| accel.test_slot(&s, slot, t, 0.0))
            }
            _ => run(&|slot, t| accel.test_slot(&shear, slot, t, 0.0)),
        }
    }

    /// The 8-wide triangle test (where the CPU has AVX2) gives the one-at-a-time test's hits
    /// bit for bit where it matters most: rays through the shared edges and vertices of a
    /// tessellated, bumpy grid (zero edge functions, which take the scalar double-precision
    /// fallback; ties between neighbours, which the visiting order decides), with `t_max` cut
    /// right at and just past the surface.
    #[test]
    fn lane_wise_triangle_tests_match_one_at_a_time_on_edges_and_vertices() {
        let n = 24;
        let height = |i: usize, j: usize| ((i * 7 + j * 13) % 5) as f32 * 0.01;
        let v = |i: usize, j: usize| Vec3A::new(i as f32 / n as f32, j as f32 / n as f32, height(i, j));
        let mut tris = Vec::new();
        for i in 0..n {
            for j in 0..n {
                tris.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                tris.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        let (mut base, mut wide) = (Accel::new(&tris), Accel::new(&tris));
        base.set_simd_level(SimdLevel::Baseline);
        if wide.set_simd_level(SimdLevel::Avx2) != SimdLevel::Avx2 {
            eprintln!("this CPU has no AVX2: nothing to compare");
            return;
        }
        let mut targets = Vec::new();
        for t in &tris {
            for k in 0..3 {
                targets.extend([t[k], t[k].lerp(t[(k + 1) % 3], 0.5), t[k].lerp(t[(k + 1) % 3], 0.25)]);
            }
        }
        let origins = [Vec3A::new(0.5, 0.5, 2.0), Vec3A::new(-0.3, 0.2, 0.7), Vec3A::new(0.25, 0.75, -1.0)];
        let (mut hits, mut rays) = (0, 0);
        for o in origins {
            for &p in &targets {
                let d = (p - o).normalize();
                let at = (p - o).length();
                for t_max in [f32::INFINITY, at, at * 1.000_001, at * 0.5] {
                    let want = base.intersect(o, d, t_max);
                    assert_eq!(bits(wide.intersect(o, d, t_max)), bits(want), "ray {o} to {p}, t_max {t_max}");
                    assert_eq!(wide.occluded(o, d, t_max), base.occluded(o, d, t_max), "ray {o} to {p}, t_max {t_max}");
                    hits += usize::from(want.is_some());
                    rays += 1;
                }
            }
        }
        // Rays in the plane of the grid's flat triangles (z = 0): edge functions of zero.
        for k in 0..200 {
            let (y, angle) = (k as f32 / 200.0, (k % 7) as f32 * 0.1 - 0.3);
            let (o, d) = (Vec3A::new(-0.5, y, 0.0), Vec3A::new(angle.cos(), angle.sin(), 0.0));
            let want = base.intersect(o, d, f32::INFINITY);
            assert_eq!(bits(wide.intersect(o, d, f32::INFINITY)), bits(want), "ray {o} {d}");
            assert_eq!(wide.occluded(o, d, f32::INFINITY), base.occluded(o, d, f32::INFINITY), "ray {o} {d}");
        }
        assert!(hits > rays / 3, "{hits} of {rays} rays hit");
    }

    /// Coherent rays traced as packets (`intersect_many`) get the single-ray hits bit for bit
    /// (and `occluded_many`, one by one, the same blocked or not):
    /// camera-like bundles through a soup of triangles and through the vertices and edges of a
    /// bumpy grid (ties and zero edge functions), with finite and infinite `t_max`, full and
    /// partial packets, and bundles that break up (mixed octants).
    #[test]
    fn packets_of_coherent_rays_get_the_single_ray_hits() {
        use crate::render::wide::unit;
        let n = 16;
        let height = |i: usize, j: usize| ((i * 7 + j * 13) % 5) as f32 * 0.01;
        let v = |i: usize, j: usize| Vec3A::new(i as f32 / n as f32, j as f32 / n as f32, height(i, j));
        let mut tris = soup(2000, 7);
        for i in 0..n {
            for j in 0..n {
                tris.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                tris.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        let mut accel = Accel::new(&tris);
        for level in packet_levels() {
            accel.set_simd_level(level);
            let mut batches = Vec::new();
            for b in 0..400u64 {
                let r = |k: u64| unit(b * 64 + k) * 2.0 - 1.0;
                let o = Vec3A::new(r(0), r(1), r(2)) * 3.0;
                let center = Vec3A::new(r(3), r(4), r(5));
                let spread = [0.0, 1e-3, 0.05, 0.5][(b % 4) as usize];
                let len = 1 + (b % 11) as usize * 3;
                batches.push(
                    (0..len as u64)
                        .map(|k| {
                            let j = |m: u64| (unit(b * 4096 + k * 8 + m) - 0.5) * spread;
                            let t_max = if k % 3 == 0 { 2.0 + unit(b * 4096 + k * 8 + 7) } else { f32::INFINITY };
                            RayQuery { o, d: center + Vec3A::new(j(0), j(1), j(2)), t_max, time: 0.0 }
                        })
                        .collect::<Vec<_>>(),
                );
            }
            // Bundles from one point through the grid's vertices and edge midpoints, row by row.
            for o in [Vec3A::new(0.5, 0.5, 2.0), Vec3A::new(0.3, 0.6, -1.5)] {
                for i in 0..=n {
                    batches.push(
                        (0..=n)
                            .flat_map(|j| {
                                let p = v(i, j);
                                let q = v(i.min(n - 1) + 1, j).lerp(p, 0.5);
                                [p - o, q - o]
                            })
                            .map(|d| RayQuery { o, d, t_max: f32::INFINITY, time: 0.0 })
                            .collect(),
                    );
                }
            }
            let (mut hits, mut total) = (0, 0);
            let (mut got, mut blocked) = (Vec::new(), Vec::new());
            for rays in &batches {
                accel.intersect_many(rays, &mut got);
                accel.occluded_many(rays, &mut blocked);
                assert_eq!((got.len(), blocked.len()), (rays.len(), rays.len()));
                for ((r, h), b) in rays.iter().zip(&got).zip(&blocked) {
                    let want = accel.intersect_at(r.o, r.d, r.t_max, r.time);
                    assert_eq!(bits(*h), bits(want), "ray {} {} {}", r.o, r.d, r.t_max);
                    assert_eq!(*b, accel.occluded_at(r.o, r.d, r.t_max, r.time), "ray {} {} {}", r.o, r.d, r.t_max);
                    hits += usize::from(want.is_some());
                    total += 1;
                }
            }
            assert!(hits > total / 4 && hits < total, "{hits} of {total} rays hit");
            // A fine flat grid alone (a deep tree): rays through its vertices, which 6 triangles in
            // different subtrees share, so the order of the visit decides every tie.
            let m = 64;
            let w = |i: usize, j: usize| Vec3A::new(i as f32 / m as f32, j as f32 / m as f32, 0.0);
            let mut grid = Vec::new();
            for i in 0..m {
                for j in 0..m {
                    grid.push([w(i, j), w(i + 1, j), w(i + 1, j + 1)]);
                    grid.push([w(i, j), w(i + 1, j + 1), w(i, j + 1)]);
                }
            }
            let mut accel = Accel::new(&grid);
            accel.set_simd_level(level);
            for o in [Vec3A::new(0.5, 0.5, 1.0), Vec3A::new(0.1, 0.8, 0.3)] {
                for i in 0..=m {
                    let rays: Vec<_> =
                        (0..=m).map(|j| RayQuery { o, d: w(i, j) - o, t_max: f32::INFINITY, time: 0.0 }).collect();
                    accel.intersect_many(&rays, &mut got);
                    for (r, h) in rays.iter().zip(&got) {
                        assert_eq!(bits(*h), bits(accel.intersect(r.o, r.d, r.t_max)), "ray {} {}", r.o, r.d);
                    }
                }
            }
        }
    }

    /// Packets of a small object's camera rays that miss it, graze it or hit it: packets whose
    /// rays all miss the union of the root's children's boxes end before the traversal (see
    /// `trace_packet`). Rays aimed at the corners and edges of the object's bounds, a few ulps
    /// inside and outside, from near and from far (1e4 times the object's size), get the
    /// single-ray hits.
    #[test]
    fn packets_that_miss_the_root_get_the_single_ray_hits() {
        let cube = cube();
        let mut accel = Accel::new(&cube);
        for level in packet_levels() {
            accel.set_simd_level(level);
            let (lo, hi) = cube
                .iter()
                .flatten()
                .fold((Vec3A::splat(f32::MAX), Vec3A::splat(f32::MIN)), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
            let nudge = |x: f32, k: i32| f32::from_bits((x.to_bits() as i32 + k) as u32);
            let (mut hits, mut misses, mut total) = (0, 0, 0);
            let mut got = Vec::new();
            for o in [Vec3A::new(0.3, -4.0, 0.7), Vec3A::new(-3.0, 2.5, 6.0), Vec3A::new(2e4, 1e4, -3e4)] {
                for corner in 0..8 {
                    let c = Vec3A::new(
                        if corner & 1 == 0 { lo.x } else { hi.x },
                        if corner & 2 == 0 { lo.y } else { hi.y },
                        if corner & 4 == 0 { lo.z } else { hi.z },
                    );
                    let mid = (c + (lo + hi) * 0.5) * 0.5;
                    for target in [c, mid, Vec3A::new(c.x, mid.y, c.z), Vec3A::new(mid.x, c.y, c.z)] {
                        // 8 rays a packet: the target nudged by -4..4 ulps per axis (and far off).
                        for step in [1, 64, 1 << 12, 1 << 20] {
                            let rays: Vec<RayQuery> = (0..8)
                                .map(|k: i32| {
                                    let p = Vec3A::new(
                                        nudge(target.x, (k - 4) * step),
                                        nudge(target.y, (3 - k) * step),
                                        nudge(target.z, (k % 3 - 1) * step),
                                    );
                                    RayQuery { o, d: p - o, t_max: f32::INFINITY, time: 0.0 }
                                })
                                .collect();
                            accel.intersect_many(&rays, &mut got);
                            for (r, h) in rays.iter().zip(&got) {
                                let want = accel.intersect_at(r.o, r.d, r.t_max, r.time);
                                assert_eq!(bits(*h), bits(want), "ray {} {}", r.o, r.d);
                                hits += usize::from(want.is_some());
                                misses += usize::from(want.is_none());
                                total += 1;
                            }
                        }
                    }
                }
            }
            assert!(hits > total / 10 && misses > total / 10, "{hits} hits and {misses} misses of {total} rays");
        }
    }

    /// Packets of the awkward rays (axis-aligned with -0 and +0 components, components of
    /// 1e-30, scales of 1e-20 and 1e20, NaN, zero and infinite directions, `t_max` of 0, finite
    /// and infinite), each ray 8 times with its neighbours' small changes: the single-ray hits.
    #[test]
    fn packets_of_awkward_rays_get_the_single_ray_hits() {
        let mut accel = Accel::new(&soup(3000, 3));
        for level in packet_levels() {
            accel.set_simd_level(level);
            let mut base = crate::render::wide::test_rays(600);
            base.push((Vec3A::ZERO, Vec3A::new(f32::NAN, 0.0, 1.0), f32::INFINITY));
            base.push((Vec3A::ZERO, Vec3A::ZERO, f32::INFINITY));
            base.push((Vec3A::ZERO, Vec3A::new(0.0, f32::INFINITY, 0.1), f32::INFINITY));
            base.push((Vec3A::new(0.1, 0.2, 5.0), -Vec3A::Z, 0.0));
            let mut got = Vec::new();
            for (o, d, t_max) in base {
                let rays: Vec<RayQuery> =
                    (0..8).map(|k| RayQuery { o: o + Vec3A::splat(k as f32 * 1e-4), d, t_max, time: 0.0 }).collect();
                accel.intersect_many(&rays, &mut got);
                for (r, h) in rays.iter().zip(&got) {
                    assert_eq!(bits(*h), bits(accel.intersect(r.o, r.d, r.t_max)), "ray {} {} {}", r.o, r.d, r.t_max);
                }
            }
        }
    }

    /// A small scene's batches go through the BVH in packets sorted by octant and dominant
    /// axis, however incoherent the rays: each ray still gets its single-ray hit (each shadow
    /// ray its single-ray answer), in its place in the batch (batches of every size around a
    /// packet's and the sorted batch's limits).
    #[test]
    fn sorted_packets_of_incoherent_rays_get_the_single_ray_hits() {
        let mut accel = Accel::new(&soup(100, 5));
        for level in packet_levels() {
            accel.set_simd_level(level);
            assert!(accel.sorted_packets(SORTED_BATCH) && !accel.sorted_packets(SORTED_BATCH + 1));
            let mut rays: Vec<RayQuery> = crate::render::wide::test_rays(700)
                .into_iter()
                .map(|(o, d, t_max)| RayQuery { o, d, t_max, time: 0.0 })
                .collect();
            // Rays from inside the cube, all ways, many of them at once in each class.
            for k in 0..300u64 {
                let u = |j: u64| crate::render::wide::unit(k * 8 + j) * 2.0 - 1.0;
                rays.push(RayQuery {
                    o: Vec3A::new(u(0), u(1), u(2)) * 0.5,
                    d: Vec3A::new(u(3), u(4), u(5)),
                    t_max: 10.0,
                    time: 0.0,
                });
            }
            // Shadow rays too: some blocked, some not (segments of every length).
            let segments: Vec<RayQuery> =
                rays.iter().enumerate().map(|(k, r)| RayQuery { t_max: (k % 7) as f32 * 0.4, ..*r }).collect();
            let mut got = Vec::new();
            let mut blocked = Vec::new();
            let (mut hit, mut shadowed) = (0, 0);
            // Up to 256 rays sorted by class; above, by class and origin octant (`ORIGIN_CELLS`).
            for len in [1, 3, 4, 8, 9, 37, 255, 256, 257, SORTED_BATCH] {
                for batch in rays.chunks(len) {
                    accel.intersect_many(batch, &mut got);
                    assert_eq!(got.len(), batch.len());
                    for (r, h) in batch.iter().zip(&got) {
                        assert_eq!(
                            bits(*h),
                            bits(accel.intersect(r.o, r.d, r.t_max)),
                            "ray {} {} {}",
                            r.o,
                            r.d,
                            r.t_max
                        );
                        hit += usize::from(h.is_some());
                    }
                }
                for batch in segments.chunks(len) {
                    accel.occluded_many(batch, &mut blocked);
                    assert_eq!(blocked.len(), batch.len());
                    for (r, b) in batch.iter().zip(&blocked) {
                        assert_eq!(*b, accel.occluded(r.o, r.d, r.t_max), "segment {} {} {}", r.o, r.d, r.t_max);
                        shadowed += usize::from(*b);
                    }
                }
            }
            let n = 10 * rays.len();
            assert!(
                hit > n / 4 && shadowed > n / 8 && shadowed < n - n / 8,
                "too one-sided to tell: {hit}, {shadowed} of {n}"
            );
        }
    }

    /// Above 256 triangles sorted packets run while they pay: on trial for their first
    /// `SORTED_TRIAL_TESTS` triangle tests, then while each serves at least 2.6 rays; each ray's
    /// hit is its single-ray hit either way (the soup's incoherent rays: sorted packets on trial,
    /// then off).
    #[test]
    fn sorted_packets_run_above_256_triangles_while_they_pay() {
        assert!(sorting_pays(SORTED_PACKET_TRIANGLES, u64::MAX / 100, 0), "small scenes always sort");
        let trial = SORTED_TRIAL_TESTS;
        assert!(sorting_pays(300, trial - 1, 0), "on trial");
        assert!(sorting_pays(300, 10 * trial, 26 * trial), "2.6 rays a test pay");
        assert!(!sorting_pays(300, 10 * trial, 26 * trial - 1), "fewer do not");
        for level in packet_levels() {
            let mut accel = Accel::new(&soup(3000, 9));
            accel.set_simd_level(level);
            assert!(accel.sorted_packets(SORTED_BATCH), "on trial at first");
            let rays: Vec<RayQuery> = (0..40_000u64)
                .map(|k| {
                    let u = |j: u64| crate::render::wide::unit(k * 8 + j) * 2.0 - 1.0;
                    RayQuery {
                        o: Vec3A::new(u(0), u(1), u(2)),
                        d: Vec3A::new(u(3), u(4), u(5)),
                        t_max: 10.0,
                        time: 0.0,
                    }
                })
                .collect();
            let mut got = Vec::new();
            let mut sorted_batches = 0;
            for batch in rays.chunks(SORTED_BATCH) {
                sorted_batches += usize::from(accel.sorted_packets(batch.len()));
                accel.intersect_many(batch, &mut got);
                for (r, h) in batch.iter().zip(&got) {
                    assert_eq!(bits(*h), bits(accel.intersect(r.o, r.d, r.t_max)), "ray {} {}", r.o, r.d);
                }
            }
            let (tests, lanes) = (accel.packet_tests.load(Relaxed), accel.packet_lanes.load(Relaxed));
            assert!(tests >= trial, "{tests} packet triangle tests");
            assert!(sorted_batches > 0 && !accel.sorted_packets(SORTED_BATCH), "{lanes} rays in {tests} tests");
        }
    }

    /// The SIMD levels with packets that this CPU has: AVX2, and AVX-512 (the same kernels
    /// compiled for x86-64-v4); none without AVX2.
    fn packet_levels() -> Vec<SimdLevel> {
        let best = SimdLevel::detect();
        if best == SimdLevel::Baseline {
            eprintln!("this CPU has no AVX2: no packets to compare");
        }
        [SimdLevel::Avx2, SimdLevel::Avx512].into_iter().filter(|&l| l <= best).collect()
    }

    fn bits(h: Option<Hit>) -> Option<(u32, u32, u32, u32)> {
        h.map(|h| (h.t.to_bits(), h.prim, h.b1.to_bits(), h.b2.to_bits()))
    }

    /// The AVX2 and AVX-512 kernels (where the CPU has them) and the baseline give the same
    /// hits, bit for bit, and the same as obvhs' traversal; for static and moving triangles.
    #[test]
    fn simd_levels_give_bit_identical_hits() {
        let tris = soup(3000, 1);
        let moved: Vec<_> = tris.iter().map(|t| t.map(|v| v + Vec3A::new(0.3, -0.1, 0.2))).collect();
        let (mut base, mut wide) = (Accel::new(&tris), Accel::new(&tris));
        let (mut base_m, mut wide_m) = (Accel::new_moving(&tris, &moved), Accel::new_moving(&tris, &moved));
        assert_eq!(base.set_simd_level(SimdLevel::Baseline), SimdLevel::Baseline);
        assert_eq!(base_m.set_simd_level(SimdLevel::Baseline), SimdLevel::Baseline);
        let has_avx2 = wide.set_simd_level(SimdLevel::Avx2) == SimdLevel::Avx2;
        wide_m.set_simd_level(SimdLevel::Avx2);
        // The AVX-512 level where the CPU has it (else AVX2 again).
        let (mut wide4, mut wide4_m) = (Accel::new(&tris), Accel::new_moving(&tris, &moved));
        wide4.set_simd_level(SimdLevel::Avx512);
        wide4_m.set_simd_level(SimdLevel::Avx512);
        let (mut hits, mut blocked) = (0, 0);
        for (i, (o, d, t_max)) in crate::render::wide::test_rays(3000).into_iter().enumerate() {
            let want = base.intersect(o, d, t_max);
            assert_eq!(bits(want), bits(reference_intersect(&base, o, d, t_max)), "ray {o} {d} {t_max}");
            assert_eq!(bits(wide.intersect(o, d, t_max)), bits(want), "ray {o} {d} {t_max}");
            assert_eq!(bits(wide4.intersect(o, d, t_max)), bits(want), "avx512: ray {o} {d} {t_max}");
            let occluded = base.occluded(o, d, t_max);
            assert_eq!(occluded, want.is_some(), "ray {o} {d} {t_max}");
            assert_eq!(wide.occluded(o, d, t_max), occluded);
            assert_eq!(wide4.occluded(o, d, t_max), occluded);
            let time = (i % 5) as f32 / 4.0;
            let want_m = base_m.intersect_at(o, d, t_max, time);
            assert_eq!(bits(wide_m.intersect_at(o, d, t_max, time)), bits(want_m));
            assert_eq!(wide_m.occluded_at(o, d, t_max, time), base_m.occluded_at(o, d, t_max, time));
            assert_eq!(bits(wide4_m.intersect_at(o, d, t_max, time)), bits(want_m));
            assert_eq!(wide4_m.occluded_at(o, d, t_max, time), base_m.occluded_at(o, d, t_max, time));
            hits += usize::from(want.is_some());
            blocked += usize::from(occluded);
        }
        assert!(hits > 400 && blocked > 400, "{hits} hits, {blocked} blocked");
        if !has_avx2 {
            eprintln!("this CPU has no AVX2: only the baseline was checked against obvhs");
        }
    }
}
