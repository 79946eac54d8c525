//! The film: per-pixel sums, their merge, and EXR / PNG encoding.
//!
//! A pixel is a [`PixelSums`] of 64 bytes (asserted by a test from the type's size), so a film
//! costs 64 bytes per pixel, BDPT's light-tracing splats included: 506 MiB for 3840 x 2160
//! ([`Film::bytes_for`]). Two kinds of channels, with two different guarantees:
//!
//! * **Exact channels** (radiance RGB, camera-sample luminance, squared luminance, sample weight
//!   and hit count) are unsigned integers. Every sample's radiance is clamped to
//!   `[0, `[`MAX_SAMPLE_VALUE`]`]` and rounded once to a fixed-point number with [`FRAC_BITS`]
//!   fractional bits (squared luminance: [`LUM_SQ_FRAC_BITS`]); sums are saturating unsigned
//!   additions. Saturating addition of non-negative integers is `min(sum, MAX)`, which is
//!   associative and commutative, so a pixel's sums are the same bits however its samples were
//!   split into tiles, passes, workers or threads and in whatever order the parts arrive. The
//!   bound: one pixel's camera samples add at most `max_spp * MAX_SAMPLE_VALUE * 2^FRAC_BITS =
//!   2^20 * 2^19 * 2^24 = 2^63 < 2^64` (Limits' default `max_spp` is 2^20; a larger limit is
//!   refused by `RenderSettings::validate`), so radiance never saturates from camera samples; only
//!   BDPT splats (whose count per pixel is not bounded by the pixel's samples) or squared
//!   luminance (`lum^2` of very bright samples) can reach `u64::MAX`, where the sum stays
//!   (never wraps) and [`Film::resolve`] reports it: radiance as the saturated value, the
//!   variance layer as `+inf`, and [`Film::saturated_pixels`] counts them.
//!   One sample's rounding is at most 2^-25 absolute (3e-8), so a mean's error is at most
//!   2^-25: below an 8-bit display step (1/255 / 12.92 = 3e-4 linear, the sRGB step at black)
//!   by four orders of magnitude and below f32's resolution for every value above 0.5.
//! * **AOV channels** (albedo, normal, depth) are per-pixel means: albedo as 16-bit unsigned
//!   fixed point (2^-15, range [0, 2)), the normal as 16-bit signed normalized (1/32767, range
//!   [-1, 1]), depth (over the samples that hit) as f32. A mean is merged with another by their
//!   weights in f64 and rounded once; that is commutative but not associative, so the AOVs are the same
//!   bits only when the parts are folded in the same order. The renderer accumulates a unit's
//!   samples in f64 in sample order ([`PixelAccum`]), and both the farm and a local render fold
//!   each tile's passes in pass order (the coordinator holds a pass that arrives early until the
//!   tile's earlier passes are merged: DESIGN.md, "Work units and the merge"), so the AOVs are
//!   bit-identical too. Their error is half a step (1.5e-5) per merge; they guide the denoiser
//!   and need no more.
//!
//! BDPT's light-tracing splats (t = 1) land on any pixel. They are added into the same radiance
//! sums as the camera samples (exact, order-independent) when the unit that traced them is
//! merged, and divided by the pixel's sample weight like the camera samples: once every pixel
//! has all its samples (the finished image) that is the light-path count per pixel, pbrt's
//! divisor. A preview while tiles are at different passes divides some splats by a slightly
//! different count; the finished image is exact. The camera samples' own luminance sum is kept
//! apart (`lum`), so the variance layer stays the camera samples' variance.

use crate::job::TileRect;
use std::path::Path;

/// A fixed-point sum: an unsigned integer in units of 2^-[`FRAC_BITS`] (squared luminance:
/// 2^-[`LUM_SQ_FRAC_BITS`]).
pub type Fixed = u64;

/// Fractional bits of the radiance and luminance sums.
pub const FRAC_BITS: u32 = 24;
/// Fractional bits of the squared-luminance sum.
pub const LUM_SQ_FRAC_BITS: u32 = 20;
const SCALE: f64 = (1u64 << FRAC_BITS) as f64;
const LUM_SQ_SCALE: f64 = (1u64 << LUM_SQ_FRAC_BITS) as f64;

/// The largest value one sample (or one splat) adds to a radiance channel; larger ones are
/// clamped to it, negative ones to 0.
pub const MAX_SAMPLE_VALUE: f32 = (1u32 << 19) as f32;

/// The most samples per pixel whose radiance sums cannot saturate:
/// `2^64 / (MAX_SAMPLE_VALUE * 2^FRAC_BITS) = 2^21` (with a factor 2 of margin: 2^20).
pub const MAX_EXACT_SPP: u32 = 1 << 20;

/// Converts one sample value to fixed point with `frac` fractional bits: clamped to
/// `[0, MAX_SAMPLE_VALUE]` (squared luminance: `[0, MAX_SAMPLE_VALUE^2]`); non-finite values
/// become 0 (the caller counts them).
#[inline]
fn quantize(v: f32, scale: f64, max: f64) -> Fixed {
    if v.is_finite() && v > 0.0 { round_to_fixed(f64::from(v).min(max) * scale) } else { 0 }
}

/// `x.round() as Fixed` (to nearest, halves away from zero, saturating) for `x >= 0`, without
/// `f64::round`: on baseline x86-64 (no SSE4.1) that is a call into libm's software rounding
/// (replacing it took 117M of 2,185M instructions off the bench's `tiny large`). Below 2^52,
/// `x + 2^52` rounds `x` to an integer (the f64 spacing there is 1; halves to even), read back
/// from its bits without a float-to-integer conversion (Rust's saturating `as` costs several
/// instructions each way); the one case where halves-to-even and halves-away differ, `x` an
/// integer plus exactly one half rounded down, is then raised (`x - r` is exact). From 2^52 on
/// every f64 is an integer.
#[inline(always)]
fn round_to_fixed(x: f64) -> Fixed {
    if x < INTEGERS_FROM { round_below_2_52(x) } else { x as Fixed }
}

/// From 2^52 on every f64 is an integer.
const INTEGERS_FROM: f64 = (1u64 << 52) as f64;

/// [`round_to_fixed`] of an `x` in `[0, 2^52)` (or -0): no branch, so that the optimizer can
/// round several channels in SIMD lanes at once.
#[inline(always)]
fn round_below_2_52(x: f64) -> Fixed {
    let y = x + INTEGERS_FROM;
    let r = y.to_bits().wrapping_sub(INTEGERS_FROM.to_bits());
    r.wrapping_add(Fixed::from(x - (y - INTEGERS_FROM) == 0.5))
}

/// Converts one radiance sample value to fixed point: clamped to `[0, MAX_SAMPLE_VALUE]`, non-finite
/// values become 0 (the caller counts them).
#[inline]
pub fn to_fixed(v: f32) -> Fixed {
    quantize(v, SCALE, f64::from(MAX_SAMPLE_VALUE))
}

