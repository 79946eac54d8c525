//! Lights: point, spot and directional (KHR_lights_punctual, delta lights) and triangle area
//! lights (emissive triangles), sampled by area or by solid angle; light selection by power.

use super::sampling::{
    MAX_SPHERICAL_SAMPLE_AREA, MIN_SPHERICAL_SAMPLE_AREA, sample_spherical_triangle, sample_uniform_triangle,
    triangle_solid_angle,
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
                let cd = axis.dot(-s.wi);
                let scale = 1.0 / (cos_inner - cos_outer).max(1e-3);
                let att = ((cd - cos_outer) * scale).clamp(0.0, 1.0);
                let att = att * att;
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
