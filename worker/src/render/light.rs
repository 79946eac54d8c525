//! Lights: point, spot and directional (KHR_lights_punctual, delta lights), triangle area
//! lights (emissive triangles), sampled by area or by solid angle, and the environment (an
//! equirectangular image importance-sampled by luminance x sin(theta), or a constant colour);
//! light selection by power.

use super::geometry::Frame;
use super::math;
use super::math::Real;
use super::sampling::{
    Distribution2D, MAX_SPHERICAL_SAMPLE_AREA, MIN_SPHERICAL_SAMPLE_AREA, SphericalTriangle, cosine_hemisphere_pdf,
    sample_cosine_hemisphere, sample_uniform_cone, sample_uniform_disk_concentric, sample_uniform_sphere,
    sample_uniform_triangle, uniform_cone_pdf, uniform_sphere_pdf,
};
use super::wide::Vec3Lanes;
use glam::{Vec2, Vec3A};
use pathfarm_common::job::LightSampling;
use pathfarm_common::scene::EnvironmentImage;
use std::f32::consts::PI;
use std::sync::Arc;

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
    /// Light from infinitely far away in every direction (found by rays that escape the scene).
    Environment(Arc<EnvironmentLight>),
}

/// The environment: radiance `scale` x the equirectangular image (or `scale` alone), turned
/// about +Y. Directions are sampled from a 2-D distribution over the image proportional to
/// luminance x sin(theta), so the solid-angle density is `pdf_uv / (2 pi^2 sin(theta))`
/// (pbrt-v3's `InfiniteAreaLight`); a constant environment is sampled uniformly over the sphere.
#[derive(Clone, Debug)]
pub struct EnvironmentLight {
    scale: Vec3A,
    image: Option<(EnvironmentImage, Distribution2D)>,
    /// cos and sin of the rotation about +Y (light -> world).
    cos_rot: f32,
    sin_rot: f32,
    /// The sphere that bounds the scene: emitted rays start on its tangent disks.
    pub center: Vec3A,
    pub radius: f32,
}

impl EnvironmentLight {
    /// `image` x `scale` (or `scale` alone), turned by `rotation_deg` about +Y; `center` and
    /// `radius` bound the scene.
    pub fn new(image: Option<EnvironmentImage>, scale: Vec3A, rotation_deg: f32, center: Vec3A, radius: f32) -> Self {
        let image = image.and_then(|img| {
            let (w, h) = (img.width as usize, img.height as usize);
            let mut weights = Vec::with_capacity(w * h);
            for y in 0..h {
                let sin_theta = math::sin(PI * (y as f32 + 0.5) / h as f32);
                weights.extend(img.texels[y * w..(y + 1) * w].iter().map(|t| {
                    let c = Vec3A::from(*t) * scale;
                    super::scene::luminance(c).max(0.0) * sin_theta
                }));
            }
            Some((img, Distribution2D::new(&weights, w, h)?))
        });
        // Whole turns first: the sine's range reduction is for moderate angles.
        let (sin_rot, cos_rot) = math::sin_cos(rotation_deg.rem_euclid(360.0).to_radians());
        Self { scale, image, cos_rot, sin_rot, center, radius }
    }

    fn to_world(&self, w: Vec3A) -> Vec3A {
        Vec3A::new(self.cos_rot * w.x + self.sin_rot * w.z, w.y, -self.sin_rot * w.x + self.cos_rot * w.z)
    }

    fn to_light(&self, w: Vec3A) -> Vec3A {
        Vec3A::new(self.cos_rot * w.x - self.sin_rot * w.z, w.y, self.sin_rot * w.x + self.cos_rot * w.z)
    }

    /// Image coordinates of a light-space direction: `u` from the azimuth (centre = -X), `v`
    /// from the polar angle (0 = +Y).
    fn uv(w: Vec3A) -> Vec2 {
        let phi = math::atan2(-w.z, -w.x);
        Vec2::new(0.5 + phi * (0.5 / PI), math::acos(w.y.clamp(-1.0, 1.0)) / PI)
    }

    /// The light-space direction of image coordinates, and its sin(theta).
    fn direction(uv: Vec2) -> (Vec3A, f32) {
        let (sin_t, cos_t) = math::sin_cos(uv.y * PI);
        let (sin_p, cos_p) = math::sin_cos((uv.x - 0.5) * 2.0 * PI);
        (Vec3A::new(-sin_t * cos_p, cos_t, -sin_t * sin_p), sin_t)
    }

