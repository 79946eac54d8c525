//! Uniform sampling of a spherical triangle: a triangle light as seen from a point, sampled by
//! solid angle (Arvo 1995, as pbrt-v4's `SampleSphericalTriangle`), written once over
//! [`Real`]: one sample as `f32` (`sampling::sample_spherical_triangle`, `Light::sample_li`)
//! and 8 as AVX2 lanes (`RenderScene::sample_light_at_many`). Both do the same f32 operations
//! in glam's order (`(x x' + y y') + z z'` dot products, `1 / sqrt` normalization), so a lane's
//! sample is the scalar sample, bit for bit. The step that needs double precision (the arc to
//! the sub-triangle's third vertex, `arc`) is written once over `math::Real64`: `f64`, or 4
//! lanes of it (the 8 lanes in two halves).

use super::math::{self, Real, Real64};
use super::vec3::{add, cross, dot, finite, is_zero, length, neg, normalize_or_zero, scale, select3, sub};

/// A triangle's vertices projected onto the unit sphere around a point, and the spherical
/// triangle's area (the triangle's solid angle).
#[derive(Clone, Copy, Debug)]
pub struct Projection<R: Real> {
    pub a: [R; 3],
    pub b: [R; 3],
    pub c: [R; 3],
    pub area: R,
    /// The point is not a vertex (no direction is zero). Elsewhere the other values are
    /// meaningless.
    pub ok: R::Mask,
}

/// The solid-angle sample of [`sample`].
pub struct SphericalSample<R: Real> {
    /// The sample exists (the lane was asked for one and nothing degenerate was met).
    pub ok: R::Mask,
    /// Barycentrics of the triangle's point in the sampled direction.
    pub b: [R; 3],
    /// `1 / area`.
    pub pdf: R,
}

/// `f32::clamp`: `lo` below it, `hi` above it, NaN stays NaN.
#[inline(always)]
fn clamp<R: Real>(x: R, lo: f32, hi: f32) -> R {
    R::select(x.lt(x.splat(lo)), x.splat(lo), R::select(x.gt(x.splat(hi)), x.splat(hi), x))
}

/// `x` where it is above zero, else zero (NaN included).
#[inline(always)]
fn positive_part<R: Real>(x: R) -> R {
    R::select(x.gt(x.splat(0.0)), x, x.splat(0.0))
}

/// `v` minus its component along the unit vector `w`.
#[inline(always)]
fn gram_schmidt<R: Real>(v: [R; 3], w: [R; 3]) -> [R; 3] {
    sub(v, scale(dot(v, w), w))
}

/// The angle between two unit vectors, accurate for nearly parallel and nearly opposite ones
/// (from the half chord: `2 asin(|v2 - v1| / 2)`, or `pi - 2 asin(|v1 + v2| / 2)`).
#[inline(always)]
fn angle_between<R: Real>(v1: [R; 3], v2: [R; 3]) -> R {
    let x = v1[0];
    let two = x.splat(2.0);
    // One chord per lane (one square root and one arcsine), the one its case needs.
    let opposite = dot(v1, v2).lt(x.splat(0.0));
    let chord = select3(opposite, add(v1, v2), sub(v2, v1));
    let angle = two * math::asin(clamp(length(chord) / two, -1.0, 1.0));
    R::select(opposite, x.splat(std::f32::consts::PI) - angle, angle)
}

/// The area of the spherical triangle of unit vectors `a`, `b`, `c` (Van Oosterom and
/// Strackee: `2 atan2(a . (b x c), 1 + a.b + a.c + b.c)`).
#[inline(always)]
pub fn area<R: Real>(a: [R; 3], b: [R; 3], c: [R; 3]) -> R {
    let x = a[0];
    (x.splat(2.0) * math::atan2(dot(a, cross(b, c)), x.splat(1.0) + dot(a, b) + dot(a, c) + dot(b, c))).abs()
}

/// The triangle `v` projected onto the unit sphere around `p`.
#[inline(always)]
pub fn project<R: Real>(v: [[R; 3]; 3], p: [R; 3]) -> Projection<R> {
    let a = normalize_or_zero(sub(v[0], p));
    let b = normalize_or_zero(sub(v[1], p));
    let c = normalize_or_zero(sub(v[2], p));
    Projection { a, b, c, area: area(a, b, c), ok: !(is_zero(a) | is_zero(b) | is_zero(c)) }
}

