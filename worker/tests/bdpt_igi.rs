//! Bidirectional path tracing and instant global illumination against analytic answers, the
//! Mitsuba reference, the path tracer, and themselves split into units.
//!
//! Statistical tests fix their seeds. BDPT's light-tracing splats are not in the film's variance
//! layer, and IGI's error is correlated across pixels through the shared VPLs, so their noise is
//! measured from independent renders (different seeds): the variance of a pixel's mean is the
//! sample variance over the renders divided by their number, and a block's variance is the sum
//! of its pixels' variances over the squared pixel count (for BDPT; the covariance that one light
//! path's splats put between pixels is neglected). IGI's pixels share VPLs, so its block
//! variances come from the spread of the seeds' block means instead. Bounds are in those sigmas.

mod common;

use common::{file_scene, glb_scene, luminance, mean_rgb, reference};
use pathfarm_common::film::{Film, ImageLayers};
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::scene::Scene;
use pathfarm_common::scene::demo::{caustics_glb, cornell_demo_glb, furnace_glb, point_furnace_glb};
use pathfarm_worker::render::{Renderer, render_local};
use std::sync::OnceLock;
use std::time::Instant;

fn path(max_depth: u32) -> IntegratorSettings {
    IntegratorSettings::Path {
        max_depth,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    }
}

fn bdpt(max_depth: u32) -> IntegratorSettings {
    IntegratorSettings::Bdpt { max_depth, mis: MisHeuristic::Power, rr_depth: 5, strategy: None }
}

fn igi(g_limit: f32, bias_compensation: bool) -> IntegratorSettings {
    IntegratorSettings::Igi { vpls: 64, vpl_sets: 4, g_limit, bias_compensation, max_depth: 8 }
}

fn settings(w: u32, spp: u32, integrator: IntegratorSettings, seed: u64) -> RenderSettings {
    let mut s = RenderSettings::new(w, w, spp);
    s.integrator = integrator;
    s.seed = seed;
    s
}

fn film(scene: &Scene, s: &RenderSettings) -> Film {
    render_local(&Renderer::new(scene, s).expect("renderer"), |_, _| {})
}

fn render(scene: &Scene, s: &RenderSettings) -> ImageLayers {
    film(scene, s).resolve()
}

fn lum(p: [f32; 3]) -> f64 {
    luminance([p[0].into(), p[1].into(), p[2].into()])
}

/// The mean of renders with `seeds` and the variance of each pixel's luminance in that mean.
struct Estimate {
    rgb: Vec<[f64; 3]>,
    var: Vec<f64>,
    /// Luminance of each seed's render (empty for a single render).
    seeds: Vec<Vec<f64>>,
}

impl Estimate {
    fn from_seeds(scene: &Scene, base: &RenderSettings, seeds: &[u64]) -> Self {
        let imgs: Vec<ImageLayers> = seeds
            .iter()
            .map(|&seed| {
                let mut s = base.clone();
                s.seed = seed;
                render(scene, &s)
            })
            .collect();
        let k = imgs.len() as f64;
        let n = imgs[0].rgb.len();
        let mut rgb = vec![[0.0; 3]; n];
        let mut var = vec![0.0; n];
        for i in 0..n {
            for img in &imgs {
                for (sum, v) in rgb[i].iter_mut().zip(img.rgb[i]) {
                    *sum += f64::from(v) / k;
                }
            }
            let m = luminance(rgb[i]);
            let ss: f64 = imgs.iter().map(|img| (lum(img.rgb[i]) - m).powi(2)).sum();
            var[i] = ss / (k - 1.0) / k;
        }
        let seeds = imgs.iter().map(|img| img.rgb.iter().map(|&p| lum(p)).collect()).collect();
        Self { rgb, var, seeds }
    }

    /// Mean luminance of each `block x block` block of a `w x w` image and the variance of that
    /// mean from the spread of the seeds' block means (which keeps the covariance of pixels that
    /// share random numbers, as IGI's pixels share VPLs).
    fn blocks_between_seeds(&self, w: usize, block: usize) -> Vec<(f64, f64)> {
        let k = self.seeds.len() as f64;
        let mut out = Vec::new();
        for by in 0..w / block {
            for bx in 0..w / block {
                let means: Vec<f64> = self
                    .seeds
                    .iter()
                    .map(|img| {
                        let mut m = 0.0;
                        for y in by * block..(by + 1) * block {
                            for x in bx * block..(bx + 1) * block {
                                m += img[y * w + x] / (block * block) as f64;
                            }
                        }
                        m
                    })
                    .collect();
                let mean = means.iter().sum::<f64>() / k;
                let var = means.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (k - 1.0) / k;
                out.push((mean, var));
            }
        }
        out
    }