/// Converts a radiance or luminance fixed-point sum back to a float.
#[inline]
pub fn from_fixed(v: Fixed) -> f64 {
    v as f64 / SCALE
}

/// What one camera sample contributes to its pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SampleValue {
    pub radiance: [f32; 3],
    pub albedo: [f32; 3],
    pub normal: [f32; 3],
    /// Distance to the first hit, `None` for a miss.
    pub depth: Option<f32>,
}

/// Relative luminance of linear sRGB primaries (Rec. 709).
#[inline]
pub fn luminance(rgb: [f32; 3]) -> f32 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// One pixel's sums: 64 bytes. The integer fields are exact sums (see the module doc); the
/// AOVs are means in fixed point (depth: `f32` bits, so that equality is bitwise).
///
/// Aligned to 64 bytes, so that a pixel is one cache line: films are larger than the caches, and
/// with 8-byte alignment most pixels straddled two lines (twice the memory traffic per merge).
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct PixelSums {
    /// Radiance sums (camera samples and BDPT splats), units of 2^-[`FRAC_BITS`].
    pub rgb: [Fixed; 3],
    /// Luminance sum of the camera samples (no splats), units of 2^-[`FRAC_BITS`].
    pub lum: Fixed,
    /// Sum of the camera samples' squared luminance, units of 2^-[`LUM_SQ_FRAC_BITS`].
    pub lum_sq: Fixed,
    /// Sample weight (box filter: 1 per sample).
    pub weight: u32,
    /// Samples that hit something.
    pub hits: u32,
    /// Mean first-hit distance over the `hits` samples (`f32` bits; 0 without hits).
    pub depth: u32,
    /// Mean albedo over the `weight` samples, units of 2^-15 (`[0, 2)`).
    pub albedo: [u16; 3],
    /// Mean shading normal over the `weight` samples, units of 1/32767 (`[-1, 1]`; not
    /// renormalized).
    pub normal: [i16; 3],
}

/// Bytes of one pixel in a film, a tile accumulator and on the wire.
pub const PIXEL_BYTES: usize = std::mem::size_of::<PixelSums>();

const _: () = assert!(PIXEL_BYTES == 64);

const ALBEDO_SCALE: f64 = (1u32 << 15) as f64;
const NORMAL_SCALE: f64 = i16::MAX as f64;

/// An albedo mean to its fixed point (clamped to the range; NaN to 0).
#[inline]
fn albedo_code(v: f64) -> u16 {
    // Truncation of a non-negative number + 0.5 rounds (and is fast: no libm call).
    ((v * ALBEDO_SCALE).clamp(0.0, f64::from(u16::MAX)) + 0.5) as u16
}

/// A normal component mean to its fixed point (clamped to [-1, 1]; NaN to 0).
#[inline]
fn normal_code(v: f64) -> i16 {
    let c = (v * NORMAL_SCALE).clamp(-NORMAL_SCALE, NORMAL_SCALE);
    ((c + NORMAL_SCALE + 0.5) as i32 - i16::MAX as i32) as i16
}

/// [`normal_code`] of a mean already in units of 1/32767 (no division by the scale and
/// multiplication back: a merge runs for every pixel of every result).
#[inline]
fn normal_code_scaled(c: f64) -> i16 {
    let c = c.clamp(-NORMAL_SCALE, NORMAL_SCALE);
    ((c + NORMAL_SCALE + 0.5) as i32 - i16::MAX as i32) as i16
}

/// Weighted mean of two means in f64 (`inv` = 1 / (wa + wb)): commutative, as IEEE addition
/// and multiplication are.
#[inline]
fn blend(a: f64, wa: f64, b: f64, wb: f64, inv: f64) -> f64 {
    (a * wa + b * wb) * inv
}

impl PixelSums {
    /// The sums of one sample.
    pub fn from_sample(s: &SampleValue) -> Self {
        let mut a = PixelAccum::default();
        a.add(s);
        a.finish()
    }

    /// Adds `other` (see the module doc: exact channels in any order, AOVs in canonical order).
    #[inline]
    pub fn merge(&mut self, o: &PixelSums) {
        for c in 0..3 {
            self.rgb[c] = self.rgb[c].saturating_add(o.rgb[c]);
        }
        self.lum = self.lum.saturating_add(o.lum);
        self.lum_sq = self.lum_sq.saturating_add(o.lum_sq);
        if o.weight > 0 {
            if self.weight == 0 {
                self.albedo = o.albedo;
                self.normal = o.normal;
            } else {
                let (wa, wb) = (f64::from(self.weight), f64::from(o.weight));
                let inv = 1.0 / (wa + wb);
                for c in 0..3 {
                    let a = blend(f64::from(self.albedo[c]), wa, f64::from(o.albedo[c]), wb, inv);
                    self.albedo[c] = (a + 0.5) as u16;
                    let n = blend(f64::from(self.normal[c]), wa, f64::from(o.normal[c]), wb, inv);
                    self.normal[c] = normal_code_scaled(n);
                }
            }
        }
        if o.hits > 0 {
            if self.hits == 0 {
                self.depth = o.depth;
            } else {
                let (ha, hb) = (f64::from(self.hits), f64::from(o.hits));
                let (da, db) = (f64::from(f32::from_bits(self.depth)), f64::from(f32::from_bits(o.depth)));
                let d = blend(da, ha, db, hb, 1.0 / (ha + hb));
                self.depth = (d as f32).to_bits();
            }
        }
        self.weight = self.weight.saturating_add(o.weight);
        self.hits = self.hits.saturating_add(o.hits);
    }

    /// Sample weight.
    pub fn weight(&self) -> f64 {
        f64::from(self.weight)
    }

    /// Radiance sums (camera samples and splats).
    pub fn radiance_sum(&self) -> [f64; 3] {
        self.rgb.map(from_fixed)
    }

    /// Sum of the camera samples' luminance.
    pub fn luminance_sum(&self) -> f64 {
        from_fixed(self.lum)
    }

    /// Sum of the camera samples' squared luminance (`+inf` once saturated).
    pub fn luminance_sq_sum(&self) -> f64 {
        if self.lum_sq == Fixed::MAX { f64::INFINITY } else { self.lum_sq as f64 / LUM_SQ_SCALE }
    }

    /// Mean albedo.
    pub fn albedo(&self) -> [f32; 3] {
        self.albedo.map(|v| (f64::from(v) / ALBEDO_SCALE) as f32)
    }

    /// Mean normal.
    pub fn normal(&self) -> [f32; 3] {
        self.normal.map(|v| (f64::from(v) / NORMAL_SCALE) as f32)
    }

    /// Mean first-hit distance, `+inf` without hits.
    pub fn depth(&self) -> f32 {
        if self.hits > 0 { f32::from_bits(self.depth) } else { f32::INFINITY }
    }

