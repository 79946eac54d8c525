//! Addressable samplers (pbrt-v4's `Sampler` interface, `IndependentSampler`, and a padded,
//! Owen-scrambled Sobol sampler after Burley 2020, "Practical Hash-based Owen Scrambling").
//!
//! Every number a sampler returns is a pure function of (seed, pixel, sample index, dimension).
//! It never depends on what was sampled before, on the tile, the thread or how the samples of a
//! pixel are split into passes, so a farm render is bit-identical to a local one.
//!
//! # Dimension convention
//! [`Sampler::start_pixel_sample`] sets the current dimension. [`Sampler::get_1d`] reads one
//! number at the current dimension and advances it by 1. [`Sampler::get_2d`] and
//! [`Sampler::get_pixel_2d`] read a pair keyed by the current dimension and advance it by 2.
//! A pair is keyed by its first dimension, whatever its parity (pbrt-v4's `PaddedSobolSampler`),
//! so `get_1d` before `get_2d` does not break the 2D stratification.
//! The camera calls `get_pixel_2d` first, at dimension 0.
//!
//! # Streams not tied to a pixel
//! Light paths (BDPT) or virtual point lights (IGI) use a pseudo pixel, for example
//! `UVec2::new(pass_index, u32::MAX)`, with their own seed or dimension offset. Any `UVec2` is a
//! valid address.

use glam::{UVec2, Vec2};
use pathfarm_common::job::SamplerKind;

/// The 64-bit golden-ratio increment (SplitMix64), used to keep hashed values away from zero.
const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// A 64-bit bit mixer with full avalanche (pbrt-v4's `MixBits`); a bijection.
#[inline]
pub fn mix_bits(mut v: u64) -> u64 {
    v ^= v >> 31;
    v = v.wrapping_mul(0x7fb5_d329_728e_a185);
    v ^= v >> 27;
    v = v.wrapping_mul(0x81da_def4_bc2d_d44d);
    v ^= v >> 33;
    v
}

/// Hashes a tuple of values into 64 well-mixed bits. Order matters: `[a, b]` and `[b, a]` hash
/// differently, and so do `[a]` and `[a, 0]`.
#[inline]
pub fn hash_u64(values: &[u64]) -> u64 {
    let mut h = 0x6A09_E667_F3BC_C909; // fractional bits of sqrt(2): any nonzero start works
    for &v in values {
        // mix_bits is a bijection, so for a fixed prefix distinct values give distinct hashes.
        h = mix_bits(h ^ v.wrapping_add(GOLDEN));
    }
    h
}

/// Maps 32 random bits to a float in [0, 1): the top 24 bits on a uniform grid of step 2^-24,
/// so the result is at most `1 - 2^-24` and never rounds up to 1.
#[inline]
pub fn u32_to_unit_float(v: u32) -> f32 {
    (v >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// The fast hash-based Laine-Karras permutation of Burley 2020 with Vegdahl's improved constants
/// (pbrt-v4's `FastOwenScrambler` core). It operates on bit-reversed values: every step changes
/// a bit only as a function of the bits below it, which is exactly a nested (Owen) permutation
/// once the bits are reversed back.
#[inline]
pub fn laine_karras_permutation(mut x: u32, seed: u32) -> u32 {
    x ^= x.wrapping_mul(0x3d20_adea);
    x = x.wrapping_add(seed);
    x = x.wrapping_mul((seed >> 16) | 1);
    x ^= x.wrapping_mul(0x0552_6c56);
    x ^= x.wrapping_mul(0x53a2_2864);
    x
}

/// Owen scrambling of a 32-bit fixed-point number in [0, 1) (most significant bit first), or of
/// a sample index (Burley's shuffle). Applied to the indices `0..2^m`, it permutes an aligned
/// block of `2^m` indices; applied to coordinates, it keeps every elementary interval.
#[inline]
pub fn nested_uniform_scramble(x: u32, seed: u32) -> u32 {
    laine_karras_permutation(x.reverse_bits(), seed).reverse_bits()
}

/// Direction numbers of the second Sobol dimension (the tests' reference for
/// [`sobol_dim1_reversed`]): the Pascal matrix modulo 2, column `k`
/// being `v_k = v_{k-1} ^ (v_{k-1} >> 1)` from `v_0 = 2^31`.
#[cfg(test)]
const SOBOL_DIM1_MATRIX: [u32; 32] = {
    let mut m = [0u32; 32];
    let mut v = 1u32 << 31;
    let mut k = 0;
    while k < 32 {
        m[k] = v;
        v ^= v >> 1;
        k += 1;
    }
    m
};

/// First Sobol dimension (van der Corput in base 2) as 32-bit fixed point.
#[inline]
pub fn sobol_dim0(index: u32) -> u32 {
    index.reverse_bits()
}

/// Second Sobol dimension as 32-bit fixed point: [`sobol_dim1_reversed`], its bits reversed.
#[inline]
pub fn sobol_dim1(index: u32) -> u32 {
    sobol_dim1_reversed(index).reverse_bits()
}

/// [`sobol_dim1`] with its bits reversed (bit `j` the coefficient of `2^-(j + 1)`): the product
/// of `SOBOL_DIM1_MATRIX` (Pascal's triangle mod 2, entry (row `j`, column `k`) = C(k, j) mod 2)
/// with the index, in five shifts and XORs, no table. By Lucas's theorem the matrix on 2^m bits
/// is [[P, P], [0, P]] in blocks of halves (P the matrix on 2^(m-1) bits): the low half of the
/// product is P (low ^ high), the high half P high. So the high half of every block is XORed
/// into its low half, blocks of 16 bits first, then 8, 4, 2 and 1.
///
/// It replaced a table of 4 x 256 entries (the matrix's columns folded per index byte), looked
/// up per byte: in lanes, 4 gathers per 2D request. On an AVX2-only AMD EPYC (Zen 3): `tiny`
/// 415.7M -> 415.6M instructions (the gathers were few instructions, but slow ones), `tiny
/// long` 0.982x the time (median of 15 interleaved pairs, quartiles 0.902-0.997; 0.954x by the
/// sums), one pass on 2 threads (`tiny long onepass threads2`) 0.979x (21 pairs).
#[inline]
pub fn sobol_dim1_reversed(index: u32) -> u32 {
    let mut x = index;
    x ^= x >> 16;
    x ^= (x >> 8) & 0x00ff_00ff;
    x ^= (x >> 4) & 0x0f0f_0f0f;
    x ^= (x >> 2) & 0x3333_3333;
    x ^ ((x >> 1) & 0x5555_5555)
}

/// A source of sample values addressed by (pixel, sample index, dimension).
pub trait Sampler {
    /// Positions the stream at (pixel, sample index, first dimension `dim`).
    fn start_pixel_sample(&mut self, pixel: UVec2, index: u32, dim: u32);
    /// One number in [0, 1) (strictly below 1); advances the dimension by 1.
    fn get_1d(&mut self) -> f32;
    /// Two numbers in [0, 1); advances the dimension by 2.
    fn get_2d(&mut self) -> Vec2;
    /// The 2D sample used for the position inside the pixel (pbrt's `GetPixel2D`); here it is
    /// `get_2d` and advances the dimension by 2.
    fn get_pixel_2d(&mut self) -> Vec2;
    /// The 2D sample at dimension `dim` of the current pixel sample, leaving the stream where it
    /// is: a dedicated dimension (the lens) that does not shift every later one.
    fn get_2d_at(&mut self, dim: u32) -> Vec2;
    /// The current dimension.
    fn dimension(&self) -> u32;
    /// Moves the stream to dimension `dim` of the current pixel sample.
    fn set_dimension(&mut self, dim: u32);
    /// The numbers a path-tracing bounce may draw from the current dimension on (see
    /// [`BounceDraws`]), without moving the stream.
    fn bounce_draws(&self) -> BounceDraws;
    /// [`Sampler::get_pixel_2d`] of many samplers at once (each one's stream moves as that call
    /// moves it), appended to `out` in order; `level` picks the SIMD kernels where the sampler
    /// has some (the values are the same).
    fn pixel_2d_many<'a>(lanes: impl Iterator<Item = &'a mut Self>, level: super::wide::SimdLevel, out: &mut Vec<Vec2>)
    where
        Self: Sized + 'a,
    {
        let _ = level;
        out.extend(lanes.map(|s| s.get_pixel_2d()));
    }
    /// [`Sampler::bounce_draws`] of many samplers at once, appended to `out` in order; `level`
    /// picks the SIMD kernels where the sampler has some (the values are the same).
    fn bounce_draws_many<'a>(
        lanes: impl Iterator<Item = &'a Self>,
        level: super::wide::SimdLevel,
        out: &mut Vec<BounceDraws>,
    ) where
        Self: Sized + 'a,
    {
        let _ = level;
        out.extend(lanes.map(|s| s.bounce_draws()));
    }
}

