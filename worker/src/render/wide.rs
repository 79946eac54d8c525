//! Runtime-dispatched SIMD kernels: the renderer's one module where `unsafe` is allowed
//! (`std::arch` intrinsics, and calls into `#[target_feature]` functions behind a proof that the
//! running CPU has the features).
//!
//! The release binary targets baseline x86-64 (SSE2), so it runs on any worker; where the CPU
//! has AVX2 (with BMI1/2, LZCNT, POPCNT and FMA: the x86-64-v3 level), [`Avx2`] runs the BVH
//! traversal compiled for it, with an 8-wide node test over the CWBVH's 8 children, and the
//! Sobol sampler's Owen scrambles for 8 requests at once (the wavefront integrator draws a
//! bounce's numbers for a batch of paths with them), and [`F32x8`], the 8-lane type the
//! renderer's lane-wise math ([`super::math::Real`]) runs on. Where the CPU also has AVX-512 (F,
//! VL, BW, DQ, CD: the x86-64-v4 level), the same kernels run compiled for it (each entry point
//! exists twice, `v3` and `v4`, and the proof's level picks one): still 8 lanes, with 32 vector
//! registers, mask registers and EVEX forms of the same operations (measured: `tiny long` 0.666
//! -> 0.647 s, `tiny solid long` 0.780 -> 0.743 s, minimum of 3-5 interleaved runs). 16 lanes
//! were tried where they fit one kernel (a packet's node test for two rays per 512-bit
//! operation, the same bits): no faster on AMD Zen 4, which runs a 512-bit operation as two
//! 256-bit halves, so they save front-end work only; nor, measurably, on an Intel Xeon with
//! full-width AVX-512 units (`tiny long`, 25 interleaved pairs: median ratio 0.998, quartiles
//! 0.958-1.037). The Sobol scrambles of a bounce's draws do pay at 16 lanes there
//! ([`Avx2::sobol_x16`]: 512-bit integer products, `tiny long` 0.981x the time, median of 21
//! interleaved pairs). Nor did the packet's triangle tests' edge functions for two triangles at
//! once (an early skip of those no ray passes): 8.5% slower there. The whole bench compiled for
//! x86-64-v3 (`RUSTFLAGS=-Ctarget-cpu=x86-64-v3`, so the stage code between the kernels too) ran
//! `tiny long` in 0.968x the time (median of 9 interleaved pairs, quartiles 0.916-0.998) on an
//! AMD EPYC (Zen 4): not worth a second build of the worker, and glam's `cross` would then fuse
//! (below), changing bits against baseline workers. On an Intel Xeon with AVX-512 (family 6,
//! model 207), the whole bench for x86-64-v4 without FMA (`-Ctarget-cpu=x86-64-v4
//! -Ctarget-feature=-fma`: the same operations) ran `tiny long` in 0.986x the time (median of 21
//! interleaved pairs, quartiles 0.923-1.036), and with FMA (other bits) 0.933x (0.892-0.988).
//!
//! Determinism: a farm mixes CPUs, and its image must be bit-identical to a local render whatever
//! worker rendered a unit. Every kernel here computes exactly the f32 operations of the baseline
//! path, in the same order: no FMA contraction (Rust never fuses `a * b + c`; glam picks its
//! fused `cross` by the compile-time `cfg(target_feature = "fma")`, which a function-level
//! `#[target_feature]` does not change), no approximate reciprocals, the same min/max operand
//! order (so NaNs propagate alike). The unit tests run every level on the same inputs and
//! compare bits.
#![allow(unsafe_code)]

#[cfg(any(test, not(target_arch = "x86_64")))]
use super::sampler::u32_to_unit_float;
use glam::Vec3A;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// The instruction-set level the renderer's kernels use on this CPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum SimdLevel {
    /// Baseline x86-64 (SSE2), or a non-x86 target: the code as compiled.
    Baseline,
    /// AVX2 + FMA + BMI1/2 + LZCNT + POPCNT (x86-64-v3) kernels.
    Avx2,
    /// The same 8-lane kernels compiled for x86-64-v4 as well (AVX-512 F, VL, BW, DQ and CD:
    /// 32 vector registers, mask registers, EVEX forms of the same lane operations).
    Avx512,
}

impl SimdLevel {
    /// The best level the running CPU supports.
    pub fn detect() -> Self {
        Avx2::new().map_or(Self::Baseline, Avx2::level)
    }

    /// The level's name, as workers report it ("sse2", "avx2" or "avx512").
    pub fn name(self) -> &'static str {
        match self {
            Self::Baseline => "sse2",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }
}

/// Declares the kernel `$body` twice, as `v3` (compiled for x86-64-v3) and `v4` (compiled for
/// x86-64-v4), for [`Avx2::run_kernel`] and the other entry points to pick by the proof's level.
#[cfg(target_arch = "x86_64")]
macro_rules! leveled {
    ($(#[$attr:meta])* fn $(<$(const $g:ident: $gt:ty),+>)? ($($arg:ident: $ty:ty),* $(,)?) -> $ret:ty $body:block) => {
        $(#[$attr])*
        #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
        fn v3 $(<$(const $g: $gt),+>)? ($($arg: $ty),*) -> $ret $body
        $(#[$attr])*
        #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f,avx512vl,avx512bw,avx512dq,avx512cd")]
        fn v4 $(<$(const $g: $gt),+>)? ($($arg: $ty),*) -> $ret $body
    };
}

/// The node test of a BVH traversal: the hit mask of a CWBVH node's children for a ray, in
/// obvhs' layout (`CwBvhNode::intersect_ray`).
pub trait NodeTest: Copy {
    fn hits(self, node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32;
    /// The proof of AVX2 where the traversal tests a node's leaf triangles 8 at a time.
    fn lanes(self) -> Option<Avx2>;
}

/// The baseline node test (obvhs' SSE2 one: two groups of four children).
#[derive(Clone, Copy, Debug)]
pub struct Baseline;

impl NodeTest for Baseline {
    #[inline(always)]
    fn hits(self, node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
        node.intersect_ray(ray, oct_inv4)
    }
    #[inline(always)]
    fn lanes(self) -> Option<Avx2> {
        None
    }
}

/// Proof that the running CPU has the x86-64-v3 features the AVX2 kernels are compiled for, and
/// of the x86-64-v4 ones where `v4` is set: only [`Avx2::new`] and [`Avx2::at`] make one, after
/// checking them. The kernels run compiled for v4 where it is set (the same lane operations, so
/// the same bits: the unit tests compare the levels).
#[derive(Clone, Copy, Debug)]
pub struct Avx2 {
    v4: bool,
}

impl Avx2 {
    /// The best proof for this CPU: `Some` where it has AVX2, FMA, BMI1, BMI2, LZCNT and POPCNT,
    /// with `v4` where it also has AVX-512 F, VL, BW, DQ and CD.
    pub fn new() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            let v3 = has!("avx2") && has!("fma") && has!("bmi1") && has!("bmi2") && has!("lzcnt") && has!("popcnt");
            let v4 = has!("avx512f") && has!("avx512vl") && has!("avx512bw") && has!("avx512dq") && has!("avx512cd");
            v3.then_some(Self { v4 })
        }
        #[cfg(not(target_arch = "x86_64"))]
        None
    }

    /// The proof for the best level up to `level` that this CPU has (`None` for the baseline).
    pub fn at(level: SimdLevel) -> Option<Self> {
        let best = Self::new()?;
        match level {
            SimdLevel::Baseline => None,
            SimdLevel::Avx2 => Some(Self { v4: false }),
            SimdLevel::Avx512 => Some(best),
        }
    }

    /// The level the kernels run at with this proof.
    pub fn level(self) -> SimdLevel {
        if self.v4 { SimdLevel::Avx512 } else { SimdLevel::Avx2 }
    }

    /// Runs `f` inside a function compiled for x86-64-v3 (or v4), so that `f` and what it
    /// inlines (the traversal kernels are `#[inline(always)]`) use AVX2 code (VEX encoding,
    /// LZCNT, POPCNT).
    #[inline(always)]
    pub fn run<R>(self, f: impl FnOnce() -> R) -> R {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
            fn v3<R>(f: impl FnOnce() -> R) -> R {
                f()
            }
            #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f,avx512vl,avx512bw,avx512dq,avx512cd")]
            fn v4<R>(f: impl FnOnce() -> R) -> R {
                f()
            }
            // SAFETY: `self` exists only where `Avx2::new` found every enabled feature.
            unsafe { if self.v4 { v4(f) } else { v3(f) } }
        }
        #[cfg(not(target_arch = "x86_64"))]
        f()
    }
}

/// Work to run compiled for x86-64-v3 ([`Avx2::run_kernel`]). Its `call` must be
/// `#[inline(always)]`: then it is compiled into the v3 function whatever its size (a closure
/// given to [`Avx2::run`] is inlined only while the optimizer finds it small enough, and runs
/// compiled for the baseline when it is not).
pub trait V3Kernel {
    type Output;
    fn call(self) -> Self::Output;
}

impl Avx2 {
    /// Runs `kernel` inside a function compiled for x86-64-v3 (see [`V3Kernel`]).
    #[inline(always)]
    pub fn run_kernel<K: V3Kernel>(self, kernel: K) -> K::Output {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
            fn v3<K: V3Kernel>(kernel: K) -> K::Output {
                kernel.call()
            }
            #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f,avx512vl,avx512bw,avx512dq,avx512cd")]
            fn v4<K: V3Kernel>(kernel: K) -> K::Output {
                kernel.call()
            }
            // SAFETY: `self` exists only where `Avx2::new` found every enabled feature.
            unsafe { if self.v4 { v4(kernel) } else { v3(kernel) } }
        }
        #[cfg(not(target_arch = "x86_64"))]
        kernel.call()
    }
}

