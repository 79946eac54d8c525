//! Lights: point, spot and directional (KHR_lights_punctual, delta lights) and triangle area
//! lights (emissive triangles), sampled by area or by solid angle; light selection by power.

use super::geometry::Frame;
use super::sampling::{
    MAX_SPHERICAL_SAMPLE_AREA, MIN_SPHERICAL_SAMPLE_AREA, cosine_hemisphere_pdf, sample_cosine_hemisphere,
    sample_spherical_triangle, sample_uniform_cone, sample_uniform_disk_concentric, sample_uniform_sphere,
    sample_uniform_triangle, triangle_solid_angle, uniform_cone_pdf, uniform_sphere_pdf,
};
use glam::{Vec2, Vec3A};
use pathfarm_common::job::LightSampling;
use std::f32::consts::PI;

/// A light.
#[derive(Clone, Debug)]
pub enum Light {
    /// Radiant intensity `i` (W/sr-equivalent) in every direction.
    Point { p: Vec3A, i: Vec3A },
    /// glTF spot: intensity `i` along `axis`, smooth falloff between the cone angles.
    Spot { p: Vec3A, i: Vec3A, axis: Vec3A, cos_inner: f32, cos_outer: f32 },
    /// Irradiance `e` on surfaces facing `-w`; light travels along `w`. `radius` bounds the scene.
    Directional { w: Vec3A, e: Vec3A, radius: f32 },
    /// An emissive triangle with constant emitted radiance factor `le` (a texture, if any, is
    /// applied by the caller), one-sided (front = `n`) unless `two_sided`.
    Triangle { prim: u32, v: [Vec3A; 3], n: Vec3A, area: f32, le: Vec3A, two_sided: bool },
}

/// The point being lit.
#[derive(Clone, Copy, Debug)]
pub struct LightSampleContext {
    pub p: Vec3A,
    /// Geometric normal (for ray offsets); zero for points in media.
    pub n: Vec3A,
}

/// A light sample toward a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightLiSample {
    /// Radiance (area lights, before any emission texture) or, for delta lights, the incident
    /// radiance-equivalent (intensity / distance^2 or irradiance).
    pub l: Vec3A,
    /// Unit direction from the reference point toward the light.
    pub wi: Vec3A,
    /// Solid-angle pdf (1 for delta lights).
    pub pdf: f32,
    /// Point on the light (for the shadow ray), its normal (`None` for point-like lights).
    pub p_light: Vec3A,
    pub n_light: Option<Vec3A>,
    /// Barycentrics of the sampled point (area lights) for emission textures.
    pub b: [f32; 3],
    /// Whether the light is at infinity (shadow rays are unbounded).
    pub infinite: bool,
}

/// Whether a triangle of this solid angle is sampled by solid angle: Arvo's method loses
/// precision on tiny and on huge spherical triangles, which are sampled by area instead (pbrt-v4's
/// cut-offs). `sample_li` and `pdf_li` decide alike, so their densities always match.
fn use_solid_angle(mode: LightSampling, solid_angle: f32) -> bool {
    mode == LightSampling::SolidAngle
        && solid_angle.is_finite()
        && (MIN_SPHERICAL_SAMPLE_AREA..MAX_SPHERICAL_SAMPLE_AREA).contains(&solid_angle)
}

impl Light {
    pub fn is_delta(&self) -> bool {
        !matches!(self, Light::Triangle { .. })
    }

    /// Emitted power (luminance-free RGB), for light selection.
    pub fn power(&self) -> Vec3A {
        match *self {
            Light::Point { i, .. } => 4.0 * PI * i,
            Light::Spot { i, cos_inner, cos_outer, .. } => 2.0 * PI * i * (1.0 - 0.5 * (cos_inner + cos_outer)),
            Light::Directional { e, radius, .. } => PI * radius * radius * e,
            Light::Triangle { area, le, two_sided, .. } => PI * area * le * if two_sided { 2.0 } else { 1.0 },
        }
    }

    /// Radiance leaving an area light at a point with direction `w` (away from the light).
    pub fn l(&self, w: Vec3A) -> Vec3A {
        match *self {
            Light::Triangle { n, le, two_sided, .. } if two_sided || n.dot(w) > 0.0 => le,
            _ => Vec3A::ZERO,
        }
    }

