//! Sampling warps and their pdfs, multiple importance sampling weights, and a discrete
//! distribution (pbrt-v4's `sampling.h`, same names in snake_case).
//!
//! Directions are in a local frame whose `z` is the axis (normal or cone axis); pdfs are per unit
//! solid angle, planar pdfs per unit area. Inputs `u` are in [0, 1); every routine stays finite
//! for `u` exactly 0 or just below 1.

use super::math::{self, Real};
use super::spherical;
use super::wide::{Avx2, SimdLevel};
use glam::{Vec2, Vec3A};
use std::f32::consts::{FRAC_1_PI, FRAC_PI_4, TAU};

/// The largest float below 1 (pbrt's `OneMinusEpsilon`).
pub const ONE_MINUS_EPSILON: f32 = 1.0 - f32::EPSILON / 2.0;

/// Below this solid angle (sr) [`sample_spherical_triangle`] returns `None`: the angle-sum
/// formula loses too much precision, and area sampling is as good (pbrt-v4's
/// `Triangle::MinSphericalSampleArea`).
pub const MIN_SPHERICAL_SAMPLE_AREA: f32 = 3e-4;
/// Above this solid angle (sr) [`sample_spherical_triangle`] returns `None`: the triangle covers
/// nearly a hemisphere and Arvo's construction becomes unstable (pbrt-v4's
/// `Triangle::MaxSphericalSampleArea`).
pub const MAX_SPHERICAL_SAMPLE_AREA: f32 = 6.22;

#[inline]
fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

#[inline]
fn spherical_direction(sin_theta: f32, cos_theta: f32, phi: f32) -> Vec3A {
    let (sin_phi, cos_phi) = math::sin_cos(phi);
    Vec3A::new(sin_theta.clamp(-1.0, 1.0) * cos_phi, sin_theta.clamp(-1.0, 1.0) * sin_phi, cos_theta.clamp(-1.0, 1.0))
}

/// Uniform point on the unit disk by Shirley-Chiu's concentric map (low distortion, keeps
/// stratification). Pdf `1 / pi` per unit area.
#[inline]
pub fn sample_uniform_disk_concentric(u: Vec2) -> Vec2 {
    let (x, y) = disk_concentric(u.x, u.y);
    Vec2::new(x, y)
}

/// [`sample_uniform_disk_concentric`] over lanes, without a branch on a lane's value: the angle
/// is `phi` or `pi/2 - phi` with |phi| <= pi/4, so the sine and cosine of `phi` alone, swapped
/// for the second case, need no range reduction.
#[inline(always)]
pub fn disk_concentric<R: Real>(ux: R, uy: R) -> (R, R) {
    let c = |v: f32| ux.splat(v);
    let (ox, oy) = (c(2.0) * ux - c(1.0), c(2.0) * uy - c(1.0));
    let wide = ox.abs().gt(oy.abs());
    let r = R::select(wide, ox, oy);
    let phi = c(FRAC_PI_4) * (R::select(wide, oy, ox) / r);
    let zero = c(0.0);
    let (sin, cos) = math::sin_cos_small(phi);
    // r = 0 only at the centre (both offsets 0), where phi is 0/0.
    let centre = r.eq(zero);
    let (x, y) = (R::select(wide, cos, sin), R::select(wide, sin, cos));
    (R::select(centre, zero, r * x), R::select(centre, zero, r * y))
}

/// Uniform point on the unit disk in polar coordinates (`r = sqrt(u0)`). Pdf `1 / pi`.
#[inline]
pub fn sample_uniform_disk_polar(u: Vec2) -> Vec2 {
    let r = u.x.sqrt();
    let (s, c) = math::sin_cos(TAU * u.y);
    r * Vec2::new(c, s)
}

/// Cosine-weighted direction on the `z >= 0` hemisphere (Malley's method on the concentric disk).
#[inline]
pub fn sample_cosine_hemisphere(u: Vec2) -> Vec3A {
    let (x, y, z) = cosine_hemisphere(u.x, u.y);
    Vec3A::new(x, y, z)
}

/// A direction of [`sample_cosine_hemisphere`] computed ahead for the 2D number `u` (the
/// wavefront integrator computes a bounce's directions for its whole batch, 8 lanes at once,
/// before shading).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CosineSample {
    pub u: Vec2,
    pub w: Vec3A,
}

impl CosineSample {
    /// `sample_cosine_hemisphere(u)`: taken from `ahead` where it was computed for these very
    /// bits of `u`, computed here otherwise (the same bits either way).
    #[inline]
    pub fn or_compute(ahead: Option<&CosineSample>, u: Vec2) -> Vec3A {
        match ahead {
            Some(a) if a.u.x.to_bits() == u.x.to_bits() && a.u.y.to_bits() == u.y.to_bits() => a.w,
            _ => sample_cosine_hemisphere(u),
        }
    }
}

/// [`sample_cosine_hemisphere`] of every `u`, appended to `out` in order: 8 at a time in AVX2
/// lanes where `level` has them ([`Avx2::at`]), one at a time otherwise (the bits are the same).
pub fn cosine_hemisphere_many(us: &[Vec2], level: SimdLevel, out: &mut Vec<CosineSample>) {
    let Some(avx2) = Avx2::at(level) else {
        out.extend(us.iter().map(|&u| CosineSample { u, w: sample_cosine_hemisphere(u) }));
        return;
    };
    for chunk in us.chunks(8) {
        // A short chunk's missing lanes compute (0.5, 0.5), and are dropped.
        let ux = std::array::from_fn(|i| chunk.get(i).map_or(0.5, |u| u.x));
        let uy = std::array::from_fn(|i| chunk.get(i).map_or(0.5, |u| u.y));
        let [x, y, z] = avx2.cosine_hemisphere(&ux, &uy);
        out.extend(chunk.iter().enumerate().map(|(i, &u)| CosineSample { u, w: Vec3A::new(x[i], y[i], z[i]) }));
    }
}