    /// A single render with its variance layer (valid for camera-only estimators).
    fn from_image(img: &ImageLayers) -> Self {
        Self {
            rgb: img.rgb.iter().map(|p| [p[0].into(), p[1].into(), p[2].into()]).collect(),
            var: img.variance.iter().map(|&v| f64::from(v)).collect(),
            seeds: Vec::new(),
        }
    }

    fn lum(&self) -> Vec<f64> {
        self.rgb.iter().map(|&p| luminance(p)).collect()
    }

    fn mean_rgb(&self) -> [f64; 3] {
        let n = self.rgb.len() as f64;
        let mut m = [0.0; 3];
        for p in &self.rgb {
            for c in 0..3 {
                m[c] += p[c] / n;
            }
        }
        m
    }
}

/// Largest |a - b| / sigma over `block x block` pixel blocks of two `w x w` luminance images;
/// `var_a`, `var_b` are per-pixel variances, `floor` an absolute sigma added in quadrature.
fn worst_block_z(w: usize, block: usize, a: &[f64], var_a: &[f64], b: &[f64], var_b: &[f64], floor: f64) -> f64 {
    let mut worst = 0.0f64;
    let n = (block * block) as f64;
    for by in 0..w / block {
        for bx in 0..w / block {
            let (mut ma, mut mb, mut v) = (0.0, 0.0, 0.0);
            for y in by * block..(by + 1) * block {
                for x in bx * block..(bx + 1) * block {
                    let i = y * w + x;
                    ma += a[i] / n;
                    mb += b[i] / n;
                    v += (var_a[i] + var_b[i]) / (n * n);
                }
            }
            let z = (ma - mb).abs() / (v + floor * floor).sqrt();
            worst = worst.max(z);
        }
    }
    worst
}

/// The Mitsuba Cornell reference box-downsampled to `w x w` (our box-filtered pixel at `w` is the
/// mean of the reference pixels it covers): per-pixel RGB.
fn mitsuba_reference(w: usize) -> Vec<[f64; 3]> {
    let reference =
        pathfarm_common::film::read_exr(&reference().join("cornell_mitsuba_box_16384spp.exr")).expect("reference exr");
    assert_eq!((reference.width, reference.height), (256, 256));
    let ch: Vec<&[f32]> = ["R", "G", "B"].iter().map(|c| reference.get(c).expect("channel")).collect();
    let f = 256 / w;
    let mut out = vec![[0.0; 3]; w * w];
    for y in 0..256 {
        for x in 0..256 {
            for c in 0..3 {
                out[(y / f) * w + x / f][c] += f64::from(ch[c][y * 256 + x]) / (f * f) as f64;
            }
        }
    }
    out
}

/// The white furnace (L = Le / (1 - rho)) and pbrt's point light in a sphere
/// (L = rho / pi * I / R^2 / (1 - rho)), no depth limit: the image mean is within 1% of the
/// answer (16 x 16 x 64 spp, seeds 1 and 2; the deviations seen are 0.05% to 0.2%, so 1% is
/// several standard errors while a missing strategy or a wrong weight is off by far more).
#[test]
fn bdpt_furnaces_match_analytic_answers() {
    let t0 = Instant::now();
    for rho in [0.5f32, 0.9] {
        let t = Instant::now();
        let scene = glb_scene(&furnace_glb(1.0, rho));
        let img = render(&scene, &settings(16, 64, bdpt(0), 1));
        let expected = f64::from(1.0 / (1.0 - rho));
        eprintln!("furnace rho {rho}: {:?} vs {expected} ({:.1} s)", mean_rgb(&img), t.elapsed().as_secs_f64());
        for (c, m) in mean_rgb(&img).into_iter().enumerate() {
            let rel = (m - expected).abs() / expected;
            assert!(rel < 0.01, "rho {rho} channel {c}: mean {m:.5}, expected {expected:.5} ({:.2}% off)", rel * 100.0);
        }
    }
    let (i, r, rho) = (3.0f32, 2.0f32, 0.5f32);
    let scene = glb_scene(&point_furnace_glb(i, rho, r));
    let img = render(&scene, &settings(16, 64, bdpt(0), 2));
    let expected = f64::from(rho / std::f32::consts::PI * i / (r * r) / (1.0 - rho));
    let m = mean_rgb(&img)[1];
    eprintln!("point furnace: {m} vs {expected}");
    let rel = (m - expected).abs() / expected;
    assert!(rel < 0.01, "point light: mean {m:.5}, expected {expected:.5} ({:.2}% off)", rel * 100.0);
    eprintln!("furnaces: {:.1} s", t0.elapsed().as_secs_f64());
}