/// Offsets from a bounce's first dimension of the 1D numbers a path-tracing bounce may draw.
/// With next-event estimation: lobe choice 0, light selection 1, light point 2-3 (2D), BSDF
/// lobe 4, direction 5-6 (2D), roulette 7. At a delta BSDF (no light sample): lobe choice 0,
/// BSDF lobe 1, direction 2-3 (2D), roulette 4. Both layouts read these addresses.
pub const BOUNCE_1D: [u32; 4] = [0, 1, 4, 7];
/// Offsets of the 2D numbers of a bounce (see [`BOUNCE_1D`]).
pub const BOUNCE_2D: [u32; 2] = [2, 5];

/// The numbers of one bounce, drawn ahead for a batch of paths ([`Sampler::bounce_draws_many`])
/// and served by [`Replay`]: the 1D numbers at `base + BOUNCE_1D[k]`, the 2D ones at
/// `base + BOUNCE_2D[k]`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BounceDraws {
    pub base: u32,
    pub d1: [f32; 4],
    pub d2: [Vec2; 2],
}

/// A sampler that serves the numbers drawn ahead in `draws` where a request's address is one of
/// theirs, and asks `inner` otherwise; its stream moves as `inner`'s would. Every number is
/// what `inner` returns at that address (the samplers are pure functions of it).
pub struct Replay<'a, S> {
    pub inner: &'a mut S,
    pub draws: &'a BounceDraws,
}

impl<S: Sampler> Sampler for Replay<'_, S> {
    fn start_pixel_sample(&mut self, pixel: UVec2, index: u32, dim: u32) {
        self.inner.start_pixel_sample(pixel, index, dim);
    }

    #[inline]
    fn get_1d(&mut self) -> f32 {
        let dim = self.inner.dimension();
        let offset = dim.wrapping_sub(self.draws.base);
        match BOUNCE_1D.iter().position(|&o| o == offset) {
            Some(k) => {
                self.inner.set_dimension(dim.wrapping_add(1));
                self.draws.d1[k]
            }
            None => self.inner.get_1d(),
        }
    }

    #[inline]
    fn get_2d(&mut self) -> Vec2 {
        let dim = self.inner.dimension();
        let offset = dim.wrapping_sub(self.draws.base);
        match BOUNCE_2D.iter().position(|&o| o == offset) {
            Some(k) => {
                self.inner.set_dimension(dim.wrapping_add(2));
                self.draws.d2[k]
            }
            None => self.inner.get_2d(),
        }
    }

    fn get_pixel_2d(&mut self) -> Vec2 {
        self.inner.get_pixel_2d()
    }

    fn get_2d_at(&mut self, dim: u32) -> Vec2 {
        self.inner.get_2d_at(dim)
    }

    fn dimension(&self) -> u32 {
        self.inner.dimension()
    }

    fn set_dimension(&mut self, dim: u32) {
        self.inner.set_dimension(dim);
    }

    fn bounce_draws(&self) -> BounceDraws {
        self.inner.bounce_draws()
    }
}