    /// Radiance arriving along a ray travelling in direction `d` that left the scene (pbrt's
    /// `Le(ray)`): the environment seen in direction `d`. Inline for a constant colour (one
    /// load), out of line for an image.
    #[inline]
    pub fn le(&self, d: Vec3A) -> Vec3A {
        match &self.image {
            None => self.scale,
            Some((img, _)) => self.le_image(img, d),
        }
    }

    #[inline(never)]
    fn le_image(&self, img: &EnvironmentImage, d: Vec3A) -> Vec3A {
        let uv = Self::uv(self.to_light(d));
        let x = (uv.x * img.width as f32) as u32;
        let y = (uv.y * img.height as f32) as u32;
        Vec3A::from(img.texel(x, y)) * self.scale
    }

    /// Samples a direction toward the environment: (wi in world space, solid-angle pdf).
    pub fn sample_wi(&self, u: Vec2) -> Option<(Vec3A, f32)> {
        match &self.image {
            None => Some((sample_uniform_sphere(u), uniform_sphere_pdf())),
            Some((_, distr)) => {
                let (uv, pdf_uv) = distr.sample(u)?;
                let (w, _) = Self::direction(uv);
                // From the direction, as pdf_wi computes it (accurate near the poles).
                let sin_theta = math::hypot(w.x, w.z);
                if !(sin_theta > 0.0) {
                    return None;
                }
                let pdf = pdf_uv / (2.0 * PI * PI * sin_theta);
                (pdf.is_finite() && pdf > 0.0).then(|| (self.to_world(w).normalize(), pdf))
            }
        }
    }

    /// Solid-angle density with which [`Self::sample_wi`] returns `wi` (world space).
    pub fn pdf_wi(&self, wi: Vec3A) -> f32 {
        match &self.image {
            None => uniform_sphere_pdf(),
            Some((_, distr)) => {
                let w = self.to_light(wi);
                let sin_theta = math::hypot(w.x, w.z);
                if !(sin_theta > 0.0) {
                    return 0.0;
                }
                distr.pdf(Self::uv(w)) / (2.0 * PI * PI * sin_theta)
            }
        }
    }