/// The strategies of one path length sum to the full estimator: rendering each `(s, t)` of
/// lengths 1 to 3 segments alone (same seed, so the same subpaths) and adding the images gives
/// the max-depth-3 render to rounding (1e-4 relative on the mean), and `(1, 1)` is empty.
#[test]
fn bdpt_strategies_sum_to_the_whole() {
    let scene = glb_scene(&cornell_demo_glb());
    let whole = mean_rgb(&render(&scene, &settings(32, 4, bdpt(3), 3)));
    let mut sum = [0.0f64; 3];
    for len in 2..=4u32 {
        for s in 0..len {
            let t = len - s;
            let i = IntegratorSettings::Bdpt {
                max_depth: 3,
                mis: MisHeuristic::Power,
                rr_depth: 5,
                strategy: Some([s, t]),
            };
            let m = mean_rgb(&render(&scene, &settings(32, 4, i, 3)));
            if (s, t) == (1, 1) {
                assert_eq!(m, [0.0; 3], "strategy (1, 1) is not used");
            }
            for c in 0..3 {
                sum[c] += m[c];
            }
        }
    }
    for c in 0..3 {
        assert!(
            (sum[c] - whole[c]).abs() <= 1e-4 * whole[c],
            "channel {c}: strategies sum to {}, whole {}",
            sum[c],
            whole[c]
        );
    }
}

/// The Cornell box against Mitsuba 3 (16,384 spp, path, max_depth 8), at 128 x 128 (the
/// reference box-downsampled 2 x 2): 4 seeds x 16 spp of bdpt (max_depth 8). Per-channel image
/// means within 0.5%; every 8 x 8 block within 5 sigma (sigma from the seeds, plus 0.06% of the
/// image mean for the reference's own noise as in `integrators.rs`); 256 blocks at 5 sigma:
/// false alarm below 1e-4 for Gaussian errors.
#[test]
fn bdpt_cornell_box_matches_mitsuba_reference() {
    let t0 = Instant::now();
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let w = 128;
    let ours = Estimate::from_seeds(&scene, &settings(w as u32, 16, bdpt(8), 0), &[9, 10, 11, 12]);
    let reference = mitsuba_reference(w);
    let om = ours.mean_rgb();
    for c in 0..3 {
        let r = reference.iter().map(|p| p[c]).sum::<f64>() / (w * w) as f64;
        let rel = (om[c] - r).abs() / r;
        assert!(rel < 0.005, "channel {c}: bdpt {:.5}, Mitsuba {r:.5} ({:.3}% off)", om[c], rel * 100.0);
    }
    let ref_lum: Vec<f64> = reference.iter().map(|&p| luminance(p)).collect();
    let zeros = vec![0.0; w * w];
    let z = worst_block_z(w, 8, &ours.lum(), &ours.var, &ref_lum, &zeros, 0.0006 * luminance(om));
    eprintln!("bdpt vs Mitsuba: worst block {z:.2} sigma ({:.1} s)", t0.elapsed().as_secs_f64());
    assert!(z < 5.0, "a block is {z:.1} sigma off the reference");
}

/// Side of the caustics renders.
const CAUSTICS_SIZE: u32 = 32;

/// A long BDPT render of the caustics scene: 32 x 32, 4 seeds x 256 spp (shared by the tests).
fn caustics_reference() -> &'static (Scene, Estimate) {
    static REFERENCE: OnceLock<(Scene, Estimate)> = OnceLock::new();
    REFERENCE.get_or_init(|| {
        let scene = glb_scene(&caustics_glb());
        let est = Estimate::from_seeds(&scene, &settings(CAUSTICS_SIZE, 256, bdpt(8), 0), &[101, 102, 103, 104]);
        (scene, est)
    })
}