/// Independent uniform numbers from a counter-based hash of (seed, pixel, index, dimension).
/// `get_2d` at dimension `d` equals two `get_1d` calls at `d` and `d + 1`.
#[derive(Clone, Debug)]
pub struct IndependentSampler {
    seed: u64,
    /// Hash of (seed, pixel, index), so each number costs one more hash.
    sample_hash: u64,
    dim: u32,
}

impl IndependentSampler {
    pub fn new(seed: u64) -> Self {
        let mut s = Self { seed, sample_hash: 0, dim: 0 };
        s.start_pixel_sample(UVec2::ZERO, 0, 0);
        s
    }

    #[inline]
    fn value(&self, dim: u32) -> f32 {
        let h = hash_u64(&[self.sample_hash, u64::from(dim)]);
        u32_to_unit_float((h >> 32) as u32)
    }
}

impl Sampler for IndependentSampler {
    fn start_pixel_sample(&mut self, pixel: UVec2, index: u32, dim: u32) {
        self.sample_hash = hash_u64(&[self.seed, u64::from(pixel.x), u64::from(pixel.y), u64::from(index)]);
        self.dim = dim;
    }

    #[inline]
    fn get_1d(&mut self) -> f32 {
        let v = self.value(self.dim);
        self.dim = self.dim.wrapping_add(1);
        v
    }

    #[inline]
    fn get_2d(&mut self) -> Vec2 {
        let v = Vec2::new(self.value(self.dim), self.value(self.dim.wrapping_add(1)));
        self.dim = self.dim.wrapping_add(2);
        v
    }

    #[inline]
    fn get_pixel_2d(&mut self) -> Vec2 {
        self.get_2d()
    }

    #[inline]
    fn get_2d_at(&mut self, dim: u32) -> Vec2 {
        let saved = std::mem::replace(&mut self.dim, dim);
        let v = self.get_2d();
        self.dim = saved;
        v
    }

    fn dimension(&self) -> u32 {
        self.dim
    }

    fn set_dimension(&mut self, dim: u32) {
        self.dim = dim;
    }

    fn bounce_draws(&self) -> BounceDraws {
        let at = |o: u32| self.value(self.dim.wrapping_add(o));
        BounceDraws { base: self.dim, d1: BOUNCE_1D.map(at), d2: BOUNCE_2D.map(|o| Vec2::new(at(o), at(o + 1))) }
    }
}

/// [`SobolSampler`]'s seeds of one bounce: per 1D request, per 2D request.
type BounceSeeds = ([[u32; 2]; BOUNCE_1D.len()], [[u32; 3]; BOUNCE_2D.len()]);

/// `make()`, or the value it gave for the same `key` last time: the batched draws' seeds, which
/// depend on (pixel, dimension) alone and repeat for a pixel's samples, which follow one another.
#[inline(always)]
fn repeat_or<K: PartialEq + Copy, V: Copy>(last: &mut Option<(K, V)>, key: K, make: impl FnOnce() -> V) -> V {
    match *last {
        Some((k, v)) if k == key => v,
        _ => {
            let v = make();
            *last = Some((key, v));
            v
        }
    }
}

/// Owen-scrambled Sobol points, padded per dimension (Burley 2020; pbrt-v4's
/// `PaddedSobolSampler` with `FastOwen` randomization).
///
/// For a 2D request at dimension `d`, the sample index is shuffled by a nested uniform scramble
/// seeded by hash(seed, pixel, d); the point is (Sobol dimension 0, Sobol dimension 1) of the
/// shuffled index, each coordinate Owen-scrambled with its own seed. A 1D request uses Sobol
/// dimension 0 alone. The samples `0..2^m` of a pixel are therefore a (0, m, 2)-net in every
/// 2D request (one point in each elementary interval of area `2^-m`), and stratified in 1D;
/// different dimensions are decorrelated by their independent shuffles. Only the first two
/// Sobol dimensions are needed, so there are no tables beyond one 32-entry matrix.
#[derive(Clone, Debug)]
pub struct SobolSampler {
    seed: u64,
    /// The pixel of the current sample, and the hash of (seed, pixel): computed once per pixel
    /// (its samples follow one another), not once per sample.
    pixel: UVec2,
    pixel_hash: u64,
    index: u32,
    dim: u32,
}

impl SobolSampler {
    pub fn new(seed: u64) -> Self {
        Self { seed, pixel: UVec2::ZERO, pixel_hash: Self::pixel_hash(seed, UVec2::ZERO), index: 0, dim: 0 }
    }

    #[inline]
    fn pixel_hash(seed: u64, pixel: UVec2) -> u64 {
        hash_u64(&[seed, u64::from(pixel.x), u64::from(pixel.y)])
    }

    /// The seeds of the request at the current dimension; `tag` separates 1D from 2D requests.
    #[inline]
    fn dim_hash(&self, tag: u64) -> u64 {
        self.hash_at(self.dim, tag)
    }

    /// The 32-bit seeds of a bounce's requests (see [`BOUNCE_1D`], [`BOUNCE_2D`]): per 1D
    /// request the two scrambles', per 2D request the three.
    #[inline]
    fn bounce_seeds(&self) -> BounceSeeds {
        let one = BOUNCE_1D.map(|o| {
            let h = self.hash_at(self.dim.wrapping_add(o), 0);
            [h as u32, (h >> 32) as u32]
        });
        let two = BOUNCE_2D.map(|o| {
            let h = self.hash_at(self.dim.wrapping_add(o), 1);
            [h as u32, (h >> 32) as u32, mix_bits(h.wrapping_add(GOLDEN)) as u32]
        });
        (one, two)
    }

    /// The seeds of a request at dimension `dim`.
    #[inline]
    fn hash_at(&self, dim: u32, tag: u64) -> u64 {
        // `pixel_hash` is already well mixed; one more bijective mix per request keeps 2D
        // requests (odd tags) and 1D requests apart at every dimension.
        mix_bits(self.pixel_hash ^ (u64::from(dim) << 1 | tag).wrapping_mul(GOLDEN))
    }
}