    /// Emitted power: the radiance integrated over the sphere, through the disk of the scene.
    pub fn power(&self) -> Vec3A {
        let disk = PI * self.radius * self.radius;
        match &self.image {
            None => 4.0 * PI * disk * self.scale,
            Some((img, _)) => {
                let (w, h) = (img.width as usize, img.height as usize);
                let mut sum = Vec3A::ZERO;
                for y in 0..h {
                    let sin_theta = math::sin(PI * (y as f32 + 0.5) / h as f32);
                    let row: Vec3A = img.texels[y * w..(y + 1) * w].iter().map(|t| Vec3A::from(*t)).sum();
                    sum += row * sin_theta;
                }
                // Each texel spans (2 pi / w) x (pi / h) in (phi, theta).
                disk * sum * (2.0 * PI * PI / (w * h) as f32) * self.scale
            }
        }
    }
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
/// Returns the spherical triangle (its area the solid angle) where it is used (computed only in
/// solid-angle mode: area sampling never needs it).
#[inline(always)]
fn use_solid_angle(mode: LightSampling, v: &[Vec3A; 3], p: Vec3A) -> Option<SphericalTriangle> {
    if mode != LightSampling::SolidAngle {
        return None;
    }
    solid_angle_in_range(v, p)
}

/// The solid angle of `v` seen from `p`, where [`sample_spherical_triangle`] samples by it. Out
/// of line: area sampling (inlined above) never calls it.
#[inline(never)]
fn solid_angle_in_range(v: &[Vec3A; 3], p: Vec3A) -> Option<SphericalTriangle> {
    // `p` at a vertex: a solid angle of 0, out of range.
    let s = SphericalTriangle::new(*v, p)?;
    (s.area().is_finite() && (MIN_SPHERICAL_SAMPLE_AREA..MAX_SPHERICAL_SAMPLE_AREA).contains(&s.area())).then_some(s)
}

/// A point sampled on a triangle light as seen from a reference point, written once for one
/// sample (`f32`) and for 8 in lanes (`Real`): the same f32 operations in the same order either
/// way. `ok` is false where the sample contributes nothing (the point at the reference point,
/// behind a one-sided light, a zero or non-finite density).
pub(super) struct TriangleSample<R: Real> {
    pub ok: R::Mask,
    pub b: [R; 3],
    pub p: [R; 3],
    pub wi: [R; 3],
    pub pdf: R,
}

/// Up to 8 triangle-light samples' inputs (`RenderScene::sample_light_at_many`): vertices,
/// normal, area, two-sidedness (1 or 0), reference point and the sample's numbers; vectors as
/// one `Vec3A` per lane (the kernel turns them into lanes). Lanes left unset hold zeros (a
/// sample that is not `ok`).
#[derive(Default)]
pub struct LightLanes {
    pub v: [Vec3Lanes; 3],
    pub n: Vec3Lanes,
    pub area: [f32; 8],
    pub two_sided: [f32; 8],
    pub p: Vec3Lanes,
    pub u: [[f32; 8]; 2],
}

impl LightLanes {
    /// Lane `lane`'s inputs.
    #[allow(clippy::too_many_arguments)]
    pub fn set(&mut self, lane: usize, v: &[Vec3A; 3], n: Vec3A, area: f32, two_sided: bool, p: Vec3A, u: Vec2) {
        let lane = lane & 7;
        for (lanes, vertex) in self.v.iter_mut().zip(v) {
            lanes.set(lane, *vertex);
        }
        self.n.set(lane, n);
        self.p.set(lane, p);
        self.u[0][lane] = u.x;
        self.u[1][lane] = u.y;
        self.area[lane] = area;
        self.two_sided[lane] = if two_sided { 1.0 } else { 0.0 };
    }
}

/// The outcome of [`LightLanes`]: `TriangleSample`'s values per lane.
#[derive(Default)]
pub struct LightLaneSamples {
    pub ok: u32,
    pub b: [[f32; 8]; 3],
    pub p: Vec3Lanes,
    pub wi: Vec3Lanes,
    pub pdf: [f32; 8],
}

impl LightLaneSamples {
    /// Lane `lane`'s light sample of a light of radiance `le` and normal `n`, as
    /// [`Light::sample_li`] makes it.
    pub fn get(&self, lane: usize, le: Vec3A, n: Vec3A) -> Option<LightLiSample> {
        let lane = lane & 7;
        (self.ok & (1 << lane) != 0).then(|| LightLiSample {
            l: le,
            wi: self.wi.get(lane),
            pdf: self.pdf[lane],
            p_light: self.p.get(lane),
            n_light: Some(n),
            b: [self.b[0][lane], self.b[1][lane], self.b[2][lane]],
            infinite: false,
        })
    }
}

impl<R: Real> TriangleSample<R> {
    /// The sample at barycentrics `b` of the triangle `v` (normal `n`, area `area`) seen from
    /// `p_ref`, with the solid-angle density `pdf` of `sa: Some((by_solid_angle, pdf))` in the
    /// lanes sampled by solid angle, else the area density converted (`d^2 / (|cos| area)`).
    #[inline(always)]
    pub fn at(
        v: [[R; 3]; 3],
        n: [R; 3],
        area: R,
        two_sided: R::Mask,
        p_ref: [R; 3],
        b: [R; 3],
        sa: Option<(R::Mask, R)>,
    ) -> Self {
        // glam's component-wise order: v0 b0 + v1 b1 + v2 b2; (x^2 + y^2) + z^2. No closures
        // (the lane form is inlined into a function compiled for AVX2; see `accel::Sheared`).
        let p = [
            v[0][0] * b[0] + v[1][0] * b[1] + v[2][0] * b[2],
            v[0][1] * b[0] + v[1][1] * b[1] + v[2][1] * b[2],
            v[0][2] * b[0] + v[1][2] * b[1] + v[2][2] * b[2],
        ];
        let d = [p[0] - p_ref[0], p[1] - p_ref[1], p[2] - p_ref[2]];
        let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let zero = d2.splat(0.0);
        let len = d2.sqrt();
        let wi = [d[0] / len, d[1] / len, d[2] / len];
        let cos_l = n[0] * -wi[0] + n[1] * -wi[1] + n[2] * -wi[2];
        let mut ok = d2.gt(zero) & (two_sided | !cos_l.le(zero));
        let by_area = d2 / (cos_l.abs() * area);
        let pdf = match sa {
            Some((by_solid_angle, pdf)) => {
                ok = ok & (by_solid_angle | !cos_l.eq(zero));
                R::select(by_solid_angle, pdf, by_area)
            }
            None => {
                ok = ok & !cos_l.eq(zero);
                by_area
            }
        };
        ok = ok & pdf.gt(zero) & pdf.lt(zero.splat(f32::INFINITY));
        Self { ok, b, p, wi, pdf }
    }
}

impl Light {
    pub fn is_delta(&self) -> bool {
        !matches!(self, Light::Triangle { .. } | Light::Environment(_))
    }