    /// Samples incident illumination at `ctx` (pbrt's `SampleLi`).
    pub fn sample_li(&self, ctx: &LightSampleContext, u: Vec2, mode: LightSampling) -> Option<LightLiSample> {
        let delta = |p_light: Vec3A, l: Vec3A| {
            let d = p_light - ctx.p;
            let d2 = d.length_squared();
            (d2 > 0.0).then(|| LightLiSample {
                l: l / d2,
                wi: d / d2.sqrt(),
                pdf: 1.0,
                p_light,
                n_light: None,
                b: [0.0; 3],
                infinite: false,
            })
        };
        match *self {
            Light::Point { p, i } => delta(p, i),
            Light::Spot { p, i, axis, cos_inner, cos_outer } => {
                let s = delta(p, i)?;
                let att = spot_falloff(axis.dot(-s.wi), cos_inner, cos_outer);
                (att > 0.0).then_some(LightLiSample { l: s.l * att, ..s })
            }
            Light::Directional { w, e, radius } => Some(LightLiSample {
                l: e,
                wi: -w,
                pdf: 1.0,
                p_light: ctx.p - w * (2.0 * radius),
                n_light: None,
                b: [0.0; 3],
                infinite: true,
            }),
            Light::Triangle { v, n, area, le, two_sided, .. } => {
                let solid_angle = triangle_solid_angle(v, ctx.p);
                let (b, pdf_sa) = if use_solid_angle(mode, solid_angle) {
                    let (b, pdf) = sample_spherical_triangle(v, ctx.p, u)?;
                    (b, Some(pdf))
                } else {
                    (sample_uniform_triangle(u), None)
                };
                let p = v[0] * b[0] + v[1] * b[1] + v[2] * b[2];
                let d = p - ctx.p;
                let d2 = d.length_squared();
                if !(d2 > 0.0) {
                    return None;
                }
                let wi = d / d2.sqrt();
                let cos_l = n.dot(-wi);
                if !two_sided && cos_l <= 0.0 {
                    return None;
                }
                let pdf = match pdf_sa {
                    Some(pdf) => pdf,
                    None => {
                        if cos_l == 0.0 {
                            return None;
                        }
                        d2 / (cos_l.abs() * area)
                    }
                };
                if !(pdf > 0.0) || !pdf.is_finite() {
                    return None;
                }
                Some(LightLiSample { l: le, wi, pdf, p_light: p, n_light: Some(n), b, infinite: false })
            }
        }
    }

    /// Solid-angle density with which [`Light::sample_li`] picks the point `p_light` (normal
    /// `n_light`) of this area light from `ctx`. Zero for delta lights.
    pub fn pdf_li(&self, ctx: &LightSampleContext, p_light: Vec3A, mode: LightSampling) -> f32 {
        let Light::Triangle { v, n, area, two_sided, .. } = *self else { return 0.0 };
        let d = p_light - ctx.p;
        let d2 = d.length_squared();
        if !(d2 > 0.0) {
            return 0.0;
        }
        let wi = d / d2.sqrt();
        let cos_l = n.dot(-wi);
        if !two_sided && cos_l <= 0.0 {
            return 0.0;
        }
        let solid_angle = triangle_solid_angle(v, ctx.p);
        if use_solid_angle(mode, solid_angle) {
            1.0 / solid_angle
        } else if cos_l == 0.0 {
            0.0
        } else {
            d2 / (cos_l.abs() * area)
        }
    }
}

/// An emitted ray sampled from a light (pbrt's `SampleLe`), for light subpaths.
#[derive(Clone, Copy, Debug)]
pub struct LightLeSample {
    /// Emitted radiance (area lights, before any emission texture), intensity (point and spot)
    /// or irradiance (directional) carried by the ray.
    pub l: Vec3A,
    /// Ray origin and unit direction.
    pub o: Vec3A,
    pub d: Vec3A,
    /// Surface normal at the origin (area lights only).
    pub n: Option<Vec3A>,
    /// Density of the origin (per unit area; 1 for point-like lights; per unit disk area for
    /// directional lights) and of the direction (per solid angle; 1 for a delta direction).
    pub pdf_pos: f32,
    pub pdf_dir: f32,
    /// Barycentrics of the origin on an area light, for emission textures.
    pub b: [f32; 3],
}

impl Light {
    /// Whether the light sits at infinity (directional).
    pub fn is_infinite(&self) -> bool {
        matches!(self, Light::Directional { .. })
    }

