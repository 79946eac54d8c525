//! Microfacet distributions (pbrt-v4's `TrowbridgeReitzDistribution`, plus the classic Blinn and
//! Ashikhmin-Shirley lobes) and the Fresnel terms the microfacet BxDFs pair them with.
//!
//! Everything works in the local shading frame (`z` = shading normal). Microfacet normals `wm`
//! live in the upper hemisphere; a `wm` with `wm.z <= 0` has density zero. Directions `w` may lie
//! on either side: the distributions are symmetric under `w -> -w`, so the lower side is handled
//! by flipping `w`, as pbrt does.

use super::math;
use glam::{Vec2, Vec3A};
use std::f32::consts::{FRAC_1_PI, FRAC_PI_2, PI};

/// Smallest GGX roughness used in the math; smaller values would overflow `D` in `f32`.
const MIN_ALPHA: f32 = 1e-4;

/// A distribution of microfacet normals.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MicrofacetDistribution {
    /// Normalized Blinn: `D(h) = (e + 2) / (2 pi) cos^e(theta_h)`. Samples `h` with density
    /// `D(h) cos(theta_h)` (independent of `wo`): `cos(theta_h) = u^(1 / (e + 2))`.
    /// Uses the V-cavity masking-shadowing function.
    Blinn { exponent: f32 },
    /// Ashikhmin-Shirley anisotropic: `D(h) = sqrt((e_x + 2)(e_y + 2)) / (2 pi) cos^e(phi_h)(theta_h)`
    /// with `e(phi) = e_x cos^2(phi) + e_y sin^2(phi)`, sampled with the routine of Ashikhmin and
    /// Shirley (2000). That sampler's density, `sqrt((e_x + 1)(e_y + 1)) / (2 pi) cos^e(theta_h)`,
    /// is *not* `D(h) cos(theta_h)`; [`MicrofacetDistribution::pdf_wm`] returns what the sampler
    /// produces. Uses the V-cavity masking-shadowing function.
    AshikhminShirley { exponent_x: f32, exponent_y: f32 },
    /// GGX / Trowbridge-Reitz, isotropic (`alpha_x == alpha_y`) or anisotropic, with Smith
    /// height-correlated masking-shadowing and visible-normal sampling (Heitz 2018, pbrt-v4's
    /// `Sample_wm`). Roughness below `1e-4` is clamped.
    TrowbridgeReitz { alpha_x: f32, alpha_y: f32 },
}

impl MicrofacetDistribution {
    /// Isotropic GGX with roughness `alpha`.
    pub fn ggx(alpha: f32) -> Self {
        Self::TrowbridgeReitz { alpha_x: alpha, alpha_y: alpha }
    }

    /// The density of microfacet normals `D(wm)`, normalized so that the projected area
    /// `integral of D(wm) cos(theta_m) dwm` over the hemisphere is 1.
    pub fn d(&self, wm: Vec3A) -> f32 {
        if !(wm.z > 0.0) {
            return 0.0;
        }
        match *self {
            Self::Blinn { exponent } => {
                let e = exponent.max(0.0);
                (e + 2.0) * (0.5 * FRAC_1_PI) * math::powf(wm.z.min(1.0), e)
            }
            Self::AshikhminShirley { exponent_x, exponent_y } => {
                let (ex, ey) = (exponent_x.max(0.0), exponent_y.max(0.0));
                ((ex + 2.0) * (ey + 2.0)).sqrt()
                    * (0.5 * FRAC_1_PI)
                    * math::powf(wm.z.min(1.0), as_exponent(ex, ey, wm))
            }
            Self::TrowbridgeReitz { alpha_x, alpha_y } => {
                let (ax, ay) = (alpha_x.max(MIN_ALPHA), alpha_y.max(MIN_ALPHA));
                // 1 / (pi ax ay cos^4 (1 + tan^2 (cos^2 phi / ax^2 + sin^2 phi / ay^2))^2), written
                // without tan so that it stays finite at every angle.
                let s = (wm.x / ax).powi(2) + (wm.y / ay).powi(2) + wm.z * wm.z;
                1.0 / (PI * ax * ay * s * s)
            }
        }
    }

    /// Smith's auxiliary function `Lambda(w)` for GGX (infinite at grazing `w`), or `None` for the
    /// V-cavity distributions, which are not Smith models.
    pub fn lambda(&self, w: Vec3A) -> Option<f32> {
        match *self {
            Self::TrowbridgeReitz { alpha_x, alpha_y } => {
                let (ax, ay) = (alpha_x.max(MIN_ALPHA), alpha_y.max(MIN_ALPHA));
                let cos2 = w.z * w.z;
                if cos2 == 0.0 {
                    return Some(f32::INFINITY);
                }
                let alpha2_tan2 = ((ax * w.x).powi(2) + (ay * w.y).powi(2)) / cos2;
                Some(((1.0 + alpha2_tan2).sqrt() - 1.0) * 0.5)
            }
            Self::Blinn { .. } | Self::AshikhminShirley { .. } => None,
        }
    }

    /// Masking function `G1(w, wm)`: the fraction of microfacets with normal `wm` visible from `w`.
    /// Zero for back-facing microfacets (`w . wm` and `w . n` of opposite signs).
    pub fn g1(&self, w: Vec3A, wm: Vec3A) -> f32 {
        if !(w.dot(wm) * w.z > 0.0) {
            return 0.0;
        }
        match self.lambda(w) {
            Some(l) => 1.0 / (1.0 + l),
            None => v_cavity_g1(w, wm),
        }
    }