    /// Emitted power (luminance-free RGB), for light selection.
    pub fn power(&self) -> Vec3A {
        match *self {
            Light::Point { i, .. } => 4.0 * PI * i,
            Light::Spot { i, cos_inner, cos_outer, .. } => 2.0 * PI * i * (1.0 - 0.5 * (cos_inner + cos_outer)),
            Light::Directional { e, radius, .. } => PI * radius * radius * e,
            Light::Triangle { area, le, two_sided, .. } => PI * area * le * if two_sided { 2.0 } else { 1.0 },
            Light::Environment(ref env) => env.power(),
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
                // The projection made for the choice is the one sampled (`sample_spherical_triangle`
                // would make it again).
                let (b, pdf_sa) = if let Some(s) = use_solid_angle(mode, &v, ctx.p) {
                    let (b, pdf) = s.sample(v, ctx.p, u)?;
                    (b, Some(pdf))
                } else {
                    (sample_uniform_triangle(u), None)
                };
                let t = TriangleSample::at(
                    [v[0].into(), v[1].into(), v[2].into()],
                    n.into(),
                    area,
                    two_sided,
                    ctx.p.into(),
                    b,
                    pdf_sa.map(|pdf| (true, pdf)),
                );
                t.ok.then(|| LightLiSample {
                    l: le,
                    wi: t.wi.into(),
                    pdf: t.pdf,
                    p_light: t.p.into(),
                    n_light: Some(n),
                    b: t.b,
                    infinite: false,
                })
            }
            Light::Environment(ref env) => {
                let (wi, pdf) = env.sample_wi(u)?;
                Some(LightLiSample {
                    l: env.le(wi),
                    wi,
                    pdf,
                    p_light: ctx.p + wi * (2.0 * env.radius),
                    n_light: None,
                    b: [0.0; 3],
                    infinite: true,
                })
            }
        }
    }

