//! glam's `Vec3A` operations on `[R; 3]` over [`Real`]: one `f32` vector, or 8 in AVX2 lanes.
//! Each is the f32 operations of glam's SSE2 form in its order (`(x x' + y y') + z z'` dot
//! products, `1 / sqrt` normalization, its cross product's operand order), so a lane gives
//! glam's bits; the lane-wise code of the renderer (`lambert`, `spherical`, `igi`, the hit
//! geometry of `scene`) is written with them.

use super::math::Real;

#[inline(always)]
pub(super) fn sub<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline(always)]
pub(super) fn add<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `s * v` (glam's `f32 * Vec3A`).
#[inline(always)]
pub(super) fn scale<R: Real>(s: R, v: [R; 3]) -> [R; 3] {
    [s * v[0], s * v[1], s * v[2]]
}

#[inline(always)]
pub(super) fn neg<R: Real>(a: [R; 3]) -> [R; 3] {
    [-a[0], -a[1], -a[2]]
}

/// glam's `Vec3A::dot`: `(x x' + y y') + z z'`.
#[inline(always)]
pub(super) fn dot<R: Real>(a: [R; 3], b: [R; 3]) -> R {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// glam's `Vec3A::cross` (its SSE2 form: `a.y b.z - b.y a.z`, ...).
#[inline(always)]
pub(super) fn cross<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [a[1] * b[2] - b[1] * a[2], a[2] * b[0] - b[2] * a[0], a[0] * b[1] - b[0] * a[1]]
}

#[inline(always)]
pub(super) fn length<R: Real>(v: [R; 3]) -> R {
    dot(v, v).sqrt()
}

/// Where `x` is neither infinite nor NaN.
#[inline(always)]
pub(super) fn finite<R: Real>(x: R) -> R::Mask {
    x.abs().lt(x.splat(f32::INFINITY))
}

/// glam's `Vec3A::normalize_or`: `v * (1 / |v|)` where that factor is finite and positive, else
/// `fallback`.
#[inline(always)]
pub(super) fn normalize_or<R: Real>(v: [R; 3], fallback: [R; 3]) -> [R; 3] {
    let zero = v[0].splat(0.0);
    let rcp = v[0].splat(1.0) / length(v);
    let ok = finite(rcp) & rcp.gt(zero);
    select3(ok, scale(rcp, v), fallback)
}

/// glam's `Vec3A::normalize_or_zero`.
#[inline(always)]
pub(super) fn normalize_or_zero<R: Real>(v: [R; 3]) -> [R; 3] {
    normalize_or(v, [v[0].splat(0.0); 3])
}

#[inline(always)]
pub(super) fn select3<R: Real>(m: R::Mask, a: [R; 3], b: [R; 3]) -> [R; 3] {
    [R::select(m, a[0], b[0]), R::select(m, a[1], b[1]), R::select(m, a[2], b[2])]
}

/// Where all three are zero (glam's `== Vec3A::ZERO`).
#[inline(always)]
pub(super) fn is_zero<R: Real>(a: [R; 3]) -> R::Mask {
    let zero = a[0].splat(0.0);
    a[0].eq(zero) & a[1].eq(zero) & a[2].eq(zero)
}