impl Sampler for SobolSampler {
    fn start_pixel_sample(&mut self, pixel: UVec2, index: u32, dim: u32) {
        if pixel != self.pixel {
            self.pixel = pixel;
            self.pixel_hash = Self::pixel_hash(self.seed, pixel);
        }
        self.index = index;
        self.dim = dim;
    }

    #[inline]
    fn get_1d(&mut self) -> f32 {
        let h = self.dim_hash(0);
        let shuffled = nested_uniform_scramble(self.index, h as u32);
        let x = nested_uniform_scramble(sobol_dim0(shuffled), (h >> 32) as u32);
        self.dim = self.dim.wrapping_add(1);
        u32_to_unit_float(x)
    }

    #[inline]
    fn get_2d(&mut self) -> Vec2 {
        let h = self.dim_hash(1);
        let h2 = mix_bits(h.wrapping_add(GOLDEN));
        let shuffled = nested_uniform_scramble(self.index, h as u32);
        let x = nested_uniform_scramble(sobol_dim0(shuffled), (h >> 32) as u32);
        // nested_uniform_scramble(sobol_dim1(shuffled), ..), its two reversals before the
        // permutation cancelled.
        let y = laine_karras_permutation(sobol_dim1_reversed(shuffled), h2 as u32).reverse_bits();
        self.dim = self.dim.wrapping_add(2);
        Vec2::new(u32_to_unit_float(x), u32_to_unit_float(y))
    }

    #[inline]
    fn get_pixel_2d(&mut self) -> Vec2 {
        self.get_2d()
    }

    #[inline]
    fn get_2d_at(&mut self, dim: u32) -> Vec2 {
        let saved = std::mem::replace(&mut self.dim, dim);
        let v = self.get_2d();
        self.dim = saved;
        v
    }

    fn dimension(&self) -> u32 {
        self.dim
    }

    fn set_dimension(&mut self, dim: u32) {
        self.dim = dim;
    }

    fn bounce_draws(&self) -> BounceDraws {
        let at = |o: u32| Self { dim: self.dim.wrapping_add(o), ..self.clone() };
        BounceDraws { base: self.dim, d1: BOUNCE_1D.map(|o| at(o).get_1d()), d2: BOUNCE_2D.map(|o| at(o).get_2d()) }
    }

    // Out of line: inlined into the camera stage, it costs the 130k scene 8M instructions.
    #[inline(never)]
    fn pixel_2d_many<'a>(lanes: impl Iterator<Item = &'a mut Self>, level: super::wide::SimdLevel, out: &mut Vec<Vec2>)
    where
        Self: 'a,
    {
        let Some(avx2) = super::wide::Avx2::at(level) else {
            out.extend(lanes.map(|s| s.get_pixel_2d()));
            return;
        };
        // One kernel for the whole batch (one call per 8 samplers left each call's scrambles
        // waiting on the last).
        avx2.run_kernel(Pixel2dMany { avx2, lanes, out });
    }

    // Inline into its one caller (the wavefront's bounce loop): left to the inliner, it went in
    // or out of line as unrelated code changed, and out of line cost 0.5% more instructions.
    #[inline(always)]
    fn bounce_draws_many<'a>(
        lanes: impl Iterator<Item = &'a Self>,
        level: super::wide::SimdLevel,
        out: &mut Vec<BounceDraws>,
    ) where
        Self: 'a,
    {
        let Some(avx2) = super::wide::Avx2::at(level) else {
            out.extend(lanes.map(|s| s.bounce_draws()));
            return;
        };
        // One kernel for the whole batch (see `pixel_2d_many`).
        avx2.run_kernel(BounceDrawsMany { avx2, lanes, out });
    }
}

/// [`SobolSampler::pixel_2d_many`]'s loop, run as one kernel compiled for the CPU's level.
///
/// Tried on an Intel Xeon (AVX-512) and dropped: 16 samplers at a time in 512-bit operations
/// ([`super::wide::Avx2::sobol_x16`], which pays for a bounce's draws): `tiny large long` 1.027x
/// the time (median of 15 interleaved pairs), `tiny long` 1.007x (11), the same instructions.
struct Pixel2dMany<'o, I> {
    avx2: super::wide::Avx2,
    lanes: I,
    out: &'o mut Vec<Vec2>,
}

impl<'a, I: Iterator<Item = &'a mut SobolSampler>> super::wide::V3Kernel for Pixel2dMany<'_, I> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let Self { avx2, lanes, out } = self;
        // Eight samplers at a time: the 64-bit seeds of `get_2d` here (made once for a pixel's
        // samples: `repeat_or`), its scrambles 8-wide.
        let mut lanes = lanes.peekable();
        let mut last: Option<((u64, u32), [u32; 3])> = None;
        while lanes.peek().is_some() {
            let mut index = [0u32; 8];
            let mut seeds = [[0u32; 8]; 3];
            let mut n = 0;
            for s in lanes.by_ref().take(8) {
                let lane_seeds = repeat_or(&mut last, (s.pixel_hash, s.dim), || {
                    let h = s.dim_hash(1);
                    [h as u32, (h >> 32) as u32, mix_bits(h.wrapping_add(GOLDEN)) as u32]
                });
                index[n] = s.index;
                (seeds[0][n], seeds[1][n], seeds[2][n]) = (lane_seeds[0], lane_seeds[1], lane_seeds[2]);
                s.dim = s.dim.wrapping_add(2);
                n += 1;
            }
            let (x, y) = avx2.sobol_xy(&index, &seeds[0], &seeds[1], &seeds[2]);
            out.extend((0..n).map(|i| Vec2::new(x[i], y[i])));
        }
    }
}

