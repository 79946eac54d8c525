//! Statistical test harness (tests only): Pearson's chi-square test of a sampling routine
//! against its pdf, after pbrt-v3's `bsdfs_test.cpp` / Mitsuba's `ChiSquareTest`.
//!
//! Samples are histogrammed on a grid; the expected count of each cell is the pdf integrated
//! over the cell (adaptive Simpson) times the sample count. Cells whose expected count is below
//! 5 are pooled. The null hypothesis "samples follow the pdf" is rejected below a Sidak-corrected
//! significance level, so a suite of `tests` independent checks keeps an overall level `alpha`.

use glam::{Vec2, Vec3A};
use statrs::distribution::{ChiSquared, ContinuousCDF};
use std::f64::consts::PI;

/// A deterministic random stream for tests (SplitMix64); tests never seed from entropy.
pub struct TestRng(u64);

impl TestRng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
    pub fn uniform_2d(&mut self) -> Vec2 {
        Vec2::new(self.uniform(), self.uniform())
    }
}

/// Options of a chi-square test.
#[derive(Clone, Copy, Debug)]
pub struct Chi2Options {
    pub samples: usize,
    /// Grid resolution along the first (theta, or x) and second (phi, or y) axis.
    pub res: (usize, usize),
    /// Overall significance level of the suite.
    pub alpha: f64,
    /// Number of tests in the suite (Sidak correction).
    pub tests: usize,
    pub seed: u64,
}

impl Default for Chi2Options {
    fn default() -> Self {
        // The figures: about 80 x 160 bins, 10^6 samples, alpha = 0.01.
        Self { samples: 1_000_000, res: (80, 160), alpha: 0.01, tests: 1, seed: 7 }
    }
}

fn simpson_1d(f: &dyn Fn(f64) -> f64, a: f64, b: f64, eps: f64, depth: u32) -> f64 {
    #[allow(clippy::too_many_arguments)] // the classic recursive Simpson signature
    fn rec(f: &dyn Fn(f64) -> f64, a: f64, b: f64, fa: f64, fm: f64, fb: f64, whole: f64, eps: f64, depth: u32) -> f64 {
        let m = 0.5 * (a + b);
        let (lm, rm) = (0.5 * (a + m), 0.5 * (m + b));
        let (flm, frm) = (f(lm), f(rm));
        let left = (m - a) / 6.0 * (fa + 4.0 * flm + fm);
        let right = (b - m) / 6.0 * (fm + 4.0 * frm + fb);
        let both = left + right;
        if depth == 0 || (both - whole).abs() <= 15.0 * eps {
            both + (both - whole) / 15.0
        } else {
            rec(f, a, m, fa, flm, fm, left, eps * 0.5, depth - 1)
                + rec(f, m, b, fm, frm, fb, right, eps * 0.5, depth - 1)
        }
    }
    let (fa, fm, fb) = (f(a), f(0.5 * (a + b)), f(b));
    let whole = (b - a) / 6.0 * (fa + 4.0 * fm + fb);
    rec(f, a, b, fa, fm, fb, whole, eps, depth)
}

/// Integrates `f(x, y)` over a rectangle with nested adaptive Simpson quadrature.
pub fn integrate_2d(f: &dyn Fn(f64, f64) -> f64, x: (f64, f64), y: (f64, f64)) -> f64 {
    let inner = |xv: f64| simpson_1d(&|yv| f(xv, yv), y.0, y.1, 1e-7, 6);
    simpson_1d(&inner, x.0, x.1, 1e-7, 6)
}

/// Spherical coordinates (theta from +z, phi in [0, 2 pi)) of a unit vector.
pub fn to_spherical(w: Vec3A) -> (f64, f64) {
    let theta = f64::from(w.z.clamp(-1.0, 1.0)).acos();
    let mut phi = f64::from(w.y).atan2(f64::from(w.x));
    if phi < 0.0 {
        phi += 2.0 * PI;
    }
    (theta, phi)
}

pub fn from_spherical(theta: f64, phi: f64) -> Vec3A {
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Vec3A::new((st * cp) as f32, (st * sp) as f32, ct as f32)
}