    /// A radiance or luminance sum reached `u64::MAX` (splats or squared luminance).
    pub fn is_saturated(&self) -> bool {
        self.rgb.contains(&Fixed::MAX) || self.lum == Fixed::MAX || self.lum_sq == Fixed::MAX
    }

    /// Variance of the pixel mean's luminance (sample variance / n) from the camera samples;
    /// `+inf` when the squared sum saturated, 0 below two samples.
    pub fn variance_of_mean(&self) -> f64 {
        let w = self.weight();
        if w <= 1.0 {
            return 0.0;
        }
        let sq = self.luminance_sq_sum();
        if sq.is_infinite() {
            return f64::INFINITY;
        }
        let mean = self.luminance_sum() / w;
        ((sq / w - mean * mean).max(0.0) * w / (w - 1.0)) / w
    }

    /// The encoded little-endian bytes of this pixel (the wire and checkpoint layout: the
    /// fields in declaration order).
    #[inline]
    pub fn write_le(&self, out: &mut [u8; PIXEL_BYTES]) {
        let mut o = 0;
        let mut put = |b: &[u8]| {
            out[o..o + b.len()].copy_from_slice(b);
            o += b.len();
        };
        for v in self.rgb {
            put(&v.to_le_bytes());
        }
        put(&self.lum.to_le_bytes());
        put(&self.lum_sq.to_le_bytes());
        put(&self.weight.to_le_bytes());
        put(&self.hits.to_le_bytes());
        put(&self.depth.to_le_bytes());
        for v in self.albedo {
            put(&v.to_le_bytes());
        }
        for v in self.normal {
            put(&v.to_le_bytes());
        }
    }

    /// Parses [`write_le`](Self::write_le)'s layout. Any 64 bytes are some pixel (a hostile body
    /// can give nonsense sums, never a panic).
    #[inline]
    pub fn read_le(b: &[u8; PIXEL_BYTES]) -> Self {
        let u64_at =
            |i: usize| u64::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3], b[i + 4], b[i + 5], b[i + 6], b[i + 7]]);
        let u32_at = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let u16_at = |i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
        Self {
            rgb: [u64_at(0), u64_at(8), u64_at(16)],
            lum: u64_at(24),
            lum_sq: u64_at(32),
            weight: u32_at(40),
            hits: u32_at(44),
            depth: u32_at(48),
            albedo: [u16_at(52), u16_at(54), u16_at(56)],
            normal: [u16_at(58), u16_at(60), u16_at(62)].map(|v| v as i16),
        }
    }
}

/// A pixel's samples of one unit as the renderer accumulates them: the exact channels as in
/// [`PixelSums`], the AOVs as f64 sums (so that thousands of samples lose nothing), rounded to
/// means once by [`finish`](Self::finish).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelAccum {
    exact: PixelSums,
    albedo: [f64; 3],
    normal: [f64; 3],
    depth: f64,
}

impl PixelAccum {
    /// Adds one sample (radiance clamped and rounded as [`to_fixed`] says).
    #[inline(always)]
    pub fn add(&mut self, s: &SampleValue) {
        let rgb = s.radiance.map(|v| if v.is_finite() { v.clamp(0.0, MAX_SAMPLE_VALUE) } else { 0.0 });
        let lum = luminance(rgb);
        let e = &mut self.exact;
        // `to_fixed` and `quantize` without their checks: the channels are finite and in
        // [0, MAX_SAMPLE_VALUE] (or -0) already, so their luminance is finite and not negative
        // (it may round a little above the maximum, which `min` keeps), and its square is finite
        // (below 2^39). The same values, for about 70 fewer instructions per sample (measured
        // with the bench's `tiny large`).
        // The three channels and the luminance are at most 2^19 (luminance clamped to it), 2^43
        // in fixed point: [`round_to_fixed`]'s first case, rounded side by side (in lanes where
        // the accumulating kernel is compiled for AVX2 or AVX-512).
        let x = [
            f64::from(rgb[0]) * SCALE,
            f64::from(rgb[1]) * SCALE,
            f64::from(rgb[2]) * SCALE,
            f64::from(lum).min(f64::from(MAX_SAMPLE_VALUE)) * SCALE,
        ];
        let fixed = x.map(round_below_2_52);
        let sums = [e.rgb[0], e.rgb[1], e.rgb[2], e.lum];
        let [r, g, b, l] = [0, 1, 2, 3].map(|i| sums[i].saturating_add(fixed[i]));
        (e.rgb, e.lum) = ([r, g, b], l);
        e.lum_sq = e.lum_sq.saturating_add(round_to_fixed(f64::from(lum * lum) * LUM_SQ_SCALE));
        for c in 0..3 {
            self.albedo[c] += f64::from(s.albedo[c]);
            self.normal[c] += f64::from(s.normal[c]);
        }
        if let Some(d) = s.depth {
            self.depth += f64::from(d);
            e.hits = e.hits.saturating_add(1);
        }
        e.weight = e.weight.saturating_add(1);
    }

    /// The pixel's sums, AOVs as means.
    #[inline(always)]
    pub fn finish(&self) -> PixelSums {
        let mut p = self.exact;
        if p.weight > 0 {
            let w = f64::from(p.weight);
            p.albedo = self.albedo.map(|v| albedo_code(v / w));
            p.normal = self.normal.map(|v| normal_code(v / w));
        }
        if p.hits > 0 {
            p.depth = ((self.depth / f64::from(p.hits)) as f32).to_bits();
        }
        p
    }
}

/// Adds one sample to a pixel's sums (as a one-sample part: for tests and one-off use; the
/// renderer accumulates a unit in [`PixelAccum`]).
#[inline]
pub fn add_sample(pixel: &mut PixelSums, s: &SampleValue) {
    pixel.merge(&PixelSums::from_sample(s));
}

/// Sums of a rectangle of pixels, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileAccum {
    pub rect: TileRect,
    pub sums: Vec<PixelSums>,
}

impl TileAccum {
    pub fn new(rect: TileRect) -> Self {
        Self { rect, sums: vec![PixelSums::default(); rect.pixel_count()] }
    }

    /// The sums of pixel `(x, y)` in tile-local coordinates.
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut PixelSums {
        &mut self.sums[(y * self.rect.width() + x) as usize]
    }

    /// Adds another accumulator of the same rectangle.
    pub fn merge(&mut self, other: &TileAccum) {
        assert_eq!(self.rect, other.rect, "merging tiles of different rectangles");
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            a.merge(b);
        }
    }
}

/// Full-frame RGB sums of light-tracing splats (BDPT `t = 1`) of one unit, on their way to a
/// film's radiance sums ([`Film::add_splats`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplatBuffer {
    pub width: u32,
    pub height: u32,
    /// `(y * width + x) * 3 + c`, units of 2^-[`FRAC_BITS`].
    pub sums: Vec<Fixed>,
}