impl NodeTest for Avx2 {
    #[inline(always)]
    fn hits(self, node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe {
            node_hits_avx2(node, ray, oct_inv4)
        }
        #[cfg(not(target_arch = "x86_64"))]
        node.intersect_ray(ray, oct_inv4)
    }
    #[inline(always)]
    fn lanes(self) -> Option<Avx2> {
        Some(self)
    }
}

impl Avx2 {
    /// The 8 x 8 matrix of rows `m`, transposed (row `i` of the result: element `i` of every
    /// row). Data movement only.
    #[inline(always)]
    pub fn transpose8x8(self, m: &[[f32; 8]; 8]) -> [[f32; 8]; 8] {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe {
            transpose8x8_avx(m)
        }
        #[cfg(not(target_arch = "x86_64"))]
        std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
    }
}

impl Avx2 {
    /// The first coordinate of 8 Owen-scrambled Sobol requests ([`super::sampler::SobolSampler`]'s
    /// `x` of `get_1d` and `get_2d`) from each lane's sample index and its two request
    /// seeds: `nested_uniform_scramble(sobol_dim0(nested_uniform_scramble(index, s1)), s2)`, as
    /// the sampler's number in [0, 1) (`u32_to_unit_float`, exact in lanes). Integer
    /// operations, then exact conversions: the same bits as the scalar code.
    #[inline(always)]
    pub fn sobol_x(self, index: &[u32; 8], s1: &[u32; 8], s2: &[u32; 8]) -> [f32; 8] {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe {
            sobol_x8(index, s1, s2, None).0
        }
        #[cfg(not(target_arch = "x86_64"))]
        std::array::from_fn(|i| u32_to_unit_float(sobol_scalar(index[i], s1[i], s2[i], None).0))
    }

    /// Whether this proof runs 16-lane kernels ([`Avx2::sobol_x16`]) in 512-bit operations: the
    /// x86-64-v4 level. Elsewhere those kernels run as two 8-lane halves.
    #[inline(always)]
    pub fn has_16_lanes(self) -> bool {
        self.v4
    }

    /// [`Avx2::sobol_x`] and, with `s3`, [`Avx2::sobol_xy`] for 16 requests: one pass of
    /// 512-bit operations at the x86-64-v4 level, two 8-lane halves below it (the same bits).
    #[inline(always)]
    pub fn sobol_x16(
        self,
        index: &[u32; 16],
        s1: &[u32; 16],
        s2: &[u32; 16],
        s3: Option<&[u32; 16]>,
    ) -> ([f32; 16], [f32; 16]) {
        #[cfg(target_arch = "x86_64")]
        if self.v4 {
            // SAFETY: `v4` is set only where `Avx2::new` found AVX-512 F and BW.
            return unsafe { sobol_x16(index, s1, s2, s3) };
        }
        let half = |v: &[u32; 16], h: usize| -> [u32; 8] { std::array::from_fn(|i| v[h * 8 + i]) };
        let halves: [([f32; 8], [f32; 8]); 2] = std::array::from_fn(|h| match s3 {
            Some(s3) => self.sobol_xy(&half(index, h), &half(s1, h), &half(s2, h), &half(s3, h)),
            None => (self.sobol_x(&half(index, h), &half(s1, h), &half(s2, h)), [0.0; 8]),
        });
        (std::array::from_fn(|i| halves[i / 8].0[i % 8]), std::array::from_fn(|i| halves[i / 8].1[i % 8]))
    }

    /// Both coordinates of 8 Sobol 2D requests: [`Avx2::sobol_x`], and the second coordinate
    /// `nested_uniform_scramble(sobol_dim1(shuffled), s3)` of the same shuffled index.
    #[inline(always)]
    pub fn sobol_xy(self, index: &[u32; 8], s1: &[u32; 8], s2: &[u32; 8], s3: &[u32; 8]) -> ([f32; 8], [f32; 8]) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe {
            sobol_x8(index, s1, s2, Some(s3))
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let v: [(u32, u32); 8] = std::array::from_fn(|i| sobol_scalar(index[i], s1[i], s2[i], Some(s3[i])));
            (v.map(|p| u32_to_unit_float(p.0)), v.map(|p| u32_to_unit_float(p.1)))
        }
    }
}

/// 8 values of one vector, a `Vec3A` per lane (lane `i`: path or sample `i`): each is written
/// and read whole, and a kernel turns the 8 into 3 lanes and back with a few shuffles
/// ([`Avx2::vec3_lanes`], [`Avx2::lanes_vec3`]), instead of each scattering and gathering 3
/// components.
#[derive(Clone, Copy, Default)]
pub struct Vec3Lanes(pub [Vec3A; 8]);

impl Vec3Lanes {
    /// Writes `v` into lane `lane`.
    #[inline(always)]
    pub fn set(&mut self, lane: usize, v: Vec3A) {
        self.0[lane & 7] = v;
    }

    /// Lane `lane`.
    #[inline(always)]
    pub fn get(&self, lane: usize) -> Vec3A {
        self.0[lane & 7]
    }
}

// `Avx2::vec3_lanes` and `Avx2::lanes_vec3` read and write `Vec3A`s as 4 floats each (glam's SSE2
// `__m128`: its fourth lane is initialised).
#[cfg(target_arch = "x86_64")]
const _: () = assert!(std::mem::size_of::<Vec3A>() == 16 && std::mem::align_of::<Vec3A>() == 16);