/// Caustics (glass sphere, small bright light): path tracing (32 x 32 x 4096 spp, seed 7, its
/// variance layer) and the long BDPT reference agree on each 16 x 16 quarter of the image and
/// on the whole image within 5 sigma (5 comparisons: false alarm about 3e-6 for Gaussian errors).
/// The blocks are large because the path tracer finds light reflected and refracted by the glass
/// only when a BSDF sample hits the small light: with fewer than about a million samples per
/// block its block means are heavy-tailed (mostly low, with rare fireflies), and 8 x 8 blocks of
/// a 64 x 64 x 1024 render differed by up to 18 sigma of its own (underestimated) variance.
#[test]
fn bdpt_and_path_agree_on_caustics() {
    let t0 = Instant::now();
    let (scene, reference) = caustics_reference();
    let w = CAUSTICS_SIZE as usize;
    let p = Estimate::from_image(&render(scene, &settings(CAUSTICS_SIZE, 4096, path(8), 7)));
    let quarters = worst_block_z(w, w / 2, &p.lum(), &p.var, &reference.lum(), &reference.var, 0.0);
    let whole = worst_block_z(w, w, &p.lum(), &p.var, &reference.lum(), &reference.var, 0.0);
    let z = quarters.max(whole);
    eprintln!(
        "caustics: image mean path {:.5}, bdpt {:.5}; worst block {z:.2} sigma ({:.1} s)",
        luminance(p.mean_rgb()),
        luminance(reference.mean_rgb()),
        t0.elapsed().as_secs_f64()
    );
    assert!(z < 5.0, "path and bdpt differ by {z:.1} sigma on a block");
}

/// Pixels that see a light directly, or touch one that does: their error is the anti-aliasing
/// of the light's edge, which every integrator shares, so the error measures leave them out.
/// Found from emission seen directly (path, max depth 1, 16 spp), dilated by one pixel.
fn emitter_mask(scene: &Scene, size: u32) -> Vec<bool> {
    let mut s = RenderSettings::new(size, size, 16);
    s.integrator = IntegratorSettings::Path {
        max_depth: 1,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    let Ok(renderer) = Renderer::new(scene, &s) else { return vec![false; (size * size) as usize] };
    let img = render_local(&renderer, |_, _| {}).resolve();
    let w = size as i64;
    let lit = |x: i64, y: i64| x >= 0 && y >= 0 && x < w && y < w && lum(img.rgb[(y * w + x) as usize]) > 0.0;
    (0..w * w).map(|i| (-1..=1).any(|dy| (-1..=1).any(|dx| lit(i % w + dx, i / w + dy)))).collect()
}

/// Luminance RMSE against `reference` over the pixels not in `mask`.
fn rmse(img: &ImageLayers, reference: &[f64], mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0.0f64);
    for ((&p, &r), &m) in img.rgb.iter().zip(reference).zip(mask) {
        if !m {
            sum += (lum(p) - r).powi(2);
            n += 1.0;
        }
    }
    (sum / n.max(1.0)).sqrt()
}

/// BDPT finds the caustics that path tracing can only reach by hitting the small light through
/// the glass: at the same 32 spp (seeds 21 and 22), BDPT's luminance RMSE and MAE against the
/// long BDPT reference are below path tracing's. The reference's own noise (its mean pixel
/// variance) is subtracted from the mean squared errors; pixels that see the light are left out
/// ([`emitter_mask`]). Measured: bdpt RMSE 0.263 / MAE 0.032, path 0.290 / 0.037. Deterministic
/// (fixed seeds): the equal-*time* comparison depends on the machine and is printed by
/// `cargo run --release -p pathfarm-worker --example igi_sequence`, not asserted in a test (it
/// was a timed test; since glass keeps its internal reflections, BDPT's longer subpaths cost
/// more and path tracing about matches it at equal time on this scene).
#[test]
fn bdpt_beats_path_on_caustics_at_equal_samples() {
    let (scene, reference) = caustics_reference();
    let ref_lum = reference.lum();
    let b = render(scene, &settings(CAUSTICS_SIZE, 32, bdpt(8), 21));
    let p = render(scene, &settings(CAUSTICS_SIZE, 32, path(8), 22));
    let mask = emitter_mask(scene, CAUSTICS_SIZE);
    // The reference's own variance adds to both mean squared errors; take it out.
    let kept = mask.iter().filter(|&&m| !m).count() as f64;
    let ref_var = reference.var.iter().zip(&mask).filter(|(_, m)| !**m).map(|(v, _)| v).sum::<f64>() / kept;
    let corrected = |e: f64| (e * e - ref_var).max(0.0).sqrt();
    let (eb, ep) = (corrected(rmse(&b, &ref_lum, &mask)), corrected(rmse(&p, &ref_lum, &mask)));
    let mae = |img: &ImageLayers| {
        let pairs = img.rgb.iter().zip(&ref_lum).zip(&mask).filter(|(_, m)| !**m);
        pairs.map(|((&p, &r), _)| (lum(p) - r).abs()).sum::<f64>() / kept
    };
    let (mb, mp) = (mae(&b), mae(&p));
    eprintln!(
        "caustics at 32 spp: bdpt RMSE {eb:.4} MAE {mb:.4}, path RMSE {ep:.4} MAE {mp:.4} (reference's noise {:.4} taken out of the RMSE)",
        ref_var.sqrt()
    );
    assert!(eb < ep && mb < mp, "bdpt (RMSE {eb:.4}, MAE {mb:.4}) not below path (RMSE {ep:.4}, MAE {mp:.4})");
}