/// [`sample_cosine_hemisphere`] over lanes.
#[inline(always)]
pub fn cosine_hemisphere<R: Real>(ux: R, uy: R) -> (R, R, R) {
    let (x, y) = disk_concentric(ux, uy);
    let z2 = ux.splat(1.0) - x * x - y * y;
    // safe_sqrt: 1 - x^2 - y^2 is never -0, so this is `max(0, z2).sqrt()`, NaN included.
    let zero = ux.splat(0.0);
    (x, y, R::select(z2.gt(zero), z2, zero).sqrt())
}

/// Pdf of [`sample_cosine_hemisphere`]: `cos_theta / pi`, 0 below the horizon.
#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    cos_theta.max(0.0) * FRAC_1_PI
}

/// Uniform direction on the `z >= 0` hemisphere.
#[inline]
pub fn sample_uniform_hemisphere(u: Vec2) -> Vec3A {
    let z = u.x;
    spherical_direction(safe_sqrt(1.0 - z * z), z, TAU * u.y)
}

/// Pdf of [`sample_uniform_hemisphere`] on its support: `1 / (2 pi)`.
#[inline]
pub fn uniform_hemisphere_pdf() -> f32 {
    0.5 * FRAC_1_PI
}

/// Uniform direction on the unit sphere.
#[inline]
pub fn sample_uniform_sphere(u: Vec2) -> Vec3A {
    let z = 1.0 - 2.0 * u.x;
    spherical_direction(safe_sqrt(1.0 - z * z), z, TAU * u.y)
}

/// Pdf of [`sample_uniform_sphere`]: `1 / (4 pi)`.
#[inline]
pub fn uniform_sphere_pdf() -> f32 {
    0.25 * FRAC_1_PI
}

/// Uniform direction in the cone around `+z` of half-angle `acos(cos_theta_max)`.
/// `cos_theta_max = 1` degenerates to `+z`.
#[inline]
pub fn sample_uniform_cone(u: Vec2, cos_theta_max: f32) -> Vec3A {
    let cos_theta_max = cos_theta_max.clamp(-1.0, 1.0);
    let cos_theta = (1.0 - u.x) + u.x * cos_theta_max;
    spherical_direction(safe_sqrt(1.0 - cos_theta * cos_theta), cos_theta, TAU * u.y)
}

/// Pdf of [`sample_uniform_cone`] inside the cone: `1 / (2 pi (1 - cos_theta_max))`; infinite (a
/// delta direction, as for a point light) when `cos_theta_max >= 1`, never NaN.
#[inline]
pub fn uniform_cone_pdf(cos_theta_max: f32) -> f32 {
    let one_minus = 1.0 - cos_theta_max.clamp(-1.0, 1.0);
    if one_minus > 0.0 { 1.0 / (TAU * one_minus) } else { f32::INFINITY }
}

/// Uniform point on a triangle by area: barycentrics `(b0, b1, b2)` (pbrt-v4's
/// `SampleUniformTriangle`, Heitz's low-distortion warp that keeps stratification). Pdf
/// `1 / area`, or 2 in the `(b1, b2)` plane.
#[inline]
pub fn sample_uniform_triangle(u: Vec2) -> [f32; 3] {
    uniform_triangle([u.x, u.y])
}

/// [`sample_uniform_triangle`] written once over [`Real`] (the light samples in lanes take
/// theirs 8 at a time): both halves of the warp computed, the one where `u.x < u.y` kept.
#[inline(always)]
pub fn uniform_triangle<R: Real>(u: [R; 2]) -> [R; 3] {
    let half = u[0].splat(2.0);
    let below = u[0].lt(u[1]);
    let (b0_below, b1_above) = (u[0] / half, u[1] / half);
    let b0 = R::select(below, b0_below, u[0] - b1_above);
    let b1 = R::select(below, u[1] - b0_below, b1_above);
    [b0, b1, (u[0].splat(1.0) - b0 - b1).max(u[0].splat(0.0))]
}

/// Solid angle of the spherical triangle of unit vectors `a`, `b`, `c` (Van Oosterom and
/// Strackee's formula, accurate for small triangles).
#[inline]
pub fn spherical_triangle_area(a: Vec3A, b: Vec3A, c: Vec3A) -> f32 {
    spherical::area(a.to_array(), b.to_array(), c.to_array())
}

/// Solid angle subtended by the triangle `v` seen from `p` (0 if `p` is a vertex). Light
/// sampling code compares it with [`MIN_SPHERICAL_SAMPLE_AREA`] and
/// [`MAX_SPHERICAL_SAMPLE_AREA`] to know which strategy [`sample_spherical_triangle`] used.
#[inline]
pub fn triangle_solid_angle(v: [Vec3A; 3], p: Vec3A) -> f32 {
    SphericalTriangle::new(v, p).map_or(0.0, |s| s.area())
}

/// The triangle `v` projected onto the unit sphere around `p`: its vertices' directions and its
/// area (the solid angle), made once for both the choice of strategy and the sample (one
/// sample of [`spherical`]'s, which also samples 8 in lanes).
#[derive(Clone, Copy, Debug)]
pub struct SphericalTriangle(spherical::Projection<f32>);

impl SphericalTriangle {
    /// `None` where `p` is a vertex.
    #[inline]
    pub fn new(v: [Vec3A; 3], p: Vec3A) -> Option<Self> {
        let s = spherical::project(v.map(|v| v.to_array()), p.to_array());
        s.ok.then_some(Self(s))
    }

    /// The solid angle ([`triangle_solid_angle`]).
    #[inline]
    pub fn area(&self) -> f32 {
        self.0.area
    }

    /// [`sample_spherical_triangle`] of the triangle `v` seen from `p`, this its projection
    /// (whatever its area).
    #[inline]
    pub fn sample(&self, v: [Vec3A; 3], p: Vec3A, u: Vec2) -> Option<([f32; 3], f32)> {
        let s = spherical::sample(v.map(|v| v.to_array()), p.to_array(), &self.0, [u.x, u.y], true);
        s.ok.then_some((s.b, s.pdf))
    }
}