impl Avx2 {
    /// 8 vectors as 3 lanes (x, y, z of vector `i` in lane `i`): two 4 x 4 transposes (the
    /// unused fourth components are dropped).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn vec3_lanes(self, v: &[Vec3A; 8]) -> [F32x8; 3] {
        self.vec3_lanes_of([&v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7]])
    }

    /// [`Avx2::vec3_lanes`] of 8 vectors wherever they are (a packet's rays' origins).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn vec3_lanes_of(self, v: [&Vec3A; 8]) -> [F32x8; 3] {
        use std::arch::x86_64::*;
        let p = v.map(|v| -> *const f32 { (v as *const Vec3A).cast() });
        // SAFETY: `self` proves the CPU has AVX; each load reads the 16 bytes of one `Vec3A`
        // (x, y, z and its padding, which is initialised: see the size assertion above).
        unsafe {
            let t = [
                _mm256_set_m128(_mm_loadu_ps(p[4]), _mm_loadu_ps(p[0])),
                _mm256_set_m128(_mm_loadu_ps(p[5]), _mm_loadu_ps(p[1])),
                _mm256_set_m128(_mm_loadu_ps(p[6]), _mm_loadu_ps(p[2])),
                _mm256_set_m128(_mm_loadu_ps(p[7]), _mm_loadu_ps(p[3])),
            ];
            let xy01 = _mm256_unpacklo_ps(t[0], t[1]);
            let zw01 = _mm256_unpackhi_ps(t[0], t[1]);
            let xy23 = _mm256_unpacklo_ps(t[2], t[3]);
            let zw23 = _mm256_unpackhi_ps(t[2], t[3]);
            [
                F32x8(_mm256_shuffle_ps::<0x44>(xy01, xy23)),
                F32x8(_mm256_shuffle_ps::<0xEE>(xy01, xy23)),
                F32x8(_mm256_shuffle_ps::<0x44>(zw01, zw23)),
            ]
        }
    }

    /// [`Avx2::vec3_lanes`] back: lane `i` of x, y, z as vector `i` (its fourth component z,
    /// as `Vec3A::new` makes it).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn lanes_vec3(self, v: [F32x8; 3]) -> [Vec3A; 8] {
        use std::arch::x86_64::*;
        let mut out = [Vec3A::ZERO; 8];
        // SAFETY: `self` proves the CPU has AVX; each store writes the 16 bytes of one `Vec3A`
        // of `out` (x, y, z and z again in its padding).
        unsafe {
            let (x, y, z) = (v[0].0, v[1].0, v[2].0);
            let xy_lo = _mm256_unpacklo_ps(x, y);
            let xy_hi = _mm256_unpackhi_ps(x, y);
            let zz_lo = _mm256_unpacklo_ps(z, z);
            let zz_hi = _mm256_unpackhi_ps(z, z);
            let rows = [
                _mm256_shuffle_ps::<0x44>(xy_lo, zz_lo),
                _mm256_shuffle_ps::<0xEE>(xy_lo, zz_lo),
                _mm256_shuffle_ps::<0x44>(xy_hi, zz_hi),
                _mm256_shuffle_ps::<0xEE>(xy_hi, zz_hi),
            ];
            let p: *mut f32 = out.as_mut_ptr().cast();
            for (i, r) in rows.into_iter().enumerate() {
                _mm_storeu_ps(p.add(4 * i), _mm256_castps256_ps128(r));
                _mm_storeu_ps(p.add(4 * i + 16), _mm256_extractf128_ps::<1>(r));
            }
        }
        out
    }

    /// The 8 bytes of `v` as 8 lanes of `f32` (exact).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn bytes_f32x8(self, v: &[u8; 8]) -> F32x8 {
        // SAFETY: `self` proves the CPU has AVX2.
        F32x8(unsafe { bytes_to_f32x8(v) })
    }

    /// 8 lanes of `f32` from `v` (the one way to make an [`F32x8`]: its values exist only where
    /// AVX2 does).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn f32x8(self, v: &[f32; 8]) -> F32x8 {
        // SAFETY: `self` proves the CPU has AVX; an unaligned load of 8 f32 of `v`.
        F32x8(unsafe { std::arch::x86_64::_mm256_loadu_ps(v.as_ptr()) })
    }

    /// [`super::sampling::cosine_hemisphere`] of 8 pairs of numbers, lane-wise in AVX2: the
    /// scalar function's bits in every lane.
    #[inline(always)]
    pub fn cosine_hemisphere(self, ux: &[f32; 8], uy: &[f32; 8]) -> [[f32; 8]; 3] {
        // A function compiled for AVX2 (the lane operations and their intrinsics inline into it
        // whatever the caller is compiled for).
        #[cfg(target_arch = "x86_64")]
        leveled! {
            fn (avx2: Avx2, ux: &[f32; 8], uy: &[f32; 8]) -> [[f32; 8]; 3] {
                let (x, y, z) = super::sampling::cosine_hemisphere(avx2.f32x8(ux), avx2.f32x8(uy));
                [x.to_array(), y.to_array(), z.to_array()]
            }
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe {
            if self.v4 { v4(self, ux, uy) } else { v3(self, ux, uy) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let w: [(f32, f32, f32); 8] = std::array::from_fn(|i| super::sampling::cosine_hemisphere(ux[i], uy[i]));
            [w.map(|v| v.0), w.map(|v| v.1), w.map(|v| v.2)]
        }
    }
}

impl Avx2 {
    /// [`super::camera::Camera::pinhole_directions`] of 8 camera samples (pixel coordinates as
    /// f32, offsets), lane-wise in AVX2: the scalar ray's bits in every lane. `None` where the
    /// camera is not a pinhole.
    #[inline(always)]
    pub fn pinhole_directions(
        self,
        camera: &super::camera::Camera,
        pixel: [&[f32; 8]; 2],
        u: [&[f32; 8]; 2],
    ) -> Option<[[f32; 8]; 3]> {
        #[cfg(target_arch = "x86_64")]
        leveled! {
            fn (
                avx2: Avx2,
                camera: &super::camera::Camera,
                pixel: [&[f32; 8]; 2],
                u: [&[f32; 8]; 2],
            ) -> Option<[[f32; 8]; 3]> {
                let [px, py] = pixel.map(|v| avx2.f32x8(v));
                let [ux, uy] = u.map(|v| avx2.f32x8(v));
                let (x, y, z) = camera.pinhole_directions(px, py, ux, uy)?;
                Some([x.to_array(), y.to_array(), z.to_array()])
            }
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe {
            if self.v4 { v4(self, camera, pixel, u) } else { v3(self, camera, pixel, u) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let mut out = [[0.0f32; 8]; 3];
            for i in 0..8 {
                let (x, y, z) = camera.pinhole_directions(pixel[0][i], pixel[1][i], u[0][i], u[1][i])?;
                (out[0][i], out[1][i], out[2][i]) = (x, y, z);
            }
            Some(out)
        }
    }
}

#[cfg(target_arch = "x86_64")]
impl Avx2 {
    /// [`super::accel::lane_candidates`]: the watertight test of 8 consecutive BVH slots,
    /// lane-wise, in a function compiled for AVX2.
    #[inline(always)]
    pub(super) fn watertight8<const KX: usize, const KY: usize, const KZ: usize>(
        self,
        soa: &[Vec<f32>; 9],
        shear: &super::accel::RayShear<KX, KY, KZ>,
        first: usize,
        t_max: f32,
    ) -> super::accel::LaneCandidates {
        #[target_feature(enable = "avx2")]
        #[inline]
        fn kernel<const KX: usize, const KY: usize, const KZ: usize>(
            avx2: Avx2,
            soa: &[Vec<f32>; 9],
            shear: &super::accel::RayShear<KX, KY, KZ>,
            first: usize,
            t_max: f32,
        ) -> super::accel::LaneCandidates {
            super::accel::lane_candidates(avx2, soa, shear, first, t_max)
        }
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe { kernel(self, soa, shear, first, t_max) }
    }
}

#[cfg(target_arch = "x86_64")]
impl Avx2 {
    /// [`super::accel::trace_packet`]: the closest hits (`ANY`: whether anything is hit) of a
    /// packet of up to 8 rays, in a function compiled for AVX2.
    #[inline(always)]
    pub(super) fn trace_packet<const ANY: bool, const KX: usize, const KY: usize, const KZ: usize>(
        self,
        accel: &super::accel::Accel,
        rays: &[&super::accel::RayQuery],
        hits: super::accel::PacketOut<'_>,
        stats: &mut super::accel::PacketStats,
    ) -> bool {
        // Kept out of the query loop it is called from (measured: `tiny large` 1,857M -> 1,841M
        // instructions).
        leveled! {
            #[inline(never)]
            fn <const ANY: bool, const KX: usize, const KY: usize, const KZ: usize>(
                avx2: Avx2,
                accel: &super::accel::Accel,
                rays: &[&super::accel::RayQuery],
                hits: super::accel::PacketOut<'_>,
                stats: &mut super::accel::PacketStats,
            ) -> bool {
                super::accel::trace_packet::<ANY, KX, KY, KZ>(avx2, accel, rays, hits, stats)
            }
        }
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe {
            if self.v4 {
                v4::<ANY, KX, KY, KZ>(self, accel, rays, hits, stats)
            } else {
                v3::<ANY, KX, KY, KZ>(self, accel, rays, hits, stats)
            }
        }
    }

    /// A box's interval test for 8 rays in lanes, from each ray's entry and exit distances of
    /// its near and far planes per axis (`q * dir_inv + origin`, made as the node test makes
    /// them): the node test's max/min order, its entry epsilon and `<=` against `t_max`. Bit
    /// `i`: ray `i` meets the box.
    #[inline(always)]
    pub(super) fn box_hits(self, near: &[F32x8; 3], far: &[F32x8; 3], t_max: F32x8) -> u32 {
        let near = [near[0].0, near[1].0, near[2].0];
        let far = [far[0].0, far[1].0, far[2].0];
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe { interval_hits_avx2(&near, &far, t_max.0) }
    }

    /// The single-ray node test's box test of a node's 8 children (`near`, `far`: their planes
    /// per axis, swapped for the ray's direction signs) against one ray of a packet, from its
    /// `extent * inv_direction`, `(p - origin) * inv_direction` and `t_max`. Bit `c`: the box of
    /// child slot `c` is hit.
    #[inline(always)]
    pub(super) fn child_box_hits(
        self,
        near: &[F32x8; 3],
        far: &[F32x8; 3],
        dir_inv: [f32; 3],
        origin: [f32; 3],
        t_max: f32,
    ) -> u32 {
        let near = [near[0].0, near[1].0, near[2].0];
        let far = [far[0].0, far[1].0, far[2].0];
        // SAFETY: `self` proves the CPU has AVX2.
        unsafe { child_box_hits_avx2(&near, &far, dir_inv, origin, t_max) }
    }
}

#[cfg(target_arch = "x86_64")]
pub use lanes::{F32x8, F64x4, I32x8, M32x8};

/// [`super::math::Real`] over 8 AVX2 lanes. Every operation is one AVX/AVX2 instruction doing the
/// lane-wise IEEE operation of `f32` (no FMA, no approximate reciprocal), so a lane gives the
/// scalar function's bits. Values exist only where the CPU has AVX2 (they are made from an
/// [`Avx2`] proof, or from other values), so the operations are safe.
#[cfg(target_arch = "x86_64")]
mod lanes {
    use super::super::math::{Real, Real64};
    use std::arch::x86_64::*;
    use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};

    /// 8 lanes of `f32`.
    #[derive(Clone, Copy, Debug)]
    pub struct F32x8(pub(super) __m256);
    /// 8 lanes of `i32` (the bits and integers of [`F32x8`]).
    #[derive(Clone, Copy, Debug)]
    pub struct I32x8(__m256i);
    /// 8 truth values, each lane all ones (true) or all zeros.
    #[derive(Clone, Copy, Debug)]
    pub struct M32x8(__m256);

    impl F32x8 {
        /// The lanes.
        #[inline(always)]
        pub fn to_array(self) -> [f32; 8] {
            let mut out = [0.0f32; 8];
            // SAFETY: this value exists, so the CPU has AVX; an unaligned store of 8 f32.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), self.0) };
            out
        }
    }

    // SAFETY (every `unsafe` block below): an operand of the operation exists, so the CPU has
    // AVX2 (see the module's doc); the intrinsics touch no memory.
    macro_rules! binary {
        ($ty:ident, $tr:ident, $f:ident, $intrinsic:ident) => {
            impl $tr for $ty {
                type Output = $ty;
                #[inline(always)]
                fn $f(self, o: $ty) -> $ty {
                    $ty(unsafe { $intrinsic(self.0, o.0) })
                }
            }
        };
    }
    binary!(F32x8, Add, add, _mm256_add_ps);
    binary!(F32x8, Sub, sub, _mm256_sub_ps);
    binary!(F32x8, Mul, mul, _mm256_mul_ps);
    binary!(F32x8, Div, div, _mm256_div_ps);
    binary!(I32x8, Add, add, _mm256_add_epi32);
    binary!(I32x8, Sub, sub, _mm256_sub_epi32);
    binary!(I32x8, BitAnd, bitand, _mm256_and_si256);
    binary!(I32x8, BitOr, bitor, _mm256_or_si256);
    binary!(I32x8, BitXor, bitxor, _mm256_xor_si256);
    binary!(M32x8, BitAnd, bitand, _mm256_and_ps);
    binary!(M32x8, BitOr, bitor, _mm256_or_ps);

    impl Neg for F32x8 {
        type Output = F32x8;
        /// The sign bit flipped, as `-x` does.
        #[inline(always)]
        fn neg(self) -> F32x8 {
            F32x8(unsafe { _mm256_xor_ps(self.0, _mm256_set1_ps(-0.0)) })
        }
    }

    impl M32x8 {
        /// The lanes' truth values as bits 0..8 (lane `i` true sets bit `i`).
        #[inline(always)]
        pub fn bits(self) -> u32 {
            // SAFETY: this value exists, so the CPU has AVX.
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
    }

    impl Not for M32x8 {
        type Output = M32x8;
        #[inline(always)]
        fn not(self) -> M32x8 {
            M32x8(unsafe { _mm256_xor_ps(self.0, _mm256_castsi256_ps(_mm256_set1_epi32(-1))) })
        }
    }

    impl Real for F32x8 {
        type Int = I32x8;
        type Mask = M32x8;

        #[inline(always)]
        fn splat(self, v: f32) -> Self {
            F32x8(unsafe { _mm256_set1_ps(v) })
        }
        #[inline(always)]
        fn int(self, v: i32) -> I32x8 {
            I32x8(unsafe { _mm256_set1_epi32(v) })
        }
        #[inline(always)]
        fn to_bits(self) -> I32x8 {
            I32x8(unsafe { _mm256_castps_si256(self.0) })
        }
        #[inline(always)]
        fn from_bits(i: I32x8) -> Self {
            F32x8(unsafe { _mm256_castsi256_ps(i.0) })
        }
        #[inline(always)]
        fn shl<const N: i32>(i: I32x8) -> I32x8 {
            I32x8(unsafe { _mm256_slli_epi32::<N>(i.0) })
        }
        #[inline(always)]
        fn sar<const N: i32>(i: I32x8) -> I32x8 {
            I32x8(unsafe { _mm256_srai_epi32::<N>(i.0) })
        }
        #[inline(always)]
        fn int_eq(a: I32x8, b: I32x8) -> M32x8 {
            M32x8(unsafe { _mm256_castsi256_ps(_mm256_cmpeq_epi32(a.0, b.0)) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            F32x8(unsafe { _mm256_sqrt_ps(self.0) })
        }
        /// `_CMP_LT_OQ`: false where either is NaN, as `<`.
        #[inline(always)]
        fn lt(self, o: Self) -> M32x8 {
            M32x8(unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0) })
        }
        /// `_CMP_EQ_OQ`: false where either is NaN, as `==`.
        #[inline(always)]
        fn eq(self, o: Self) -> M32x8 {
            M32x8(unsafe { _mm256_cmp_ps::<_CMP_EQ_OQ>(self.0, o.0) })
        }
        /// `_CMP_LE_OQ`: the trait's `lt | eq` in one instruction (false where either is NaN).
        #[inline(always)]
        fn le(self, o: Self) -> M32x8 {
            M32x8(unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0) })
        }
        /// `_CMP_GE_OQ`: the trait's `gt | eq` in one instruction (false where either is NaN).
        #[inline(always)]
        fn ge(self, o: Self) -> M32x8 {
            M32x8(unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(self.0, o.0) })
        }
        #[inline(always)]
        fn select(m: M32x8, a: Self, b: Self) -> Self {
            F32x8(unsafe { _mm256_blendv_ps(b.0, a.0, m.0) })
        }
        #[inline(always)]
        fn mask_of_bits(self, bits: u32) -> M32x8 {
            // Lane `i` holds bit `i` alone; where `bits` has it, the lane is all ones.
            M32x8(unsafe {
                let lane_bit = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
                let set = _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bit);
                _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, lane_bit))
            })
        }
        /// `super::super::geometry::offset_component` in lanes: the same operations as the SSE2
        /// `super::offset_along`, 8 wide.
        #[inline(always)]
        fn offset_along(self, n: Self) -> Self {
            use super::super::geometry::{OFFSET_FLOAT_SCALE, OFFSET_INT_SCALE, OFFSET_ORIGIN};
            // SAFETY: this value exists, so the CPU has AVX2.
            F32x8(unsafe {
                let (p, n) = (self.0, n.0);
                let s = _mm256_mul_ps(_mm256_set1_ps(OFFSET_INT_SCALE), n);
                let s = _mm256_and_ps(s, _mm256_cmp_ps::<_CMP_ORD_Q>(s, s));
                let big = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GE_OQ>(s, _mm256_set1_ps(2_147_483_648.0)));
                let t = _mm256_cvttps_epi32(s);
                let of_i =
                    _mm256_or_si256(_mm256_and_si256(big, _mm256_set1_epi32(i32::MAX)), _mm256_andnot_si256(big, t));
                let negative = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>(p, _mm256_setzero_ps()));
                let offset = _mm256_sub_epi32(_mm256_xor_si256(of_i, negative), negative);
                let moved = _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(p), offset));
                let abs = _mm256_and_ps(p, _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX)));
                let near = _mm256_cmp_ps::<_CMP_LT_OQ>(abs, _mm256_set1_ps(OFFSET_ORIGIN));
                let nudged = _mm256_add_ps(p, _mm256_mul_ps(_mm256_set1_ps(OFFSET_FLOAT_SCALE), n));
                _mm256_blendv_ps(moved, nudged, near)
            })
        }
        /// One `vmaxps`: `_mm256_max_ps(a, b)` is `a > b ? a : b` in each lane (`b` where either
        /// is NaN or both are zeros), so `max_ps(o, self)` is the trait's `self < o ? o : self`,
        /// bit for bit.
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            F32x8(unsafe { _mm256_max_ps(o.0, self.0) })
        }
        type F64 = F64x4;
        const HALVES: usize = 2;
        /// `vcvtps2pd` of each half (exact).
        #[inline(always)]
        fn widen(self) -> [F64x4; 2] {
            unsafe {
                [
                    F64x4(_mm256_cvtps_pd(_mm256_castps256_ps128(self.0))),
                    F64x4(_mm256_cvtps_pd(_mm256_extractf128_ps::<1>(self.0))),
                ]
            }
        }
        /// `vcvtpd2ps` of each half (to nearest, as `as f32`).
        #[inline(always)]
        fn narrow(self, w: [F64x4; 2]) -> Self {
            F32x8(unsafe { _mm256_set_m128(_mm256_cvtpd_ps(w[1].0), _mm256_cvtpd_ps(w[0].0)) })
        }
    }

    /// 4 lanes of `f64` ([`Real64`]; made only from [`F32x8`] values, so the CPU has AVX2).
    #[derive(Clone, Copy, Debug)]
    pub struct F64x4(__m256d);
    /// 4 lanes of `i64` (the bits of [`F64x4`]).
    #[derive(Clone, Copy, Debug)]
    pub struct I64x4(__m256i);
    /// 4 truth values, each lane all ones (true) or all zeros.
    #[derive(Clone, Copy, Debug)]
    pub struct M64x4(__m256d);

    binary!(F64x4, Add, add, _mm256_add_pd);
    binary!(F64x4, Sub, sub, _mm256_sub_pd);
    binary!(F64x4, Mul, mul, _mm256_mul_pd);
    binary!(F64x4, Div, div, _mm256_div_pd);
    binary!(I64x4, Add, add, _mm256_add_epi64);
    binary!(I64x4, BitAnd, bitand, _mm256_and_si256);
    binary!(M64x4, BitAnd, bitand, _mm256_and_pd);
    binary!(M64x4, BitOr, bitor, _mm256_or_pd);

    impl Neg for F64x4 {
        type Output = F64x4;
        /// The sign bit flipped, as `-x` does.
        #[inline(always)]
        fn neg(self) -> F64x4 {
            F64x4(unsafe { _mm256_xor_pd(self.0, _mm256_set1_pd(-0.0)) })
        }
    }

    impl Not for M64x4 {
        type Output = M64x4;
        #[inline(always)]
        fn not(self) -> M64x4 {
            M64x4(unsafe { _mm256_xor_pd(self.0, _mm256_castsi256_pd(_mm256_set1_epi64x(-1))) })
        }
    }

    impl Real64 for F64x4 {
        type Int = I64x4;
        type Mask = M64x4;

        #[inline(always)]
        fn splat(self, v: f64) -> Self {
            F64x4(unsafe { _mm256_set1_pd(v) })
        }
        #[inline(always)]
        fn int(self, v: i64) -> I64x4 {
            I64x4(unsafe { _mm256_set1_epi64x(v) })
        }
        #[inline(always)]
        fn to_bits(self) -> I64x4 {
            I64x4(unsafe { _mm256_castpd_si256(self.0) })
        }
        #[inline(always)]
        fn int_eq(a: I64x4, b: I64x4) -> M64x4 {
            M64x4(unsafe { _mm256_castsi256_pd(_mm256_cmpeq_epi64(a.0, b.0)) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            F64x4(unsafe { _mm256_sqrt_pd(self.0) })
        }
        /// `_CMP_LT_OQ`: false where either is NaN, as `<`.
        #[inline(always)]
        fn lt(self, o: Self) -> M64x4 {
            M64x4(unsafe { _mm256_cmp_pd::<_CMP_LT_OQ>(self.0, o.0) })
        }
        #[inline(always)]
        fn select(m: M64x4, a: Self, b: Self) -> Self {
            F64x4(unsafe { _mm256_blendv_pd(b.0, a.0, m.0) })
        }
        #[inline(always)]
        fn negate_where(self, m: M64x4) -> Self {
            F64x4(unsafe { _mm256_xor_pd(self.0, _mm256_and_pd(m.0, _mm256_set1_pd(-0.0))) })
        }
        #[inline(always)]
        fn abs(self) -> Self {
            F64x4(unsafe { _mm256_andnot_pd(_mm256_set1_pd(-0.0), self.0) })
        }
        #[inline(always)]
        fn mask_bits(m: M64x4) -> u32 {
            unsafe { _mm256_movemask_pd(m.0) as u32 }
        }
    }
}

impl Avx2 {
    /// `super::light::TriangleSample` of 8 triangle-light samples at once, in a function
    /// compiled for AVX2 (the scalar sample's bits in every lane), written into `out` (returned,
    /// the 330-byte value was copied by a `memcpy` call per 8 samples).
    #[inline(always)]
    pub fn triangle_samples(
        self,
        lanes: &super::light::LightLanes,
        solid_angle: bool,
        out: &mut super::light::LightLaneSamples,
    ) {
        #[cfg(target_arch = "x86_64")]
        leveled! {
        fn (avx2: Avx2, l: &super::light::LightLanes, solid_angle: bool, out: &mut super::light::LightLaneSamples) -> () {
            use super::math::Real;
            use super::sampling::{MAX_SPHERICAL_SAMPLE_AREA, MIN_SPHERICAL_SAMPLE_AREA};
            use super::spherical;
            // No closures: see `accel::Sheared::new`.
            let v = [avx2.vec3_lanes(&l.v[0].0), avx2.vec3_lanes(&l.v[1].0), avx2.vec3_lanes(&l.v[2].0)];
            let n = avx2.vec3_lanes(&l.n.0);
            let p = avx2.vec3_lanes(&l.p.0);
            let u = [avx2.f32x8(&l.u[0]), avx2.f32x8(&l.u[1])];
            // The point by area (`sample_uniform_triangle`), the fallback of solid angle.
            let b = super::sampling::uniform_triangle(u);
            let area = avx2.f32x8(&l.area);
            let two_sided = avx2.f32x8(&l.two_sided).gt(area.splat(0.0));
            let t = if solid_angle {
                // `Light::sample_li`: by solid angle where the spherical triangle's area is in
                // range (a sample that then fails is no sample), else by area.
                let s = spherical::project(v, p);
                let sa = s.area;
                let by_solid_angle = s.ok
                    & sa.abs().lt(sa.splat(f32::INFINITY))
                    & sa.ge(sa.splat(MIN_SPHERICAL_SAMPLE_AREA))
                    & sa.lt(sa.splat(MAX_SPHERICAL_SAMPLE_AREA));
                let sample = spherical::sample(v, p, &s, u, by_solid_angle);
                let b = super::vec3::select3(by_solid_angle, sample.b, b);
                let t =
                    super::light::TriangleSample::at(v, n, area, two_sided, p, b, Some((by_solid_angle, sample.pdf)));
                super::light::TriangleSample { ok: t.ok & (!by_solid_angle | sample.ok), ..t }
            } else {
                super::light::TriangleSample::at(v, n, area, two_sided, p, b, None)
            };
            *out = super::light::LightLaneSamples {
                ok: t.ok.bits(),
                b: [t.b[0].to_array(), t.b[1].to_array(), t.b[2].to_array()],
                p: Vec3Lanes(avx2.lanes_vec3(t.p)),
                wi: Vec3Lanes(avx2.lanes_vec3(t.wi)),
                pdf: t.pdf.to_array(),
            };
        }
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe {
            if self.v4 { v4(self, lanes, solid_angle, out) } else { v3(self, lanes, solid_angle, out) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (lanes, solid_angle, out);
            unreachable!("no AVX2 proof exists on this architecture")
        }
    }
}

#[cfg(target_arch = "x86_64")]
impl Avx2 {
    /// `super::lambert::lane_bounces`: 8 plain Lambertian bounces, in a function compiled for
    /// AVX2 (the scalar bounce's bits in every lane).
    #[inline(always)]
    pub fn lambert_bounces(self, lanes: &super::lambert::LambertLanes, power: bool) -> super::lambert::LambertLaneOut {
        leveled! {
            fn (avx2: Avx2, l: &super::lambert::LambertLanes, power: bool) -> super::lambert::LambertLaneOut {
                super::lambert::lane_bounces(avx2, l, power)
            }
        }
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe { if self.v4 { v4(self, lanes, power) } else { v3(self, lanes, power) } }
    }
}

#[cfg(target_arch = "x86_64")]
impl Avx2 {
    /// `super::igi::lane_vpl_terms`: 8 VPLs' terms at a point, in a function compiled for AVX2
    /// (the scalar terms' bits in every lane).
    #[inline(always)]
    pub fn vpl_terms(
        self,
        x: &super::igi::VplPoint<f32>,
        v: &super::igi::VplLanes,
        valid: u32,
    ) -> super::igi::VplTerms {
        leveled! {
            fn (
                avx2: Avx2,
                x: &super::igi::VplPoint<f32>,
                v: &super::igi::VplLanes,
                valid: u32,
            ) -> super::igi::VplTerms {
                super::igi::lane_vpl_terms(avx2, x, v, valid)
            }
        }
        // SAFETY: `self` proves the CPU has the level's features.
        unsafe { if self.v4 { v4(self, x, v, valid) } else { v3(self, x, v, valid) } }
    }
}

/// `super::geometry::offset_along` on the three components at once in SSE2 lanes (every
/// x86-64 CPU has SSE2): the same multiplications and additions, Rust's saturating `as i32`
/// (NaN to 0, beyond the range to its ends) and the same integer steps on the bits, so the
/// same point.
#[cfg(target_arch = "x86_64")]
#[inline]
pub fn offset_along(p: Vec3A, n: Vec3A) -> Vec3A {
    use super::geometry::{OFFSET_FLOAT_SCALE, OFFSET_INT_SCALE, OFFSET_ORIGIN};
    use std::arch::x86_64::*;
    let (p, n) = (__m128::from(p), __m128::from(n));
    // SAFETY: SSE2 is part of x86-64, so its intrinsics are always available here.
    let out = unsafe {
        let s = _mm_mul_ps(_mm_set1_ps(OFFSET_INT_SCALE), n);
        // `s as i32`: NaN to 0, then truncation, with values from 2^31 on to i32::MAX (the
        // instruction gives i32::MIN there, which is right below -2^31).
        let s = _mm_and_ps(s, _mm_cmpord_ps(s, s));
        let big = _mm_castps_si128(_mm_cmpge_ps(s, _mm_set1_ps(2_147_483_648.0)));
        let t = _mm_cvttps_epi32(s);
        let of_i = _mm_or_si128(_mm_and_si128(big, _mm_set1_epi32(i32::MAX)), _mm_andnot_si128(big, t));
        // `bits + (p < 0 ? -of_i : of_i)`, wrapping: negation is (x ^ m) - m with m all ones.
        let negative = _mm_castps_si128(_mm_cmplt_ps(p, _mm_setzero_ps()));
        let offset = _mm_sub_epi32(_mm_xor_si128(of_i, negative), negative);
        let moved = _mm_castsi128_ps(_mm_add_epi32(_mm_castps_si128(p), offset));
        // `|p| < ORIGIN ? p + FLOAT_SCALE * n : moved`.
        let abs = _mm_and_ps(p, _mm_castsi128_ps(_mm_set1_epi32(i32::MAX)));
        let near = _mm_cmplt_ps(abs, _mm_set1_ps(OFFSET_ORIGIN));
        let nudged = _mm_add_ps(p, _mm_mul_ps(_mm_set1_ps(OFFSET_FLOAT_SCALE), n));
        _mm_or_ps(_mm_and_ps(near, nudged), _mm_andnot_ps(near, moved))
    };
    Vec3A::from(out)
}

/// [`Avx2::transpose8x8`]: unpack pairs, then quads, then swap the 128-bit halves.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn transpose8x8_avx(m: &[[f32; 8]; 8]) -> [[f32; 8]; 8] {
    use std::arch::x86_64::*;
    // SAFETY (loads and stores): unaligned accesses to rows of 8 f32. No closures (see
    // `accel::Sheared::new`).
    let r = unsafe {
        [
            _mm256_loadu_ps(m[0].as_ptr()),
            _mm256_loadu_ps(m[1].as_ptr()),
            _mm256_loadu_ps(m[2].as_ptr()),
            _mm256_loadu_ps(m[3].as_ptr()),
            _mm256_loadu_ps(m[4].as_ptr()),
            _mm256_loadu_ps(m[5].as_ptr()),
            _mm256_loadu_ps(m[6].as_ptr()),
            _mm256_loadu_ps(m[7].as_ptr()),
        ]
    };
    let t0 = _mm256_unpacklo_ps(r[0], r[1]);
    let t1 = _mm256_unpackhi_ps(r[0], r[1]);
    let t2 = _mm256_unpacklo_ps(r[2], r[3]);
    let t3 = _mm256_unpackhi_ps(r[2], r[3]);
    let t4 = _mm256_unpacklo_ps(r[4], r[5]);
    let t5 = _mm256_unpackhi_ps(r[4], r[5]);
    let t6 = _mm256_unpacklo_ps(r[6], r[7]);
    let t7 = _mm256_unpackhi_ps(r[6], r[7]);
    let s0 = _mm256_shuffle_ps::<0x44>(t0, t2);
    let s1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
    let s2 = _mm256_shuffle_ps::<0x44>(t1, t3);
    let s3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
    let s4 = _mm256_shuffle_ps::<0x44>(t4, t6);
    let s5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
    let s6 = _mm256_shuffle_ps::<0x44>(t5, t7);
    let s7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
    let out = [
        _mm256_permute2f128_ps::<0x20>(s0, s4),
        _mm256_permute2f128_ps::<0x20>(s1, s5),
        _mm256_permute2f128_ps::<0x20>(s2, s6),
        _mm256_permute2f128_ps::<0x20>(s3, s7),
        _mm256_permute2f128_ps::<0x31>(s0, s4),
        _mm256_permute2f128_ps::<0x31>(s1, s5),
        _mm256_permute2f128_ps::<0x31>(s2, s6),
        _mm256_permute2f128_ps::<0x31>(s3, s7),
    ];
    let mut t = [[0.0f32; 8]; 8];
    for (row, v) in t.iter_mut().zip(out) {
        unsafe { _mm256_storeu_ps(row.as_mut_ptr(), v) };
    }
    t
}

/// The scalar form of the Sobol kernels (the sampler's own functions).
#[cfg(any(test, not(target_arch = "x86_64")))]
fn sobol_scalar(index: u32, s1: u32, s2: u32, s3: Option<u32>) -> (u32, u32) {
    use super::sampler::{nested_uniform_scramble, sobol_dim0, sobol_dim1};
    let shuffled = nested_uniform_scramble(index, s1);
    let x = nested_uniform_scramble(sobol_dim0(shuffled), s2);
    (x, s3.map_or(0, |s3| nested_uniform_scramble(sobol_dim1(shuffled), s3)))
}

/// 8 (AVX2) or 16 (AVX-512) lanes of `u32`: the integer operations the Sobol kernels are
/// written with, once ([`sobol_lanes`]), for [`sobol_x8`] and [`sobol_x16`]. Private to them:
/// values are made only inside those kernels, compiled with the lanes' features (the same
/// convention as [`F32x8`]: an existing value proves the features).
#[cfg(target_arch = "x86_64")]
trait WordLanes: Copy {
    /// The lanes as an array of `u32`, and of `f32`.
    type Words;
    type Floats;
    /// # Safety
    /// The CPU has the lanes' features.
    unsafe fn load(v: &Self::Words) -> Self;
    /// `v` in every lane.
    fn splat(self, v: u32) -> Self;
    /// `bytes` in every 128-bit block (a byte-shuffle table).
    fn table(self, bytes: [u8; 16]) -> Self;
    fn xor(self, o: Self) -> Self;
    fn and(self, o: Self) -> Self;
    fn or(self, o: Self) -> Self;
    /// Wrapping 32-bit addition and product.
    fn add(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    /// 32-bit lanes shifted right by `n`; 16-bit halves shifted right or left by `n`.
    fn shr32(self, n: i32) -> Self;
    fn shr16(self, n: i32) -> Self;
    fn shl16(self, n: i32) -> Self;
    /// Each byte looked up in `self`'s 128-bit block by `index`'s byte (`vpshufb`).
    fn shuffle_bytes(self, index: Self) -> Self;
    /// `u32_to_unit_float` of each lane: the top 24 bits (an i32 below 2^24, converted
    /// exactly) times 2^-24 (exact).
    fn unit_floats(self) -> Self::Floats;
}

/// A [`WordLanes`] type over one register of `$n` lanes: the trait's operations as the
/// register width's intrinsics (the same operation on every width).
#[cfg(target_arch = "x86_64")]
macro_rules! word_lanes {
    (
        $(#[$doc:meta])* $name:ident($reg:ty, $n:literal): load $load:ident, splat $splat:ident,
        table $table:ident, xor $xor:ident, and $and:ident, or $or:ident, add $add:ident,
        mul $mul:ident, shr32 $shr32:ident, shr16 $shr16:ident, shl16 $shl16:ident,
        shuffle $shuffle:ident, shr32_8 $shr32_8:ident, to_float $to_float:ident,
        mul_float $mul_float:ident, splat_float $splat_float:ident, store_float $store_float:ident
    ) => {
        $(#[$doc])*
        #[derive(Clone, Copy)]
        struct $name($reg);

        // SAFETY (every `unsafe` block below): a value exists only where the CPU has the
        // register's features (made by `load`, whose caller promises it), and the intrinsics
        // other than the load and store touch no memory; those access whole arrays of `$n`.
        impl WordLanes for $name {
            type Words = [u32; $n];
            type Floats = [f32; $n];
            #[inline(always)]
            unsafe fn load(v: &[u32; $n]) -> Self {
                Self(unsafe { std::arch::x86_64::$load(v.as_ptr().cast()) })
            }
            #[inline(always)]
            fn splat(self, v: u32) -> Self {
                Self(unsafe { std::arch::x86_64::$splat(v as i32) })
            }
            #[inline(always)]
            fn table(self, bytes: [u8; 16]) -> Self {
                use std::arch::x86_64::*;
                Self(unsafe { $table(_mm_loadu_si128(bytes.as_ptr().cast())) })
            }
            #[inline(always)]
            fn xor(self, o: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$xor(self.0, o.0) })
            }
            #[inline(always)]
            fn and(self, o: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$and(self.0, o.0) })
            }
            #[inline(always)]
            fn or(self, o: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$or(self.0, o.0) })
            }
            #[inline(always)]
            fn add(self, o: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$add(self.0, o.0) })
            }
            #[inline(always)]
            fn mul(self, o: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$mul(self.0, o.0) })
            }
            #[inline(always)]
            fn shr32(self, n: i32) -> Self {
                use std::arch::x86_64::*;
                Self(unsafe { $shr32(self.0, _mm_cvtsi32_si128(n)) })
            }
            #[inline(always)]
            fn shr16(self, n: i32) -> Self {
                use std::arch::x86_64::*;
                Self(unsafe { $shr16(self.0, _mm_cvtsi32_si128(n)) })
            }
            #[inline(always)]
            fn shl16(self, n: i32) -> Self {
                use std::arch::x86_64::*;
                Self(unsafe { $shl16(self.0, _mm_cvtsi32_si128(n)) })
            }
            #[inline(always)]
            fn shuffle_bytes(self, index: Self) -> Self {
                Self(unsafe { std::arch::x86_64::$shuffle(self.0, index.0) })
            }
            #[inline(always)]
            fn unit_floats(self) -> [f32; $n] {
                use std::arch::x86_64::*;
                let mut out = [0.0f32; $n];
                unsafe {
                    let top = $to_float($shr32_8::<8>(self.0));
                    $store_float(out.as_mut_ptr(), $mul_float(top, $splat_float(1.0 / (1u32 << 24) as f32)));
                }
                out
            }
        }
    };
}