/// A direction from `p` uniform in the solid angle of the triangle `v` (`s` its projection),
/// from the numbers `u`, in the lanes of `wanted`: the barycentrics of the triangle's point in
/// that direction, and the density `1 / area`. Fails (`ok` false) where the spherical
/// triangle is degenerate (a zero great-circle normal, a non-finite arc) or the direction
/// meets the triangle's plane edge on.
#[inline(always)]
pub fn sample<R: Real>(v: [[R; 3]; 3], p: [R; 3], s: &Projection<R>, u: [R; 2], wanted: R::Mask) -> SphericalSample<R> {
    let (a, b, c) = (s.a, s.b, s.c);
    let x = a[0];
    let (zero, one, two) = (x.splat(0.0), x.splat(1.0), x.splat(2.0));
    // Normals of the great circles through each pair of vertices.
    let (n_ab, n_bc, n_ca) =
        (normalize_or_zero(cross(a, b)), normalize_or_zero(cross(b, c)), normalize_or_zero(cross(c, a)));
    let mut ok = wanted & !(is_zero(n_ab) | is_zero(n_bc) | is_zero(n_ca));
    // Interior angles at the vertices.
    let alpha = angle_between(n_ab, neg(n_ca));
    let beta = angle_between(n_bc, neg(n_ab));
    let gamma = angle_between(n_ca, neg(n_bc));
    // The arc from a to c' (the sub-triangle's third vertex), in f64 (4 lanes at a time).
    let (alpha, beta, gamma, ab, u0) = (alpha.widen(), beta.widen(), gamma.widen(), dot(a, b).widen(), u[0].widen());
    let (mut cos_bp, mut sin_bp) = (alpha, alpha);
    let mut arcs = 0u32;
    for h in 0..R::HALVES.min(2) {
        let (cos, sin, finite) = arc(alpha[h], beta[h], gamma[h], ab[h], u0[h]);
        (cos_bp[h], sin_bp[h]) = (cos, sin);
        arcs |= R::F64::mask_bits(finite) << (4 * h);
    }
    ok = ok & x.mask_of_bits(arcs);
    let cp = add(scale(x.narrow(cos_bp), a), scale(x.narrow(sin_bp), normalize_or_zero(gram_schmidt(c, a))));

    // The arc from b towards c', uniform in cos theta. 1 - cos theta is computed from the
    // half-angle, 2 sin^2(theta / 2), which keeps its precision for short arcs.
    let half = x.splat(0.5) * angle_between(b, normalize_or_zero(cp));
    let sin_half = math::sin_cos(half).0;
    let one_minus_cos = u[1] * two * sin_half * sin_half;
    let cos_theta = one - one_minus_cos;
    let sin_theta = positive_part(one_minus_cos * (two - one_minus_cos)).sqrt();
    let w = add(scale(cos_theta, b), scale(sin_theta, normalize_or_zero(gram_schmidt(cp, b))));

    // Barycentrics of the ray (p, w) with the triangle (Moller-Trumbore).
    let (e1, e2) = (sub(v[1], v[0]), sub(v[2], v[0]));
    let s1 = cross(w, e2);
    let divisor = dot(s1, e1);
    ok = ok & !divisor.eq(zero) & finite(divisor);
    let inv_divisor = one / divisor;
    let sp = sub(p, v[0]);
    let b1 = clamp(dot(sp, s1) * inv_divisor, 0.0, 1.0);
    let b2 = clamp(dot(w, cross(sp, e1)) * inv_divisor, 0.0, 1.0);
    ok = ok & finite(b1) & finite(b2);
    let sum = b1 + b2;
    let over = sum.gt(one);
    let (b1, b2) = (R::select(over, b1 / sum, b1), R::select(over, b2 / sum, b2));
    SphericalSample { ok, b: [positive_part(one - b1 - b2), b1, b2], pdf: one / s.area }
}

/// The cosine and sine of the arc b' from `a` to the third vertex c' of the sub-triangle (a, b,
/// c') whose area is the fraction `u0` of the whole (interior angles `alpha`, `beta`, `gamma`;
/// `ab` the cosine of the side from a to b), and where they are good (the closed form is
/// finite). In f64: for thin or grazing triangles (an interior angle near 0 or pi) the closed
/// form for cos b' cancels catastrophically in f32, and the sampled density visibly departs
/// from uniform (see the barycentric chi-square tests).
#[inline(always)]
fn arc<W: Real64>(alpha: W, beta: W, gamma: W, ab: W, u0: W) -> (W, W, W::Mask) {
    let c = |v: f64| alpha.splat(v);
    let pi = c(std::f64::consts::PI);
    // The sub-triangle's area A' sampled uniformly, as the angle sum A' + pi.
    let ap_pi = pi + u0 * (alpha + beta + gamma - pi);
    let (sin_alpha, cos_alpha) = math::sin_cos_f64_lanes(alpha);
    let (sin_ap, cos_ap) = math::sin_cos_f64_lanes(ap_pi);
    let sin_phi = sin_ap * cos_alpha - cos_ap * sin_alpha;
    let cos_phi = cos_ap * cos_alpha + sin_ap * sin_alpha;
    let k1 = cos_phi + cos_alpha;
    let k2 = sin_phi - sin_alpha * ab;
    let cos_bp = (k2 + (k2 * cos_phi - k1 * sin_phi) * cos_alpha) / ((k2 * sin_phi + k1 * cos_phi) * sin_alpha);
    let finite = cos_bp.abs().lt(c(f64::INFINITY));
    let (lo, hi) = (c(-1.0), c(1.0));
    let cos_bp = W::select(cos_bp.lt(lo), lo, W::select(cos_bp.gt(hi), hi, cos_bp));
    // 1 - cos^2 is never -0 (x - x rounds to +0), and not NaN where the arc is finite.
    let one_minus = c(1.0) - cos_bp * cos_bp;
    let sin_bp = W::select(one_minus.gt(c(0.0)), one_minus, c(0.0)).sqrt();
    (cos_bp, sin_bp, finite)
}