impl SplatBuffer {
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, sums: vec![0; width as usize * height as usize * 3] }
    }

    /// Adds a splat (each channel clamped as [`to_fixed`] says; the sum saturates).
    #[inline]
    pub fn add(&mut self, x: u32, y: u32, rgb: [f32; 3]) {
        if x < self.width && y < self.height {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            for (sum, v) in self.sums[i..i + 3].iter_mut().zip(rgb) {
                *sum = sum.saturating_add(to_fixed(v));
            }
        }
    }

    pub fn merge(&mut self, other: &SplatBuffer) {
        assert_eq!((self.width, self.height), (other.width, other.height), "splat buffer size");
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            *a = a.saturating_add(*b);
        }
    }

    pub fn is_empty(&self) -> bool {
        self.sums.iter().all(|&v| v == 0)
    }
}

/// A whole image's sums.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    /// Row-major.
    pub sums: Vec<PixelSums>,
}
/// How previews (PNG) are exposed: `ev` stops, added to the automatic exposure when `auto`.
/// From a job's `exposure` and `auto_exposure`; the EXR is never affected.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PreviewExposure {
    pub ev: f32,
    pub auto: bool,
}

impl PreviewExposure {
    pub fn of(settings: &crate::job::RenderSettings) -> Self {
        Self { ev: settings.exposure, auto: settings.auto_exposure }
    }
}

/// Float layers of a resolved image, each `width * height` (or x3 for RGB), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageLayers {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    pub depth: Vec<f32>,
    pub samples: Vec<f32>,
    pub variance: Vec<f32>,
    /// The colour denoised (OIDN, from colour, albedo and normal), when asked for: written as
    /// the EXR layer `denoised` and shown by the PNG preview.
    pub denoised: Option<Vec<[f32; 3]>>,
}

impl Film {
    /// Bytes a film of this size holds: [`PIXEL_BYTES`] per pixel, splats included.
    pub fn bytes_for(width: u32, height: u32) -> u64 {
        u64::from(width) * u64::from(height) * PIXEL_BYTES as u64
    }

    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, sums: vec![PixelSums::default(); width as usize * height as usize] }
    }

    /// Adds a tile's sums. The exact channels in any order; the AOV means are bit-identical
    /// when every tile's passes are added in pass order (module doc). Returns the sample weights
    /// added, summed.
    pub fn add_tile(&mut self, tile: &TileAccum) -> u64 {
        self.add_tile_with(tile.rect, |i| tile.sums.get(i).copied().unwrap_or_default())
    }

    /// [`Film::add_tile`] of the sums `pixel(i)` gives for the tile's pixel `i` (row-major in
    /// `rect`): merged as they are read, with no tile in between. Returns the sample weights
    /// merged, summed.
    pub fn add_tile_with(&mut self, rect: TileRect, pixel: impl Fn(usize) -> PixelSums) -> u64 {
        assert!(rect.x1 <= self.width && rect.y1 <= self.height, "tile outside the film");
        let row = rect.width() as usize;
        let mut weights = 0u64;
        for y in rect.y0..rect.y1 {
            let src = (y - rect.y0) as usize * row;
            let dst = y as usize * self.width as usize + rect.x0 as usize;
            for (i, a) in self.sums[dst..dst + row].iter_mut().enumerate() {
                let p = pixel(src + i);
                weights += u64::from(p.weight);
                a.merge(&p);
            }
        }
        weights
    }

    /// Adds a unit's light-tracing splats to the radiance sums (exact, any order).
    pub fn add_splats(&mut self, splats: &SplatBuffer) {
        assert_eq!((self.width, self.height), (splats.width, splats.height), "splat buffer size");
        for (p, s) in self.sums.iter_mut().zip(splats.sums.chunks_exact(3)) {
            for (sum, v) in p.rgb.iter_mut().zip(s) {
                *sum = sum.saturating_add(*v);
            }
        }
    }

    /// Copies the film's sums of `rect` into a tile accumulator.
    pub fn tile(&self, rect: TileRect) -> TileAccum {
        let mut t = TileAccum::new(rect);
        let row = rect.width() as usize;
        for y in rect.y0..rect.y1 {
            let src = y as usize * self.width as usize + rect.x0 as usize;
            let dst = (y - rect.y0) as usize * row;
            t.sums[dst..dst + row].copy_from_slice(&self.sums[src..src + row]);
        }
        t
    }

    /// A copy of rows `y0..y1` as a film of their own (rows past the end are left out).
    pub fn band(&self, y0: u32, y1: u32) -> Film {
        let (y0, y1) = (y0.min(self.height), y1.min(self.height).max(y0.min(self.height)));
        let w = self.width as usize;
        Film { width: self.width, height: y1 - y0, sums: self.sums[y0 as usize * w..y1 as usize * w].to_vec() }
    }

    /// Pixels whose radiance or luminance sums saturated (see the module doc).
    pub fn saturated_pixels(&self) -> usize {
        self.sums.iter().filter(|p| p.is_saturated()).count()
    }

    /// Per-pixel means and AOVs as floats.
    pub fn resolve(&self) -> ImageLayers {
        let n = self.width as usize * self.height as usize;
        let mut out = ImageLayers {
            width: self.width,
            height: self.height,
            rgb: Vec::with_capacity(n),
            albedo: Vec::with_capacity(n),
            normal: Vec::with_capacity(n),
            depth: Vec::with_capacity(n),
            samples: Vec::with_capacity(n),
            variance: Vec::with_capacity(n),
            denoised: None,
        };
        for p in &self.sums {
            let w = p.weight();
            out.samples.push(w as f32);
            if w > 0.0 {
                out.rgb.push(p.radiance_sum().map(|v| (v / w) as f32));
                out.albedo.push(p.albedo());
                out.normal.push(p.normal());
                out.depth.push(p.depth());
                out.variance.push(p.variance_of_mean() as f32);
            } else {
                out.rgb.push([0.0; 3]);
                out.albedo.push([0.0; 3]);
                out.normal.push([0.0; 3]);
                out.depth.push(f32::INFINITY);
                out.variance.push(0.0);
            }
        }
        out
    }
}
/// Errors writing or reading images.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("EXR {path}: {source}")]
    Exr { path: String, source: exr::error::Error },
    #[error("PNG {path}: {source}")]
    Png { path: String, source: image::ImageError },
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("EXR {path}: {message}")]
    Format { path: String, message: String },
}

impl ImageLayers {
    /// The EXR channel list, as (name, values) pairs.
    pub fn exr_channels(&self) -> Vec<(&'static str, Vec<f32>)> {
        self.clone().into_exr_channels()
    }

