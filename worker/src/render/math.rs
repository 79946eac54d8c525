//! The renderer's own elementary functions (sin, cos, tan, atan2, asin, acos, exp, pow, hypot),
//! written with `+ - * /`, `sqrt`, comparisons and integer bit operations only.
//!
//! Why not the standard library's: `f32::sin` and its kin call the system's C library (glibc's
//! `sinf`, musl's, ...), whose results differ between implementations and versions by an ulp
//! here and there. A farm mixes machines, and a unit must be a pure function of its inputs
//! whatever worker renders it: one worker on another glibc would give other bits (a real
//! determinism risk, not a theoretical one: glibc rewrote `sinf`, `expf` and `powf` in 2.28).
//! IEEE 754 makes `+ - * /` and `sqrt` correctly rounded everywhere, so functions built from them
//! alone give the same bits on every machine.
//!
//! Why generic: the wavefront integrator samples 8 paths at once, and each lane must give the
//! scalar path's bits. The lane-wise functions ([`sin_cos`], [`sin_cos_small`], [`atan2`],
//! [`asin`], [`acos`], [`exp`]) have one body over [`Real`], implemented by `f32` and by
//! [`super::wide::F32x8`] (8 lanes of AVX2 instructions): the same IEEE operations in the same
//! order, so the same bits, and no branch on a lane's value (both sides are computed, then
//! selected).
//!
//! Accuracy (measured by the tests over dense sweeps against `f64` std, which they assert):
//! - [`sin_cos`] ([`sin_cos_small`] on [-pi/4, pi/4]): absolute error <= 1.2e-7 for |x| <= 8192 (the range reduction by pi/2 is
//!   Cody-Waite's in three parts; beyond 8192 it loses bits, and beyond 2^22 it is meaningless:
//!   callers pass angles, and reduce user input such as degrees first); <= 2 ulp on [-pi, pi]
//!   where |sin| >= 1e-3.
//! - [`atan2`]: <= 3 ulp; [`asin`], [`acos`]: <= 2 ulp; [`exp`]: <= 2 ulp (normal results;
//!   subnormal results within one ulp of the smallest normal's spacing).
//! - [`powf`], [`hypot`], [`sin_cos_f64`]: computed in `f64`; `powf` and `hypot` are within
//!   one ulp (nearly always correctly rounded), `sin_cos_f64` within 2 ulp of f64 (one body
//!   over [`Real64`]: `f64` or 4 AVX2 lanes of it).
//!
//! Polynomials: Cephes' single-precision minimax coefficients (Moshier) for the f32 kernels,
//! fdlibm's for `sin_cos_f64`.

// The polynomial and reduction constants are quoted digit for digit from Cephes and fdlibm, so
// that they can be checked against those sources; each rounds to the float the source meant.
#![allow(clippy::excessive_precision)]

use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};

/// A number type the lane-wise functions are written over: `f32`, or 8 lanes of it
/// ([`super::wide::F32x8`], AVX2).
///
/// Implementations must make every operation the lane-wise IEEE operation of `f32` (no fused
/// multiply-add, no approximate reciprocal or square root), so that a lane of the result is the
/// scalar function's result for that lane's input. Constants are made from an existing value
/// ([`Real::splat`] takes `self`): a lane type's values exist only where its instructions do.
pub trait Real:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self> + Neg<Output = Self>
{
    /// The 32-bit integers of the lanes (two's complement, wrapping).
    type Int: Copy
        + Add<Output = Self::Int>
        + Sub<Output = Self::Int>
        + BitAnd<Output = Self::Int>
        + BitOr<Output = Self::Int>
        + BitXor<Output = Self::Int>;
    /// One truth value per lane.
    type Mask: Copy + BitAnd<Output = Self::Mask> + BitOr<Output = Self::Mask> + Not<Output = Self::Mask>;

    /// `v` in every lane.
    fn splat(self, v: f32) -> Self;
    /// `v` in every lane.
    fn int(self, v: i32) -> Self::Int;
    fn to_bits(self) -> Self::Int;
    fn from_bits(i: Self::Int) -> Self;
    /// Shift left by `N` (below 32).
    fn shl<const N: i32>(i: Self::Int) -> Self::Int;
    /// Arithmetic shift right by `N` (below 32).
    fn sar<const N: i32>(i: Self::Int) -> Self::Int;
    fn int_eq(a: Self::Int, b: Self::Int) -> Self::Mask;
    fn sqrt(self) -> Self;
    /// `self < o`, false where either is NaN.
    fn lt(self, o: Self) -> Self::Mask;
    /// `self == o`, false where either is NaN.
    fn eq(self, o: Self) -> Self::Mask;
    /// `a` where `m` holds, else `b`.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
    /// The ray-origin offset of one coordinate `self` along the normal's component `n`
    /// (`super::geometry::offset_component`: integer ULPs, a fixed step near the origin).
    fn offset_along(self, n: Self) -> Self;
    /// Bits 0..8 of `bits` as a mask (lane `i` true where bit `i` is set; `f32`: bit 0).
    fn mask_of_bits(self, bits: u32) -> Self::Mask;
    /// The lanes as f64: `f64` for `f32`, and 4 lanes of it for 8 lanes of `f32`.
    type F64: Real64;
    /// How many [`Real::F64`] values hold the lanes (1 or 2).
    const HALVES: usize;
    /// The lanes converted (exactly) to f64, in [`Real::HALVES`] values (lanes 0..4, then 4..8).
    fn widen(self) -> [Self::F64; 2];
    /// The first [`Real::HALVES`] values' lanes rounded to f32 (to nearest, as `as f32`).
    fn narrow(self, w: [Self::F64; 2]) -> Self;