    /// Masking-shadowing `G(wo, wi, wm)`: Smith height-correlated `1 / (1 + Lambda(wo) + Lambda(wi))`
    /// for GGX; the V-cavity `min(1, 2 (n.h)(n.wo) / (wo.h), 2 (n.h)(n.wi) / (wi.h))` (Torrance-Sparrow,
    /// Blinn) for the others. For the half vector `wo.h == wi.h`, which gives the textbook form.
    pub fn g(&self, wo: Vec3A, wi: Vec3A, wm: Vec3A) -> f32 {
        if !(wo.dot(wm) * wo.z > 0.0) || !(wi.dot(wm) * wi.z > 0.0) {
            return 0.0;
        }
        match (self.lambda(wo), self.lambda(wi)) {
            (Some(lo), Some(li)) => 1.0 / (1.0 + lo + li),
            _ => v_cavity_g1(wo, wm).min(v_cavity_g1(wi, wm)),
        }
    }

    /// Samples a microfacet normal (upper hemisphere) for outgoing direction `wo`. Its density is
    /// [`MicrofacetDistribution::pdf_wm`].
    pub fn sample_wm(&self, wo: Vec3A, u: Vec2) -> Vec3A {
        match *self {
            Self::Blinn { exponent } => {
                let cos_theta = math::powf(u.x, 1.0 / (exponent.max(0.0) + 2.0));
                spherical(cos_theta, 2.0 * PI * u.y)
            }
            Self::AshikhminShirley { exponent_x, exponent_y } => {
                let (ex, ey) = (exponent_x.max(0.0), exponent_y.max(0.0));
                // Pick a quadrant, then invert the quadrant's azimuth distribution.
                let quadrant = ((u.x * 4.0) as u32).min(3);
                let up = u.x * 4.0 - quadrant as f32;
                let k = ((ex + 1.0) / (ey + 1.0)).sqrt();
                let (s, c) = math::sin_cos(FRAC_PI_2 * up);
                let phi0 = math::atan2(k * s, c);
                let phi = match quadrant {
                    0 => phi0,
                    1 => PI - phi0,
                    2 => PI + phi0,
                    _ => 2.0 * PI - phi0,
                };
                let (sp, cp) = math::sin_cos(phi);
                let e = ex * cp * cp + ey * sp * sp;
                spherical(math::powf(u.y, 1.0 / (e + 1.0)), phi)
            }
            Self::TrowbridgeReitz { alpha_x, alpha_y } => {
                let (ax, ay) = (alpha_x.max(MIN_ALPHA), alpha_y.max(MIN_ALPHA));
                // Stretch wo to the configuration where the distribution is the unit hemisphere.
                let mut wh = Vec3A::new(ax * wo.x, ay * wo.y, wo.z).normalize_or_zero();
                if wh == Vec3A::ZERO {
                    wh = Vec3A::Z;
                }
                if wh.z < 0.0 {
                    wh = -wh;
                }
                let t1 = if wh.z < 0.99999 { Vec3A::Z.cross(wh).normalize() } else { Vec3A::X };
                let t2 = wh.cross(t1);
                // Uniform disk point, warped to the visible half of the projected hemisphere.
                let r = u.x.sqrt();
                let (sp, cp) = math::sin_cos(2.0 * PI * u.y);
                let (px, py) = (r * cp, r * sp);
                let h = (1.0 - px * px).max(0.0).sqrt();
                let t = 0.5 * (1.0 + wh.z);
                let py = (1.0 - t) * h + t * py;
                let pz = (1.0 - px * px - py * py).max(0.0).sqrt();
                let nh = px * t1 + py * t2 + pz * wh;
                Vec3A::new(ax * nh.x, ay * nh.y, nh.z.max(1e-6)).normalize()
            }
        }
    }

    /// The density (solid angle) with which [`MicrofacetDistribution::sample_wm`] returns `wm`:
    /// `D(wm) cos(theta_m)` for Blinn, the Ashikhmin-Shirley sampler's own density, and the
    /// distribution of visible normals `G1(wo, wm) max(0, wo.wm) D(wm) / |cos(theta_o)|` for GGX.
    pub fn pdf_wm(&self, wo: Vec3A, wm: Vec3A) -> f32 {
        self.pdf_wm_with(wo, wm, || self.d(wm))
    }

    /// [`MicrofacetDistribution::pdf_wm`] with `D(wm)` from `d` (a value made already).
    #[inline]
    pub fn pdf_wm_with(&self, wo: Vec3A, wm: Vec3A, d: impl FnOnce() -> f32) -> f32 {
        if !(wm.z > 0.0) {
            return 0.0;
        }
        match *self {
            Self::Blinn { .. } => d() * wm.z,
            Self::AshikhminShirley { exponent_x, exponent_y } => {
                let (ex, ey) = (exponent_x.max(0.0), exponent_y.max(0.0));
                ((ex + 1.0) * (ey + 1.0)).sqrt()
                    * (0.5 * FRAC_1_PI)
                    * math::powf(wm.z.min(1.0), as_exponent(ex, ey, wm))
            }
            Self::TrowbridgeReitz { .. } => {
                let w = if wo.z < 0.0 { -wo } else { wo };
                if !(w.z > 0.0) {
                    return 0.0;
                }
                let cos_m = w.dot(wm);
                if !(cos_m > 0.0) {
                    return 0.0;
                }
                self.g1(w, wm) / w.z * d() * cos_m
            }
        }
    }
}

/// The albedo tables of [`GgxAlbedo`] and [`SheenAlbedo`] as their quadratures compute them
/// (`compute`), embedded as `f32` bits: the quadratures take about 0.3 s, which every process
/// that shades a glTF material paid at its first hit (a CLI render of a one-triangle scene: 0.19
/// s of 0.2). The test `embedded_albedo_tables_are_the_computed_ones` computes them again and,
/// where they differ, writes the new file to `target/albedo_tables.rs`.
mod albedo_tables;