/// Samples a direction from `p` uniformly in the solid angle subtended by the triangle `v`
/// (Arvo 1995, as in pbrt-v4's `SampleSphericalTriangle`). Returns the barycentrics of the point
/// of the triangle in the sampled direction and the pdf `1 / solid angle` (per unit solid angle,
/// computed with [`triangle_solid_angle`] so that it matches a later pdf query bit for bit).
///
/// `None` when the triangle is degenerate as seen from `p` (`p` on its plane or at a vertex), or
/// its solid angle lies outside [`MIN_SPHERICAL_SAMPLE_AREA`, `MAX_SPHERICAL_SAMPLE_AREA`];
/// the caller then samples by area.
pub fn sample_spherical_triangle(v: [Vec3A; 3], p: Vec3A, u: Vec2) -> Option<([f32; 3], f32)> {
    let s = SphericalTriangle::new(v, p)?;
    if !(MIN_SPHERICAL_SAMPLE_AREA..=MAX_SPHERICAL_SAMPLE_AREA).contains(&s.area()) {
        return None;
    }
    s.sample(v, p, u)
}

/// Multiple importance sampling weight of strategy f by the power heuristic (beta = 2), with
/// `nf`, `ng` samples taken from strategies f and g. A delta strategy (infinite pdf) gets weight
/// 1; a zero or NaN pdf gets 0. Never NaN.
#[inline]
pub fn power_heuristic(nf: f32, f_pdf: f32, ng: f32, g_pdf: f32) -> f32 {
    let (f, g) = (nf * f_pdf, ng * g_pdf);
    if f.is_infinite() {
        return 1.0;
    }
    if !(f > 0.0) {
        return 0.0;
    }
    // The ratio form neither overflows nor underflows where f^2 and g^2 would.
    let r = if g > 0.0 { g / f } else { 0.0 };
    1.0 / (1.0 + r * r)
}

/// Multiple importance sampling weight of strategy f by the balance heuristic; the same edge
/// cases as [`power_heuristic`].
#[inline]
pub fn balance_heuristic(nf: f32, f_pdf: f32, ng: f32, g_pdf: f32) -> f32 {
    let (f, g) = (nf * f_pdf, ng * g_pdf);
    if f.is_infinite() {
        return 1.0;
    }
    if !(f > 0.0) {
        return 0.0;
    }
    let r = if g > 0.0 { g / f } else { 0.0 };
    1.0 / (1.0 + r)
}

/// A discrete distribution proportional to weights (pbrt's `PiecewiseConstant1D` used for
/// light selection by power). Negative, NaN and infinite weights count as 0; if no weight is
/// positive the distribution is uniform.
///
/// Only the cdf is stored, and `pmf(i)` is the cdf step, so the pmf reported is the probability
/// that [`Distribution1D::sample`] really has (up to the 2^-24 resolution of `u`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Distribution1D {
    /// `cdf[0] = 0`, `cdf[n] = 1`, non-decreasing.
    cdf: Vec<f32>,
}

/// The most entries [`Distribution1D::sample`] counts rather than searches.
const SMALL_DISTRIBUTION: usize = 16;

impl Distribution1D {
    pub fn new(weights: &[f32]) -> Self {
        let n = weights.len();
        if n == 0 {
            return Self { cdf: Vec::new() };
        }
        let clean = |w: f32| if w.is_finite() && w > 0.0 { f64::from(w) } else { 0.0 };
        // Sum in f64 so long lists of small weights keep their share.
        let total: f64 = weights.iter().map(|&w| clean(w)).sum();
        let mut cdf = Vec::with_capacity(n + 1);
        cdf.push(0.0);
        if total > 0.0 {
            let mut acc = 0.0f64;
            for &w in weights {
                acc += clean(w);
                cdf.push((acc / total) as f32);
            }
        } else {
            cdf.extend((1..=n).map(|i| (i as f64 / n as f64) as f32));
        }
        // Trailing zero weights already sit at 1; make the last entry exactly 1 regardless.
        cdf[n] = 1.0;
        Self { cdf }
    }

    /// Number of entries.
    #[inline]
    pub fn len(&self) -> usize {
        self.cdf.len().saturating_sub(1)
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Probability of choosing entry `i` (0 outside the range).
    #[inline]
    pub fn pmf(&self, i: usize) -> f32 {
        if i < self.len() { self.cdf[i + 1] - self.cdf[i] } else { 0.0 }
    }

    /// Chooses an entry with `u` in [0, 1): returns (index, pmf, `u` remapped to [0, 1) within the
    /// entry, reusable as a fresh uniform number). Never returns an entry of pmf 0. An empty
    /// distribution returns `(0, 0.0, u)`.
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32, f32) {
        let n = self.len();
        if n == 0 {
            return (0, 0.0, u);
        }
        let u = if u >= 0.0 { u.min(ONE_MINUS_EPSILON) } else { 0.0 };
        // The last i with cdf[i] <= u; as cdf[n] = 1 > u, cdf[i + 1] > u, so pmf(i) > 0. A few
        // entries are counted (the same i, the cdf being non-decreasing): independent compares,
        // not a binary search's chain of dependent loads.
        let i = if n <= SMALL_DISTRIBUTION {
            self.cdf.get(1..n).map_or(0, |inner| inner.iter().filter(|&&c| c <= u).count())
        } else {
            self.cdf.partition_point(|&c| c <= u) - 1
        }
        .min(n - 1);
        let (lo, hi) = (self.cdf[i], self.cdf[i + 1]);
        let pmf = hi - lo;
        let remapped = if pmf > 0.0 { ((u - lo) / pmf).clamp(0.0, ONE_MINUS_EPSILON) } else { 0.0 };
        (i, pmf, remapped)
    }
}

/// A piecewise-constant density over `[0, 1]^2` on an `nu x nv` grid of non-negative weights
/// (pbrt's `PiecewiseConstant2D`): a marginal distribution over rows and one conditional
/// distribution per row. Samples are continuous inside the chosen cell, so the density is
/// constant over each cell and [`Distribution2D::pdf`] is exactly the density of
/// [`Distribution2D::sample`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Distribution2D {
    nu: usize,
    nv: usize,
    conditional: Vec<Distribution1D>,
    marginal: Distribution1D,
}