    #[inline(always)]
    fn gt(self, o: Self) -> Self::Mask {
        o.lt(self)
    }
    /// `self <= o`, false where either is NaN.
    #[inline(always)]
    fn le(self, o: Self) -> Self::Mask {
        self.lt(o) | self.eq(o)
    }
    /// `self >= o`, false where either is NaN.
    #[inline(always)]
    fn ge(self, o: Self) -> Self::Mask {
        o.lt(self) | self.eq(o)
    }
    /// The larger of the two (`o` where `self < o`, else `self`: `f32::max` for numbers).
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        Self::select(self.lt(o), o, self)
    }
    /// `|x|` (the sign bit cleared).
    #[inline(always)]
    fn abs(self) -> Self {
        Self::from_bits(self.to_bits() & self.int(i32::MAX))
    }
    /// The sign bit of `self` alone, as an integer.
    #[inline(always)]
    fn sign_bit(self) -> Self::Int {
        self.to_bits() & self.int(i32::MIN)
    }
    /// `self` with `bits` xor-ed into its bits.
    #[inline(always)]
    fn xor_bits(self, bits: Self::Int) -> Self {
        Self::from_bits(self.to_bits() ^ bits)
    }
}

impl Real for f32 {
    type Int = i32;
    type Mask = bool;