/// `f32`s from their bits (at compile time).
const fn floats<const N: usize>(bits: &[u32; N]) -> [f32; N] {
    let mut out = [0.0f32; N];
    let mut i = 0;
    while i < N {
        out[i] = f32::from_bits(bits[i]);
        i += 1;
    }
    out
}

/// GGX roughness below which a lobe is treated as a perfect (delta) reflection, as pbrt-v4's
/// `EffectivelySmooth` and Mitsuba do: such a lobe is too narrow to evaluate or to light by
/// next-event estimation, and only sampling it finds what it reflects.
pub const SMOOTH_ALPHA: f32 = 1e-3;

/// Table size of [`GgxAlbedo`]: cosines of the outgoing direction (`mu = x^2` for `x` uniform
/// on [0, 1], so that the fast change near grazing is resolved) ...
const ALBEDO_COS: usize = 40;
/// ... and perceptual roughness `sqrt(alpha)`, both uniform on [0, 1].
const ALBEDO_ROUGHNESS: usize = 32;
/// Quadrature points per table entry along each of the two sample dimensions.
#[cfg(test)]
const ALBEDO_QUADRATURE: usize = 64;

/// Directional albedos of the isotropic GGX microfacet lobe `D G / (4 |cos_o| |cos_i|)`
/// (Smith height-correlated `G`), tabulated at start-up for energy-conserving layering and
/// Kulla-Conty multiple-scattering compensation:
///
/// - `E1(mu, alpha) = integral of D G / (4 mu mu_i) mu_i dw_i` (no Fresnel),
/// - `E5(mu, alpha)`, the same weighted by `(1 - wo.h)^5` (so that a Schlick Fresnel
///   `F0 + (1 - F0)(1 - wo.h)^5` reflects `F0 E1 + (1 - F0) E5`),
///
/// and their cosine-weighted hemispherical averages `2 integral of E(mu) mu dmu`. Entries are
/// computed by a deterministic midpoint quadrature of `G / G1(wo)` over the visible-normal
/// samples; lookups interpolate bilinearly in (`sqrt(mu)`, `sqrt(alpha)`), and the averages are the
/// exact averages of the interpolated table, so that a lobe `(1 - E(mu_o))(1 - E(mu_i)) / (pi (1 - E_avg))`
/// reflects exactly `1 - E(mu_o)`.
pub struct GgxAlbedo {
    e1: [f32; ALBEDO_COS * ALBEDO_ROUGHNESS],
    e5: [f32; ALBEDO_COS * ALBEDO_ROUGHNESS],
    avg1: [f32; ALBEDO_ROUGHNESS],
    avg5: [f32; ALBEDO_ROUGHNESS],
}

/// The embedded GGX tables, made at compile time.
static GGX_ALBEDO: GgxAlbedo = GgxAlbedo::embedded();
/// The embedded sheen table, made at compile time.
static SHEEN_ALBEDO: SheenAlbedo = SheenAlbedo::embedded();