#[cfg(target_arch = "x86_64")]
word_lanes! {
    /// [`WordLanes`] in one AVX2 register.
    Words8(std::arch::x86_64::__m256i, 8): load _mm256_loadu_si256, splat _mm256_set1_epi32,
    table _mm256_broadcastsi128_si256, xor _mm256_xor_si256, and _mm256_and_si256,
    or _mm256_or_si256, add _mm256_add_epi32, mul _mm256_mullo_epi32, shr32 _mm256_srl_epi32,
    shr16 _mm256_srl_epi16, shl16 _mm256_sll_epi16, shuffle _mm256_shuffle_epi8,
    shr32_8 _mm256_srli_epi32, to_float _mm256_cvtepi32_ps, mul_float _mm256_mul_ps,
    splat_float _mm256_set1_ps, store_float _mm256_storeu_ps
}

#[cfg(target_arch = "x86_64")]
word_lanes! {
    /// [`WordLanes`] in one AVX-512 register.
    Words16(std::arch::x86_64::__m512i, 16): load _mm512_loadu_si512, splat _mm512_set1_epi32,
    table _mm512_broadcast_i32x4, xor _mm512_xor_si512, and _mm512_and_si512,
    or _mm512_or_si512, add _mm512_add_epi32, mul _mm512_mullo_epi32, shr32 _mm512_srl_epi32,
    shr16 _mm512_srl_epi16, shl16 _mm512_sll_epi16, shuffle _mm512_shuffle_epi8,
    shr32_8 _mm512_srli_epi32, to_float _mm512_cvtepi32_ps, mul_float _mm512_mul_ps,
    splat_float _mm512_set1_ps, store_float _mm512_storeu_ps
}