/// IGI with bias compensation agrees with path tracing and with the Mitsuba reference on the
/// Cornell box: 64 x 64 (reference downsampled 4 x 4), igi 8 seeds x 8 spp, our path tracer
/// 128 spp (seed 8, its variance layer). IGI's pixels share VPLs, so its block variance comes
/// from the spread of the 8 seeds' block means (7 degrees of freedom): every 16 x 16 block and
/// the whole image within 6.5 of those sigmas of each (2 x 17 comparisons; Student t with 7 dof
/// exceeds 6.5 with probability 3.3e-4, family-wise false alarm about 1%). The clamped estimator
/// (same seeds, g_limit 1, 3.5% dark) must fail the same check.
#[test]
fn igi_with_compensation_matches_path_and_reference() {
    let t0 = Instant::now();
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let w = 64;
    let reference = mitsuba_reference(w);
    let ref_lum: Vec<f64> = reference.iter().map(|&p| luminance(p)).collect();
    let ref_mean = ref_lum.iter().sum::<f64>() / (w * w) as f64;
    let p = Estimate::from_image(&render(&scene, &settings(w as u32, 128, path(8), 8)));
    let block_mean = |img: &[f64], var: Option<&[f64]>, block: usize, bx: usize, by: usize| {
        let n = (block * block) as f64;
        let (mut m, mut v) = (0.0, 0.0);
        for y in by * block..(by + 1) * block {
            for x in bx * block..(bx + 1) * block {
                m += img[y * w + x] / n;
                v += var.map_or(0.0, |var| var[y * w + x]) / (n * n);
            }
        }
        (m, v)
    };
    let check = |bias_compensation: bool| {
        let seeds: Vec<u64> = (1..=8).collect();
        let est = Estimate::from_seeds(&scene, &settings(w as u32, 8, igi(1.0, bias_compensation), 0), &seeds);
        let (mut z_ref, mut z_path) = (0.0f64, 0.0f64);
        for block in [16, w] {
            for (i, (m, v)) in est.blocks_between_seeds(w, block).into_iter().enumerate() {
                let (bx, by) = (i % (w / block), i / (w / block));
                let (r, _) = block_mean(&ref_lum, None, block, bx, by);
                let (pm, pv) = block_mean(&p.lum(), Some(&p.var), block, bx, by);
                z_ref = z_ref.max((m - r).abs() / (v + (0.0006 * ref_mean).powi(2)).sqrt());
                z_path = z_path.max((m - pm).abs() / (v + pv).sqrt());
            }
        }
        (luminance(est.mean_rgb()) / ref_mean - 1.0, z_ref, z_path)
    };
    let (rel, z, zp) = check(true);
    let (rel_clamped, z_clamped, zp_clamped) = check(false);
    eprintln!(
        "igi (g_limit 1) vs Mitsuba / vs path: compensated {:+.3}%, worst block {z:.2} / {zp:.2} sigma; clamped \
         {:+.3}%, worst block {z_clamped:.2} / {zp_clamped:.2} sigma ({:.1} s)",
        rel * 100.0,
        rel_clamped * 100.0,
        t0.elapsed().as_secs_f64()
    );
    assert!(z < 6.5, "compensated igi is {:+.3}% / {z:.1} sigma off Mitsuba", rel * 100.0);
    assert!(zp < 6.5, "compensated igi is {zp:.1} sigma off path tracing on a block");
    assert!(z_clamped > 6.5 && zp_clamped > 6.5, "the clamped estimator should be detectably dark");
}

/// Clamping the geometry term loses energy, less as the clamp rises: the Cornell box (64 x 64 x
/// 8 spp, seed 5, the same random numbers for every g_limit, so the comparison is exact) without
/// compensation, against the compensated render. The loss shrinks strictly as g_limit grows, is
/// large (> 3%) at g_limit 0.25 and small (< 1%) at 64.
#[test]
fn igi_clamping_loses_less_energy_as_g_limit_grows() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let mean = |i| luminance(mean_rgb(&render(&scene, &settings(64, 8, i, 5))));
    let full = mean(igi(1.0, true));
    let mut losses = Vec::new();
    for g in [0.25f32, 1.0, 4.0, 16.0, 64.0] {
        let loss = 1.0 - mean(igi(g, false)) / full;
        eprintln!("g_limit {g:>5}: energy lost {:.3}%", loss * 100.0);
        losses.push(loss);
    }
    for w in losses.windows(2) {
        assert!(w[1] < w[0], "loss did not shrink: {losses:?}");
    }
    assert!(losses[0] > 0.03 && losses[4] < 0.01, "{losses:?}");
}