impl GgxAlbedo {
    /// The tables (embedded: `albedo_tables`).
    pub fn get() -> &'static Self {
        &GGX_ALBEDO
    }

    const fn embedded() -> Self {
        use albedo_tables::{GGX_AVG1, GGX_AVG5, GGX_E1, GGX_E5};
        Self { e1: floats(&GGX_E1), e5: floats(&GGX_E5), avg1: floats(&GGX_AVG1), avg5: floats(&GGX_AVG5) }
    }

    /// The tables by their quadrature (what [`albedo_tables`] holds).
    #[cfg(test)]
    fn compute() -> Self {
        let (mut e1, mut e5) = ([0.0f32; ALBEDO_COS * ALBEDO_ROUGHNESS], [0.0f32; ALBEDO_COS * ALBEDO_ROUGHNESS]);
        for r in 0..ALBEDO_ROUGHNESS {
            let roughness = r as f32 / (ALBEDO_ROUGHNESS - 1) as f32;
            let ggx = MicrofacetDistribution::ggx(roughness * roughness);
            for c in 0..ALBEDO_COS {
                // mu = 0 is a limit; evaluate just above it.
                let mu = (c as f32 / (ALBEDO_COS - 1) as f32).powi(2).max(1e-4);
                let wo = Vec3A::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
                let lambda_o = ggx.lambda(wo).unwrap_or(0.0);
                let (mut s1, mut s5) = (0.0f64, 0.0f64);
                for i in 0..ALBEDO_QUADRATURE {
                    for j in 0..ALBEDO_QUADRATURE {
                        let u = Vec2::new(
                            (i as f32 + 0.5) / ALBEDO_QUADRATURE as f32,
                            (j as f32 + 0.5) / ALBEDO_QUADRATURE as f32,
                        );
                        let wm = ggx.sample_wm(wo, u);
                        let cos_h = wo.dot(wm);
                        let wi = -wo + 2.0 * cos_h * wm;
                        if !(wi.z > 0.0) || !(cos_h > 0.0) {
                            continue;
                        }
                        // f cos_i / pdf with pdf = D G1(wo) max(0, wo.h) / (4 mu wo.h) = G / G1(wo).
                        let lambda_i = ggx.lambda(wi).unwrap_or(0.0);
                        let w = f64::from((1.0 + lambda_o) / (1.0 + lambda_o + lambda_i));
                        s1 += w;
                        s5 += w * f64::from((1.0 - cos_h.min(1.0)).powi(5));
                    }
                }
                let q = (ALBEDO_QUADRATURE * ALBEDO_QUADRATURE) as f64;
                e1[r * ALBEDO_COS + c] = (s1 / q).min(1.0) as f32;
                e5[r * ALBEDO_COS + c] = (s5 / q).min(1.0) as f32;
            }
        }
        let average = |e: &[f32]| -> [f32; ALBEDO_ROUGHNESS] {
            std::array::from_fn(|r| {
                let row = &e[r * ALBEDO_COS..(r + 1) * ALBEDO_COS];
                let h = 1.0 / (ALBEDO_COS - 1) as f64;
                // With mu = x^2, 2 mu E dmu = 4 x^3 E(x) dx, a quintic on each segment of the
                // piecewise-linear E(x): three-point Gauss-Legendre is exact.
                let gauss = [(-(0.6f64.sqrt()), 5.0 / 9.0), (0.0, 8.0 / 9.0), (0.6f64.sqrt(), 5.0 / 9.0)];
                let sum: f64 = row
                    .windows(2)
                    .enumerate()
                    .map(|(k, pair)| {
                        let (ea, eb) = (f64::from(pair[0]), f64::from(pair[1]));
                        let mid = (k as f64 + 0.5) * h;
                        gauss
                            .iter()
                            .map(|&(t, w)| {
                                let x = mid + 0.5 * h * t;
                                let e = ea + (eb - ea) * (0.5 + 0.5 * t);
                                w * 0.5 * h * 4.0 * x * x * x * e
                            })
                            .sum::<f64>()
                    })
                    .sum();
                sum as f32
            })
        };
        let (avg1, avg5) = (average(&e1), average(&e5));
        Self { e1, e5, avg1, avg5 }
    }

    /// The roughness row below `alpha` and the weight of the row above.
    fn row(alpha: f32) -> (usize, f32) {
        let x = alpha.max(0.0).sqrt().min(1.0) * (ALBEDO_ROUGHNESS - 1) as f32;
        let r = (x as usize).min(ALBEDO_ROUGHNESS - 2);
        (r, x - r as f32)
    }

    /// `(E1, E5)` at outgoing cosine `mu` (its absolute value) and roughness `alpha`.
    pub fn e(&self, mu: f32, alpha: f32) -> (f32, f32) {
        let (r, tr) = Self::row(alpha);
        let x = mu.abs().min(1.0).sqrt() * (ALBEDO_COS - 1) as f32;
        let c = (x as usize).min(ALBEDO_COS - 2);
        let tc = x - c as f32;
        let lerp2 = |t: &[f32]| {
            let at = |r: usize| t[r * ALBEDO_COS + c] * (1.0 - tc) + t[r * ALBEDO_COS + c + 1] * tc;
            at(r) * (1.0 - tr) + at(r + 1) * tr
        };
        (lerp2(&self.e1), lerp2(&self.e5))
    }

    /// The averages `(E1_avg, E5_avg)` at roughness `alpha`.
    pub fn average(&self, alpha: f32) -> (f32, f32) {
        let (r, t) = Self::row(alpha);
        let lerp = |a: &[f32]| a[r] * (1.0 - t) + a[r + 1] * t;
        (lerp(&self.avg1), lerp(&self.avg5))
    }
}

/// The Ashikhmin-Shirley exponent `e_x cos^2(phi) + e_y sin^2(phi)` at microfacet normal `wm`.
fn as_exponent(ex: f32, ey: f32, wm: Vec3A) -> f32 {
    let sin2 = wm.x * wm.x + wm.y * wm.y;
    // At the pole the azimuth is undefined but cos(theta) = 1, so any exponent gives 1.
    if sin2 == 0.0 { ex } else { (ex * wm.x * wm.x + ey * wm.y * wm.y) / sin2 }
}

/// V-cavity masking `min(1, 2 |n.h| |n.w| / |w.h|)`; the caller has checked that `w` sees `h`.
fn v_cavity_g1(w: Vec3A, wm: Vec3A) -> f32 {
    (2.0 * wm.z.abs() * w.z.abs() / w.dot(wm).abs()).min(1.0)
}

fn spherical(cos_theta: f32, phi: f32) -> Vec3A {
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    let (sp, cp) = math::sin_cos(phi);
    Vec3A::new(sin_theta * cp, sin_theta * sp, cos_theta)
}

/// A Fresnel reflectance term, evaluated at the cosine between the incident direction and the
/// (micro)surface normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Fresnel {
    /// No Fresnel effect: reflectance 1 (the lobe's colour alone sets the reflectance).
    One,
    /// Schlick's approximation `f0 + (1 - f0)(1 - cos)^5`.
    Schlick { f0: Vec3A },
    /// Exact unpolarized Fresnel reflectance of a dielectric interface; `eta` is the index of the
    /// side below the surface (`-z`) over that above it.
    Dielectric { eta: f32 },
    /// Exact reflectance of a conductor with complex index `eta + i k` (per channel).
    Conductor { eta: Vec3A, k: Vec3A },
}

impl Fresnel {
    /// Reflectance for an incident direction at cosine `cos_theta_i` to the normal.
    pub fn evaluate(&self, cos_theta_i: f32) -> Vec3A {
        match *self {
            Self::One => Vec3A::ONE,
            Self::Schlick { f0 } => {
                let m = (1.0 - cos_theta_i.abs().min(1.0)).powi(5);
                f0 + (Vec3A::ONE - f0) * m
            }
            Self::Dielectric { eta } => Vec3A::splat(fr_dielectric(cos_theta_i, eta)),
            Self::Conductor { eta, k } => {
                let c = cos_theta_i.abs();
                Vec3A::new(
                    fr_complex(c, Complex(eta.x, k.x)),
                    fr_complex(c, Complex(eta.y, k.y)),
                    fr_complex(c, Complex(eta.z, k.z)),
                )
            }
        }
    }
}