/// Reverses the bits of each 32-bit lane: each byte's bits through a nibble table, then the
/// bytes (`vpshufb` works within 128-bit blocks, so each table repeats per block).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn reverse_bits_lanes<V: WordLanes>(x: V) -> V {
    let nibbles = x.table([0, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15]);
    let low4 = x.splat(0x0f0f_0f0f);
    let lo = x.and(low4);
    let hi = x.shr16(4).and(low4);
    // Each byte holds a value below 16, so the 16-bit shift moves nothing across bytes.
    let bytes = nibbles.shuffle_bytes(lo).shl16(4).or(nibbles.shuffle_bytes(hi));
    bytes.shuffle_bytes(bytes.table([3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12]))
}

/// `laine_karras_permutation` on each lane (wrapping 32-bit products, as the scalar code).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn laine_karras_lanes<V: WordLanes>(x: V, seed: V) -> V {
    let mut x = x.xor(x.mul(x.splat(0x3d20_adea)));
    x = x.add(seed);
    x = x.mul(seed.shr32(16).or(x.splat(1)));
    x = x.xor(x.mul(x.splat(0x0552_6c56)));
    x.xor(x.mul(x.splat(0x53a2_2864)))
}

/// The Sobol kernels' steps, once for 8 and 16 lanes: the first coordinate of each request
/// (`nested_uniform_scramble(sobol_dim0(shuffled), s2)`, the index shuffled by `s1`) and, with
/// `s3`, the second (`nested_uniform_scramble(sobol_dim1(shuffled), s3)`), as 32-bit words.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn sobol_lanes<V: WordLanes>(index: V, s1: V, s2: V, s3: Option<V>) -> (V, Option<V>) {
    // nested_uniform_scramble(v, s) = reverse(LK(reverse(v), s)); sobol_dim0 = reverse.
    let shuffled = reverse_bits_lanes(laine_karras_lanes(reverse_bits_lanes(index), s1));
    let x = reverse_bits_lanes(laine_karras_lanes(shuffled, s2));
    let Some(s3) = s3 else { return (x, None) };
    // `sobol_dim1_reversed`: each block's high half XORed into its low half (16, 8, 4, 2, 1
    // bits), so that the scramble's reversal before the permutation is not needed.
    let mut dim1 = shuffled.xor(shuffled.shr32(16));
    for (shift, mask) in [(8, 0x00ff_00ff), (4, 0x0f0f_0f0f), (2, 0x3333_3333), (1, 0x5555_5555)] {
        dim1 = dim1.xor(dim1.shr32(shift).and(dim1.splat(mask)));
    }
    (x, Some(reverse_bits_lanes(laine_karras_lanes(dim1, s3))))
}