    /// Solid-angle density with which [`Light::sample_li`] picks the point `p_light` (normal
    /// `n_light`) of this area light from `ctx`. Zero for delta lights.
    pub fn pdf_li(&self, ctx: &LightSampleContext, p_light: Vec3A, mode: LightSampling) -> f32 {
        if let Light::Environment(env) = self {
            return env.pdf_wi((p_light - ctx.p).normalize_or_zero());
        }
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
        if let Some(s) = use_solid_angle(mode, &v, ctx.p) {
            1.0 / s.area()
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
    /// Whether the light sits at infinity (directional, environment).
    pub fn is_infinite(&self) -> bool {
        matches!(self, Light::Directional { .. } | Light::Environment(_))
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
            Light::Environment(ref env) => {
                // A direction toward the environment, then a point on the disk of the scene's
                // bounding sphere facing it, pushed out to the sphere (pbrt's `SampleLe`).
                let (wi, pdf_dir) = env.sample_wi(u2)?;
                let frame = Frame::from_z(-wi);
                let disk = sample_uniform_disk_concentric(u1) * env.radius;
                let o = env.center + (frame.x * disk.x + frame.y * disk.y) + wi * env.radius;
                Some(LightLeSample {
                    l: env.le(wi),
                    o,
                    d: -wi,
                    n: None,
                    pdf_pos: 1.0 / (PI * env.radius * env.radius),
                    pdf_dir,
                    b: [0.0; 3],
                })
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
            Light::Environment(ref env) => (1.0 / (PI * env.radius * env.radius), env.pdf_wi(-w)),
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

    /// A 24 x 12 sky: a gradient, a bright 2 x 1 sun and one black row, turned 30 degrees.
    fn sky() -> EnvironmentLight {
        let (w, h) = (24u32, 12u32);
        let texels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (x, y) == (5, 3) || (x, y) == (6, 3) {
                    glam::Vec3::new(40.0, 30.0, 20.0)
                } else if y == 9 {
                    glam::Vec3::ZERO
                } else {
                    glam::Vec3::new(0.2 + 0.05 * x as f32, 0.5, 1.0 - 0.07 * y as f32)
                }
            })
            .collect();
        let img = EnvironmentImage::new(w, h, texels).expect("image");
        EnvironmentLight::new(Some(img), Vec3A::new(1.0, 0.8, 1.2), 30.0, Vec3A::ZERO, 2.0)
    }

    /// The harness bins directions about +Z; the environment's poles are on +-Y, where its
    /// density has the integrable 1 / sin(theta) of the equirectangular map. Turning +Y to +Z
    /// puts the poles where the harness's sin(theta) cancels it.
    fn y_to_z(w: Vec3A) -> Vec3A {
        Vec3A::new(w.z, w.x, w.y)
    }
    fn z_to_y(w: Vec3A) -> Vec3A {
        Vec3A::new(w.y, w.z, w.x)
    }

    #[test]
    fn environment_sampling_matches_its_pdf() {
        // Chi-square of sample_wi against pdf_wi (image and constant) and of sample_le's
        // directions against pdf_le; Sidak-corrected alpha 0.01 over the three, fixed seeds.
        // pdf_wi agrees with the density sample_wi reports, but for the rare sample that f32
        // rounding moves across a cell edge (as in pbrt): at most 1 in 10^4.
        let mismatches = std::cell::Cell::new(0u32);
        let image = sky();
        let constant = EnvironmentLight::new(None, Vec3A::splat(0.7), 0.0, Vec3A::ZERO, 1.0);
        for (k, env) in [image.clone(), constant].into_iter().enumerate() {
            let opts =
                Chi2Options { samples: 1_000_000, res: (60, 120), tests: 3, seed: 90 + k as u64, ..Default::default() };
            let result = test_sphere(
                &format!("environment {k}"),
                |u, _| {
                    let (w, pdf) = env.sample_wi(u)?;
                    if (env.pdf_wi(w) - pdf).abs() > 2e-3 * pdf {
                        mismatches.set(mismatches.get() + 1);
                    }
                    Some(y_to_z(w))
                },
                |w| env.pdf_wi(z_to_y(w)),
                &opts,
            );
            assert!(result.is_ok(), "{result:?}");
            let total = crate::render::chi2::sphere_integral(|w| env.pdf_wi(z_to_y(w)));
            assert!((total - 1.0).abs() < 2e-3, "pdf integrates to {total}");
        }
        let light = Light::Environment(Arc::new(image));
        let opts = Chi2Options { samples: 1_000_000, res: (60, 120), tests: 3, seed: 97, ..Default::default() };
        let result = test_sphere(
            "environment sample_le",
            |u, _| {
                let s = light.sample_le(Vec2::new(0.3, 0.8), u, Vec3A::ZERO)?;
                let (pdf_pos, pdf_dir) = light.pdf_le(s.d);
                if (pdf_dir - s.pdf_dir).abs() > 2e-3 * s.pdf_dir {
                    mismatches.set(mismatches.get() + 1);
                }
                assert!((pdf_pos - s.pdf_pos).abs() < 1e-6, "{pdf_pos} vs {}", s.pdf_pos);
                // The origin lies on the bounding sphere's tangent disk facing the environment.
                assert!((s.o.dot(-s.d) - 2.0).abs() < 1e-4, "{} {}", s.o, s.d);
                Some(y_to_z(s.d))
            },
            |w| light.pdf_le(z_to_y(w)).1,
            &opts,
        );
        assert!(result.is_ok(), "{result:?}");
        assert!(mismatches.get() <= 300, "{} of 3 x 10^6 densities disagree", mismatches.get());
    }

    #[test]
    fn environment_lookup_follows_the_documented_mapping() {
        // Texel (x, y) of a w x h image is seen in the direction of its centre: the image's
        // centre column looks along -X, its top row up (+Y); rotation turns it about +Y,
        // counter-clockwise seen from above.
        let (w, h) = (8u32, 4u32);
        let texels = (0..w * h).map(|i| glam::Vec3::new((i % w) as f32, (i / w) as f32, 1.0)).collect();
        let img = EnvironmentImage::new(w, h, texels).expect("image");
        let env = EnvironmentLight::new(Some(img.clone()), Vec3A::ONE, 0.0, Vec3A::ZERO, 1.0);
        let near = |d: Vec3A| d.normalize();
        // Just below the horizon along -X: column 4 (centre), row 2.
        assert_eq!(env.le(near(Vec3A::new(-1.0, -0.1, 0.0))), Vec3A::new(4.0, 2.0, 1.0));
        // Straight up: top row; straight down: bottom row.
        assert_eq!(env.le(Vec3A::Y).y, 0.0);
        assert_eq!(env.le(-Vec3A::Y).y, 3.0);
        // +X is the image's left/right edge; -Z a quarter turn from the centre (column 6).
        assert_eq!(env.le(near(Vec3A::new(0.0, -0.1, -1.0))).x, 6.0);
        assert_eq!(env.le(near(Vec3A::new(0.0, -0.1, 1.0))).x, 2.0);
        // Turned 90 degrees counter-clockwise seen from above, -X goes to +Z.
        let turned = EnvironmentLight::new(Some(img), Vec3A::ONE, 90.0, Vec3A::ZERO, 1.0);
        assert_eq!(turned.le(near(Vec3A::new(0.0, -0.1, 1.0))), Vec3A::new(4.0, 2.0, 1.0));
        // Power: the radiance integrated over the sphere through the scene's disk.
        let constant = EnvironmentLight::new(None, Vec3A::splat(2.0), 0.0, Vec3A::ZERO, 3.0);
        assert!((constant.power().x - 4.0 * PI * PI * 9.0 * 2.0).abs() < 1e-2);
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

#[cfg(test)]
mod lane_tests {
    use super::*;
    use crate::render::wide::{Avx2, unit};

    /// Triangle-light samples by solid angle taken 8 at a time in lanes (AVX2) are
    /// `Light::sample_li`'s, bit for bit, on random and degenerate inputs: tiny, huge and thin
    /// spherical triangles (both strategies, and the range's ends), points at a vertex, on the
    /// triangle's plane and edges, behind one-sided lights, degenerate triangles, and numbers
    /// 0 and 1.
    #[test]
    fn solid_angle_samples_in_lanes_are_the_single_samples() {
        let Some(avx2) = Avx2::new() else { return };
        let (mut compared, mut by_solid_angle) = (0, 0);
        for case in 0..6000u64 {
            let mut lanes = LightLanes::default();
            let mut want = Vec::new();
            for lane in 0..8 {
                let i = case * 8 + lane as u64;
                let r = |k: u64| unit(i * 32 + k) * 2.0 - 1.0;
                let v3 = |k: u64| Vec3A::new(r(k), r(k + 1), r(k + 2));
                let mut v = [v3(0), v3(3), v3(6)];
                match i % 7 {
                    // Thin: the third vertex near the first edge.
                    0 => v[2] = v[0].lerp(v[1], r(9).abs()) + v3(10) * 1e-4,
                    // Degenerate: two vertices the same.
                    1 => v[2] = v[1],
                    _ => {}
                }
                let scale = [1e-3, 0.05, 1.0, 4.0][(i / 7 % 4) as usize];
                let v = v.map(|x| x * scale);
                let p = match i % 5 {
                    0 => v[(i / 5 % 3) as usize],
                    1 => v[0].lerp(v[1], 0.5),
                    2 => (v[0] + v[1] + v[2]) / 3.0 + v3(12) * scale * 0.01,
                    _ => v3(12) * (0.5 + 2.0 * r(15).abs()),
                };
                let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize_or(Vec3A::Z);
                let area = 0.5 * (v[1] - v[0]).cross(v[2] - v[0]).length();
                let two_sided = i.is_multiple_of(3);
                let u = match i % 11 {
                    0 => Vec2::ZERO,
                    1 => Vec2::ONE,
                    _ => Vec2::new(r(16).abs().min(0.999_999_9), r(17).abs().min(0.999_999_9)),
                };
                lanes.set(lane, &v, n, area, two_sided, p, u);
                let light = Light::Triangle { prim: 0, v, n, area, le: Vec3A::ONE, two_sided };
                let ctx = LightSampleContext { p, n: Vec3A::ZERO };
                if use_solid_angle(LightSampling::SolidAngle, &v, p).is_some() {
                    by_solid_angle += 1;
                }
                want.push((light.sample_li(&ctx, u, LightSampling::SolidAngle), n));
            }
            let mut got = LightLaneSamples::default();
            avx2.triangle_samples(&lanes, true, &mut got);
            let bits = |s: Option<LightLiSample>| {
                s.map(|s| {
                    let v = |v: Vec3A| v.to_array().map(f32::to_bits);
                    (v(s.wi), s.pdf.to_bits(), v(s.p_light), s.b.map(f32::to_bits))
                })
            };
            for (lane, (w, n)) in want.into_iter().enumerate() {
                let g = got.get(lane, Vec3A::ONE, n);
                assert_eq!(bits(g), bits(w), "case {case} lane {lane}");
                compared += usize::from(w.is_some());
            }
        }
        assert!(compared > 10_000 && by_solid_angle > 10_000, "{compared} samples, {by_solid_angle} by solid angle");
    }
}