    /// [`ImageLayers::exr_channels`] from layers given up: each interleaved layer is split into
    /// its planes and dropped before the next, and the planar ones move, so at most one
    /// layer is held twice (a 4K frame's layers are ~400 MB).
    pub fn into_exr_channels(self) -> Vec<(&'static str, Vec<f32>)> {
        fn planes(v: Vec<[f32; 3]>, names: [&'static str; 3], out: &mut Vec<(&'static str, Vec<f32>)>) {
            for (c, name) in names.into_iter().enumerate() {
                out.push((name, v.iter().map(|p| p[c]).collect()));
            }
        }
        let mut out = Vec::with_capacity(15);
        planes(self.rgb, ["R", "G", "B"], &mut out);
        planes(self.albedo, ["albedo.R", "albedo.G", "albedo.B"], &mut out);
        planes(self.normal, ["normal.X", "normal.Y", "normal.Z"], &mut out);
        out.push(("depth.Z", self.depth));
        out.push(("samples.Y", self.samples));
        out.push(("variance.Y", self.variance));
        if let Some(d) = self.denoised {
            planes(d, ["denoised.R", "denoised.G", "denoised.B"], &mut out);
        }
        out
    }

    /// Writes `channels` as a float32 OpenEXR file to `w`: ZIP compression of single scanlines
    /// (OpenEXR's `ZIPS`), lossless; a third less CPU than 16-line blocks for a 1% larger file
    /// (bench `film`: 0.47 against 0.69 s for 1024 x 1024).
    fn write_exr_channels(
        width: u32,
        height: u32,
        channels: Vec<(&'static str, Vec<f32>)>,
        w: impl std::io::Write + std::io::Seek,
    ) -> Result<(), exr::error::Error> {
        use exr::prelude::*;
        let size = (width as usize, height as usize);
        let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> =
            channels.into_iter().map(|(name, v)| AnyChannel::new(name, FlatSamples::F32(v))).collect();
        let attrs = LayerAttributes { software_name: Some(Text::from("pathfarm")), ..Default::default() };
        let enc =
            Encoding { compression: Compression::ZIP1, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
        let layer = Layer::new(size, attrs, enc, AnyChannels::sort(channels));
        Image::from_layer(layer).write().to_buffered(w)
    }

    /// Encodes the layers as a float32 OpenEXR file in memory (ZIP compression, lossless).
    pub fn encode_exr(&self) -> Result<Vec<u8>, exr::error::Error> {
        let mut buf = std::io::Cursor::new(Vec::new());
        Self::write_exr_channels(self.width, self.height, self.exr_channels(), &mut buf)?;
        Ok(buf.into_inner())
    }

    /// Writes the EXR atomically: a temporary file beside `path`, then a rename.
    pub fn write_exr(&self, path: &Path) -> Result<(), ImageError> {
        self.clone().into_exr_file(path)
    }

    /// [`ImageLayers::write_exr`] from layers given up ([`ImageLayers::into_exr_channels`]),
    /// streamed to the file: the encoded file is never held in memory whole. The same bytes as
    /// [`ImageLayers::encode_exr`].
    pub fn into_exr_file(self, path: &Path) -> Result<(), ImageError> {
        let (width, height) = (self.width, self.height);
        let channels = self.into_exr_channels();
        let mut failed = None;
        let written = write_atomic_with(path, |w| {
            Self::write_exr_channels(width, height, channels, w).map_err(|e| {
                let io = std::io::Error::other(e.to_string());
                failed = Some(e);
                io
            })
        });
        match (written, failed) {
            (Err(_), Some(source)) => Err(ImageError::Exr { path: path.display().to_string(), source }),
            (r, _) => r,
        }
    }

    /// The exposure (EV) that brings the log-average luminance of the shown colour (denoised if
    /// there is one) to middle grey, 0.18 (Reinhard's key value): `log2(0.18 / exp(mean(ln(1e-4
    /// + L))))` over the finite pixels, within +-20 EV; 0 for an all-black image.
    pub fn auto_exposure(&self) -> f32 {
        let shown = self.denoised.as_deref().unwrap_or(&self.rgb);
        let (mut sum, mut n, mut max) = (0.0f64, 0usize, 0.0f32);
        for c in shown {
            let l = 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
            if l.is_finite() && l >= 0.0 {
                sum += f64::from(1e-4 + l).ln();
                n += 1;
                max = max.max(l);
            }
        }
        if n == 0 || max <= 0.0 {
            return 0.0;
        }
        let log_average = (sum / n as f64).exp();
        ((0.18 / log_average).log2() as f32).clamp(-20.0, 20.0)
    }

    /// The EV a preview uses: `exposure.ev`, plus [`ImageLayers::auto_exposure`] when
    /// `exposure.auto`.
    pub fn preview_ev(&self, exposure: PreviewExposure) -> f32 {
        if exposure.auto { exposure.ev + self.auto_exposure() } else { exposure.ev }
    }

    /// An 8-bit sRGB preview of the denoised colour if there is one, else of the colour:
    /// `exposure` in stops, clamped, sRGB-encoded.
    pub fn preview_rgb8(&self, exposure: f32) -> image::RgbImage {
        let scale = exposure.exp2();
        let mut img = image::RgbImage::new(self.width, self.height);
        let shown = self.denoised.as_deref().unwrap_or(&self.rgb);
        for (i, px) in img.pixels_mut().enumerate() {
            let c = shown[i];
            *px = image::Rgb([encode_srgb8(c[0] * scale), encode_srgb8(c[1] * scale), encode_srgb8(c[2] * scale)]);
        }
        img
    }

    /// PNG bytes of [`ImageLayers::preview_rgb8`].
    pub fn encode_png(&self, exposure: f32) -> Result<Vec<u8>, image::ImageError> {
        let mut buf = std::io::Cursor::new(Vec::new());
        self.preview_rgb8(exposure).write_to(&mut buf, image::ImageFormat::Png)?;
        Ok(buf.into_inner())
    }

    /// Writes the PNG preview atomically.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), ImageError> {
        let bytes =
            self.encode_png(exposure).map_err(|source| ImageError::Png { path: path.display().to_string(), source })?;
        write_atomic(path, &bytes)
    }
}

/// sRGB transfer function, linear [0, 1] -> 8-bit code.
pub fn encode_srgb8(v: f32) -> u8 {
    let v = if v.is_finite() { v.clamp(0.0, 1.0) } else { 0.0 };
    let s = if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0 + 0.5) as u8
}

/// Writes `bytes` to `path` through a temporary file in the same directory and a rename, so
/// readers never see a half-written file.
/// Writes `bytes` to `path` atomically and durably: a unique temporary file in the same
/// directory, fsynced, renamed over `path`, then the directory fsynced. On failure the temporary
/// file is removed and `path` keeps its old contents.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ImageError> {
    write_atomic_with(path, |w| std::io::Write::write_all(w, bytes))
}