/// [`SobolSampler::bounce_draws_many`]'s loop, run as one kernel compiled for the CPU's level.
///
/// Tried on an Intel Xeon (AVX-512) and dropped: the seeds of a chunk of samplers of several
/// pixels or dimensions hashed in lanes (64-bit `mix_bits` made of 32-bit products, straight
/// into the scrambles' lanes), not one sampler at a time and scattered into the lanes' arrays:
/// `tiny` 417.9M -> 415.6M instructions, `tiny large` 1,353.6M -> 1,351.9M, `tiny long` 1.005x
/// and `tiny long onepass threads2` 1.002x the time (medians of 11 interleaved pairs): noise.
/// Also dropped there: only the 1D rows the shading stage may read drawn (the lobe choices
/// left out where every hit shades in Lambertian lanes, roulette's number before roulette
/// plays; `Replay` asking the sampler for a missing one): the Cornell box's early bounces drew
/// one 1D row of four, yet `tiny long` took 0.982x the time (median of 21 interleaved pairs,
/// quartiles 0.961-1.022), `tiny long depth2` 0.993x, `tiny large long` 0.978x (11 pairs,
/// quartiles 0.964-1.044), and the AVX2 kernels' `tiny` 412.3M -> 414.2M instructions (the
/// rows' branches cost the inliner more than the rows saved): within the machine's noise.
struct BounceDrawsMany<'o, I> {
    avx2: super::wide::Avx2,
    lanes: I,
    out: &'o mut Vec<BounceDraws>,
}

impl<'a, I: Iterator<Item = &'a SobolSampler>> super::wide::V3Kernel for BounceDrawsMany<'_, I> {
    type Output = ();
    #[inline(always)]
    fn call(self) {
        let Self { avx2, lanes, out } = self;
        if avx2.has_16_lanes() {
            bounce_draws_lanes::<16>(avx2, lanes, out, |index, s1, s2, s3| avx2.sobol_x16(index, s1, s2, s3));
        } else {
            bounce_draws_lanes::<8>(avx2, lanes, out, |index, s1, s2, s3| match s3 {
                Some(s3) => avx2.sobol_xy(index, s1, s2, s3),
                None => (avx2.sobol_x(index, s1, s2), [0.0; 8]),
            });
        }
    }
}

/// [`BounceDrawsMany`]'s loop over `N` samplers at a time (8, or 16 where the CPU runs 512-bit
/// kernels: measured on an Intel Xeon with AVX-512, `tiny long` 0.981x the time, median of 21
/// interleaved pairs, quartiles 0.966-0.988), with `sobol` the Sobol kernel for `N` lanes:
/// the 64-bit seeds here (made once for a pixel's paths at one bounce: `repeat_or`), the
/// scrambles in lanes.
#[inline(always)]
fn bounce_draws_lanes<'a, const N: usize>(
    avx2: super::wide::Avx2,
    lanes: impl Iterator<Item = &'a SobolSampler>,
    out: &mut Vec<BounceDraws>,
    sobol: impl Fn(&[u32; N], &[u32; N], &[u32; N], Option<&[u32; N]>) -> ([f32; N], [f32; N]),
) {
    let mut chunk: Vec<&SobolSampler> = Vec::with_capacity(N);
    let mut lanes = lanes.peekable();
    let mut last: Option<((u64, u32), BounceSeeds)> = None;
    while lanes.peek().is_some() {
        chunk.clear();
        chunk.extend(lanes.by_ref().take(N));
        let mut index = [0u32; N];
        let mut seeds1 = [[[0u32; N]; 2]; 4];
        let mut seeds2 = [[[0u32; N]; 3]; 2];
        for (lane, s) in chunk.iter().enumerate() {
            index[lane] = s.index;
        }
        for (h, eight) in chunk.chunks(8).enumerate() {
            let lanes = h * 8..h * 8 + 8;
            let first = (eight[0].pixel_hash, eight[0].dim);
            if eight.len() == 8 && eight.iter().all(|s| (s.pixel_hash, s.dim) == first) {
                // One pixel's paths at one bounce (the common case: a pixel's samples follow
                // one another): the same seeds in each of these 8 lanes.
                let (one, two) = repeat_or(&mut last, first, || eight[0].bounce_seeds());
                for k in 0..BOUNCE_1D.len() {
                    seeds1[k][0][lanes.clone()].fill(one[k][0]);
                    seeds1[k][1][lanes.clone()].fill(one[k][1]);
                }
                for k in 0..BOUNCE_2D.len() {
                    for j in 0..3 {
                        seeds2[k][j][lanes.clone()].fill(two[k][j]);
                    }
                }
            } else {
                for (lane, s) in lanes.zip(eight) {
                    let (one, two) = repeat_or(&mut last, (s.pixel_hash, s.dim), || s.bounce_seeds());
                    for k in 0..BOUNCE_1D.len() {
                        (seeds1[k][0][lane], seeds1[k][1][lane]) = (one[k][0], one[k][1]);
                    }
                    for k in 0..BOUNCE_2D.len() {
                        (seeds2[k][0][lane], seeds2[k][1][lane], seeds2[k][2][lane]) =
                            (two[k][0], two[k][1], two[k][2]);
                    }
                }
            }
        }
        // The requests' values (4 1D, then 2 2D) in rows of `N` lanes, transposed 8 lanes at a
        // time: lane `i`'s 8 numbers in a row.
        let x1: [[f32; N]; 4] = std::array::from_fn(|k| sobol(&index, &seeds1[k][0], &seeds1[k][1], None).0);
        let (x20, y20) = sobol(&index, &seeds2[0][0], &seeds2[0][1], Some(&seeds2[0][2]));
        let (x21, y21) = sobol(&index, &seeds2[1][0], &seeds2[1][1], Some(&seeds2[1][2]));
        let rows = [&x1[0], &x1[1], &x1[2], &x1[3], &x20, &y20, &x21, &y21];
        for (h, eight) in chunk.chunks(8).enumerate() {
            let by_lane = avx2.transpose8x8(&rows.map(|r| std::array::from_fn(|i| r[h * 8 + i])));
            for (s, v) in eight.iter().zip(&by_lane) {
                out.push(BounceDraws {
                    base: s.dim,
                    d1: [v[0], v[1], v[2], v[3]],
                    d2: [Vec2::new(v[4], v[5]), Vec2::new(v[6], v[7])],
                });
            }
        }
    }
}