    #[inline(always)]
    fn splat(self, v: f32) -> Self {
        v
    }
    #[inline(always)]
    fn int(self, v: i32) -> i32 {
        v
    }
    #[inline(always)]
    fn to_bits(self) -> i32 {
        f32::to_bits(self) as i32
    }
    #[inline(always)]
    fn from_bits(i: i32) -> Self {
        f32::from_bits(i as u32)
    }
    #[inline(always)]
    fn shl<const N: i32>(i: i32) -> i32 {
        i << N
    }
    #[inline(always)]
    fn sar<const N: i32>(i: i32) -> i32 {
        i >> N
    }
    #[inline(always)]
    fn int_eq(a: i32, b: i32) -> bool {
        a == b
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> bool {
        self < o
    }
    #[inline(always)]
    fn eq(self, o: Self) -> bool {
        self == o
    }
    #[inline(always)]
    fn offset_along(self, n: Self) -> Self {
        super::geometry::offset_component(self, n)
    }
    #[inline(always)]
    fn select(m: bool, a: Self, b: Self) -> Self {
        if m { a } else { b }
    }
    #[inline(always)]
    fn mask_of_bits(self, bits: u32) -> bool {
        bits & 1 != 0
    }
    type F64 = f64;
    const HALVES: usize = 1;
    #[inline(always)]
    fn widen(self) -> [f64; 2] {
        [f64::from(self); 2]
    }
    #[inline(always)]
    fn narrow(self, w: [f64; 2]) -> Self {
        w[0] as f32
    }
}

/// 1.5 * 2^23: adding it to an f32 of magnitude below 2^22 rounds it to an integer (to nearest,
/// ties to even), held in the sum's low mantissa bits.
const ROUND_MAGIC: f32 = 12_582_912.0;
/// pi/2 in three parts (Cephes' DP1..DP3 doubled): the first two have 8 and 11 significant bits,
/// so `j * part` is exact for the quadrant numbers `j` of |x| <= 8192.
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_512_969_970_703_125e-4;
const PIO2_3: f32 = 7.549_789_954_891_882_16e-8;
const FRAC_PI_2: f32 = std::f32::consts::FRAC_PI_2;
const FRAC_PI_4: f32 = std::f32::consts::FRAC_PI_4;
const PI: f32 = std::f32::consts::PI;

/// `(sin x, cos x)` for |x| <= pi/4 (no range reduction): Cephes' `sinf`/`cosf` polynomials.
#[inline(always)]
pub fn sin_cos_small<R: Real>(r: R) -> (R, R) {
    let c = |v: f32| r.splat(v);
    let z = r * r;
    let s = ((c(-1.951_529_589_1e-4) * z + c(8.332_160_873_6e-3)) * z + c(-1.666_665_461_1e-1)) * z * r + r;
    // sin(-0) = -0 (the sum above makes it +0).
    let s = R::select(r.eq(c(0.0)), r, s);
    let cos =
        ((c(2.443_315_711_809_948e-5) * z + c(-1.388_731_625_493_765e-3)) * z + c(4.166_664_568_298_827e-2)) * z * z
            - c(0.5) * z
            + c(1.0);
    (s, cos)
}

/// `(sin x, cos x)`: Cody-Waite reduction to [-pi/4, pi/4] by the nearest multiple of pi/2,
/// [`sin_cos_small`], then the quadrant's swap and signs. NaN or infinite `x` gives NaN.
#[inline(always)]
pub fn sin_cos<R: Real>(x: R) -> (R, R) {
    let c = |v: f32| x.splat(v);
    let n = |v: i32| x.int(v);
    let t = x * c(std::f32::consts::FRAC_2_PI) + c(ROUND_MAGIC);
    let j = t - c(ROUND_MAGIC);
    // The quadrant, j mod 4, in the low bits of t's mantissa.
    let q = t.to_bits();
    let r = ((x - j * c(PIO2_1)) - j * c(PIO2_2)) - j * c(PIO2_3);
    let (s0, c0) = sin_cos_small(r);
    let odd = R::int_eq(q & n(1), n(1));
    let (sin, cos) = (R::select(odd, c0, s0), R::select(odd, s0, c0));
    // sin changes sign in quadrants 2 and 3, cos in quadrants 1 and 2.
    let sin_sign = R::shl::<30>(q & n(2));
    let cos_sign = R::shl::<30>((q + n(1)) & n(2));
    (sin.xor_bits(sin_sign), cos.xor_bits(cos_sign))
}

/// `sin x` ([`sin_cos`]).
#[inline]
pub fn sin(x: f32) -> f32 {
    sin_cos(x).0
}

/// `cos x` ([`sin_cos`]).
#[inline]
pub fn cos(x: f32) -> f32 {
    sin_cos(x).1
}

/// `tan x` as `sin x / cos x` (<= 3 ulp; used to set up cameras).
#[inline]
pub fn tan(x: f32) -> f32 {
    let (s, c) = sin_cos(x);
    s / c
}

/// `atan a` for `a` in [0, 1] (Cephes' `atanf`: above tan(pi/8), `pi/4 + atan((a-1)/(a+1))`).
#[inline(always)]
fn atan_unit<R: Real>(a: R) -> R {
    let c = |v: f32| a.splat(v);
    let big = a.gt(c(0.414_213_562_373_095_0));
    let x = R::select(big, (a - c(1.0)) / (a + c(1.0)), a);
    let z = x * x;
    let p = (((c(8.053_744_495_38e-2) * z + c(-1.387_768_560_32e-1)) * z + c(1.997_771_064_78e-1)) * z
        + c(-3.333_294_915_39e-1))
        * z
        * x
        + x;
    R::select(big, c(FRAC_PI_4) + p, p)
}

/// `atan2(y, x)`, the angle of (x, y) in [-pi, pi], with IEEE 754's special cases (signed
/// zeros: `atan2(+-0, -0) = +-pi`; infinities). NaN in, NaN out.
#[inline(always)]
pub fn atan2<R: Real>(y: R, x: R) -> R {
    let c = |v: f32| y.splat(v);
    let n = |v: i32| y.int(v);
    let (ax, ay) = (x.abs(), y.abs());
    let steep = ay.gt(ax);
    let (lo, hi) = (R::select(steep, ax, ay), R::select(steep, ay, ax));
    // 0/0 (both zero) is 0; inf/inf (both infinite) is 1.
    let a = R::select(hi.eq(c(0.0)), c(0.0), R::select(lo.eq(c(f32::INFINITY)), c(1.0), lo / hi));
    let r = atan_unit(a);
    let r = R::select(steep, c(FRAC_PI_2) - r, r);
    let r = R::select(R::int_eq(x.sign_bit(), n(0)), r, c(PI) - r);
    r.xor_bits(y.sign_bit())
}

/// `atan x`.
#[inline]
pub fn atan(x: f32) -> f32 {
    atan2(x, 1.0)
}

/// The polynomial of Cephes' `asinf`: `asin(s)` for `s` in [-0.5, 0.5], given `z = s * s`.
#[inline(always)]
fn asin_kernel<R: Real>(s: R, z: R) -> R {
    let c = |v: f32| s.splat(v);
    ((((c(4.216_319_904_8e-2) * z + c(2.418_131_104_9e-2)) * z + c(4.547_002_599_8e-2)) * z + c(7.495_300_268_6e-2))
        * z
        + c(1.666_675_242_2e-1))
        * z
        * s
        + s
}

/// `asin x` in [-pi/2, pi/2]; NaN outside [-1, 1]. Above 1/2 through
/// `asin a = pi/2 - 2 asin(sqrt((1 - a) / 2))`.
#[inline(always)]
pub fn asin<R: Real>(x: R) -> R {
    let c = |v: f32| x.splat(v);
    let a = x.abs();
    let big = a.gt(c(0.5));
    let z = R::select(big, c(0.5) * (c(1.0) - a), a * a);
    let s = R::select(big, z.sqrt(), a);
    let p = asin_kernel(s, z);
    R::select(big, c(FRAC_PI_2) - (p + p), p).xor_bits(x.sign_bit())
}

/// `acos x` in [0, pi]; NaN outside [-1, 1]. Near +-1 through
/// `acos a = 2 asin(sqrt((1 - a) / 2))`, so small angles keep their precision.
#[inline(always)]
pub fn acos<R: Real>(x: R) -> R {
    let c = |v: f32| x.splat(v);
    let n = |v: i32| x.int(v);
    let a = x.abs();
    let big = a.gt(c(0.5));
    let z = R::select(big, c(0.5) * (c(1.0) - a), x * x);
    let s = R::select(big, z.sqrt(), x);
    let p = asin_kernel(s, z);
    let twice = p + p;
    let negative = R::int_eq(x.sign_bit(), n(0));
    R::select(big, R::select(negative, twice, c(PI) - twice), c(FRAC_PI_2) - p)
}

/// `e^x`: `2^n e^r` with `n` the nearest integer to `x / ln 2` and |r| <= ln 2 / 2 (Cephes'
/// `expf`), the power of two applied in two factors so that subnormal results round once.
/// Overflows to infinity, underflows to 0; NaN in, NaN out.
#[inline(always)]
pub fn exp<R: Real>(x: R) -> R {
    let c = |v: f32| x.splat(v);
    let n = |v: i32| x.int(v);
    // Clamped where the result is already infinite or 0, so that n stays small.
    let x = R::select(x.gt(c(100.0)), c(100.0), x);
    let x = R::select(x.lt(c(-110.0)), c(-110.0), x);
    let t = x * c(std::f32::consts::LOG2_E) + c(ROUND_MAGIC);
    let nf = t - c(ROUND_MAGIC);
    let k = t.to_bits() - c(ROUND_MAGIC).to_bits();
    let r = (x - nf * c(0.693_359_375)) - nf * c(-2.121_944_40e-4);
    let z = r * r;
    let p = (((((c(1.987_569_150_0e-4) * r + c(1.398_199_950_7e-3)) * r + c(8.333_451_907_3e-3)) * r
        + c(4.166_579_589_4e-2))
        * r
        + c(1.666_666_545_9e-1))
        * r
        + c(5.000_000_120_1e-1))
        * z
        + r
        + c(1.0);
    let k1 = R::sar::<1>(k);
    let k2 = k - k1;
    let pow2 = |e: R::Int| R::from_bits(R::shl::<23>(e + n(127)));
    p * pow2(k1) * pow2(k2)
}

/// `ln x` in f64 for a finite normal `x > 0` (every positive f32 is one in f64):
/// `k ln 2 + ln m` with `m` in [sqrt(1/2), sqrt(2)), and `ln m = 2 atanh(s)`,
/// `s = (m - 1) / (m + 1)`, by its series (|s| <= 0.1716: 11 terms reach f64's precision).
fn ln_f64(x: f64) -> f64 {
    let bits = x.to_bits();
    let mut k = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mut m = f64::from_bits((bits & ((1 << 52) - 1)) | (1023 << 52));
    if m > std::f64::consts::SQRT_2 {
        m *= 0.5;
        k += 1;
    }
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let mut series = 1.0 / 21.0;
    for d in [19.0, 17.0, 15.0, 13.0, 11.0, 9.0, 7.0, 5.0, 3.0] {
        series = series * s2 + 1.0 / d;
    }
    let ln_m = 2.0 * s + 2.0 * s * s2 * series;
    let k = k as f64;
    // ln 2 in two parts (fdlibm's ln2_hi has trailing zeros: k * ln2_hi is exact).
    k * 6.931_471_803_691_238_164_9e-1 + (ln_m + k * 1.908_214_929_270_587_700_02e-10)
}

/// `e^t` in f64 for |t| <= 700: `2^n e^r`, |r| <= ln 2 / 2, by Taylor's series to r^13.
fn exp_f64(t: f64) -> f64 {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52
    let n = (t * std::f64::consts::LOG2_E + MAGIC) - MAGIC;
    let r = (t - n * 6.931_471_803_691_238_164_9e-1) - n * 1.908_214_929_270_587_700_02e-10;
    let mut p = 1.0 / 6_227_020_800.0; // 1/13!
    for f in [479_001_600.0, 39_916_800.0, 3_628_800.0, 362_880.0, 40_320.0, 5_040.0, 720.0, 120.0, 24.0, 6.0, 2.0] {
        p = p * r + 1.0 / f;
    }
    let e = (p * r + 1.0) * r + 1.0;
    e * f64::from_bits(((n as i64 + 1023) as u64) << 52)
}

/// `x^y` (std's `powf` special cases: `x^0 = 1`, `1^y = 1`, `0^y`, infinities, negative `x` with
/// integer `y`; NaN for negative `x` with any other `y`), as `e^(y ln x)` in f64, rounded once
/// to f32.
pub fn powf(x: f32, y: f32) -> f32 {
    if y == 0.0 || x == 1.0 {
        return 1.0;
    }
    if x.is_nan() || y.is_nan() {
        return f32::NAN;
    }
    let integer = y == y.trunc();
    let odd = integer && y.abs() < 16_777_216.0 && (y.abs() as u32) % 2 == 1;
    let a = x.abs();
    if x < 0.0 && !integer {
        return f32::NAN;
    }
    let sign = if x.is_sign_negative() && odd { -1.0 } else { 1.0 };
    if a == 0.0 {
        return sign * if y > 0.0 { 0.0 } else { f32::INFINITY };
    }
    if a == f32::INFINITY {
        return sign * if y > 0.0 { f32::INFINITY } else { 0.0 };
    }
    if a == 1.0 {
        // (-1)^y for integer or infinite y (ln 1 * inf would be NaN).
        return sign;
    }
    let t = f64::from(y) * ln_f64(f64::from(a));
    if t > 200.0 {
        return sign * f32::INFINITY;
    }
    if t < -200.0 {
        return sign * 0.0;
    }
    sign * exp_f64(t) as f32
}

/// `sqrt(x^2 + y^2)` without overflow or underflow: in f64, where the squares of f32s are exact.
#[inline]
pub fn hypot(x: f32, y: f32) -> f32 {
    let (x, y) = (f64::from(x), f64::from(y));
    (x * x + y * y).sqrt() as f32
}

/// `(sin x, cos x)` in f64 for |x| <= 2^20 ([`sin_cos_f64_lanes`]).
pub fn sin_cos_f64(x: f64) -> (f64, f64) {
    sin_cos_f64_lanes(x)
}

/// `(sin x, cos x)` in f64 for |x| <= 2^20, written once over [`Real64`]: Cody-Waite reduction
/// by pi/2 in two parts (fdlibm's `pio2_1`, `pio2_1t`) with the reduction's rounding error
/// carried into fdlibm's `__kernel_sin` and `__kernel_cos`, then the quadrant's swap and signs.
#[inline(always)]
pub fn sin_cos_f64_lanes<R: Real64>(x: R) -> (R, R) {
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52
    const PIO2_1: f64 = 1.570_796_326_734_125_614_17; // first 33 bits of pi/2
    const PIO2_1T: f64 = 6.077_100_506_506_192_249_32e-11; // pi/2 - PIO2_1
    let c = |v: f64| x.splat(v);
    // The nearest multiple n of pi/2, held in t's low mantissa bits (n mod 4 is the quadrant).
    let t = x * c(std::f64::consts::FRAC_2_PI) + c(MAGIC);
    let n = t - c(MAGIC);
    let hi = x - n * c(PIO2_1);
    let r = hi - n * c(PIO2_1T);
    let y = (hi - r) - n * c(PIO2_1T);
    let z = r * r;
    let v = z * r;
    let rs = c(8.333_333_333_322_489_461_24e-3)
        + z * (c(-1.984_126_982_985_794_931_34e-4)
            + z * (c(2.755_731_370_707_006_767_89e-6)
                + z * (c(-2.505_076_025_340_686_341_95e-8) + z * c(1.589_690_995_211_550_102_21e-10))));
    let s = r - ((z * (c(0.5) * y - v * rs) - y) - v * c(-1.666_666_666_666_663_243_48e-1));
    let rc = z
        * (c(4.166_666_666_666_660_190_37e-2)
            + z * (c(-1.388_888_888_887_410_957_49e-3)
                + z * (c(2.480_158_728_947_672_941_78e-5)
                    + z * (c(-2.755_731_435_139_066_330_35e-7)
                        + z * (c(2.087_572_321_298_174_827_90e-9) + z * c(-1.135_964_755_778_819_482_65e-11))))));
    let hz = c(0.5) * z;
    let w = c(1.0) - hz;
    let cos = w + (((c(1.0) - w) - hz) + (z * rc - r * y));
    // Quadrants 0..3: (s, c), (c, -s), (-s, -c), (-c, s).
    let q = t.to_bits();
    let bit = |k: i64| R::int_eq(q & t.int(k), t.int(k));
    let odd = bit(1);
    let sin_negative = bit(2);
    let cos_negative = R::int_eq((q + t.int(1)) & t.int(2), t.int(2));
    (R::select(odd, cos, s).negate_where(sin_negative), R::select(odd, s, cos).negate_where(cos_negative))
}

/// A number type the f64 lane-wise functions are written over: `f64`, or 4 lanes of it
/// (`super::wide::F64x4`, AVX2), with the same rules as [`Real`] (every operation the
/// lane-wise IEEE operation of `f64`).
pub trait Real64:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self> + Neg<Output = Self>
{
    /// The 64-bit integers of the lanes (two's complement, wrapping).
    type Int: Copy + Add<Output = Self::Int> + BitAnd<Output = Self::Int>;
    type Mask: Copy + BitAnd<Output = Self::Mask> + BitOr<Output = Self::Mask> + Not<Output = Self::Mask>;