/// Runs Pearson's test of `observed` counts against `expected` counts; returns `Err(report)`
/// if the null hypothesis is rejected.
pub fn pearson(name: &str, observed: &[f64], expected: &[f64], opts: &Chi2Options) -> Result<f64, String> {
    let mut cells: Vec<(f64, f64)> = expected.iter().copied().zip(observed.iter().copied()).collect();
    cells.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut pooled_e, mut pooled_o, mut dof, mut stat) = (0.0, 0.0, 0i64, 0.0);
    for (e, o) in cells {
        if e == 0.0 {
            if o > opts.samples as f64 * 1e-5 {
                return Err(format!("{name}: {o} samples fell in a cell of expected count 0"));
            }
            continue;
        }
        if e < 5.0 {
            pooled_e += e;
            pooled_o += o;
            if pooled_e >= 5.0 {
                stat += (pooled_o - pooled_e) * (pooled_o - pooled_e) / pooled_e;
                dof += 1;
                pooled_e = 0.0;
                pooled_o = 0.0;
            }
            continue;
        }
        stat += (o - e) * (o - e) / e;
        dof += 1;
    }
    if pooled_e > 0.0 || pooled_o > 0.0 {
        stat += (pooled_o - pooled_e) * (pooled_o - pooled_e) / pooled_e.max(1e-9);
        dof += 1;
    }
    dof -= 1;
    if dof < 1 {
        return Err(format!("{name}: too few cells with enough expected samples"));
    }
    let dist = ChiSquared::new(dof as f64).map_err(|e| format!("{name}: {e}"))?;
    let p = 1.0 - dist.cdf(stat);
    let level = 1.0 - (1.0 - opts.alpha).powf(1.0 / opts.tests.max(1) as f64);
    if p < level {
        Err(format!(
            "{name}: chi-square rejects the null hypothesis: stat {stat:.1}, dof {dof}, p = {p:.3e} < {level:.3e} (seed {})",
            opts.seed
        ))
    } else {
        Ok(p)
    }
}

/// Chi-square test of a direction sampler against its solid-angle pdf over the whole sphere.
/// `sample(u)` returns a unit direction, or `None` when sampling fails (counts as no sample; the
/// pdf must then integrate to the success probability).
pub fn test_sphere(
    name: &str,
    mut sample: impl FnMut(Vec2, f32) -> Option<Vec3A>,
    pdf: impl Fn(Vec3A) -> f32,
    opts: &Chi2Options,
) -> Result<f64, String> {
    let (nt, np) = opts.res;
    let mut rng = TestRng::new(opts.seed);
    let mut observed = vec![0.0; nt * np];
    for _ in 0..opts.samples {
        let uc = rng.uniform();
        let u = rng.uniform_2d();
        if let Some(w) = sample(u, uc) {
            if !w.is_finite() || (w.length() - 1.0).abs() > 1e-3 {
                return Err(format!("{name}: sampled direction {w} is not a unit vector"));
            }
            let (t, p) = to_spherical(w);
            let it = ((t / PI * nt as f64) as usize).min(nt - 1);
            let ip = ((p / (2.0 * PI) * np as f64) as usize).min(np - 1);
            observed[it * np + ip] += 1.0;
        }
    }
    // Each cell's integral stays a hair inside the cell: at a cell edge on the horizon,
    // cos(pi / 2) = 6e-17 > 0 reads as the upper hemisphere, and a lobe cut off there would leak
    // expected counts into the cell below (rejecting correct samplers at grazing incidence).
    const INSET: f64 = 1e-9;
    let mut expected = vec![0.0; nt * np];
    for it in 0..nt {
        for ip in 0..np {
            let t = (it as f64 * PI / nt as f64 + INSET, (it + 1) as f64 * PI / nt as f64 - INSET);
            let p = (ip as f64 * 2.0 * PI / np as f64, (ip + 1) as f64 * 2.0 * PI / np as f64);
            let f = |theta: f64, phi: f64| f64::from(pdf(from_spherical(theta, phi))) * theta.sin();
            expected[it * np + ip] = integrate_2d(&f, t, p) * opts.samples as f64;
        }
    }
    pearson(name, &observed, &expected, opts)
}