/// The sampler a job chose. The integrator matches on it once per unit and runs a loop
/// monomorphized for the concrete sampler; this enum's own `Sampler` impl is for cold paths.
#[derive(Clone, Debug)]
pub enum AnySampler {
    Independent(IndependentSampler),
    Sobol(SobolSampler),
}

impl AnySampler {
    pub fn new(kind: SamplerKind, seed: u64) -> Self {
        match kind {
            SamplerKind::Independent => Self::Independent(IndependentSampler::new(seed)),
            SamplerKind::Sobol => Self::Sobol(SobolSampler::new(seed)),
        }
    }
}

impl Sampler for AnySampler {
    #[inline]
    fn start_pixel_sample(&mut self, pixel: UVec2, index: u32, dim: u32) {
        match self {
            Self::Independent(s) => s.start_pixel_sample(pixel, index, dim),
            Self::Sobol(s) => s.start_pixel_sample(pixel, index, dim),
        }
    }

    #[inline]
    fn get_1d(&mut self) -> f32 {
        match self {
            Self::Independent(s) => s.get_1d(),
            Self::Sobol(s) => s.get_1d(),
        }
    }

    #[inline]
    fn get_2d(&mut self) -> Vec2 {
        match self {
            Self::Independent(s) => s.get_2d(),
            Self::Sobol(s) => s.get_2d(),
        }
    }

    #[inline]
    fn get_pixel_2d(&mut self) -> Vec2 {
        match self {
            Self::Independent(s) => s.get_pixel_2d(),
            Self::Sobol(s) => s.get_pixel_2d(),
        }
    }

    #[inline]
    fn get_2d_at(&mut self, dim: u32) -> Vec2 {
        match self {
            Self::Independent(s) => s.get_2d_at(dim),
            Self::Sobol(s) => s.get_2d_at(dim),
        }
    }

    fn dimension(&self) -> u32 {
        match self {
            Self::Independent(s) => s.dimension(),
            Self::Sobol(s) => s.dimension(),
        }
    }

    fn set_dimension(&mut self, dim: u32) {
        match self {
            Self::Independent(s) => s.set_dimension(dim),
            Self::Sobol(s) => s.set_dimension(dim),
        }
    }