    /// Samples an emitted ray: `u1` picks the position, `u2` the direction. `center` and the
    /// directional light's `radius` describe the disk that covers the scene.
    pub fn sample_le(&self, u1: Vec2, u2: Vec2, center: Vec3A) -> Option<LightLeSample> {
        match *self {
            Light::Point { p, i } => Some(LightLeSample {
                l: i,
                o: p,
                d: sample_uniform_sphere(u2),
                n: None,
                pdf_pos: 1.0,
                pdf_dir: uniform_sphere_pdf(),
                b: [0.0; 3],
            }),
            Light::Spot { p, i, axis, cos_inner, cos_outer } => {
                let local = sample_uniform_cone(u2, cos_outer);
                let d = Frame::from_z(axis).from_local(local).normalize();
                let l = i * spot_falloff(local.z, cos_inner, cos_outer);
                Some(LightLeSample {
                    l,
                    o: p,
                    d,
                    n: None,
                    pdf_pos: 1.0,
                    pdf_dir: uniform_cone_pdf(cos_outer),
                    b: [0.0; 3],
                })
            }
            Light::Directional { w, e, radius } => {
                let frame = Frame::from_z(w);
                let disk = sample_uniform_disk_concentric(u1) * radius;
                let o = center + (frame.x * disk.x + frame.y * disk.y) - w * radius;
                Some(LightLeSample {
                    l: e,
                    o,
                    d: w,
                    n: None,
                    pdf_pos: 1.0 / (PI * radius * radius),
                    pdf_dir: 1.0,
                    b: [0.0; 3],
                })
            }
            Light::Triangle { v, n, area, le, two_sided, .. } => {
                let b = sample_uniform_triangle(u1);
                let o = v[0] * b[0] + v[1] * b[1] + v[2] * b[2];
                // Cosine-weighted about the front normal; a two-sided light picks a side first.
                let (u2, side) = if two_sided {
                    if u2.x < 0.5 {
                        (Vec2::new(u2.x * 2.0, u2.y), 1.0)
                    } else {
                        (Vec2::new(u2.x * 2.0 - 1.0, u2.y), -1.0)
                    }
                } else {
                    (u2, 1.0)
                };
                let local = sample_cosine_hemisphere(Vec2::new(u2.x.min(ONE_MINUS_EPSILON), u2.y));
                let d = Frame::from_z(n * side).from_local(local).normalize();
                let pdf_dir = cosine_hemisphere_pdf(local.z) * if two_sided { 0.5 } else { 1.0 };
                (pdf_dir > 0.0).then_some(LightLeSample { l: le, o, d, n: Some(n), pdf_pos: 1.0 / area, pdf_dir, b })
            }
        }
    }

    /// Densities (position, direction) with which [`Light::sample_le`] emits direction `w` from
    /// a point of the light with normal `n` (pbrt's `PDF_Le`). Delta densities read 0 here
    /// except the position of point-like lights (1, as in pbrt's MIS bookkeeping).
    pub fn pdf_le(&self, w: Vec3A) -> (f32, f32) {
        match *self {
            Light::Point { .. } => (1.0, uniform_sphere_pdf()),
            Light::Spot { axis, cos_outer, .. } => {
                let pdf = if axis.dot(w) >= cos_outer { uniform_cone_pdf(cos_outer) } else { 0.0 };
                (1.0, pdf)
            }
            Light::Directional { radius, .. } => (1.0 / (PI * radius * radius), 0.0),
            Light::Triangle { n, area, two_sided, .. } => {
                let cos = n.dot(w);
                let pdf_dir =
                    if two_sided { 0.5 * cosine_hemisphere_pdf(cos.abs()) } else { cosine_hemisphere_pdf(cos) };
                (1.0 / area, pdf_dir)
            }
        }
    }
}

/// The spot light's smooth falloff for `cos_theta` from its axis.
fn spot_falloff(cos_theta: f32, cos_inner: f32, cos_outer: f32) -> f32 {
    let scale = 1.0 / (cos_inner - cos_outer).max(1e-3);
    let att = ((cos_theta - cos_outer) * scale).clamp(0.0, 1.0);
    att * att
}