impl Distribution2D {
    /// `weights` row-major (`nv` rows of `nu`); `None` if the sizes disagree or are zero.
    pub fn new(weights: &[f32], nu: usize, nv: usize) -> Option<Self> {
        if nu == 0 || nv == 0 || weights.len() != nu.checked_mul(nv)? {
            return None;
        }
        let clean = |w: f32| if w.is_finite() && w > 0.0 { f64::from(w) } else { 0.0 };
        let conditional: Vec<Distribution1D> = weights.chunks_exact(nu).map(Distribution1D::new).collect();
        let row_sums: Vec<f32> =
            weights.chunks_exact(nu).map(|row| row.iter().map(|&w| clean(w)).sum::<f64>() as f32).collect();
        Some(Self { nu, nv, conditional, marginal: Distribution1D::new(&row_sums) })
    }

    /// A point in `[0, 1)^2` and its density, from `u` in `[0, 1)^2`.
    #[inline]
    pub fn sample(&self, u: Vec2) -> Option<(Vec2, f32)> {
        let (iv, pmf_v, rv) = self.marginal.sample(u.y);
        let row = self.conditional.get(iv)?;
        let (iu, pmf_u, ru) = row.sample(u.x);
        let pdf = pmf_v * pmf_u * (self.nu * self.nv) as f32;
        let p = Vec2::new((iu as f32 + ru) / self.nu as f32, (iv as f32 + rv) / self.nv as f32);
        (pdf > 0.0).then_some((p.min(Vec2::splat(ONE_MINUS_EPSILON)), pdf))
    }