/// Chi-square test of a sampler of points in the rectangle `[x0, x1] x [y0, y1]` against its
/// area pdf.
pub fn test_rect(
    name: &str,
    mut sample: impl FnMut(Vec2) -> Option<Vec2>,
    pdf: impl Fn(Vec2) -> f32,
    (x0, x1): (f32, f32),
    (y0, y1): (f32, f32),
    opts: &Chi2Options,
) -> Result<f64, String> {
    let (nx, ny) = opts.res;
    let mut rng = TestRng::new(opts.seed);
    let mut observed = vec![0.0; nx * ny];
    for _ in 0..opts.samples {
        if let Some(p) = sample(rng.uniform_2d()) {
            let fx = (p.x - x0) / (x1 - x0);
            let fy = (p.y - y0) / (y1 - y0);
            if !(0.0..=1.0).contains(&fx) || !(0.0..=1.0).contains(&fy) {
                return Err(format!("{name}: sample {p} outside the domain"));
            }
            let ix = ((fx * nx as f32) as usize).min(nx - 1);
            let iy = ((fy * ny as f32) as usize).min(ny - 1);
            observed[ix * ny + iy] += 1.0;
        }
    }
    let (x0, x1, y0, y1) = (f64::from(x0), f64::from(x1), f64::from(y0), f64::from(y1));
    let mut expected = vec![0.0; nx * ny];
    for ix in 0..nx {
        for iy in 0..ny {
            let xr = (x0 + (x1 - x0) * ix as f64 / nx as f64, x0 + (x1 - x0) * (ix + 1) as f64 / nx as f64);
            let yr = (y0 + (y1 - y0) * iy as f64 / ny as f64, y0 + (y1 - y0) * (iy + 1) as f64 / ny as f64);
            let f = |x: f64, y: f64| f64::from(pdf(Vec2::new(x as f32, y as f32)));
            expected[ix * ny + iy] = integrate_2d(&f, xr, yr) * opts.samples as f64;
        }
    }
    pearson(name, &observed, &expected, opts)
}

/// Integral of a solid-angle pdf over the sphere (should be 1, or the success probability).
pub fn sphere_integral(pdf: impl Fn(Vec3A) -> f32) -> f64 {
    let f = |theta: f64, phi: f64| f64::from(pdf(from_spherical(theta, phi))) * theta.sin();
    // Split the domain so narrow lobes are resolved.
    let (nt, np) = (32, 64);
    let mut sum = 0.0;
    for it in 0..nt {
        for ip in 0..np {
            let t = (it as f64 * PI / nt as f64, (it + 1) as f64 * PI / nt as f64);
            let p = (ip as f64 * 2.0 * PI / np as f64, (ip + 1) as f64 * 2.0 * PI / np as f64);
            sum += integrate_2d(&f, t, p);
        }
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uniform_sphere(u: Vec2) -> Vec3A {
        let z = 1.0 - 2.0 * u.x;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = 2.0 * std::f32::consts::PI * u.y;
        Vec3A::new(r * phi.cos(), r * phi.sin(), z)
    }

    #[test]
    fn accepts_a_correct_sampler() {
        let opts = Chi2Options { samples: 200_000, res: (20, 40), ..Default::default() };
        let pdf = |_| 1.0 / (4.0 * std::f32::consts::PI);
        test_sphere("uniform sphere", |u, _| Some(uniform_sphere(u)), pdf, &opts).expect("should pass");
        assert!((sphere_integral(pdf) - 1.0).abs() < 1e-4);
    }

    #[test]
    fn rejects_a_wrong_pdf() {
        // The test must be able to fail: uniform samples against a cosine-weighted pdf.
        let opts = Chi2Options { samples: 200_000, res: (20, 40), ..Default::default() };
        let pdf = |w: Vec3A| if w.z > 0.0 { w.z / std::f32::consts::PI } else { 0.0 };
        let upper = |u: Vec2, _| {
            let w = uniform_sphere(u);
            Some(Vec3A::new(w.x, w.y, w.z.abs()))
        };
        assert!(test_sphere("wrong pdf", upper, pdf, &opts).is_err());
    }

    #[test]
    fn rect_test_accepts_uniform_and_rejects_skewed() {
        let opts = Chi2Options { samples: 100_000, res: (16, 16), ..Default::default() };
        test_rect("uniform square", Some, |_| 1.0, (0.0, 1.0), (0.0, 1.0), &opts).expect("uniform");
        let skewed = |u: Vec2| Some(Vec2::new(u.x * u.x, u.y));
        assert!(test_rect("skewed", skewed, |_| 1.0, (0.0, 1.0), (0.0, 1.0), &opts).is_err());
    }
}