/// Unpolarized Fresnel reflectance of a dielectric interface (pbrt-v4 `FrDielectric`).
/// `eta` is the relative index of the `-z` side over the `+z` side; a negative `cos_theta_i`
/// means the incident direction is below the surface. Returns 1 under total internal reflection.
pub fn fr_dielectric(cos_theta_i: f32, eta: f32) -> f32 {
    let mut cos_i = cos_theta_i.clamp(-1.0, 1.0);
    let mut eta = eta;
    if cos_i < 0.0 {
        eta = 1.0 / eta;
        cos_i = -cos_i;
    }
    let sin2_i = 1.0 - cos_i * cos_i;
    let sin2_t = sin2_i / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

#[derive(Clone, Copy, Debug)]
struct Complex(f32, f32);

impl Complex {
    fn add(self, o: Self) -> Self {
        Self(self.0 + o.0, self.1 + o.1)
    }
    fn sub(self, o: Self) -> Self {
        Self(self.0 - o.0, self.1 - o.1)
    }
    fn mul(self, o: Self) -> Self {
        Self(self.0 * o.0 - self.1 * o.1, self.0 * o.1 + self.1 * o.0)
    }
    fn div(self, o: Self) -> Self {
        let d = o.0 * o.0 + o.1 * o.1;
        Self((self.0 * o.0 + self.1 * o.1) / d, (self.1 * o.0 - self.0 * o.1) / d)
    }
    fn norm(self) -> f32 {
        self.0 * self.0 + self.1 * self.1
    }
    fn sqrt(self) -> Self {
        let n = self.norm().sqrt();
        if n == 0.0 {
            return Self(0.0, 0.0);
        }
        let t1 = (0.5 * (n + self.0.abs())).sqrt();
        let t2 = 0.5 * self.1 / t1;
        if self.0 >= 0.0 { Self(t1, t2) } else { Self(t2.abs(), t1.copysign(self.1)) }
    }
}

/// Fresnel reflectance of a conductor (pbrt-v4 `FrComplex`), `cos_theta_i` in [0, 1].
fn fr_complex(cos_theta_i: f32, eta: Complex) -> f32 {
    let cos_i = Complex(cos_theta_i.clamp(0.0, 1.0), 0.0);
    let sin2_i = Complex(1.0 - cos_i.0 * cos_i.0, 0.0);
    let sin2_t = sin2_i.div(eta.mul(eta));
    let cos_t = Complex(1.0, 0.0).sub(sin2_t).sqrt();
    let r_parl = eta.mul(cos_i).sub(cos_t).div(eta.mul(cos_i).add(cos_t));
    let r_perp = cos_i.sub(eta.mul(cos_t)).div(cos_i.add(eta.mul(cos_t)));
    0.5 * (r_parl.norm() + r_perp.norm())
}

/// Smallest sheen roughness used (the glTF sample viewer's floor): below it the Charlie
/// distribution's `sin^(1 / alpha)` is too peaked for `f32` and for the albedo table.
const SHEEN_MIN_ROUGHNESS: f32 = 0.07;

/// The "Charlie" sheen microfacet lobe of KHR_materials_sheen (Estevez and Kulla 2017,
/// "Production Friendly Microfacet Sheen BRDF"): `D(h) = (2 + 1 / alpha) sin^(1 / alpha)(theta_h) / (2 pi)`
/// with `alpha = roughness^2`, and their Smith-style masking-shadowing
/// `G = 1 / (1 + Lambda(mu_o) + Lambda(mu_i))` with the fitted `Lambda` (as the glTF sample viewer
/// writes it). `f = D G / (4 mu_o mu_i)`, no Fresnel; white, so its directional albedo is at
/// most 1 ([`SheenAlbedo`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sheen {
    /// Perceptual roughness, clamped to [`SHEEN_MIN_ROUGHNESS`, 1].
    pub roughness: f32,
}

impl Sheen {
    pub fn new(roughness: f32) -> Self {
        Self { roughness: roughness.clamp(SHEEN_MIN_ROUGHNESS, 1.0) }
    }

    fn alpha(&self) -> f32 {
        self.roughness * self.roughness
    }

    /// `D(wm)` for an upper-side `wm`.
    pub fn d(&self, wm: Vec3A) -> f32 {
        let inv = 1.0 / self.alpha();
        let sin2 = (1.0 - wm.z * wm.z).max(0.0);
        (2.0 + inv) * math::powf(sin2, 0.5 * inv) * (0.5 * FRAC_1_PI)
    }

    /// Estevez and Kulla's fitted `Lambda(mu)`.
    fn lambda(&self, mu: f32) -> f32 {
        let t = (1.0 - self.alpha()).powi(2);
        let lerp = |a: f32, b: f32| a + (b - a) * t;
        let l = |x: f32| {
            let (a, b, c) = (lerp(21.5473, 25.3245), lerp(3.82987, 3.32435), lerp(0.19823, 0.16801));
            let (d, e) = (lerp(-1.97760, -1.27393), lerp(-4.32054, -4.85967));
            a / (1.0 + b * math::powf(x.max(0.0), c)) + d * x + e
        };
        let mu = mu.abs().min(1.0);
        if mu < 0.5 { math::exp(l(mu)) } else { math::exp(2.0 * l(0.5) - l(1.0 - mu)) }
    }

    /// `D G / (4 mu_o mu_i)` for upper-side `wo`, `wi`.
    pub fn f(&self, wo: Vec3A, wi: Vec3A) -> f32 {
        if !(wo.z > 0.0) || !(wi.z > 0.0) {
            return 0.0;
        }
        let h = wo + wi;
        let len2 = h.length_squared();
        if !(len2 > 0.0) {
            return 0.0;
        }
        let g = 1.0 / (1.0 + self.lambda(wo.z) + self.lambda(wi.z));
        let f = self.d(h / len2.sqrt()) * g / (4.0 * wo.z * wi.z);
        if f.is_finite() { f } else { 0.0 }
    }
}