    /// Density at `p` in `[0, 1]^2` (the edge 1 belongs to the last cell).
    #[inline]
    pub fn pdf(&self, p: Vec2) -> f32 {
        let iu = ((p.x.max(0.0) * self.nu as f32) as usize).min(self.nu.saturating_sub(1));
        let iv = ((p.y.max(0.0) * self.nv as f32) as usize).min(self.nv.saturating_sub(1));
        let pmf_u = self.conditional.get(iv).map_or(0.0, |row| row.pmf(iu));
        self.marginal.pmf(iv) * pmf_u * (self.nu * self.nv) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::chi2::{
        Chi2Options, TestRng, integrate_2d, pearson, sphere_integral, test_rect, test_sphere, to_spherical,
    };
    use glam::DVec3;
    use std::f32::consts::FRAC_PI_2;

    /// Number of chi-square tests in this module: each runs at the Sidak-corrected level
    /// 1 - (1 - 0.01)^(1 / CHI2_TESTS), so the whole suite has alpha = 0.01.
    const CHI2_TESTS: usize = 19;

    fn opts(seed: u64) -> Chi2Options {
        Chi2Options { samples: 1_000_000, res: (80, 160), alpha: 0.01, tests: CHI2_TESTS, seed }
    }

    fn pass(r: Result<f64, String>) {
        if let Err(e) = r {
            panic!("{e}");
        }
    }

    /// Integral over a rectangle split into `n x n` cells, so discontinuities are resolved.
    fn integrate_split(f: &dyn Fn(f64, f64) -> f64, (x0, x1): (f64, f64), (y0, y1): (f64, f64), n: usize) -> f64 {
        let mut sum = 0.0;
        for i in 0..n {
            for j in 0..n {
                let xr = (x0 + (x1 - x0) * i as f64 / n as f64, x0 + (x1 - x0) * (i + 1) as f64 / n as f64);
                let yr = (y0 + (y1 - y0) * j as f64 / n as f64, y0 + (y1 - y0) * (j + 1) as f64 / n as f64);
                sum += integrate_2d(f, xr, yr);
            }
        }
        sum
    }

    /// The `u` values at the edges of the domain, where warps tend to produce NaN.
    fn edge_us() -> Vec<Vec2> {
        let e = [0.0, 1e-7, 0.5, 1.0 - 1e-6, ONE_MINUS_EPSILON];
        e.iter().flat_map(|&x| e.iter().map(move |&y| Vec2::new(x, y))).collect()
    }

    fn disk_pdf(p: Vec2) -> f32 {
        if p.length_squared() <= 1.0 { FRAC_1_PI } else { 0.0 }
    }

    #[test]
    fn disk_warps_chi2() {
        let mut o = opts(11);
        o.res = (50, 50);
        let concentric = |u| Some(sample_uniform_disk_concentric(u));
        pass(test_rect("concentric disk", concentric, disk_pdf, (-1.0, 1.0), (-1.0, 1.0), &o));
        o.seed = 12;
        let polar = |u| Some(sample_uniform_disk_polar(u));
        pass(test_rect("polar disk", polar, disk_pdf, (-1.0, 1.0), (-1.0, 1.0), &o));
        let integral =
            integrate_split(&|x, y| f64::from(disk_pdf(Vec2::new(x as f32, y as f32))), (-1.0, 1.0), (-1.0, 1.0), 32);
        assert!((integral - 1.0).abs() < 2e-3, "disk pdf integrates to {integral}");
        for u in edge_us() {
            for p in [sample_uniform_disk_concentric(u), sample_uniform_disk_polar(u)] {
                assert!(p.is_finite() && p.length() <= 1.0 + 1e-6, "{u} -> {p}");
            }
        }
        assert_eq!(sample_uniform_disk_concentric(Vec2::splat(0.5)), Vec2::ZERO);
    }

    #[test]
    fn hemisphere_and_sphere_warps_chi2() {
        let cosine_pdf = |w: Vec3A| cosine_hemisphere_pdf(w.z);
        pass(test_sphere("cosine hemisphere", |u, _| Some(sample_cosine_hemisphere(u)), cosine_pdf, &opts(21)));
        let hemi_pdf = |w: Vec3A| if w.z >= 0.0 { uniform_hemisphere_pdf() } else { 0.0 };
        pass(test_sphere("uniform hemisphere", |u, _| Some(sample_uniform_hemisphere(u)), hemi_pdf, &opts(22)));
        let sphere_pdf = |_: Vec3A| uniform_sphere_pdf();
        pass(test_sphere("uniform sphere", |u, _| Some(sample_uniform_sphere(u)), sphere_pdf, &opts(23)));
        for (name, pdf) in
            [("cosine", &cosine_pdf as &dyn Fn(Vec3A) -> f32), ("hemisphere", &hemi_pdf), ("sphere", &sphere_pdf)]
        {
            // Simpson quadrature across the horizon's jump is good to about 1e-4.
            let integral = sphere_integral(pdf);
            assert!((integral - 1.0).abs() < 5e-4, "{name} pdf integrates to {integral}");
        }
        for u in edge_us() {
            for (w, lower) in [
                (sample_cosine_hemisphere(u), 0.0),
                (sample_uniform_hemisphere(u), 0.0),
                (sample_uniform_sphere(u), -1.0),
            ] {
                assert!(w.is_finite() && (w.length() - 1.0).abs() < 1e-5 && w.z >= lower, "{u} -> {w}");
            }
        }
        assert_eq!(cosine_hemisphere_pdf(-0.5), 0.0);
    }

    #[test]
    fn cone_warp_chi2() {
        for (k, cos_max) in [-0.3f32, 0.95].into_iter().enumerate() {
            let pdf = move |w: Vec3A| if w.z >= cos_max { uniform_cone_pdf(cos_max) } else { 0.0 };
            let name = format!("cone cos_theta_max = {cos_max}");
            pass(test_sphere(&name, |u, _| Some(sample_uniform_cone(u, cos_max)), pdf, &opts(31 + k as u64)));
            let integral = sphere_integral(pdf);
            assert!((integral - 1.0).abs() < 2e-3, "{name}: pdf integrates to {integral}");
            for u in edge_us() {
                let w = sample_uniform_cone(u, cos_max);
                assert!(w.is_finite() && (w.length() - 1.0).abs() < 1e-5 && w.z >= cos_max - 1e-6, "{u} -> {w}");
            }
        }
        // Degenerate cones: a single direction with an infinite (delta) pdf, and the whole sphere.
        for u in edge_us() {
            assert_eq!(sample_uniform_cone(u, 1.0), Vec3A::Z);
            let w = sample_uniform_cone(u, -1.0);
            assert!(w.is_finite() && (w.length() - 1.0).abs() < 1e-5);
        }
        assert_eq!(uniform_cone_pdf(1.0), f32::INFINITY);
        assert_eq!(uniform_cone_pdf(1.5), f32::INFINITY);
        assert!((uniform_cone_pdf(-1.0) - uniform_sphere_pdf()).abs() < 1e-7);
    }

    #[test]
    fn uniform_triangle_chi2() {
        let mut o = opts(41);
        o.res = (64, 64);
        let pdf = |b: Vec2| if b.x + b.y <= 1.0 { 2.0 } else { 0.0 };
        let sample = |u| {
            let b = sample_uniform_triangle(u);
            Some(Vec2::new(b[1], b[2]))
        };
        pass(test_rect("uniform triangle (b1, b2)", sample, pdf, (0.0, 1.0), (0.0, 1.0), &o));
        let integral =
            integrate_split(&|x, y| f64::from(pdf(Vec2::new(x as f32, y as f32))), (0.0, 1.0), (0.0, 1.0), 32);
        assert!((integral - 1.0).abs() < 2e-3, "triangle pdf integrates to {integral}");
        for u in edge_us() {
            let b = sample_uniform_triangle(u);
            assert!(b.iter().all(|&x| (0.0..=1.0).contains(&x)), "{u} -> {b:?}");
            assert!((b[0] + b[1] + b[2] - 1.0).abs() < 1e-6, "{u} -> {b:?}");
        }
    }

    /// Where the ray (p, w) hits the triangle, if it does (Moller-Trumbore in f64).
    fn hits_triangle(v: [Vec3A; 3], p: Vec3A, w: Vec3A) -> bool {
        let f = |a: Vec3A| glam::DVec3::new(a.x.into(), a.y.into(), a.z.into());
        let (v0, v1, v2, p, w) = (f(v[0]), f(v[1]), f(v[2]), f(p), f(w));
        let (e1, e2) = (v1 - v0, v2 - v0);
        let s1 = w.cross(e2);
        let det = s1.dot(e1);
        if det == 0.0 {
            return false;
        }
        let s = p - v0;
        let b1 = s.dot(s1) / det;
        let q = s.cross(e1);
        let b2 = w.dot(q) / det;
        let t = e2.dot(q) / det;
        b1 >= 0.0 && b2 >= 0.0 && b1 + b2 <= 1.0 && t > 0.0
    }

    /// The test triangles, seen from `p`: (name, vertices, p).
    fn spherical_triangles() -> Vec<(&'static str, [Vec3A; 3], Vec3A)> {
        vec![
            (
                "moderate",
                [Vec3A::new(-0.5, -0.3, 1.0), Vec3A::new(0.6, -0.4, 1.2), Vec3A::new(0.1, 0.7, 0.9)],
                Vec3A::ZERO,
            ),
            (
                "large and close",
                [Vec3A::new(-1.0, -1.0, 0.0), Vec3A::new(1.5, -0.8, 0.0), Vec3A::new(0.0, 1.2, 0.0)],
                Vec3A::new(0.1, 0.05, 0.15),
            ),
            ("thin", [Vec3A::new(0.0, 0.0, 1.0), Vec3A::new(1.5, 0.2, 0.3), Vec3A::new(1.4, 0.28, 0.4)], Vec3A::ZERO),
            (
                "oblique, below the horizon",
                [Vec3A::new(2.0, 0.0, -0.5), Vec3A::new(2.0, 1.5, 0.5), Vec3A::new(2.5, -1.0, -1.3)],
                Vec3A::new(0.2, 0.1, 0.0),
            ),
        ]
    }

    fn dvec(a: Vec3A) -> DVec3 {
        DVec3::new(a.x.into(), a.y.into(), a.z.into())
    }

    /// The polar angles `(theta_lo, theta_hi)` of the directions from `p` in the meridian
    /// half-plane at azimuth `phi` that hit the triangle `v`, if any. A half-plane cuts a
    /// triangle not containing `p` in one segment, seen from `p` under one interval of theta.
    fn meridian_interval(v: [Vec3A; 3], p: Vec3A, phi: f64) -> Option<(f64, f64)> {
        let t = [dvec(v[0] - p), dvec(v[1] - p), dvec(v[2] - p)];
        let (n, m) = (DVec3::new(-phi.sin(), phi.cos(), 0.0), DVec3::new(phi.cos(), phi.sin(), 0.0));
        let s = t.map(|q| q.dot(n));
        let mut pts = Vec::new();
        for (i, j) in [(0, 1), (1, 2), (2, 0)] {
            if s[i] == 0.0 {
                pts.push(t[i]);
            } else if s[i] * s[j] < 0.0 {
                pts.push(t[i] + (t[j] - t[i]) * (s[i] / (s[i] - s[j])));
            }
        }
        let (mut a, mut b) = (*pts.first()?, *pts.last()?);
        // Clip the segment to the half-plane m . q >= 0; the cut lies on the z axis.
        let (ma, mb) = (a.dot(m), b.dot(m));
        if ma < 0.0 && mb < 0.0 {
            return None;
        }
        if ma < 0.0 || mb < 0.0 {
            let cut = a + (b - a) * (ma / (ma - mb));
            if ma < 0.0 { a = cut } else { b = cut }
        }
        let theta = |q: DVec3| q.dot(m).max(0.0).atan2(q.z);
        let (ta, tb) = (theta(a), theta(b));
        Some((ta.min(tb), ta.max(tb)))
    }

    /// Chi-square test of the directions to the sampled points against the uniform solid-angle
    /// pdf, on `test_sphere`'s (theta, phi) grid. The expected counts are exact in theta and
    /// integrated with a fine midpoint rule in phi, because adaptive Simpson on the indicator of
    /// a thin triangle can miss it entirely.
    fn spherical_triangle_directions_chi2(name: &str, v: [Vec3A; 3], p: Vec3A, o: &Chi2Options) -> Result<f64, String> {
        use std::f64::consts::PI as PI64;
        let (nt, np) = o.res;
        let solid_angle = f64::from(triangle_solid_angle(v, p));
        let mut rng = TestRng::new(o.seed);
        let mut observed = vec![0.0; nt * np];
        for _ in 0..o.samples {
            let u = rng.uniform_2d();
            let Some((b, _)) = sample_spherical_triangle(v, p, u) else { continue };
            let w = (b[0] * v[0] + b[1] * v[1] + b[2] * v[2] - p).normalize();
            let (theta, phi) = to_spherical(w);
            let it = ((theta / PI64 * nt as f64) as usize).min(nt - 1);
            let ip = ((phi / (2.0 * PI64) * np as f64) as usize).min(np - 1);
            observed[it * np + ip] += 1.0;
        }
        let mut expected = vec![0.0; nt * np];
        let steps = 256;
        let dphi = 2.0 * PI64 / (np * steps) as f64;
        for ip in 0..np {
            for k in 0..steps {
                let phi = (ip * steps + k) as f64 * dphi + 0.5 * dphi;
                let Some((lo, hi)) = meridian_interval(v, p, phi) else { continue };
                for it in 0..nt {
                    let (t0, t1) = (it as f64 * PI64 / nt as f64, (it + 1) as f64 * PI64 / nt as f64);
                    let (a, b) = (lo.max(t0), hi.min(t1));
                    if a < b {
                        expected[it * np + ip] += (a.cos() - b.cos()) * dphi / solid_angle * o.samples as f64;
                    }
                }
            }
        }
        let total: f64 = expected.iter().sum();
        if (total / o.samples as f64 - 1.0).abs() > 1e-3 {
            return Err(format!("{name}: expected counts sum to {total}: solid angle is off"));
        }
        pearson(name, &observed, &expected, o)
    }

    #[test]
    fn spherical_triangle_directions_chi2_test() {
        for (k, (name, v, p)) in spherical_triangles().into_iter().enumerate() {
            let solid_angle = triangle_solid_angle(v, p);
            assert!(
                (MIN_SPHERICAL_SAMPLE_AREA..=MAX_SPHERICAL_SAMPLE_AREA).contains(&solid_angle),
                "{name}: solid angle {solid_angle}"
            );
            for u in edge_us() {
                let (_, pdf) = sample_spherical_triangle(v, p, u).unwrap_or_else(|| panic!("{name} at {u}"));
                assert_eq!(pdf, 1.0 / solid_angle, "{name}: pdf {pdf}");
            }
            let name = format!("spherical triangle {name}, directions");
            pass(spherical_triangle_directions_chi2(&name, v, p, &opts(51 + k as u64)));
        }
    }

    /// The same samples, as barycentrics `(b1, b2)` against the pdf the uniform solid-angle
    /// density induces on them: `cos theta_l / r^2 * 2 area / solid angle`. This pdf is smooth,
    /// so small and grazing triangles get as many well-filled cells as large ones. (pbrt-v4's
    /// all-f32 arithmetic fails this test on the grazing triangle.)
    #[test]
    fn spherical_triangle_barycentrics_chi2() {
        for (k, (name, v, p)) in spherical_triangles().into_iter().enumerate() {
            let solid_angle = triangle_solid_angle(v, p);
            let n = (v[1] - v[0]).cross(v[2] - v[0]);
            let area2 = n.length();
            let pdf = |b: Vec2| {
                if b.x + b.y > 1.0 {
                    return 0.0;
                }
                let d = (1.0 - b.x - b.y) * v[0] + b.x * v[1] + b.y * v[2] - p;
                d.normalize().dot(n / area2).abs() / d.length_squared() * area2 / solid_angle
            };
            let sample = |u| sample_spherical_triangle(v, p, u).map(|(b, _)| Vec2::new(b[1], b[2]));
            let mut o = opts(55 + k as u64);
            o.res = (40, 40);
            pass(test_rect(
                &format!("spherical triangle {name}, barycentrics"),
                sample,
                pdf,
                (0.0, 1.0),
                (0.0, 1.0),
                &o,
            ));
            let integral =
                integrate_split(&|x, y| f64::from(pdf(Vec2::new(x as f32, y as f32))), (0.0, 1.0), (0.0, 1.0), 16);
            assert!((integral - 1.0).abs() < 2e-3, "{name}: barycentric pdf integrates to {integral}");
        }
    }

    #[test]
    fn spherical_triangle_area_matches_known_values_and_monte_carlo() {
        let octant = spherical_triangle_area(Vec3A::X, Vec3A::Y, Vec3A::Z);
        assert!((octant - FRAC_PI_2).abs() < 1e-6, "octant {octant}");
        assert!((spherical_triangle_area(Vec3A::X, Vec3A::Z, Vec3A::Y) - FRAC_PI_2).abs() < 1e-6);
        // Solid angle vs the fraction of uniform directions that hit the triangle (seed 61,
        // 10^6 directions: 5 standard deviations).
        let n = 1_000_000;
        for (name, v, p) in spherical_triangles() {
            let mut rng = TestRng::new(61);
            let hits = (0..n).filter(|_| hits_triangle(v, p, sample_uniform_sphere(rng.uniform_2d()))).count();
            let frac = hits as f64 / n as f64;
            let estimate = 4.0 * std::f64::consts::PI * frac;
            let sd = 4.0 * std::f64::consts::PI * (frac * (1.0 - frac) / n as f64).sqrt();
            let exact = f64::from(triangle_solid_angle(v, p));
            assert!((estimate - exact).abs() < 5.0 * sd + 1e-6, "{name}: {estimate} vs {exact}");
        }
    }

    #[test]
    fn spherical_triangle_degenerate_cases() {
        let v = [Vec3A::new(0.0, 0.0, 1.0), Vec3A::new(1.0, 0.0, 1.0), Vec3A::new(0.0, 1.0, 1.0)];
        let u = Vec2::new(0.3, 0.7);
        // p on the triangle's plane: inside, outside, on an edge.
        for p in [Vec3A::new(0.2, 0.2, 1.0), Vec3A::new(3.0, 3.0, 1.0), Vec3A::new(0.5, 0.0, 1.0)] {
            assert!(sample_spherical_triangle(v, p, u).is_none(), "p = {p}");
        }
        // p at a vertex; collinear vertices; a tiny, far triangle.
        assert!(sample_spherical_triangle(v, v[1], u).is_none());
        let line = [Vec3A::new(0.0, 0.0, 1.0), Vec3A::new(1.0, 0.0, 1.0), Vec3A::new(2.0, 0.0, 1.0)];
        assert!(sample_spherical_triangle(line, Vec3A::ZERO, u).is_none());
        let far = v.map(|x| x * 1e-3 + Vec3A::new(0.0, 0.0, 10.0));
        assert!(triangle_solid_angle(far, Vec3A::ZERO) < MIN_SPHERICAL_SAMPLE_AREA);
        assert!(sample_spherical_triangle(far, Vec3A::ZERO, u).is_none());
        assert_eq!(triangle_solid_angle(v, v[0]), 0.0);
        // Valid triangles: finite barycentrics at the edges of the u domain.
        for (name, v, p) in spherical_triangles() {
            for u in edge_us() {
                let (b, pdf) = sample_spherical_triangle(v, p, u).unwrap_or_else(|| panic!("{name} at {u}"));
                assert!(pdf.is_finite() && pdf > 0.0, "{name}: pdf {pdf}");
                assert!(b.iter().all(|&x| (0.0..=1.0).contains(&x)), "{name} at {u}: {b:?}");
                assert!((b.iter().sum::<f32>() - 1.0).abs() < 1e-5, "{name} at {u}: {b:?}");
            }
        }
    }

    #[test]
    fn mis_weights_sum_to_one() {
        let mut rng = TestRng::new(71);
        for _ in 0..10_000 {
            let (nf, ng) = (1.0 + (rng.uniform() * 4.0).floor(), 1.0 + (rng.uniform() * 4.0).floor());
            // Pdfs over many orders of magnitude, including values whose squares under- or overflow.
            let (fp, gp) = (10f32.powf(rng.uniform() * 60.0 - 30.0), 10f32.powf(rng.uniform() * 60.0 - 30.0));
            for h in [power_heuristic, balance_heuristic] {
                let (wf, wg) = (h(nf, fp, ng, gp), h(ng, gp, nf, fp));
                assert!((0.0..=1.0).contains(&wf) && (0.0..=1.0).contains(&wg));
                assert!((wf + wg - 1.0).abs() < 1e-5, "{nf} {fp} {ng} {gp}: {wf} + {wg}");
            }
        }
        for h in [power_heuristic, balance_heuristic] {
            // A delta strategy takes all the weight; a strategy that cannot sample takes none.
            assert_eq!(h(1.0, f32::INFINITY, 1.0, 3.0), 1.0);
            assert_eq!(h(1.0, 3.0, 1.0, f32::INFINITY), 0.0);
            assert_eq!(h(1.0, 0.0, 1.0, 3.0), 0.0);
            assert_eq!(h(1.0, 3.0, 1.0, 0.0), 1.0);
            assert_eq!(h(1.0, 0.0, 1.0, 0.0), 0.0);
            assert_eq!(h(1.0, f32::NAN, 1.0, 2.0), 0.0);
            assert_eq!(h(1.0, 2.0, 1.0, f32::NAN), 1.0);
        }
        assert!((power_heuristic(1.0, 1.0, 1.0, 2.0) - 0.2).abs() < 1e-7);
        assert!((balance_heuristic(1.0, 1.0, 1.0, 3.0) - 0.25).abs() < 1e-7);
    }

    const WEIGHTS: [f32; 12] = [0.0, 1.0, 2.0, f32::NAN, -3.0, 5.0, 0.5, 0.0, 10.0, 0.02, f32::INFINITY, 0.0];

    fn clean_weight(w: f32) -> f64 {
        if w.is_finite() && w > 0.0 { f64::from(w) } else { 0.0 }
    }

    #[test]
    fn distribution_2d_matches_its_pdf() {
        // A 7 x 5 grid with a zero cell, a zero row and a hot cell: chi-square of the samples
        // against pdf on a 70 x 50 grid of the unit square (so every cell is split), and the
        // density integrates to 1 over the square.
        let (nu, nv) = (7usize, 5usize);
        let w: Vec<f32> = (0..nu * nv)
            .map(|i| match (i % nu, i / nu) {
                (3, 1) => 0.0,
                (_, 2) => 0.0,
                (5, 4) => 30.0,
                (x, y) => 1.0 + x as f32 * 0.5 + y as f32,
            })
            .collect();
        let d = Distribution2D::new(&w, nu, nv).expect("sizes agree");
        assert!(Distribution2D::new(&w, nu, nv + 1).is_none());
        let o = Chi2Options { res: (70, 50), ..opts(83) };
        pass(test_rect(
            "distribution 2d",
            |u| {
                d.sample(u).map(|(p, pdf)| {
                    assert!((d.pdf(p) - pdf).abs() <= 1e-3 * pdf, "{} vs {pdf} at {p}", d.pdf(p));
                    p
                })
            },
            |p| d.pdf(p),
            (0.0, 1.0),
            (0.0, 1.0),
            &o,
        ));
        let total =
            integrate_split(&|x, y| f64::from(d.pdf(Vec2::new(x as f32, y as f32))), (0.0, 1.0), (0.0, 1.0), 70);
        assert!((total - 1.0).abs() < 1e-3, "integral {total}");
    }

    #[test]
    fn distribution_1d_pmf() {
        let d = Distribution1D::new(&WEIGHTS);
        assert_eq!(d.len(), WEIGHTS.len());
        let total: f64 = WEIGHTS.iter().map(|&w| clean_weight(w)).sum();
        let sum: f64 = (0..d.len()).map(|i| f64::from(d.pmf(i))).sum();
        assert!((sum - 1.0).abs() < 1e-6, "pmf sums to {sum}");
        for (i, &w) in WEIGHTS.iter().enumerate() {
            assert!((f64::from(d.pmf(i)) - clean_weight(w) / total).abs() < 1e-6, "pmf({i}) = {}", d.pmf(i));
        }
        assert_eq!(d.pmf(WEIGHTS.len()), 0.0);

        // No positive weight: uniform. No weight at all: empty.
        for weights in [&[0.0f32, 0.0, 0.0, 0.0][..], &[f32::NAN, -1.0, 0.0, f32::NEG_INFINITY][..]] {
            let u = Distribution1D::new(weights);
            assert!((0..4).all(|i| u.pmf(i) == 0.25), "{u:?}");
            assert_eq!(u.sample(0.6).0, 2);
        }
        let empty = Distribution1D::new(&[]);
        assert!(empty.is_empty());
        assert_eq!(empty.sample(0.5), (0, 0.0, 0.5));
        assert!(!d.is_empty());
    }

    #[test]
    fn distribution_1d_edges_never_pick_zero_weights() {
        let d = Distribution1D::new(&WEIGHTS);
        let mut us = vec![0.0, -0.0, 1e-30, ONE_MINUS_EPSILON, 1.0, f32::NAN, -1.0];
        // Exactly at the cdf steps, and one float either side.
        for i in 0..=d.len() {
            let c = d.cdf[i];
            us.extend([c, f32::from_bits(c.to_bits().saturating_sub(1)), f32::from_bits(c.to_bits() + 1)]);
        }
        for u in us {
            let (i, pmf, r) = d.sample(u);
            assert!(i < d.len() && pmf > 0.0 && pmf == d.pmf(i), "u = {u}: ({i}, {pmf})");
            assert!((0.0..1.0).contains(&r), "u = {u}: remapped {r}");
        }
        assert_eq!(d.sample(0.0).0, 1);
        assert_eq!(d.sample(ONE_MINUS_EPSILON).0, 9);
        assert_eq!(d.sample(d.cdf[5]), (5, d.pmf(5), 0.0));
    }

    /// The entry `sample` picks is the last `i` with `cdf[i] <= u` (found here by a plain scan):
    /// for small distributions, which count their cdf's entries at or below `u`
    /// (`SMALL_DISTRIBUTION`), and for larger ones, which search; at and beside every cdf step,
    /// with zero weights (repeated cdf entries) among the others.
    #[test]
    fn distribution_1d_picks_the_last_step_at_or_below_u() {
        let mut rng = TestRng::new(7);
        for n in 1..=2 * SMALL_DISTRIBUTION {
            let weights: Vec<f32> = (0..n).map(|i| if i % 3 == 1 { 0.0 } else { rng.uniform() + 0.01 }).collect();
            let d = Distribution1D::new(&weights);
            let mut us = vec![0.0, ONE_MINUS_EPSILON, 0.5];
            for &c in &d.cdf {
                us.extend([c, f32::from_bits(c.to_bits().saturating_sub(1)), f32::from_bits(c.to_bits() + 1)]);
            }
            for u in us {
                let clamped = if u >= 0.0 { u.min(ONE_MINUS_EPSILON) } else { 0.0 };
                let last = (0..n).rev().find(|&i| d.cdf[i] <= clamped).unwrap_or(0);
                assert_eq!(d.sample(u).0, last, "n = {n}, u = {u}");
            }
        }
    }

    #[test]
    fn distribution_1d_chi2() {
        let d = Distribution1D::new(&WEIGHTS);
        let (n, bins) = (1_000_000usize, 20usize);
        let o = Chi2Options { samples: n, res: (d.len(), bins), alpha: 0.01, tests: CHI2_TESTS, seed: 81 };
        let mut rng = TestRng::new(o.seed);
        let mut counts = vec![0.0; d.len()];
        let mut remap_counts = vec![0.0; d.len() * bins];
        for _ in 0..n {
            let (i, _, r) = d.sample(rng.uniform());
            counts[i] += 1.0;
            remap_counts[i * bins + ((r * bins as f32) as usize).min(bins - 1)] += 1.0;
        }
        let expected: Vec<f64> = (0..d.len()).map(|i| f64::from(d.pmf(i)) * n as f64).collect();
        pass(pearson("Distribution1D index", &counts, &expected, &o));
        // The remapped u is uniform within each entry, so it can be reused.
        let remap_expected: Vec<f64> = (0..d.len() * bins).map(|k| expected[k / bins] / bins as f64).collect();
        pass(pearson("Distribution1D remapped u", &remap_counts, &remap_expected, &o));
    }
}