    fn bounce_draws(&self) -> BounceDraws {
        match self {
            Self::Independent(s) => s.bounce_draws(),
            Self::Sobol(s) => s.bounce_draws(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::chi2::{Chi2Options, test_rect};

    const SEED: u64 = 0x5EED_0001;

    fn samplers(seed: u64) -> [AnySampler; 2] {
        [AnySampler::new(SamplerKind::Independent, seed), AnySampler::new(SamplerKind::Sobol, seed)]
    }

    /// The first `n` numbers at (pixel, index, dim) as bits: 1D requests then 2D requests.
    fn stream(s: &mut impl Sampler, pixel: UVec2, index: u32, dim: u32, n: usize) -> Vec<u32> {
        s.start_pixel_sample(pixel, index, dim);
        let mut out = Vec::new();
        for k in 0..n {
            if k % 3 == 0 {
                out.push(s.get_1d().to_bits());
            } else {
                let v = s.get_2d();
                out.extend([v.x.to_bits(), v.y.to_bits()]);
            }
        }
        out
    }

    #[test]
    fn hash_helpers_are_sensitive_to_order_and_length() {
        assert_ne!(hash_u64(&[1, 2]), hash_u64(&[2, 1]));
        assert_ne!(hash_u64(&[1]), hash_u64(&[1, 0]));
        assert_ne!(hash_u64(&[0]), hash_u64(&[]));
        assert_eq!(mix_bits(0), 0);
        assert_ne!(mix_bits(1), 1);
        assert_eq!(u32_to_unit_float(0), 0.0);
        assert!(u32_to_unit_float(u32::MAX) < 1.0);
        assert_eq!(u32_to_unit_float(u32::MAX), crate::render::sampling::ONE_MINUS_EPSILON);
    }

    /// The numbers of a bounce drawn ahead, one sampler or a batch at every SIMD level, are the
    /// stream's own numbers at those dimensions; `Replay` serves them and moves the stream as
    /// the sampler would.
    #[test]
    fn bounce_draws_are_the_streams_numbers() {
        use crate::render::wide::SimdLevel;
        for kind in [SamplerKind::Sobol, SamplerKind::Independent] {
            // Samplers of different pixels and dimensions, then 14 of one pixel at one dimension
            // (a chunk of 8 lanes of the same seeds), then a last few.
            let lanes: Vec<AnySampler> = (0..37u32)
                .map(|i| {
                    let mut s = AnySampler::new(kind, 7);
                    match i {
                        21..35 => s.start_pixel_sample(UVec2::new(3, 4), i, 5),
                        _ => s.start_pixel_sample(UVec2::new(i * 37, i % 5), i * 1001 + i / 3, (i * 13) % 40),
                    }
                    s
                })
                .collect();
            let sobol: Vec<SobolSampler> = lanes
                .iter()
                .filter_map(|s| match s {
                    AnySampler::Sobol(s) => Some(s.clone()),
                    AnySampler::Independent(_) => None,
                })
                .collect();
            for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
                let mut many = Vec::new();
                AnySampler::bounce_draws_many(lanes.iter(), level, &mut many);
                let mut many_sobol = Vec::new();
                SobolSampler::bounce_draws_many(sobol.iter(), level, &mut many_sobol);
                assert_eq!(many.len(), lanes.len());
                if kind == SamplerKind::Sobol {
                    assert_eq!(many_sobol, many, "{level:?}");
                }
                for (s, draws) in lanes.iter().zip(&many) {
                    assert_eq!(*draws, s.bounce_draws());
                    for (k, &o) in BOUNCE_1D.iter().enumerate() {
                        let mut t = s.clone();
                        t.set_dimension(s.dimension() + o);
                        assert_eq!(t.get_1d().to_bits(), draws.d1[k].to_bits(), "{kind:?} {level:?} 1D at +{o}");
                    }
                    for (k, &o) in BOUNCE_2D.iter().enumerate() {
                        let mut t = s.clone();
                        t.set_dimension(s.dimension() + o);
                        assert_eq!(t.get_2d(), draws.d2[k], "{kind:?} {level:?} 2D at +{o}");
                    }
                    // Replay: a delta bounce's layout (1D, 2D, 1D from base + 1), then numbers
                    // it has not drawn ahead.
                    let (mut a, mut b) = (s.clone(), s.clone());
                    let mut r = Replay { inner: &mut a, draws };
                    let got = (r.get_1d(), r.get_1d(), r.get_2d(), r.get_1d(), r.get_1d(), r.get_2d(), r.get_1d());
                    let want = (b.get_1d(), b.get_1d(), b.get_2d(), b.get_1d(), b.get_1d(), b.get_2d(), b.get_1d());
                    assert_eq!(got, want);
                    assert_eq!(a.dimension(), b.dimension());
                }
            }
        }
    }

    #[test]
    fn sobol_dim1_matches_the_matrix_product() {
        let reference = |mut index: u32| {
            let (mut r, mut k) = (0u32, 0);
            while index != 0 {
                if index & 1 != 0 {
                    r ^= SOBOL_DIM1_MATRIX[k];
                }
                index >>= 1;
                k += 1;
            }
            r
        };
        for i in (0..100_000u32).chain([u32::MAX, 0x8000_0000, 0xdead_beef]) {
            let i = mix_bits(u64::from(i)) as u32;
            assert_eq!(sobol_dim1(i), reference(i), "index {i:#x}");
        }
    }

    #[test]
    fn sobol_dim1_matches_the_known_sequence() {
        // Sobol's second dimension in index (not Gray code) order.
        let expected = [0.0, 0.5, 0.75, 0.25, 0.625, 0.125, 0.375, 0.875];
        for (i, e) in expected.iter().enumerate() {
            assert_eq!(sobol_dim1(i as u32) as f64 / 2f64.powi(32), *e, "index {i}");
            assert_eq!(sobol_dim0(i as u32), (i as u32).reverse_bits());
        }
    }

    #[test]
    fn nested_uniform_scramble_permutes_aligned_blocks() {
        for seed in [0u32, 1, 0xdead_beef, 0x1234_5678] {
            for m in [1u32, 4, 8] {
                let mut seen: Vec<u32> = (0..1u32 << m).map(|i| nested_uniform_scramble(i, seed)).collect();
                let block = seen[0] >> m;
                assert!(seen.iter().all(|&v| v >> m == block), "seed {seed} m {m}: not one aligned block");
                seen.sort_unstable();
                seen.dedup();
                assert_eq!(seen.len(), 1 << m, "seed {seed} m {m}: not a permutation");
            }
        }
    }

    #[test]
    fn values_depend_only_on_the_address() {
        let addresses: Vec<(UVec2, u32, u32)> =
            (0..40u32).map(|k| (UVec2::new(k * 7 % 13, k * 5 % 11), k * 37 % 64, k % 9 * 3)).collect();
        for kind in [SamplerKind::Independent, SamplerKind::Sobol] {
            let mut fresh = AnySampler::new(kind, SEED);
            let reference: Vec<Vec<u32>> = addresses.iter().map(|&(p, i, d)| stream(&mut fresh, p, i, d, 6)).collect();
            // Another instance, with unrelated work interleaved, in reverse order.
            let mut busy = AnySampler::new(kind, SEED);
            for (k, &(p, i, d)) in addresses.iter().enumerate().rev() {
                busy.start_pixel_sample(UVec2::new(999, k as u32), 12345, 77);
                for _ in 0..k % 5 {
                    busy.get_1d();
                    busy.get_2d();
                }
                assert_eq!(stream(&mut busy, p, i, d, 6), reference[k], "{kind:?} address {p} {i} {d}");
            }
            // Starting at a later dimension gives the tail of the same stream.
            let (p, i) = (UVec2::new(3, 4), 5);
            fresh.start_pixel_sample(p, i, 0);
            let head: Vec<u32> = (0..3).map(|_| fresh.get_1d().to_bits()).collect();
            let pair = fresh.get_2d();
            fresh.start_pixel_sample(p, i, 2);
            assert_eq!(fresh.get_1d().to_bits(), head[2], "{kind:?}");
            assert_eq!(fresh.get_2d(), pair, "{kind:?}");
            // get_pixel_2d is the 2D request at its dimension.
            fresh.start_pixel_sample(p, i, 4);
            let a = fresh.get_pixel_2d();
            fresh.start_pixel_sample(p, i, 4);
            assert_eq!(a, fresh.get_2d(), "{kind:?}");
        }
    }

    #[test]
    fn seeds_pixels_indices_and_dimensions_give_different_streams() {
        for kind in [SamplerKind::Independent, SamplerKind::Sobol] {
            let mut a = AnySampler::new(kind, SEED);
            let mut b = AnySampler::new(kind, SEED + 1);
            let base = stream(&mut a, UVec2::new(5, 6), 7, 0, 8);
            let others = [
                stream(&mut b, UVec2::new(5, 6), 7, 0, 8),
                stream(&mut a, UVec2::new(6, 5), 7, 0, 8),
                stream(&mut a, UVec2::new(5, 7), 7, 0, 8),
                stream(&mut a, UVec2::new(5, 6), 8, 0, 8),
                stream(&mut a, UVec2::new(5, 6), 7, 3, 8),
            ];
            for (k, o) in others.iter().enumerate() {
                let same = base.iter().zip(o).filter(|(x, y)| x == y).count();
                assert!(same <= 1, "{kind:?} variant {k}: {same} equal values");
            }
            // Within one sample, the dimensions are not copies of each other.
            let mut v = base.clone();
            v.sort_unstable();
            v.dedup();
            assert_eq!(v.len(), base.len(), "{kind:?}");
        }
    }

    #[test]
    fn values_lie_in_the_unit_interval() {
        for mut s in samplers(SEED) {
            for i in 0..4096 {
                s.start_pixel_sample(UVec2::new(i % 17, i / 17), i, 0);
                for _ in 0..8 {
                    let x = s.get_1d();
                    let v = s.get_2d();
                    let pv = s.get_pixel_2d();
                    for c in [x, v.x, v.y, pv.x, pv.y] {
                        assert!((0.0..1.0).contains(&c), "{c}");
                    }
                }
            }
        }
    }

    /// Elementary intervals: for every split a + b = m, the 2^m points of a pixel fall one in each
    /// of the 2^a x 2^b boxes.
    fn assert_net(points: &[Vec2], m: u32, what: &str) {
        for a in 0..=m {
            let b = m - a;
            let mut hit = vec![false; 1 << m];
            for p in points {
                let (ix, iy) = ((p.x * (1u32 << a) as f32) as usize, (p.y * (1u32 << b) as f32) as usize);
                let cell = ix << b | iy;
                assert!(!hit[cell], "{what}: two points in box ({ix}, {iy}) of shape 2^{a} x 2^{b}");
                hit[cell] = true;
            }
        }
    }

    #[test]
    fn sobol_pairs_are_0_m_2_nets() {
        for seed in [SEED, 42] {
            let mut s = SobolSampler::new(seed);
            for pixel in [UVec2::new(0, 0), UVec2::new(17, 3), UVec2::new(640, 479)] {
                for m in [4u32, 6, 8] {
                    for dim in [0u32, 2, 10, 5] {
                        let pts: Vec<Vec2> = (0..1u32 << m)
                            .map(|i| {
                                s.start_pixel_sample(pixel, i, dim);
                                s.get_2d()
                            })
                            .collect();
                        assert_net(&pts, m, &format!("seed {seed} pixel {pixel} m {m} dims {dim}-{}", dim + 1));
                    }
                    // 1D requests are stratified: one point in each interval of length 2^-m.
                    let mut strata: Vec<u32> = (0..1u32 << m)
                        .map(|i| {
                            s.start_pixel_sample(pixel, i, 7);
                            (s.get_1d() * (1u32 << m) as f32) as u32
                        })
                        .collect();
                    strata.sort_unstable();
                    strata.dedup();
                    assert_eq!(strata.len(), 1 << m, "1D seed {seed} pixel {pixel} m {m}");
                }
            }
        }
    }

    #[test]
    fn sobol_dimensions_are_decorrelated() {
        // Different pads must not repeat the same point set in the same order.
        let mut s = SobolSampler::new(SEED);
        let n = 256;
        let (mut same_order, mut corr) = (0, 0.0f64);
        for i in 0..n {
            s.start_pixel_sample(UVec2::new(1, 2), i, 0);
            let a = s.get_2d();
            let b = s.get_2d();
            same_order += usize::from(a == b);
            corr += f64::from((a.x - 0.5) * (b.x - 0.5));
        }
        assert!(same_order < 2);
        // Correlation coefficient of two independent sequences: about N(0, 1/sqrt(n)).
        assert!((corr / n as f64 * 12.0).abs() < 4.0 / (n as f64).sqrt(), "correlation {corr}");
    }

    // Chi-square tests of this module (Sidak correction).
    const CHI2_TESTS: usize = 2;

    #[test]
    fn independent_sampler_is_uniform_chi2() {
        // alpha = 0.01 over the module, seed SEED; 10^6 sample indices of one pixel, and of one
        // sample index over many pixels.
        let opts = Chi2Options { samples: 1_000_000, res: (64, 64), alpha: 0.01, tests: CHI2_TESTS, seed: 1 };
        let mut s = IndependentSampler::new(SEED);
        let mut index = 0;
        let by_index = |_| {
            s.start_pixel_sample(UVec2::new(3, 9), index, 4);
            index += 1;
            Some(s.get_2d())
        };
        test_rect("independent, by index", by_index, |_| 1.0, (0.0, 1.0), (0.0, 1.0), &opts)
            .unwrap_or_else(|e| panic!("{e}"));
        let mut s = IndependentSampler::new(SEED);
        let mut k = 0u32;
        let by_pixel = |_| {
            s.start_pixel_sample(UVec2::new(k % 1000, k / 1000), 0, 0);
            k += 1;
            Some(s.get_pixel_2d())
        };
        test_rect("independent, by pixel", by_pixel, |_| 1.0, (0.0, 1.0), (0.0, 1.0), &opts)
            .unwrap_or_else(|e| panic!("{e}"));
    }

    /// RMS error, over 64 pixels, of the 256-sample estimate of a 2D Gaussian bump's integral.
    fn bump_rms_error(kind: SamplerKind) -> f64 {
        let sigma = 0.15f64;
        let f = |p: Vec2| {
            let (x, y) = (f64::from(p.x) - 0.5, f64::from(p.y) - 0.5);
            (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()
        };
        let one_d =
            sigma * (2.0 * std::f64::consts::PI).sqrt() * statrs::function::erf::erf(0.5 / (sigma * 2f64.sqrt()));
        let exact = one_d * one_d;
        let mut s = AnySampler::new(kind, SEED);
        let mut sq = 0.0;
        for pixel in 0..64u32 {
            let pixel = UVec2::new(pixel % 8, pixel / 8);
            let mut sum = 0.0;
            for i in 0..256 {
                s.start_pixel_sample(pixel, i, 0);
                s.get_1d(); // an unrelated dimension first: pads are keyed by dimension
                sum += f(s.get_2d());
            }
            let err = sum / 256.0 - exact;
            sq += err * err;
        }
        (sq / 64.0).sqrt()
    }

    #[test]
    fn sobol_converges_faster_than_independent() {
        let (sobol, independent) = (bump_rms_error(SamplerKind::Sobol), bump_rms_error(SamplerKind::Independent));
        // Owen-scrambled Sobol has error near N^-1.5 on smooth integrands vs N^-0.5: at 256 spp
        // the ratio is about 1/16 (deterministic: fixed seed).
        assert!(sobol < 0.1 * independent, "sobol {sobol:e} vs independent {independent:e}");
    }
}