/// [`sobol_lanes`] of 8 requests in AVX2, as unit floats (the second coordinates with `s3`,
/// else zeros).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn sobol_x8(index: &[u32; 8], s1: &[u32; 8], s2: &[u32; 8], s3: Option<&[u32; 8]>) -> ([f32; 8], [f32; 8]) {
    // No closures (see `accel::Sheared::new`). SAFETY: this function runs only where the CPU
    // has AVX2.
    let (index, s1, s2) = unsafe { (Words8::load(index), Words8::load(s1), Words8::load(s2)) };
    let s3 = match s3 {
        Some(s3) => Some(unsafe { Words8::load(s3) }),
        None => None,
    };
    match sobol_lanes(index, s1, s2, s3) {
        (x, Some(y)) => (x.unit_floats(), y.unit_floats()),
        (x, None) => (x.unit_floats(), [0.0; 8]),
    }
}

/// [`sobol_x8`] on 16 lanes (512-bit operations: the same integer operations and exact
/// conversions, so the same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
#[inline]
fn sobol_x16(index: &[u32; 16], s1: &[u32; 16], s2: &[u32; 16], s3: Option<&[u32; 16]>) -> ([f32; 16], [f32; 16]) {
    // No closures (see `accel::Sheared::new`). SAFETY: this function runs only where the CPU
    // has AVX-512 F and BW.
    let (index, s1, s2) = unsafe { (Words16::load(index), Words16::load(s1), Words16::load(s2)) };
    let s3 = match s3 {
        Some(s3) => Some(unsafe { Words16::load(s3) }),
        None => None,
    };
    match sobol_lanes(index, s1, s2, s3) {
        (x, Some(y)) => (x.unit_floats(), y.unit_floats()),
        (x, None) => (x.unit_floats(), [0.0; 16]),
    }
}