/// Splitting a render into tiles and passes and merging gives the same radiance bits as another
/// split: tile size 8 with one-sample passes vs. tile size 32 with doubling passes, for every
/// integrator (44 x 36 pixels, so tiles are partial; bdpt on the caustics scene, with splats).
/// The exact channels (radiance, luminance, weights, hits) are the same bits; the AOV means,
/// folded per pass, agree within their rounding (a few steps of 2^-15). The units of one split
/// merged tile by tile in reverse order (each tile's passes in order, as the farm folds them)
/// give every bit of that split's local render, AOVs included.
#[test]
fn every_integrator_is_split_invariant() {
    let cornell = glb_scene(&cornell_demo_glb());
    let caustics = glb_scene(&caustics_glb());
    let cases = [
        (
            "direct",
            &cornell,
            IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: LightSampling::SolidAngle },
        ),
        ("path", &cornell, path(8)),
        ("bdpt", &caustics, bdpt(8)),
        (
            "bdpt balance",
            &caustics,
            IntegratorSettings::Bdpt { max_depth: 0, mis: MisHeuristic::Balance, rr_depth: 2, strategy: None },
        ),
        (
            "igi",
            &cornell,
            IntegratorSettings::Igi { vpls: 8, vpl_sets: 3, g_limit: 1.0, bias_compensation: true, max_depth: 8 },
        ),
    ];
    for (name, scene, integrator) in cases {
        let mut a = RenderSettings::new(44, 36, 7);
        a.integrator = integrator;
        a.seed = 17;
        a.tile_size = 8;
        a.passes = PassSchedule::Fixed { spp: 1 };
        let mut b = a.clone();
        b.tile_size = 32;
        b.passes = PassSchedule::Doubling { first: 1, max: 64 };
        let (fa, fb) = (film(scene, &a), film(scene, &b));
        assert!(fa.sums.iter().any(|p| p.rgb != [0; 3]), "{name}: empty film");
        assert_eq!(fa.sums.len(), fb.sums.len());
        for (i, (p, q)) in fa.sums.iter().zip(&fb.sums).enumerate() {
            let exact = |p: &pathfarm_common::film::PixelSums| (p.rgb, p.lum, p.lum_sq, p.weight, p.hits);
            assert_eq!(exact(p), exact(q), "{name}: pixel {i}: the two splits' exact sums differ");
            for c in 0..3 {
                assert!(p.albedo[c].abs_diff(q.albedo[c]) <= 8, "{name}: pixel {i} albedo {p:?} {q:?}");
                assert!(p.normal[c].abs_diff(q.normal[c]) <= 8, "{name}: pixel {i} normal {p:?} {q:?}");
            }
            assert!(
                p.hits == 0 || (p.depth() - q.depth()).abs() <= 1e-5 * p.depth().abs().max(1.0),
                "{name}: pixel {i} depth"
            );
        }
        // The units of split `b` rendered by a fresh renderer in reverse order and merged by hand
        // (as a farm might receive them) give the same film too.
        let renderer = Renderer::new(scene, &b).expect("renderer");
        let plan = b.plan();
        let mut fc = Film::new(b.width, b.height);
        // Reverse order of tiles; each tile's passes in pass order (the farm folds them so: the
        // AOV means are merged in that order, the radiance sums in any).
        let keys: Vec<_> = plan.units().collect();
        let mut splatted = false;
        for tile in (0..plan.tiles.len() as u32).rev() {
            for key in keys.iter().filter(|k| k.tile == tile) {
                let r = renderer.render_unit(plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
                fc.add_tile(&r.accum);
                if let Some(sp) = &r.splats {
                    splatted |= !sp.is_empty();
                    fc.add_splats(sp);
                }
            }
        }
        if name.starts_with("bdpt") {
            assert!(splatted, "{name}: no splats");
        }
        assert!(fc == fb, "{name}: merging the units in reverse tile order differs");
        let (ia, ib) = (fa.resolve(), fb.resolve());
        let bits = |i: &ImageLayers| i.rgb.iter().flat_map(|p| p.map(f32::to_bits)).collect::<Vec<u32>>();
        assert_eq!(bits(&ia), bits(&ib), "{name}: resolved images differ");
    }
}