/// The largest f32 below 1.
const ONE_MINUS_EPSILON: f32 = 1.0 - f32::EPSILON / 2.0;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::chi2::{Chi2Options, test_sphere};

    fn tri_light() -> Light {
        let v = [Vec3A::new(-0.5, 1.0, -0.3), Vec3A::new(0.6, 1.0, -0.2), Vec3A::new(0.1, 1.0, 0.7)];
        let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
        let n = if n.y > 0.0 { -n } else { n };
        let area = 0.5 * (v[1] - v[0]).cross(v[2] - v[0]).length();
        Light::Triangle { prim: 0, v, n, area, le: Vec3A::ONE, two_sided: false }
    }

    #[test]
    fn triangle_light_sampling_matches_pdf_li_in_both_modes() {
        // Chi-square of the sampled directions against pdf_li, for area and solid-angle
        // sampling; Sidak-corrected alpha 0.01 over the two tests, fixed seeds.
        let light = tri_light();
        let ctx = LightSampleContext { p: Vec3A::new(0.1, 0.2, 0.05), n: Vec3A::Y };
        for (k, mode) in [LightSampling::Area, LightSampling::SolidAngle].into_iter().enumerate() {
            let opts =
                Chi2Options { samples: 500_000, res: (60, 120), tests: 2, seed: 11 + k as u64, ..Default::default() };
            let pdf = |w: Vec3A| {
                // Direction -> point on the light plane.
                let Light::Triangle { v, n, .. } = light else { return 0.0 };
                let denom = n.dot(w);
                if denom.abs() < 1e-8 {
                    return 0.0;
                }
                let t = n.dot(v[0] - ctx.p) / denom;
                if t <= 0.0 {
                    return 0.0;
                }
                let p = ctx.p + w * t;
                // Inside test with barycentrics.
                let (e0, e1, e2) =
                    ((v[1] - v[0]).cross(p - v[0]), (v[2] - v[1]).cross(p - v[1]), (v[0] - v[2]).cross(p - v[2]));
                if e0.dot(n) * e1.dot(n) < 0.0 || e1.dot(n) * e2.dot(n) < 0.0 {
                    return 0.0;
                }
                light.pdf_li(&ctx, p, mode)
            };
            let result = test_sphere(
                &format!("triangle light {mode:?}"),
                |u, _| light.sample_li(&ctx, u, mode).map(|s| s.wi),
                pdf,
                &opts,
            );
            assert!(result.is_ok(), "{result:?}");
        }
    }

    #[test]
    fn emitted_directions_match_pdf_le() {
        // Chi-square of sample_le's directions against pdf_le for a one-sided and a two-sided
        // triangle, a spot and a point light; Sidak-corrected alpha 0.01 over the four, fixed seeds.
        let one = tri_light();
        let Light::Triangle { prim, v, n, area, le, .. } = one else { unreachable!() };
        let two = Light::Triangle { prim, v, n, area, le, two_sided: true };
        let spot = Light::Spot {
            p: Vec3A::ZERO,
            i: Vec3A::ONE,
            axis: Vec3A::new(0.3, -1.0, 0.2).normalize(),
            cos_inner: 0.9,
            cos_outer: 0.6,
        };
        let point = Light::Point { p: Vec3A::ZERO, i: Vec3A::ONE };
        for (k, light) in [one, two, spot, point].into_iter().enumerate() {
            let opts =
                Chi2Options { samples: 400_000, res: (40, 80), tests: 4, seed: 40 + k as u64, ..Default::default() };
            let result = test_sphere(
                &format!("sample_le {k}"),
                |u, _| {
                    let s = light.sample_le(Vec2::new(0.3, 0.6), u, Vec3A::ZERO)?;
                    let (pdf_pos, pdf_dir) = light.pdf_le(s.d);
                    assert!((pdf_dir - s.pdf_dir).abs() <= 1e-3 * s.pdf_dir, "{pdf_dir} vs {}", s.pdf_dir);
                    assert!((pdf_pos - s.pdf_pos).abs() <= 1e-6 * s.pdf_pos);
                    Some(s.d)
                },
                |w| light.pdf_le(w).1,
                &opts,
            );
            assert!(result.is_ok(), "{result:?}");
        }
    }

    #[test]
    fn spot_falloff_and_point_inverse_square() {
        let ctx = LightSampleContext { p: Vec3A::ZERO, n: Vec3A::Y };
        let p = Light::Point { p: Vec3A::new(0.0, 2.0, 0.0), i: Vec3A::splat(8.0) };
        let s = p.sample_li(&ctx, Vec2::ZERO, LightSampling::Area).expect("sample");
        assert!((s.l.x - 2.0).abs() < 1e-6 && (s.wi - Vec3A::Y).length() < 1e-6);
        let spot = Light::Spot {
            p: Vec3A::new(0.0, 1.0, 0.0),
            i: Vec3A::ONE,
            axis: -Vec3A::Y,
            cos_inner: 0.9,
            cos_outer: 0.8,
        };
        assert!((spot.sample_li(&ctx, Vec2::ZERO, LightSampling::Area).expect("inside").l.x - 1.0).abs() < 1e-6);
        let off = LightSampleContext { p: Vec3A::new(5.0, 0.0, 0.0), n: Vec3A::Y };
        assert!(spot.sample_li(&off, Vec2::ZERO, LightSampling::Area).is_none());
    }
}