/// obvhs' node-test epsilon (`cwbvh::node::EPSILON`, crate-private there): the smallest entry
/// distance of a child box.
#[cfg(target_arch = "x86_64")]
const NODE_EPSILON: f32 = 0.0001;

/// The 8 quantized child bounds `v` as f32 (exact: they are bytes).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn bytes_to_f32x8(v: &[u8; 8]) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    // SAFETY: reads the 8 bytes of `v` (an unaligned 64-bit load).
    unsafe { _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(v.as_ptr().cast()))) }
}

/// `CwBvhNode::intersect_ray` over all 8 children at once: per child and axis the same
/// `q * extent_inv + origin` (multiply, then add), the same max/min order and the same `<=`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn node_hits_avx2(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
    let dir_inv = node.compute_extent() * ray.inv_direction;
    let origin = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let axis = |lo: &[u8; 8], hi: &[u8; 8], negative: bool| {
        let (lo, hi) = (bytes_to_f32x8(lo), bytes_to_f32x8(hi));
        if negative { (hi, lo) } else { (lo, hi) }
    };
    let (near_x, far_x) = axis(&node.child_min_x, &node.child_max_x, ray.direction.x < 0.0);
    let (near_y, far_y) = axis(&node.child_min_y, &node.child_max_y, ray.direction.y < 0.0);
    let (near_z, far_z) = axis(&node.child_min_z, &node.child_max_z, ray.direction.z < 0.0);
    let near = [near_x, near_y, near_z];
    let far = [far_x, far_y, far_z];
    let mut mask = child_box_hits_avx2(&near, &far, dir_inv.to_array(), origin.to_array(), ray.tmax);
    let mut hit_mask = 0;
    while mask != 0 {
        let child = mask.trailing_zeros();
        mask &= mask - 1;
        let byte = |x: u64| ((x >> (child * 8)) as u32) & 0xff;
        hit_mask |= byte(child_bits8) << byte(bit_index8);
    }
    hit_mask
}

/// The box test of a node's 8 children against one ray, from the children's near and far
/// quantized planes per axis (already swapped where the ray's direction is negative), the
/// node's `extent * inv_direction` and `(p - origin) * inv_direction`: per axis `q * dir_inv +
/// origin` (multiply, then add), the max/min order of obvhs' test and its `<=`. Bit `c`: the
/// box of child slot `c` is hit. The single-ray node test and the packets' both use it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn child_box_hits_avx2(
    near: &[std::arch::x86_64::__m256; 3],
    far: &[std::arch::x86_64::__m256; 3],
    dir_inv: [f32; 3],
    origin: [f32; 3],
    t_max: f32,
) -> u32 {
    use std::arch::x86_64::*;
    let axis = |a: usize| {
        let (d, o) = (_mm256_set1_ps(dir_inv[a]), _mm256_set1_ps(origin[a]));
        (_mm256_add_ps(_mm256_mul_ps(near[a], d), o), _mm256_add_ps(_mm256_mul_ps(far[a], d), o))
    };
    let (tmin_x, tmax_x) = axis(0);
    let (tmin_y, tmax_y) = axis(1);
    let (tmin_z, tmax_z) = axis(2);
    interval_hits_avx2(&[tmin_x, tmin_y, tmin_z], &[tmax_x, tmax_y, tmax_z], _mm256_set1_ps(t_max))
}

/// The node test's last part, lane-wise: from the entry and exit distances per axis, where
/// `max(entries, epsilon) <= min(exits, t_max)`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn interval_hits_avx2(
    near: &[std::arch::x86_64::__m256; 3],
    far: &[std::arch::x86_64::__m256; 3],
    t_max: std::arch::x86_64::__m256,
) -> u32 {
    use std::arch::x86_64::*;
    let tmin = _mm256_max_ps(near[0], _mm256_max_ps(near[1], near[2]));
    let tmax = _mm256_min_ps(far[0], _mm256_min_ps(far[1], far[2]));
    let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(NODE_EPSILON));
    let tmax = _mm256_min_ps(tmax, t_max);
    // `_CMP_LE_OQ` is `cmpleps`' predicate without the signal: false on NaN like it.
    _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax)) as u32
}

#[cfg(test)]
fn hash(mut x: u64) -> u64 {
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^ (x >> 33)
}

#[cfg(test)]
pub(crate) fn unit(x: u64) -> f32 {
    (hash(x) >> 40) as f32 / (1u64 << 24) as f32
}

/// Rays of every kind the renderer makes: random origins and directions, axis-aligned ones
/// with +-0 components, tiny and huge components, finite and infinite `tmax`.
#[cfg(test)]
pub(crate) fn test_rays(n: u64) -> Vec<(Vec3A, Vec3A, f32)> {
    let mut rays = Vec::new();
    for i in 0..n {
        let r = |k: u64| unit(i * 16 + k) * 2.0 - 1.0;
        let o = Vec3A::new(r(0), r(1), r(2)) * 3.0;
        let mut d = Vec3A::new(r(3), r(4), r(5));
        match i % 8 {
            0 => d = Vec3A::new(-0.0, 0.0, if r(6) < 0.0 { -1.0 } else { 1.0 }),
            1 => d = Vec3A::new(d.x, -0.0, 1e-30),
            2 => d *= 1e-20,
            3 => d *= 1e20,
            _ => {}
        }
        let t_max = if i % 3 == 0 { f32::INFINITY } else { unit(i * 16 + 7) * 6.0 };
        rays.push((o, d, t_max));
    }
    rays
}