/// Delta lights in BDPT: the MIS scene (glossy strips from rough to near mirror, two area
/// lights) with a spot light and a directional light added. Path tracing (32 x 32 x 256 spp, seed
/// 31, its variance layer) and bdpt (4 seeds x 64 spp) agree on every 8 x 8 block and on the
/// image mean within 5 sigma (17 comparisons: false alarm about 1e-5 for Gaussian errors).
#[test]
fn bdpt_matches_path_with_spot_and_directional_lights() {
    use glam::Vec3;
    use pathfarm_common::scene::{PunctualKind, PunctualLight};
    let mut scene = glb_scene(&pathfarm_common::scene::demo::mis_glb());
    // Mean luminance clamped at 5 (the small light, seen directly, would dominate the mean).
    let lit = |img: &[f64]| img.iter().map(|v| v.min(5.0)).sum::<f64>() / img.len() as f64;
    let without = lit(&Estimate::from_image(&render(&scene, &settings(32, 16, path(8), 30))).lum());
    scene.lights.push(PunctualLight {
        name: "spot".into(),
        kind: PunctualKind::Spot { inner_cone: 0.3, outer_cone: 0.5 },
        intensity: Vec3::new(60.0, 50.0, 40.0),
        position: Vec3::new(0.6, 1.5, 0.3),
        direction: Vec3::new(-0.2, -1.0, -0.1).normalize(),
        range: None,
    });
    scene.lights.push(PunctualLight {
        name: "sun".into(),
        kind: PunctualKind::Directional,
        intensity: Vec3::new(2.0, 2.4, 3.2),
        position: Vec3::ZERO,
        direction: Vec3::new(0.4, -1.0, -0.3).normalize(),
        range: None,
    });
    let w = 32;
    let p = Estimate::from_image(&render(&scene, &settings(w as u32, 256, path(8), 31)));
    let b = Estimate::from_seeds(&scene, &settings(w as u32, 64, bdpt(8), 0), &[32, 33, 34, 35]);
    let blocks = worst_block_z(w, 8, &p.lum(), &p.var, &b.lum(), &b.var, 0.0);
    let whole = worst_block_z(w, w, &p.lum(), &p.var, &b.lum(), &b.var, 0.0);
    eprintln!(
        "delta lights: path {:.5}, bdpt {:.5}; worst block {blocks:.2} sigma, image {whole:.2} sigma",
        luminance(p.mean_rgb()),
        luminance(b.mean_rgb())
    );
    let with = lit(&p.lum());
    assert!(with > 1.5 * without, "the delta lights hardly light the scene ({without:.4} without, {with:.4} with)");
    assert!(blocks < 5.0 && whole < 5.0, "path and bdpt differ: blocks {blocks:.1}, image {whole:.1} sigma");
}

/// The CLI renders one BDPT strategy (`--bdpt-strategy s,t`) and the IGI flags, and rejects a
/// strategy that does not exist or does not parse with a message naming it.
#[test]
fn cli_bdpt_strategy_and_igi_flags() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene_path = dir.path().join("demo.glb");
    std::fs::write(&scene_path, cornell_demo_glb()).expect("write scene");
    let run = |extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_pathfarm-worker"))
            .arg("render")
            .arg(&scene_path)
            .args(["--width", "16", "--height", "16", "--spp", "2", "--quiet", "--threads", "1", "--out"])
            .arg(dir.path().join("out.exr"))
            .args(extra)
            .output()
            .expect("run pathfarm-worker")
    };
    let ok = run(&["--integrator", "bdpt", "--bdpt-strategy", "1,2"]);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let ok =
        run(&["--integrator", "igi", "--vpls", "4", "--vpl-sets", "2", "--g-limit", "2", "--bias-compensation", "on"]);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    for (bad, needle) in [("0,1", "strategy"), ("1;2", "s,t"), ("1,x", "\"x\"")] {
        let out = run(&["--integrator", "bdpt", "--bdpt-strategy", bad]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(needle), "--bdpt-strategy {bad}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
}

/// BDPT refuses an orthographic camera (light paths cannot be connected to it) and a
/// single-strategy MIS setting, with messages that say why; IGI accepts both cameras.
#[test]
fn bdpt_refuses_what_it_cannot_do() {
    let mut scene = glb_scene(&cornell_demo_glb());
    scene.cameras[0].projection = pathfarm_common::scene::Projection::Orthographic { xmag: 1.0, ymag: 1.0 };
    let err = Renderer::new(&scene, &settings(16, 1, bdpt(8), 0)).err().expect("orthographic refused");
    assert!(err.to_string().contains("perspective"), "{err}");
    assert!(Renderer::new(&scene, &settings(16, 1, igi(1.0, true), 0)).is_ok());
    let light_only = IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Light, rr_depth: 5, strategy: None };
    let err = Renderer::new(&glb_scene(&cornell_demo_glb()), &settings(16, 1, light_only, 0)).err().expect("refused");
    assert!(err.to_string().contains("mis"), "{err}");
}

