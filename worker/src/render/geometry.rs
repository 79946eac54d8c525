//! Geometry helpers: rays, shading frames, and self-intersection-free ray origins.

use glam::Vec3A;

/// A ray `o + t d`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub o: Vec3A,
    pub d: Vec3A,
}

impl Ray {
    pub fn new(o: Vec3A, d: Vec3A) -> Self {
        Self { o, d }
    }
    pub fn at(&self, t: f32) -> Vec3A {
        self.o + t * self.d
    }
}

/// An orthonormal frame; local `z` is the shading normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub x: Vec3A,
    pub y: Vec3A,
    pub z: Vec3A,
}

impl Frame {
    /// A frame around unit vector `n` (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    pub fn from_z(n: Vec3A) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let x = Vec3A::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let y = Vec3A::new(b, sign + n.y * n.y * a, -n.y);
        Self { x, y, z: n }
    }

    /// A frame with normal `n` and first axis as close as possible to tangent `t`
    /// (Gram-Schmidt); falls back to [`Frame::from_z`] for a degenerate tangent.
    pub fn from_xz(t: Vec3A, n: Vec3A) -> Self {
        let x = t - n * n.dot(t);
        let len = x.length();
        if !(len > 1e-6) {
            return Self::from_z(n);
        }
        let x = x / len;
        Self { x, y: n.cross(x), z: n }
    }

    #[inline]
    pub fn to_local(&self, v: Vec3A) -> Vec3A {
        Vec3A::new(v.dot(self.x), v.dot(self.y), v.dot(self.z))
    }

    #[inline]
    pub fn from_local(&self, v: Vec3A) -> Vec3A {
        self.x * v.x + self.y * v.y + self.z * v.z
    }
}

/// Moves a hit point off its surface along the geometric normal `ng`, to the side of `w`, so that
/// a ray leaving in direction `w` does not hit the surface it starts on. Integer-ULP offsets for
/// points far from the origin, a fixed epsilon near it (Wächter and Binder, "A Fast and Robust
/// Method for Avoiding Self-Intersection", Ray Tracing Gems, 2019).
#[inline]
pub fn offset_ray_origin(p: Vec3A, ng: Vec3A, w: Vec3A) -> Vec3A {
    let n = if ng.dot(w) < 0.0 { -ng } else { ng };
    // The same operations on the three components at once (SSE2: every x86-64 CPU has it).
    #[cfg(target_arch = "x86_64")]
    {
        super::wide::offset_along(p, n)
    }
    #[cfg(not(target_arch = "x86_64"))]
    offset_along(p, n)
}

/// [`offset_ray_origin`]: components of `p` below this in magnitude move by a fixed step...
pub(super) const OFFSET_ORIGIN: f32 = 1.0 / 32.0;
/// ... of this times the normal's component;
pub(super) const OFFSET_FLOAT_SCALE: f32 = 1.0 / 65536.0;
/// the others by this times the normal's component, in ULPs (truncated to an integer).
pub(super) const OFFSET_INT_SCALE: f32 = 256.0;

/// [`offset_ray_origin`]'s move of `p` along `n` (already turned toward the ray), one component
/// at a time: the reference of the lane-wise form (`wide::offset_along`) and the form where
/// there are no lanes.
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
pub(super) fn offset_along(p: Vec3A, n: Vec3A) -> Vec3A {
    Vec3A::new(offset_component(p.x, n.x), offset_component(p.y, n.y), offset_component(p.z, n.z))
}

/// One component of [`offset_along`]: `p` moved by `(OFFSET_INT_SCALE n) as i32` ULPs away
/// from zero's side of `n`, or by `OFFSET_FLOAT_SCALE n` where `|p| < OFFSET_ORIGIN`.
#[inline]
pub(super) fn offset_component(p: f32, n: f32) -> f32 {
    let of_i = (OFFSET_INT_SCALE * n) as i32;
    let bits = p.to_bits() as i32;
    let moved = f32::from_bits(bits.wrapping_add(if p < 0.0 { of_i.wrapping_neg() } else { of_i }) as u32);
    if p.abs() < OFFSET_ORIGIN { p + OFFSET_FLOAT_SCALE * n } else { moved }
}

/// Offsets both ends of a segment and returns (origin, direction, max t) for a shadow ray
/// from `p0` (normal `n0`) to `p1` (normal `n1`, or `None` for a point light).
// Inline: every shadow ray makes one (out of line, behind a call, when the release build's
// codegen units split it from its callers: 0.5% more of bdpt's instructions).
#[inline]
pub fn shadow_segment(p0: Vec3A, n0: Vec3A, p1: Vec3A, n1: Option<Vec3A>) -> (Vec3A, Vec3A, f32) {
    let d = p1 - p0;
    let o = offset_ray_origin(p0, n0, d);
    let target = match n1 {
        Some(n1) => offset_ray_origin(p1, n1, -d),
        None => p1,
    };
    let dir = target - o;
    let len = dir.length();
    // Stop just short of the target; the target end is already offset off its surface.
    (o, dir / len, len * (1.0 - 1e-4))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_is_orthonormal() {
        for n in [Vec3A::Z, -Vec3A::Z, Vec3A::new(0.3, -0.5, 0.8).normalize(), Vec3A::new(0.0, 0.0, -1.0)] {
            let f = Frame::from_z(n);
            assert!((f.x.length() - 1.0).abs() < 1e-5);
            assert!((f.y.length() - 1.0).abs() < 1e-5);
            assert!(f.x.dot(f.y).abs() < 1e-5 && f.x.dot(f.z).abs() < 1e-5 && f.y.dot(f.z).abs() < 1e-5);
            // Right-handed: x cross y = z.
            assert!((f.x.cross(f.y) - f.z).length() < 1e-5);
            let v = Vec3A::new(0.1, 0.7, -0.2);
            assert!((f.from_local(f.to_local(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn offset_moves_to_the_right_side() {
        for p in [Vec3A::new(100.0, -3.0, 0.01), Vec3A::new(1e-3, 5e4, -7.0)] {
            let n = Vec3A::new(0.0, 1.0, 0.0);
            assert!(offset_ray_origin(p, n, n).y > p.y);
            assert!(offset_ray_origin(p, n, -n).y < p.y);
        }
    }
}