/// [`write_atomic`] for a file written piece by piece by `write` (into a buffered writer of the
/// temporary file), so a large file is never held in memory whole.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
) -> Result<(), ImageError> {
    let io = |source| ImageError::Io { path: path.display().to_string(), source };
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io)?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    // Unique per write: threads of one process (local workers) may write the same file at once.
    static SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let seq = SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.{}.{seq}.tmp", std::process::id()));
    let written = (|| {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(&tmp)?);
        write(&mut w)?;
        let f = w.into_inner().map_err(std::io::IntoInnerError::into_error)?;
        // Durable before it replaces the old file: a crash leaves the old or the new bytes.
        f.sync_all()?;
        std::fs::rename(&tmp, path)?;
        // The rename itself is durable once the directory is synced.
        std::fs::File::open(dir).and_then(|d| d.sync_all())
    })();
    if written.is_err() {
        // A failed write (e.g. a full disk) leaves no temporary file behind.
        let _ = std::fs::remove_file(&tmp);
    }
    written.map_err(io)
}

/// Named float channels of an EXR file (first layer), for tests and tools.
#[derive(Clone, Debug)]
pub struct ExrChannels {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }
}

/// Reads all channels of the first layer of an EXR file as f32.
pub fn read_exr(path: &Path) -> Result<ExrChannels, ImageError> {
    use exr::prelude::*;
    let err = |source| ImageError::Exr { path: path.display().to_string(), source };
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(err)?;
    let layer = image.layer_data;
    let channels =
        layer.channel_data.list.iter().map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect())).collect();
    Ok(ExrChannels { width: layer.size.0, height: layer.size.1, channels })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rounding that replaces `f64::round` gives its result, saturated to `Fixed`, for
    /// halves and their neighbours, the largest fractions below a half, the range around 2^52
    /// and 2^64, and many values at every scale: so sums stay bit-identical.
    #[test]
    fn round_to_fixed_is_round_as_fixed() {
        let check = |x: f64| assert_eq!(round_to_fixed(x), x.round() as Fixed, "{x:e}");
        let mut values =
            vec![0.0, -0.0, 5e-324, 1e-300, 0.5, 1.5, 2.5, 0.499_999_999_999_999_94, 4_503_599_627_370_495.5, f64::MAX];
        for e in 0..70 {
            let p = 2f64.powi(e);
            for x in [p, p + 0.5, p - 0.5, p * 1.5, p + 0.25, p + 0.75] {
                values.extend([x, f64::from_bits(x.to_bits() + 1), f64::from_bits(x.to_bits().saturating_sub(1))]);
            }
        }
        let mut z = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..200_000 {
            z = z.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            // Any exponent from 2^-20 to 2^70, any mantissa.
            let bits = ((z >> 11) & ((1 << 52) - 1)) | ((1003 + (z >> 5) % 91) << 52);
            values.push(f64::from_bits(bits));
        }
        for x in values {
            check(x);
        }
    }

    /// `PixelAccum::add`'s exact sums are `to_fixed` and `quantize` of the clamped channels, as
    /// before it skipped their checks: for NaN, infinite, negative, -0, tiny, huge and ordinary
    /// radiance.
    #[test]
    fn accumulated_sums_are_the_checked_conversions() {
        let special = [0.0, -0.0, 1e-30, 0.5, 1.0, 3.7, 1e5, MAX_SAMPLE_VALUE, 1e9, -2.0, f32::NAN, f32::INFINITY];
        let mut z = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            z ^= z << 13;
            z ^= z >> 7;
            z ^= z << 17;
            z
        };
        for k in 0..20_000 {
            let pick = |r: u64| {
                if k < 2_000 {
                    special[(r % special.len() as u64) as usize]
                } else {
                    // Any exponent from 2^-30 to 2^25.
                    f32::from_bits((((r >> 8) & 0x7f_ffff) | (((r >> 40) % 56 + 97) << 23)) as u32)
                }
            };
            let radiance = [pick(next()), pick(next()), pick(next())];
            let mut a = PixelAccum::default();
            a.add(&SampleValue { radiance, ..SampleValue::default() });
            let rgb = radiance.map(|v| if v.is_finite() { v.clamp(0.0, MAX_SAMPLE_VALUE) } else { 0.0 });
            let lum = luminance(rgb);
            let want = (rgb.map(to_fixed), to_fixed(lum), quantize(lum * lum, LUM_SQ_SCALE, f64::MAX));
            assert_eq!((a.exact.rgb, a.exact.lum, a.exact.lum_sq), want, "{radiance:?}");
        }
    }

    #[test]
    fn a_failed_atomic_write_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let target = dir.path().join("image.exr");
        write_atomic(&target, b"one").expect("first write");
        assert_eq!(std::fs::read(&target).expect("read"), b"one");
        // A directory in the way: the rename fails, the temporary file is removed.
        let blocked = dir.path().join("blocked");
        std::fs::create_dir_all(blocked.join("inside")).expect("dir");
        assert!(write_atomic(&blocked, b"two").is_err());
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .expect("list")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        assert!(left.iter().all(|n| !n.ends_with(".tmp")), "temporary files left: {left:?}");
        assert_eq!(std::fs::read(&target).expect("read"), b"one");
    }

    fn uniform(width: u32, height: u32, rgb: [f32; 3]) -> ImageLayers {
        let n = (width * height) as usize;
        ImageLayers {
            width,
            height,
            rgb: vec![rgb; n],
            albedo: vec![[0.0; 3]; n],
            normal: vec![[0.0; 3]; n],
            depth: vec![0.0; n],
            samples: vec![1.0; n],
            variance: vec![0.0; n],
            denoised: None,
        }
    }

    /// Auto exposure brings the log-average luminance to 0.18: a uniform grey of 0.045 gets
    /// log2(0.18 / 0.0451) = +1.997 EV, so its preview shows middle grey (sRGB 118); a manual EV
    /// adds to it; a black image keeps 0; the EXR does not change.
    #[test]
    fn auto_exposure_maps_the_log_average_to_middle_grey() {
        let img = uniform(4, 2, [0.045; 3]);
        let ev = img.auto_exposure();
        assert!((ev - (0.18f32 / 0.0451).log2()).abs() < 1e-4, "{ev}");
        let auto = PreviewExposure { ev: 0.0, auto: true };
        let px = img.preview_rgb8(img.preview_ev(auto));
        assert_eq!(px.get_pixel(0, 0).0, [encode_srgb8(0.18 * 0.045 / 0.0451); 3]);
        assert_eq!(img.preview_ev(PreviewExposure { ev: -1.0, auto: true }), ev - 1.0);
        assert_eq!(img.preview_ev(PreviewExposure { ev: 1.5, auto: false }), 1.5);
        assert_eq!(uniform(2, 2, [0.0; 3]).auto_exposure(), 0.0);
        // A bright image is exposed down: 100x brighter is log2(100) = 6.6 EV less.
        let bright = uniform(2, 2, [4.5; 3]);
        assert!((ev - bright.auto_exposure() - 100f32.log2()).abs() < 0.01);
    }

    /// xorshift64: the tests' fixed random numbers.
    fn rng(seed: u64) -> impl FnMut() -> f32 {
        let mut x = seed | 1;
        move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn samples(n: usize, seed: u64) -> Vec<SampleValue> {
        let mut r = rng(seed);
        (0..n)
            .map(|i| SampleValue {
                radiance: [r() * 10.0, 1e-7 * i as f32, r().powi(8) * 1e4],
                albedo: [r(), r(), 0.5],
                normal: [r() * 2.0 - 1.0, 1.0, 0.0],
                depth: (i % 3 != 0).then(|| r() * 100.0),
            })
            .collect()
    }

    fn unit(samples: &[SampleValue]) -> PixelSums {
        let mut a = PixelAccum::default();
        for s in samples {
            a.add(s);
        }
        a.finish()
    }

    /// The exact channels of a pixel, without the AOV means.
    fn exact(p: &PixelSums) -> ([u64; 3], u64, u64, u32, u32) {
        (p.rgb, p.lum, p.lum_sq, p.weight, p.hits)
    }

    #[test]
    fn pixels_are_64_bytes_and_a_4k_film_is_506_mib() {
        assert!(std::mem::size_of::<PixelSums>() <= 64);
        assert_eq!(PIXEL_BYTES, std::mem::size_of::<PixelSums>());
        // The film holds nothing per pixel besides its sums (splats go into them).
        assert_eq!(Film::bytes_for(3840, 2160), 3840 * 2160 * std::mem::size_of::<PixelSums>() as u64);
        assert_eq!(Film::bytes_for(3840, 2160), 530_841_600);
        let film = Film::new(64, 32);
        assert_eq!((film.sums.len() * std::mem::size_of::<PixelSums>()) as u64, Film::bytes_for(64, 32));
    }

    #[test]
    fn merge_is_order_independent_for_exact_channels_and_canonical_for_aovs() {
        let rect = TileRect { x0: 0, y0: 0, x1: 2, y1: 1 };
        let all = samples(50, 7);
        let mut whole = TileAccum::new(rect);
        *whole.pixel_mut(1, 0) = unit(&all);
        // Split in three parts, merged in reverse order: the exact channels are the same bits.
        let parts: Vec<PixelSums> = all.chunks(17).map(unit).collect();
        let mut reversed = PixelSums::default();
        for p in parts.iter().rev() {
            reversed.merge(p);
        }
        assert_eq!(exact(&reversed), exact(&whole.sums[1]));
        // Folded in the canonical order twice: every bit the same, AOVs included.
        let fold = || {
            let mut t = TileAccum::new(rect);
            for p in &parts {
                let mut u = TileAccum::new(rect);
                *u.pixel_mut(1, 0) = *p;
                t.merge(&u);
            }
            t
        };
        assert_eq!(fold(), fold());
        // The AOV means of the parts agree with the whole's within the fixed point's rounding.
        let (a, b) = (fold().sums[1], whole.sums[1]);
        for c in 0..3 {
            assert!((a.albedo()[c] - b.albedo()[c]).abs() <= 1e-4, "{a:?} {b:?}");
            assert!((a.normal()[c] - b.normal()[c]).abs() <= 1e-4, "{a:?} {b:?}");
        }
        assert!((a.depth() - b.depth()).abs() <= 1e-5 * b.depth());
    }

    #[test]
    fn camera_samples_cannot_saturate_within_the_spp_bound_and_splats_saturate_without_wrapping() {
        // The largest per-sample value times the largest per-pixel sample count fits in u64.
        let per_sample = u128::from(to_fixed(MAX_SAMPLE_VALUE));
        assert_eq!(per_sample, 1u128 << (19 + FRAC_BITS));
        assert!(per_sample * u128::from(MAX_EXACT_SPP) < u128::from(u64::MAX));
        // Job validation refuses more samples per pixel, whatever the configured limit.
        assert!(crate::job::Limits::default().max_spp <= MAX_EXACT_SPP);
        let limits = crate::job::Limits { max_spp: u32::MAX, ..Default::default() };
        let ok = crate::job::RenderSettings::new(8, 8, MAX_EXACT_SPP);
        assert!(ok.validate(&limits).is_ok());
        let e = crate::job::RenderSettings::new(8, 8, MAX_EXACT_SPP + 1).validate(&limits).expect_err("refused");
        assert!(e.to_string().contains("spp") && e.to_string().contains("1048576"), "{e}");
        // Out-of-range values are clamped, not wrapped: negative and NaN to 0, huge to the max.
        assert_eq!(to_fixed(-3.0), 0);
        assert_eq!(to_fixed(f32::NAN), 0);
        assert_eq!(to_fixed(1e30), to_fixed(MAX_SAMPLE_VALUE));
        // 2^20 samples of the largest value: no saturation, the mean is the value.
        let one = PixelSums::from_sample(&SampleValue { radiance: [1e30; 3], ..Default::default() });
        let mut p = PixelSums::default();
        let mut part = one;
        // Doubling: 2^20 samples in 20 merges.
        for _ in 0..20 {
            let copy = part;
            part.merge(&copy);
        }
        p.merge(&part);
        assert_eq!(p.weight, MAX_EXACT_SPP);
        assert!(!p.rgb.contains(&u64::MAX));
        let mut film = Film::new(1, 1);
        film.sums[0] = p;
        assert_eq!(film.resolve().rgb[0], [MAX_SAMPLE_VALUE; 3]);
        // Its squared luminance saturated: the variance says so, the film counts it.
        assert_eq!(film.saturated_pixels(), 1);
        assert!(film.resolve().variance[0].is_infinite());
        // Splats beyond the bound stay at u64::MAX whatever else is added: never wrap.
        let mut s = SplatBuffer::new(1, 1);
        s.sums = vec![u64::MAX - 5; 3];
        film.add_splats(&s);
        film.add_splats(&s);
        assert_eq!(film.sums[0].rgb, [u64::MAX; 3]);
        assert_eq!(film.saturated_pixels(), 1);
    }

    /// A resolved mean is within the fixed point's rounding bound (2^-25 absolute) plus f32's
    /// rounding (2^-24 relative) of the f64 mean of the same (clamped) samples.
    #[test]
    fn resolved_means_match_an_f64_reference_within_the_rounding_bound() {
        for (seed, n) in [(1u64, 1usize), (2, 7), (3, 1000), (4, 4096)] {
            let all = samples(n, seed);
            let mut film = Film::new(1, 1);
            // Units of 3 samples, as a farm would merge them.
            let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 1, y1: 1 });
            for c in all.chunks(3) {
                t.sums[0] = unit(c);
                film.add_tile(&t);
            }
            let img = film.resolve();
            for c in 0..3 {
                let reference: f64 = all.iter().map(|s| f64::from(s.radiance[c])).sum::<f64>() / n as f64;
                let got = f64::from(img.rgb[0][c]);
                // (A hair of slack for the f64 division.)
                let bound = (2f64.powi(-25) + reference * 2f64.powi(-24)) * (1.0 + 1e-9);
                assert!((got - reference).abs() <= bound, "seed {seed} channel {c}: {got} vs {reference}");
            }
            let depths: Vec<f64> = all.iter().filter_map(|s| s.depth.map(f64::from)).collect();
            if !depths.is_empty() {
                let reference = depths.iter().sum::<f64>() / depths.len() as f64;
                // An f32 mean rounded once per merge (up to 1366 merges here): 2^-24 relative each.
                assert!((f64::from(img.depth[0]) - reference).abs() <= 1366.0 * 2f64.powi(-24) * reference, "depth");
            }
        }
    }

    #[test]
    fn resolve_mean_and_variance() {
        let mut film = Film::new(1, 1);
        let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 1, y1: 1 });
        for v in [1.0f32, 3.0] {
            add_sample(t.pixel_mut(0, 0), &SampleValue { radiance: [v, v, v], ..Default::default() });
        }
        film.add_tile(&t);
        let img = film.resolve();
        assert!((img.rgb[0][0] - 2.0).abs() < 1e-6);
        assert_eq!(img.samples[0], 2.0);
        // Sample variance of {1, 3} is 2; variance of the mean is 1.
        assert!((img.variance[0] - 1.0).abs() < 1e-5, "{}", img.variance[0]);
        assert!(img.depth[0].is_infinite());
        // A splat adds to the radiance, not to the camera samples' variance.
        let mut s = SplatBuffer::new(1, 1);
        s.add(0, 0, [2.0, 0.0, 0.0]);
        film.add_splats(&s);
        let img = film.resolve();
        assert!((img.rgb[0][0] - 3.0).abs() < 1e-6);
        assert!((img.variance[0] - 1.0).abs() < 1e-5, "{}", img.variance[0]);
    }

    #[test]
    fn pixels_roundtrip_through_their_byte_layout() {
        let p = unit(&samples(9, 11));
        let mut b = [0u8; PIXEL_BYTES];
        p.write_le(&mut b);
        assert_eq!(PixelSums::read_le(&b), p);
    }

    /// The EXR streamed from layers given up is the file `encode_exr` makes, byte for byte,
    /// with and without a denoised layer.
    #[test]
    fn streamed_exr_file_is_the_encoded_exr() {
        let mut film = Film::new(37, 21);
        let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 37, y1: 21 });
        for y in 0..21 {
            for x in 0..37 {
                let f = (x * 21 + y) as f32;
                add_sample(
                    t.pixel_mut(x, y),
                    &SampleValue {
                        radiance: [f * 0.01, 0.5, 1.0 / (1.0 + f)],
                        albedo: [0.25, 0.5, 0.75],
                        normal: [0.0, 0.6, 0.8],
                        depth: (x % 5 != 0).then_some(f),
                    },
                );
            }
        }
        film.add_tile(&t);
        let dir = tempfile::tempdir().expect("tempdir");
        let mut layers = film.resolve();
        for denoised in [None, Some(vec![[0.125f32, 0.25, 0.5]; 37 * 21])] {
            layers.denoised = denoised;
            let path = dir.path().join("image.exr");
            layers.clone().into_exr_file(&path).expect("write");
            assert!(std::fs::read(&path).expect("read") == layers.encode_exr().expect("encode"));
            let back = read_exr(&path).expect("read back");
            assert_eq!(back.get("denoised.G").is_some(), layers.denoised.is_some());
            assert_eq!(back.get("R").expect("R"), layers.rgb.iter().map(|p| p[0]).collect::<Vec<_>>());
        }
    }

    #[test]
    fn exr_roundtrip_through_our_reader() {
        let mut film = Film::new(3, 2);
        let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 3, y1: 2 });
        add_sample(
            t.pixel_mut(2, 1),
            &SampleValue {
                radiance: [0.5, 0.25, 0.125],
                albedo: [1.0, 0.0, 0.0],
                normal: [0.0, 1.0, 0.0],
                depth: Some(2.5),
            },
        );
        film.add_tile(&t);
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("x.exr");
        film.resolve().write_exr(&path).expect("write");
        let back = read_exr(&path).expect("read");
        assert_eq!((back.width, back.height), (3, 2));
        let r = back.get("R").expect("R");
        assert_eq!(r[5], 0.5);
        assert_eq!(back.get("depth.Z").expect("depth")[5], 2.5);
        assert_eq!(back.get("normal.Y").expect("normal")[5], 1.0);
        assert_eq!(back.channels.len(), 12);
    }
}