/// A glTF mirror (metallic 1, roughness 0: a delta lobe, not a glossy one) on the Cornell box
/// floor, 40 x 40, max depth 8: path (1 render, 256 spp, seed 41, its variance layer), bdpt and
/// igi (compensated, g_limit 10; 8 seeds x 8 spp each, sigma from the spread of the seeds'
/// region means, 7 dof) agree on the mean luminance of the mirror's pixels (those whose albedo
/// AOV is the mirror's base colour) within 6.5 sigma of the difference (Student t with 7 dof
/// exceeds 6.5 with probability 3.3e-4; 2 comparisons). IGI used to connect its VPLs to the
/// 1e-3 GGX lobe: the region came out 75% too dark, with fireflies (its sigma inflated so much
/// that the mean still passed at 4.2 sigma), so IGI must also be within 10% of path tracing.
/// No pixel of any IGI render may exceed 1.02 times the light's luminance (14.40): the pixels
/// that see the light read its emission plus the little its surface reflects, a mirror with
/// base colour below 1 shows less, and the lit walls are far darker. Before: 43.0.
#[test]
fn gltf_mirror_agrees_across_integrators() {
    let scene = glb_scene(&pathfarm_common::scene::demo::gltf_mirror_glb());
    let base = pathfarm_common::scene::demo::GLTF_MIRROR_BASE;
    let w = 40usize;
    let path_img = render(&scene, &settings(w as u32, 256, path(8), 41));
    let mirror: Vec<usize> =
        (0..w * w).filter(|&i| (0..3).all(|c| (path_img.albedo[i][c] - base[c]).abs() < 1e-3)).collect();
    assert!(mirror.len() > 50, "the mirror covers only {} pixels", mirror.len());
    let n = mirror.len() as f64;
    let region = |lum: &[f64]| mirror.iter().map(|&i| lum[i]).sum::<f64>() / n;
    let p = Estimate::from_image(&path_img);
    let (pm, pv) = (region(&p.lum()), mirror.iter().map(|&i| p.var[i]).sum::<f64>() / (n * n));
    let seeds: Vec<u64> = (42..50).collect();
    let between = |est: &Estimate| {
        let means: Vec<f64> = est.seeds.iter().map(|img| region(img)).collect();
        let k = means.len() as f64;
        let m = means.iter().sum::<f64>() / k;
        (m, means.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (k - 1.0) / k)
    };
    let b = Estimate::from_seeds(&scene, &settings(w as u32, 8, bdpt(8), 0), &seeds);
    let (bm, bv) = between(&b);
    let igi = IntegratorSettings::Igi { vpls: 64, vpl_sets: 4, g_limit: 10.0, bias_compensation: true, max_depth: 8 };
    let i = Estimate::from_seeds(&scene, &settings(w as u32, 8, igi, 0), &seeds);
    let (im, iv) = between(&i);
    let brightest = i.seeds.iter().flatten().fold(0.0f64, |a, &b| a.max(b));
    let z_b = (bm - pm).abs() / (bv + pv).sqrt();
    let z_i = (im - pm).abs() / (iv + pv).sqrt();
    eprintln!(
        "mirror region ({} px): path {pm:.5} +- {:.5}, bdpt {bm:.5} +- {:.5} ({z_b:.2} sigma), igi {im:.5} +- {:.5} \
         ({z_i:.2} sigma, {:+.1}%); brightest igi pixel (luminance) {brightest:.3}",
        mirror.len(),
        pv.sqrt(),
        bv.sqrt(),
        iv.sqrt(),
        (im / pm - 1.0) * 100.0
    );
    assert!(z_b < 6.5, "bdpt is {z_b:.1} sigma off path tracing on the mirror");
    assert!(z_i < 6.5, "igi is {z_i:.1} sigma off path tracing on the mirror ({:+.1}%)", (im / pm - 1.0) * 100.0);
    assert!((im / pm - 1.0).abs() < 0.1, "igi is {:+.1}% off path tracing on the mirror", (im / pm - 1.0) * 100.0);
    let light = luminance([18.387, 13.9873, 6.753_57]);
    assert!(brightest <= 1.02 * light, "an igi pixel reads luminance {brightest:.3} in one render (light {light:.3})");
}