#[cfg(test)]
mod tests {
    use super::*;
    use obvhs::BvhBuildParams;
    use obvhs::aabb::Aabb;
    use obvhs::cwbvh::builder::build_cwbvh;
    use std::time::Duration;

    /// The SSE2 offset gives the component-wise one's bits: points near and far from the
    /// origin, of both signs, zeros, subnormals, NaN and infinities; unit, scaled, NaN and huge
    /// normals.
    #[test]
    fn sse2_offset_matches_the_scalar_offset() {
        let values = [
            0.0,
            -0.0,
            1e-40,
            -1e-40,
            0.01,
            -0.01,
            0.03125,
            -0.03125,
            0.5,
            -0.75,
            3.0,
            -1e5,
            3e38,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let normals = [0.0, -0.0, 1.0, -1.0, 0.577, -0.3, 1e-3, 8.4e6, 1e10, -1e10, f32::NAN, f32::INFINITY];
        let mut cases = 0;
        for (i, &px) in values.iter().enumerate() {
            for (j, &nx) in normals.iter().enumerate() {
                let p = Vec3A::new(px, values[(i + 3) % values.len()], values[(i + 7) % values.len()]);
                let n = Vec3A::new(nx, normals[(j + 2) % normals.len()], normals[(j + 5) % normals.len()]);
                let bits = |v: Vec3A| v.to_array().map(f32::to_bits);
                assert_eq!(bits(offset_along(p, n)), bits(super::super::geometry::offset_along(p, n)), "{p} {n}");
                cases += 1;
            }
        }
        for k in 0..20_000u64 {
            let r = |m: u64| unit(k * 8 + m) * 2.0 - 1.0;
            let scale = [1e-3, 0.1, 1.0, 40.0, 1e4][(k % 5) as usize];
            let p = Vec3A::new(r(0), r(1), r(2)) * scale;
            let n = Vec3A::new(r(3), r(4), r(5)).normalize_or(Vec3A::Z);
            let bits = |v: Vec3A| v.to_array().map(f32::to_bits);
            assert_eq!(bits(offset_along(p, n)), bits(super::super::geometry::offset_along(p, n)), "{p} {n}");
            cases += 1;
        }
        assert!(cases > 20_000);
    }

    /// `transpose8x8` moves element `j` of row `i` to element `i` of row `j`.
    #[test]
    fn matrix_transpose_moves_each_element() {
        let Some(avx2) = Avx2::new() else { return };
        let m: [[f32; 8]; 8] = std::array::from_fn(|i| std::array::from_fn(|j| (i * 8 + j) as f32));
        let t = avx2.transpose8x8(&m);
        for i in 0..8 {
            for j in 0..8 {
                assert_eq!(t[j][i], m[i][j], "row {i} column {j}");
            }
        }
    }

    /// The 8-wide Sobol kernels give the scalar sampler's bits for many indices and seeds.
    #[test]
    fn avx2_sobol_kernels_match_the_scalar_sampler() {
        let Some(avx2) = Avx2::new() else { return };
        for round in 0..2000u64 {
            let word = |k: u64| (hash(round * 64 + k) >> 7) as u32;
            let index: [u32; 8] =
                std::array::from_fn(|i| if round % 3 == 0 { i as u32 + round as u32 } else { word(i as u64) });
            let (s1, s2, s3): ([u32; 8], [u32; 8], [u32; 8]) = (
                std::array::from_fn(|i| word(8 + i as u64)),
                std::array::from_fn(|i| word(16 + i as u64)),
                std::array::from_fn(|i| word(24 + i as u64)),
            );
            let x = avx2.run(|| avx2.sobol_x(&index, &s1, &s2));
            let (x2, y2) = avx2.run(|| avx2.sobol_xy(&index, &s1, &s2, &s3));
            for i in 0..8 {
                let (want_x, want_y) = sobol_scalar(index[i], s1[i], s2[i], Some(s3[i]));
                let (want_x, want_y) = (u32_to_unit_float(want_x), u32_to_unit_float(want_y));
                assert_eq!(
                    (x[i], x2[i], y2[i]),
                    (want_x, want_x, want_y),
                    "index {} seeds {} {} {}",
                    index[i],
                    s1[i],
                    s2[i],
                    s3[i]
                );
            }
        }
    }

    /// The 16-lane Sobol kernel gives the scalar sampler's bits at every level the CPU has.
    #[test]
    fn sobol_x16_matches_the_scalar_sampler() {
        let Some(best) = Avx2::new() else { return };
        for level in [SimdLevel::Avx2, best.level()] {
            let Some(avx2) = Avx2::at(level) else { continue };
            for round in 0..1000u64 {
                let word = |k: u64| (hash(round * 64 + k) >> 7) as u32;
                let index: [u32; 16] =
                    std::array::from_fn(|i| if round % 3 == 0 { i as u32 + round as u32 } else { word(i as u64) });
                let seeds: [[u32; 16]; 3] =
                    std::array::from_fn(|k| std::array::from_fn(|i| word(16 * (k as u64 + 1) + i as u64)));
                let (x, _) = avx2.run(|| avx2.sobol_x16(&index, &seeds[0], &seeds[1], None));
                let (x2, y2) = avx2.run(|| avx2.sobol_x16(&index, &seeds[0], &seeds[1], Some(&seeds[2])));
                for i in 0..16 {
                    let (want_x, want_y) = sobol_scalar(index[i], seeds[0][i], seeds[1][i], Some(seeds[2][i]));
                    let (want_x, want_y) = (u32_to_unit_float(want_x), u32_to_unit_float(want_y));
                    assert_eq!((x[i], x2[i], y2[i]), (want_x, want_x, want_y), "{level:?} lane {i} index {}", index[i]);
                }
            }
        }
    }

    /// The AVX2 node test gives obvhs' hit mask, bit for bit, for every node of a BVH and many
    /// rays (where the CPU has AVX2; elsewhere there is nothing to compare).
    #[test]
    fn avx2_node_test_matches_baseline() {
        let Some(avx2) = Avx2::new() else { return };
        let boxes: Vec<Aabb> = (0..2000u64)
            .map(|i| {
                let c = Vec3A::new(unit(i * 4), unit(i * 4 + 1), unit(i * 4 + 2)) * 4.0 - 2.0;
                let h = Vec3A::splat(0.01 + 0.2 * unit(i * 4 + 3));
                Aabb { min: c - h, max: c + h }
            })
            .collect();
        let bvh = build_cwbvh(&boxes, BvhBuildParams::medium_build(), &mut Duration::default());
        let mut compared = 0u64;
        let mut nonzero = 0u64;
        for (o, d, t_max) in test_rays(400) {
            let ray = Ray::new(o, d + Vec3A::ZERO, 0.0, t_max);
            let state = bvh.new_traversal(ray.direction);
            for node in &bvh.nodes {
                let want = Baseline.hits(node, &ray, state.oct_inv4);
                let got = avx2.run(|| avx2.hits(node, &ray, state.oct_inv4));
                assert_eq!(got, want, "ray {o} {d} {t_max}");
                compared += 1;
                nonzero += u64::from(want != 0);
            }
        }
        assert!(compared > 10_000 && nonzero > 1_000, "{compared} compared, {nonzero} with hits");
    }
}

/// Renders with both levels give the same bits (where the CPU has AVX2).
#[cfg(test)]
mod render_tests {
    use super::SimdLevel;
    use crate::render::Renderer;
    use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, Pass, RenderSettings, TileRect};
    use pathfarm_common::scene::{LoadOptions, load_scene};

    fn render(integrator: IntegratorSettings, level: SimdLevel) -> Option<crate::render::UnitResult> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../reference/cornell_spheres.glb");
        let scene = load_scene(&path, &LoadOptions::default()).expect("reference scene");
        let mut settings = RenderSettings::new(32, 32, 4);
        settings.integrator = integrator;
        let mut r = Renderer::new(&scene, &settings).expect("renderer");
        (r.set_simd_level(level) == level)
            .then(|| r.render_unit(TileRect { x0: 0, y0: 0, x1: 32, y1: 32 }, Pass { index: 0, s0: 0, s1: 4 }))
    }

    /// Path, bdpt (its shadow rays and light-subpath splats) and igi (VPL visibility): the AVX2
    /// and AVX-512 kernels give the baseline's unit result bit for bit.
    #[test]
    fn simd_levels_render_bit_identical_units() {
        let path = IntegratorSettings::Path {
            max_depth: 8,
            rr_depth: 3,
            mis: MisHeuristic::Power,
            light_sampling: LightSampling::SolidAngle,
        };
        let bdpt = IntegratorSettings::Bdpt { max_depth: 5, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
        let igi =
            IntegratorSettings::Igi { vpls: 16, vpl_sets: 2, g_limit: 10.0, bias_compensation: false, max_depth: 4 };
        for integrator in [path, bdpt, igi] {
            let base = render(integrator.clone(), SimdLevel::Baseline).expect("the baseline always runs");
            assert!(base.accum.sums.iter().any(|p| p != &Default::default()), "{integrator:?}: an empty image");
            for level in [SimdLevel::Avx2, SimdLevel::Avx512] {
                let Some(wide) = render(integrator.clone(), level) else { continue };
                assert_eq!(base, wide, "{integrator:?} at {level:?}");
            }
        }
    }
}