/// Properties of the merge on random parts.
#[cfg(test)]
mod props {
    use super::*;
    use proptest::prelude::*;

    fn sample() -> impl Strategy<Value = SampleValue> {
        (
            proptest::array::uniform3(prop_oneof![0.0f32..10.0, 0.0f32..1e6, Just(f32::NAN), -1.0f32..0.0]),
            proptest::array::uniform3(0.0f32..1.0),
            proptest::array::uniform3(-1.0f32..1.0),
            proptest::option::of(0.0f32..1e4),
        )
            .prop_map(|(radiance, albedo, normal, depth)| SampleValue { radiance, albedo, normal, depth })
    }

    fn part() -> impl Strategy<Value = PixelSums> {
        proptest::collection::vec(sample(), 0..6).prop_map(|v| {
            let mut a = PixelAccum::default();
            for s in &v {
                a.add(s);
            }
            a.finish()
        })
    }

    fn exact(p: &PixelSums) -> ([u64; 3], u64, u64, u32, u32) {
        (p.rgb, p.lum, p.lum_sq, p.weight, p.hits)
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, rng_seed: proptest::test_runner::RngSeed::Fixed(0xf11f), ..ProptestConfig::default() })]
        /// Exact channels: associative and commutative. AOV means: commutative (bitwise).
        #[test]
        fn merge_is_associative_and_commutative(a in part(), b in part(), c in part()) {
            let m = |x: &PixelSums, y: &PixelSums| { let mut r = *x; r.merge(y); r };
            prop_assert_eq!(m(&a, &b), m(&b, &a));
            prop_assert_eq!(exact(&m(&m(&a, &b), &c)), exact(&m(&a, &m(&b, &c))));
            prop_assert_eq!(exact(&m(&m(&a, &b), &c)), exact(&m(&m(&c, &a), &b)));
        }

        /// Saturating sums of huge parts stay at the top, in any order.
        #[test]
        fn saturated_sums_are_order_independent(x in any::<u64>(), y in any::<u64>(), z in any::<u64>()) {
            let p = |v: u64| PixelSums { rgb: [v; 3], lum: v, lum_sq: v, ..Default::default() };
            let m = |x: PixelSums, y: PixelSums| { let mut r = x; r.merge(&y); r };
            prop_assert_eq!(m(m(p(x), p(y)), p(z)), m(p(x), m(p(y), p(z))));
            prop_assert_eq!(m(m(p(x), p(y)), p(z)), m(m(p(z), p(y)), p(x)));
        }
    }
}