    /// `v` in every lane.
    fn splat(self, v: f64) -> Self;
    /// `v` in every lane.
    fn int(self, v: i64) -> Self::Int;
    fn to_bits(self) -> Self::Int;
    fn int_eq(a: Self::Int, b: Self::Int) -> Self::Mask;
    fn sqrt(self) -> Self;
    /// `self < o`, false where either is NaN.
    fn lt(self, o: Self) -> Self::Mask;
    /// `a` where `m` holds, else `b`.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
    /// `-self` where `m` holds (the sign bit flipped), else `self`.
    fn negate_where(self, m: Self::Mask) -> Self;
    /// `|x|` (the sign bit cleared).
    fn abs(self) -> Self;
    /// The mask's lanes as bits (lane `i` true sets bit `i`).
    fn mask_bits(m: Self::Mask) -> u32;

    #[inline(always)]
    fn gt(self, o: Self) -> Self::Mask {
        o.lt(self)
    }
}

impl Real64 for f64 {
    type Int = i64;
    type Mask = bool;

    #[inline(always)]
    fn splat(self, v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn int(self, v: i64) -> i64 {
        v
    }
    #[inline(always)]
    fn to_bits(self) -> i64 {
        f64::to_bits(self) as i64
    }
    #[inline(always)]
    fn int_eq(a: i64, b: i64) -> bool {
        a == b
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> bool {
        self < o
    }
    #[inline(always)]
    fn select(m: bool, a: Self, b: Self) -> Self {
        if m { a } else { b }
    }
    #[inline(always)]
    fn negate_where(self, m: bool) -> Self {
        if m { -self } else { self }
    }
    #[inline(always)]
    fn abs(self) -> Self {
        f64::abs(self)
    }
    #[inline(always)]
    fn mask_bits(m: bool) -> u32 {
        u32::from(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The distance in ulps between `got` and the f64 value `want`, both rounded to f32 (0 when
    /// `got` is `want` correctly rounded).
    fn ulps(got: f32, want: f64) -> u32 {
        let w = want as f32;
        if got == w || got.is_nan() && w.is_nan() {
            return 0;
        }
        let key = |v: f32| {
            let b = v.to_bits() as i64;
            if b < 0x8000_0000 { b } else { 0x8000_0000 - b }
        };
        (key(got) - key(w)).unsigned_abs() as u32
    }

    /// `n` points evenly over [a, b], plus every f32 near 0 and the ends.
    fn sweep(a: f32, b: f32, n: u32) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| a + (b - a) * (i as f32 / n as f32)).chain([a, b, 0.0, -0.0, 1e-30, -1e-30, 1e-6])
    }

    fn max_ulps(xs: impl Iterator<Item = f32>, f: impl Fn(f32) -> f32, want: impl Fn(f64) -> f64) -> (u32, f32) {
        xs.map(|x| (ulps(f(x), want(f64::from(x))), x)).max_by_key(|p| p.0).unwrap_or((0, 0.0))
    }

    #[test]
    fn sin_cos_accuracy() {
        // Absolute error over a wide range.
        let mut worst = 0.0f64;
        for x in sweep(-8192.0, 8192.0, 4_000_000) {
            let (s, c) = sin_cos(x);
            let x64 = f64::from(x);
            worst = worst.max((f64::from(s) - x64.sin()).abs()).max((f64::from(c) - x64.cos()).abs());
        }
        assert!(worst <= 1.2e-7, "sin_cos absolute error {worst:e}");
        // Ulps over a turn, where the values are not tiny.
        let turn = || sweep(-PI, PI, 4_000_000).filter(|&x| f64::from(x).sin().abs() >= 1e-3);
        let (u, at) = max_ulps(turn(), sin, f64::sin);
        assert!(u <= 2, "sin: {u} ulp at {at}");
        let turn = || sweep(-PI, PI, 4_000_000).filter(|&x| f64::from(x).cos().abs() >= 1e-3);
        let (u, at) = max_ulps(turn(), cos, f64::cos);
        assert!(u <= 2, "cos: {u} ulp at {at}");
        // The kernel alone on its interval.
        let quarter = || sweep(-FRAC_PI_4, FRAC_PI_4, 1_000_000);
        let (u, at) = max_ulps(quarter().filter(|&x| x.abs() >= 1e-3), |x| sin_cos_small(x).0, f64::sin);
        assert!(u <= 2, "sin_cos_small sin: {u} ulp at {at}");
        let (u, at) = max_ulps(quarter(), |x| sin_cos_small(x).1, f64::cos);
        assert!(u <= 2, "sin_cos_small cos: {u} ulp at {at}");
        // Signed zero, and the quadrant boundaries.
        assert_eq!(sin(-0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(sin_cos(0.0), (0.0, 1.0));
        assert!(sin(f32::INFINITY).is_nan() && cos(f32::NAN).is_nan());
        let (u, at) = max_ulps(sweep(-1.0, 1.0, 100_000).map(|x| x * 1e-3), tan, f64::tan);
        assert!(u <= 3, "tan: {u} ulp at {at}");
        let (u, at) = max_ulps(sweep(-1.5, 1.5, 1_000_000), tan, f64::tan);
        assert!(u <= 3, "tan: {u} ulp at {at}");
    }

    #[test]
    fn atan2_accuracy_and_special_cases() {
        let mut worst = (0, 0.0, 0.0);
        for i in 0..2000 {
            let angle = -PI + 2.0 * PI * (i as f32 + 0.37) / 2000.0;
            for r in [1e-30f32, 1e-3, 0.7, 1.0, 3.0, 1e30] {
                let (y, x) = (r * angle.sin(), r * angle.cos());
                let u = ulps(atan2(y, x), f64::from(y).atan2(f64::from(x)));
                if u > worst.0 {
                    worst = (u, y, x);
                }
            }
        }
        for y in sweep(-4.0, 4.0, 3000) {
            for x in sweep(-4.0, 4.0, 300) {
                let u = ulps(atan2(y, x), f64::from(y).atan2(f64::from(x)));
                if u > worst.0 {
                    worst = (u, y, x);
                }
            }
        }
        assert!(worst.0 <= 3, "atan2: {} ulp at ({}, {})", worst.0, worst.1, worst.2);
        let (u, at) = max_ulps(sweep(-100.0, 100.0, 1_000_000), atan, f64::atan);
        assert!(u <= 3, "atan: {u} ulp at {at}");
        let inf = f32::INFINITY;
        for (y, x) in [
            (0.0, 0.0),
            (-0.0, 0.0),
            (0.0, -0.0),
            (-0.0, -0.0),
            (1.0, 0.0),
            (-1.0, -0.0),
            (0.0, -1.0),
            (-0.0, -1.0),
            (inf, inf),
            (-inf, inf),
            (inf, -inf),
            (-inf, -inf),
            (1.0, inf),
            (1.0, -inf),
            (-1.0, -inf),
            (inf, 1.0),
            (-inf, -3.0),
        ] {
            let want = f32::atan2(y, x);
            assert_eq!(atan2(y, x).to_bits(), want.to_bits(), "atan2({y}, {x})");
        }
        assert!(atan2(f32::NAN, 1.0).is_nan() && atan2(1.0, f32::NAN).is_nan());
    }

    #[test]
    fn asin_acos_accuracy() {
        let (u, at) = max_ulps(sweep(-1.0, 1.0, 4_000_000), asin, f64::asin);
        assert!(u <= 2, "asin: {u} ulp at {at}");
        let (u, at) = max_ulps(sweep(-1.0, 1.0, 4_000_000), acos, f64::acos);
        assert!(u <= 2, "acos: {u} ulp at {at}");
        // Near 1, where the angle is small.
        let near_one = || (0..100_000).map(|i| 1.0 - i as f32 * f32::EPSILON / 2.0);
        let (u, at) = max_ulps(near_one(), acos, f64::acos);
        assert!(u <= 2, "acos: {u} ulp at {at}");
        let (u, at) = max_ulps(near_one(), asin, f64::asin);
        assert!(u <= 2, "asin: {u} ulp at {at}");
        assert!(asin(1.0 + f32::EPSILON).is_nan() && acos(-1.5).is_nan() && asin(f32::NAN).is_nan());
        assert_eq!((asin(1.0), acos(1.0), acos(-1.0)), (FRAC_PI_2, 0.0, PI));
        assert_eq!(asin(-0.0).to_bits(), (-0.0f32).to_bits());
    }

    #[test]
    fn exp_accuracy() {
        let normal = || sweep(-87.0, 88.7, 4_000_000);
        let (u, at) = max_ulps(normal(), exp, f64::exp);
        assert!(u <= 2, "exp: {u} ulp at {at}");
        // Subnormal results: within one ulp of the smallest normal's spacing... in absolute terms.
        for x in (0..=100_000).map(|i| -103.0 + 15.5 * (i as f32 / 1e5)) {
            let err = (f64::from(exp(x)) - f64::from(x).exp()).abs();
            assert!(err <= 2.0 * f64::from(f32::from_bits(1)), "exp({x}): {} vs {}", exp(x), f64::from(x).exp());
        }
        assert_eq!((exp(0.0), exp(-200.0), exp(200.0), exp(f32::NEG_INFINITY)), (1.0, 0.0, f32::INFINITY, 0.0));
        assert_eq!(exp(f32::INFINITY), f32::INFINITY);
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn powf_and_hypot_accuracy() {
        let mut worst = (0, 0.0, 0.0);
        for x in sweep(0.0, 4.0, 3000).chain([1e-38, 1e-44, 3e38]) {
            for y in sweep(-60.0, 60.0, 600).chain([0.5, 1.0 / 3.0, 1000.0, 1e4]) {
                let u = ulps(powf(x, y), f64::from(x).powf(f64::from(y)));
                if u > worst.0 {
                    worst = (u, x, y);
                }
            }
        }
        assert!(worst.0 <= 1, "powf: {} ulp at ({}, {})", worst.0, worst.1, worst.2);
        let inf = f32::INFINITY;
        for (x, y) in [
            (0.0, 2.0),
            (-0.0, 3.0),
            (-0.0, -3.0),
            (0.0, -0.5),
            (-2.0, 3.0),
            (-2.0, 2.0),
            (-2.0, -1.0),
            (inf, 2.0),
            (inf, -2.0),
            (-inf, 3.0),
            (f32::NAN, 0.0),
            (1.0, f32::NAN),
            (1.0, inf),
            (0.5, inf),
            (2.0, inf),
            (2.0, -inf),
            (-1.0, inf),
            (-1.0, 3.0),
            (-2.0, inf),
            (-0.5, inf),
        ] {
            let (got, want) = (powf(x, y), f32::powf(x, y));
            assert_eq!(got.to_bits(), want.to_bits(), "powf({x}, {y}): {got} vs {want}");
        }
        assert!(powf(-2.0, 0.5).is_nan() && powf(f32::NAN, 1.0).is_nan());
        let mut worst = 0;
        for x in sweep(-5.0, 5.0, 2000) {
            for y in sweep(-5.0, 5.0, 200).chain([1e30, 1e-30, 3e38]) {
                worst = worst.max(ulps(hypot(x, y), f64::from(x).hypot(f64::from(y))));
            }
        }
        assert!(worst <= 1, "hypot: {worst} ulp");
    }

    #[test]
    fn sin_cos_f64_accuracy() {
        let ulps64 = |got: f64, want: f64| ((got.to_bits() as i64) - (want.to_bits() as i64)).unsigned_abs();
        let mut worst = (0, 0.0);
        for i in 0..=2_000_000 {
            let x = -8.0 + 16.0 * f64::from(i) / 2e6;
            let ((s, c), (ws, wc)) = (sin_cos_f64(x), x.sin_cos());
            // Compare as ulps where the value is not tiny, absolutely otherwise.
            for (g, w) in [(s, ws), (c, wc)] {
                let u = if w.abs() > 1e-3 { ulps64(g, w) } else { u64::from((g - w).abs() > 1e-19) * 99 };
                if u > worst.0 {
                    worst = (u, x);
                }
            }
        }
        assert!(worst.0 <= 2, "sin_cos_f64: {} ulp at {}", worst.0, worst.1);
    }

    /// The 8-lane functions give the scalar bits in every lane (the inputs include NaN,
    /// infinities, signed zeros and out-of-domain values), where the CPU has AVX2.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn lanes_give_the_scalar_bits() {
        let Some(avx2) = super::super::wide::Avx2::new() else { return };
        let special = [0.0, -0.0, 1.0, -1.0, 0.5, -0.5, f32::INFINITY, f32::NEG_INFINITY, f32::NAN, 1e-40, 1e30, -88.0];
        let mut inputs: Vec<f32> = special.to_vec();
        inputs.extend((0..200_000u64).map(|i| {
            let u = super::super::wide::unit(i);
            match i % 4 {
                0 => u * 2.0 - 1.0,
                1 => (u - 0.5) * 20.0,
                2 => (u - 0.5) * 400.0,
                _ => (u - 0.5) * 1e4,
            }
        }));
        // A macro, not a function taking `&dyn Fn`: the 8-lane body must be inlined into the
        // AVX2 function for its code to be AVX2 code.
        macro_rules! check {
            ($name:literal, |$x:ident, $y:ident| $body:expr) => {
                for (k, chunk) in inputs.chunks_exact(8).enumerate() {
                    let xs: [f32; 8] = std::array::from_fn(|i| chunk[i]);
                    let ys: [f32; 8] = std::array::from_fn(|i| inputs[(k * 13 + i * 7) % inputs.len()]);
                    let got = avx2.run(|| {
                        let ($x, $y) = (avx2.f32x8(&xs), avx2.f32x8(&ys));
                        $body.to_array()
                    });
                    for i in 0..8 {
                        let want = {
                            let ($x, $y) = (xs[i], ys[i]);
                            $body
                        };
                        let at = (xs[i], ys[i]);
                        assert_eq!(got[i].to_bits(), want.to_bits(), "{} at {at:?}", $name);
                    }
                }
            };
        }
        check!("sin", |x, _y| sin_cos(x).0);
        check!("cos", |x, _y| sin_cos(x).1);
        check!("sin small", |x, _y| sin_cos_small(x).0);
        check!("cos small", |x, _y| sin_cos_small(x).1);
        check!("atan2", |x, y| atan2(y, x));
        check!("asin", |x, _y| asin(x));
        check!("acos", |x, _y| acos(x));
        check!("exp", |x, _y| exp(x));
        check!("max", |x, y| Real::max(x, y));
        check!("offset", |x, y| Real::offset_along(x, y));
        check!("offset of small numbers", |x, y| Real::offset_along(x * x.splat(1e-3), y));
        // Every pair of the special values (zeros of both signs, NaN on either side).
        let pairs: Vec<(f32, f32)> = special.iter().flat_map(|&x| special.iter().map(move |&y| (x, y))).collect();
        for chunk in pairs.chunks(8) {
            let xs: [f32; 8] = std::array::from_fn(|i| chunk.get(i).map_or(0.0, |p| p.0));
            let ys: [f32; 8] = std::array::from_fn(|i| chunk.get(i).map_or(0.0, |p| p.1));
            let got = avx2.run(|| Real::max(avx2.f32x8(&xs), avx2.f32x8(&ys)).to_array());
            let offset = avx2.run(|| Real::offset_along(avx2.f32x8(&xs), avx2.f32x8(&ys)).to_array());
            let (x8, y8) = (avx2.f32x8(&xs), avx2.f32x8(&ys));
            let (one, zero) = (x8.splat(1.0), x8.splat(0.0));
            let le = super::super::wide::F32x8::select(x8.le(y8), one, zero).to_array();
            let ge = super::super::wide::F32x8::select(x8.ge(y8), one, zero).to_array();
            for i in 0..8 {
                assert_eq!(got[i].to_bits(), Real::max(xs[i], ys[i]).to_bits(), "max at {:?}", (xs[i], ys[i]));
                assert_eq!(le[i] == 1.0, Real::le(xs[i], ys[i]), "le at {:?}", (xs[i], ys[i]));
                assert_eq!(ge[i] == 1.0, Real::ge(xs[i], ys[i]), "ge at {:?}", (xs[i], ys[i]));
                let want = Real::offset_along(xs[i], ys[i]);
                assert_eq!(offset[i].to_bits(), want.to_bits(), "offset at {:?}", (xs[i], ys[i]));
            }
        }
    }
}