/// Outgoing cosines of the sheen albedo table (`mu = x^2`, `x` uniform) and its roughnesses
/// (uniform on [`SHEEN_MIN_ROUGHNESS`, 1]).
const SHEEN_COS: usize = 32;
const SHEEN_ROUGHNESS: usize = 16;
/// Quadrature of one entry: `x_i` (with `mu_i = x_i^2`) by `phi` in [0, pi] (the lobe is
/// symmetric about the plane of incidence).
#[cfg(test)]
const SHEEN_QUADRATURE: (usize, usize) = (96, 48);

/// Directional albedo `E(mu, roughness)` of the white [`Sheen`] lobe, tabulated at start-up by a
/// deterministic midpoint quadrature, interpolated bilinearly; the albedo scaling of the layers
/// under a sheen (glTF's `1 - max(sheenColor) E(mu)`) reads it.
pub struct SheenAlbedo {
    e: [f32; SHEEN_COS * SHEEN_ROUGHNESS],
}

impl SheenAlbedo {
    /// The table (embedded: `albedo_tables`).
    pub fn get() -> &'static Self {
        &SHEEN_ALBEDO
    }

    const fn embedded() -> Self {
        Self { e: floats(&albedo_tables::SHEEN_E) }
    }

    #[cfg(test)]
    fn roughness_at(r: usize) -> f32 {
        SHEEN_MIN_ROUGHNESS + (1.0 - SHEEN_MIN_ROUGHNESS) * r as f32 / (SHEEN_ROUGHNESS - 1) as f32
    }

    /// The table by its quadrature (what [`albedo_tables`] holds).
    #[cfg(test)]
    fn compute() -> Self {
        let mut e = [0.0f32; SHEEN_COS * SHEEN_ROUGHNESS];
        let (nx, np) = SHEEN_QUADRATURE;
        for r in 0..SHEEN_ROUGHNESS {
            let sheen = Sheen::new(Self::roughness_at(r));
            for c in 0..SHEEN_COS {
                let mu = (c as f32 / (SHEEN_COS - 1) as f32).powi(2).max(1e-4);
                let wo = Vec3A::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
                let mut sum = 0.0f64;
                for i in 0..nx {
                    // mu_i = x^2: d mu_i = 2 x dx.
                    let x = (i as f32 + 0.5) / nx as f32;
                    let mu_i = x * x;
                    let sin_i = (1.0 - mu_i * mu_i).max(0.0).sqrt();
                    for j in 0..np {
                        let phi = PI * (j as f32 + 0.5) / np as f32;
                        let (sin_phi, cos_phi) = math::sin_cos(phi);
                        let wi = Vec3A::new(sin_i * cos_phi, sin_i * sin_phi, mu_i);
                        sum += f64::from(sheen.f(wo, wi) * mu_i * 2.0 * x);
                    }
                }
                // Both halves of phi: 2 pi / np per cell; dx = 1 / nx.
                e[r * SHEEN_COS + c] = (sum * 2.0 * std::f64::consts::PI / (np * nx) as f64) as f32;
            }
        }
        Self { e }
    }

    /// `E(mu, roughness)` (`mu` by its absolute value).
    pub fn e(&self, mu: f32, roughness: f32) -> f32 {
        let y = (roughness.clamp(SHEEN_MIN_ROUGHNESS, 1.0) - SHEEN_MIN_ROUGHNESS) / (1.0 - SHEEN_MIN_ROUGHNESS)
            * (SHEEN_ROUGHNESS - 1) as f32;
        let r = (y as usize).min(SHEEN_ROUGHNESS - 2);
        let tr = y - r as f32;
        let x = mu.abs().min(1.0).sqrt() * (SHEEN_COS - 1) as f32;
        let c = (x as usize).min(SHEEN_COS - 2);
        let tc = x - c as f32;
        let at = |r: usize| self.e[r * SHEEN_COS + c] * (1.0 - tc) + self.e[r * SHEEN_COS + c + 1] * tc;
        at(r) * (1.0 - tr) + at(r + 1) * tr
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::render::bsdf::tests::CHI2_SUITE_TESTS;
    use crate::render::chi2::test_sphere as test_sphere_open;
    use crate::render::chi2::{self, Chi2Options};

    /// Every distribution the BSDF suite uses.
    pub(crate) fn distributions() -> Vec<MicrofacetDistribution> {
        let mut v = Vec::new();
        for exponent in [1.0, 10.0, 100.0, 1000.0] {
            v.push(MicrofacetDistribution::Blinn { exponent });
        }
        for (exponent_x, exponent_y) in [(10.0, 100.0), (200.0, 10.0), (1000.0, 1000.0)] {
            v.push(MicrofacetDistribution::AshikhminShirley { exponent_x, exponent_y });
        }
        for alpha in [0.05, 0.2, 0.5, 1.0] {
            v.push(MicrofacetDistribution::ggx(alpha));
        }
        v.push(MicrofacetDistribution::TrowbridgeReitz { alpha_x: 0.1, alpha_y: 0.5 });
        v
    }

    /// Number of chi-square tests in this module (counted in the suite's Sidak correction).
    pub(crate) const MICROFACET_CHI2_TESTS: usize = 12;

    fn dir(cos_theta: f32, phi: f32) -> Vec3A {
        spherical(cos_theta, phi)
    }

    #[test]
    fn d_projected_area_is_one() {
        for d in distributions() {
            let area = chi2::sphere_integral(|h| d.d(h) * h.z.max(0.0));
            assert!((area - 1.0).abs() < 1e-3, "{d:?}: projected area {area}");
        }
    }

    #[test]
    fn pdf_wm_integrates_to_one() {
        for d in distributions() {
            for wo in [dir(1.0, 0.0), dir(0.6, 0.9), dir(0.1, 2.2), dir(-0.5, 4.0)] {
                let total = chi2::sphere_integral(|m| d.pdf_wm(wo, m));
                assert!((total - 1.0).abs() < 2e-3, "{d:?} wo {wo}: pdf_wm integrates to {total}");
            }
        }
    }

    #[test]
    fn sample_wm_matches_pdf_wm() {
        // 11 distributions, one oblique wo each; 2e5 samples on 40 x 80 bins, seed 11.
        let opts = Chi2Options { samples: 200_000, res: (40, 80), alpha: 0.01, tests: CHI2_SUITE_TESTS, seed: 11 };
        let wo = dir(0.4, 0.7);
        let mut failures = Vec::new();
        for d in distributions() {
            let name = format!("sample_wm {d:?}");
            if let Err(e) = test_sphere_open(&name, |u, _| Some(d.sample_wm(wo, u)), |m| d.pdf_wm(wo, m), &opts) {
                failures.push(e);
            }
        }
        assert!(failures.is_empty(), "{}", failures.join("\n"));
    }

    #[test]
    fn ashikhmin_shirley_sampler_is_not_d_cos() {
        // The A-S sampler's density differs from D(h) cos(theta_h) (exponent off by one, and
        // another constant); the chi-square test must tell them apart. One must-pass case counts
        // towards the suite; the rejection runs at the same level.
        let d = MicrofacetDistribution::AshikhminShirley { exponent_x: 10.0, exponent_y: 100.0 };
        let opts = Chi2Options { samples: 200_000, res: (40, 80), alpha: 0.01, tests: CHI2_SUITE_TESTS, seed: 12 };
        let wo = Vec3A::Z;
        let sample = |u: Vec2, _| Some(d.sample_wm(wo, u));
        assert!(test_sphere_open("A-S vs D cos", sample, |m| d.d(m) * m.z.max(0.0), &opts).is_err());
        test_sphere_open("A-S vs pdf_wm", sample, |m| d.pdf_wm(wo, m), &opts).expect("A-S sampler density");
    }

    #[test]
    fn masking_shadowing_properties() {
        let mut rng = chi2::TestRng::new(3);
        for d in distributions() {
            for _ in 0..2000 {
                let wo = dir(rng.uniform(), 2.0 * PI * rng.uniform());
                let wi = dir(rng.uniform(), 2.0 * PI * rng.uniform());
                let Some(wm) = (wo + wi).try_normalize() else { continue };
                let g = d.g(wo, wi, wm);
                assert!((0.0..=1.0).contains(&g), "{d:?}: G = {g}");
                assert!((g - d.g(wi, wo, wm)).abs() < 1e-5, "{d:?}: G not symmetric");
                assert!(g <= d.g1(wo, wm).min(d.g1(wi, wm)) + 1e-6, "{d:?}: G > min(G1)");
                // Back-facing microfacets are masked.
                let back = Vec3A::new(-wo.x, -wo.y, wo.z.max(0.05)).normalize();
                if wo.dot(back) < 0.0 {
                    assert_eq!(d.g1(wo, back), 0.0);
                }
            }
            assert!((d.g(Vec3A::Z, Vec3A::Z, Vec3A::Z) - 1.0).abs() < 1e-6, "{d:?}: G at normal incidence");
            assert_eq!(d.g(dir(0.0, 0.3), Vec3A::Z, Vec3A::Z), 0.0, "{d:?}: G at grazing");
        }
        // GGX G1 against the isotropic closed form 2 / (1 + sqrt(1 + alpha^2 tan^2)).
        let d = MicrofacetDistribution::ggx(0.3);
        let w = dir(0.5, 1.0);
        let tan2: f32 = (1.0 - 0.25) / 0.25;
        let expect = 2.0 / (1.0 + (1.0 + 0.09 * tan2).sqrt());
        assert!((d.g1(w, Vec3A::Z) - expect).abs() < 1e-6);
    }

    #[test]
    fn fresnel_limits() {
        // Normal incidence: ((eta - 1) / (eta + 1))^2 from either side.
        for eta in [1.33f32, 1.5, 2.4] {
            let r0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
            assert!((fr_dielectric(1.0, eta) - r0).abs() < 1e-6);
            assert!((fr_dielectric(-1.0, eta) - r0).abs() < 1e-6);
            assert!((fr_dielectric(1e-4, eta) - 1.0).abs() < 1e-2, "grazing reflects");
            // Total internal reflection beyond the critical angle, from inside.
            let cos_c = (1.0 - 1.0 / (eta * eta)).sqrt();
            assert_eq!(fr_dielectric(-(cos_c - 1e-3), eta), 1.0);
            assert!(fr_dielectric(-(cos_c + 1e-3), eta) < 1.0);
        }
        assert!(fr_dielectric(0.3, 1.0) < 1e-12);
        let f0 = Vec3A::new(0.9, 0.5, 0.04);
        let schlick = Fresnel::Schlick { f0 };
        assert!((schlick.evaluate(1.0) - f0).length() < 1e-6);
        assert!((schlick.evaluate(0.0) - Vec3A::ONE).length() < 1e-6);
        // A conductor with k = 0 is a dielectric.
        let cond = Fresnel::Conductor { eta: Vec3A::splat(1.5), k: Vec3A::ZERO };
        for c in [1.0f32, 0.7, 0.2, 0.01] {
            assert!((cond.evaluate(c).x - fr_dielectric(c, 1.5)).abs() < 1e-5, "cos {c}");
        }
        // Gold-like conductor: high reflectance, rising to 1 at grazing.
        let gold = Fresnel::Conductor { eta: Vec3A::new(0.143, 0.374, 1.442), k: Vec3A::new(3.983, 2.385, 1.603) };
        let r = gold.evaluate(1.0);
        assert!(r.x > 0.9 && r.z < 0.5 && r.z > 0.2, "gold {r}");
        assert!((gold.evaluate(1e-4) - Vec3A::ONE).abs().max_element() < 1e-2);
    }

    /// The embedded tables are what the quadratures compute today (within 1e-6: the same code,
    /// and a different build may round a `powi` otherwise). Where they are not, the new file
    /// is written to `target/albedo_tables.rs`, to be copied over
    /// `worker/src/render/microfacet/albedo_tables.rs` (then `cargo fmt`).
    #[test]
    fn embedded_albedo_tables_are_the_computed_ones() {
        let (ggx, sheen) = (GgxAlbedo::compute(), SheenAlbedo::compute());
        let (g, s) = (GgxAlbedo::get(), SheenAlbedo::get());
        let tables: [(&str, &[f32], &[f32]); 5] = [
            ("GGX_E1", &ggx.e1, &g.e1),
            ("GGX_E5", &ggx.e5, &g.e5),
            ("GGX_AVG1", &ggx.avg1, &g.avg1),
            ("GGX_AVG5", &ggx.avg5, &g.avg5),
            ("SHEEN_E", &sheen.e, &s.e),
        ];
        let same = |a: &[f32], b: &[f32]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-6);
        if tables.iter().all(|(_, computed, embedded)| same(computed, embedded)) {
            return;
        }
        let mut src = String::from(
            "//! The albedo tables of `GgxAlbedo` and `SheenAlbedo` (`f32` bits), as their `compute` makes\n\
             //! them: written by the test `embedded_albedo_tables_are_the_computed_ones`; do not edit.\n",
        );
        for (name, computed, _) in &tables {
            src += &format!("\npub(super) const {name}: [u32; {}] = [\n", computed.len());
            for row in computed.chunks(8) {
                let row: Vec<String> = row.iter().map(|v| format!("0x{:08x}", v.to_bits())).collect();
                src += &format!("    {},\n", row.join(", "));
            }
            src += "];\n";
        }
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/albedo_tables.rs");
        let written = std::fs::write(&path, src).is_ok();
        panic!(
            "the embedded albedo tables differ from the computed ones; {} (copy it over \
             worker/src/render/microfacet/albedo_tables.rs, then cargo fmt)",
            if written { format!("the new file is {}", path.display()) } else { "could not write the new file".into() }
        );
    }

    #[test]
    fn ggx_albedo_tables_match_monte_carlo() {
        // E1, E5 (bilinearly interpolated, at points between the table's nodes) and E1's
        // cosine-weighted average against independent Monte Carlo estimates (2e5 random
        // visible-normal samples each, seed 21; mu ~ sqrt(u) for the average): within
        // 4 sigma + 3e-3.
        let tables = GgxAlbedo::get();
        let mut rng = chi2::TestRng::new(21);
        let n = 200_000;
        let estimate = |ggx: MicrofacetDistribution, mu_of: &mut dyn FnMut() -> f32, rng: &mut chi2::TestRng| {
            let (mut s1, mut s5, mut q1, mut q5) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for _ in 0..n {
                let mu: f32 = mu_of();
                let wo = dir(mu, 0.0);
                let wm = ggx.sample_wm(wo, rng.uniform_2d());
                let cos_h = wo.dot(wm);
                let wi = -wo + 2.0 * cos_h * wm;
                if !(wi.z > 0.0) || !(cos_h > 0.0) {
                    continue;
                }
                let w = f64::from(ggx.g(wo, wi, wm) / ggx.g1(wo, wm));
                let w5 = w * f64::from((1.0 - cos_h).powi(5));
                (s1, s5, q1, q5) = (s1 + w, s5 + w5, q1 + w * w, q5 + w5 * w5);
            }
            let nf = n as f64;
            let sigma = |s: f64, q: f64| ((q / nf - (s / nf).powi(2)).max(0.0) / nf).sqrt();
            ((s1 / nf, sigma(s1, q1)), (s5 / nf, sigma(s5, q5)))
        };
        let mut failures = Vec::new();
        for roughness in [0.1f32, 0.3, 0.55, 0.8, 0.97] {
            let alpha = roughness * roughness;
            let ggx = MicrofacetDistribution::ggx(alpha);
            for mu in [0.05f32, 0.2, 0.5, 0.9] {
                let ((m1, s1), (m5, s5)) = estimate(ggx, &mut || mu, &mut rng);
                let (e1, e5) = tables.e(mu, alpha);
                if (f64::from(e1) - m1).abs() > 4.0 * s1 + 3e-3 || (f64::from(e5) - m5).abs() > 4.0 * s5 + 3e-3 {
                    failures.push(format!(
                        "roughness {roughness}, mu {mu}: E1 {e1} vs {m1} +- {s1}, E5 {e5} vs {m5} +- {s5}"
                    ));
                }
            }
            let mut avg_rng = chi2::TestRng::new(22 + (roughness * 100.0) as u64);
            let ((a1, s1), _) = estimate(ggx, &mut || avg_rng.uniform().sqrt().max(1e-4), &mut rng);
            let (t1, _) = tables.average(alpha);
            if (f64::from(t1) - a1).abs() > 4.0 * s1 + 3e-3 {
                failures.push(format!("roughness {roughness}: E_avg {t1} vs {a1} +- {s1}"));
            }
        }
        assert!(failures.is_empty(), "{}", failures.join("\n"));
        // Smooth lobes lose nothing; the roughest keeps only about 31% at normal incidence.
        assert!((tables.e(1.0, 0.0).0 - 1.0).abs() < 1e-3);
        assert!((0.28..0.34).contains(&tables.e(1.0, 1.0).0), "{:?}", tables.e(1.0, 1.0));
    }
}
