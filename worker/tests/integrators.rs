//! The integrators against analytic answers and against each other.
//!
//! Statistical tests use fixed seeds; bounds are stated in sigmas of the estimator's own standard
//! error (from the variance layer) unless an absolute tolerance is stated.

mod common;

use common::*;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::{cornell_demo_glb, furnace_glb, glass_furnace_glb, point_furnace_glb};

fn path(max_depth: u32, rr_depth: u32) -> IntegratorSettings {
    IntegratorSettings::Path {
        max_depth,
        rr_depth,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    }
}

fn settings(w: u32, spp: u32, integrator: IntegratorSettings, seed: u64) -> RenderSettings {
    let mut s = RenderSettings::new(w, w, spp);
    s.integrator = integrator;
    s.seed = seed;
    s
}

/// The white furnace (interior of a sphere, emission Le, Lambertian albedo rho): L = Le / (1 - rho)
/// everywhere. 32 x 32 pixels x 128 spp, seed 1, no depth limit (roulette only): the image mean
/// is within 1% of the answer.
#[test]
fn furnace_emission_matches_le_over_one_minus_rho() {
    for rho in [0.3f32, 0.5, 0.9] {
        let le = 1.0f32;
        let scene = glb_scene(&furnace_glb(le, rho));
        let img = render(&scene, &settings(32, 128, path(0, 3), 1));
        let expected = f64::from(le / (1.0 - rho));
        for (c, m) in mean_rgb(&img).into_iter().enumerate() {
            let rel = (m - expected).abs() / expected;
            assert!(rel < 0.01, "rho {rho} channel {c}: mean {m:.5}, expected {expected:.5} ({:.2}% off)", rel * 100.0);
        }
    }
}

/// A lossless glass sphere inside an emitting, black enclosure (radiance 1): every pixel must
/// read 1 whatever the path does inside the glass (Fresnel reflection, total internal
/// reflection). 48 x 48 x 64 spp, seed 11, no depth limit; the mean of the pixels that see the
/// sphere's centre, and of those that see its rim (grazing incidence), within 1% for path,
/// bdpt and igi (glass reflects and refracts only, so IGI's VPLs play no part).
#[test]
fn glass_furnace_keeps_every_internal_reflection() {
    let scene = glb_scene(&glass_furnace_glb(1.0));
    let w = 48usize;
    let integrators = [
        ("path", path(0, 3)),
        ("bdpt", IntegratorSettings::Bdpt { max_depth: 0, mis: MisHeuristic::Balance, rr_depth: 3, strategy: None }),
        ("igi", IntegratorSettings::Igi { vpls: 4, vpl_sets: 1, g_limit: 10.0, bias_compensation: true, max_depth: 0 }),
    ];
    for (name, integrator) in integrators {
        let img = render(&scene, &settings(w as u32, 64, integrator, 11));
        // The sphere (radius 0.3 at distance 0.9) covers a disc of radius ~0.3 / 0.9 / tan(0.35)
        // = 0.91 of the half-image; the rim is the ring between 0.75 and 0.88 of it.
        let (mut centre, mut nc, mut rim, mut nr) = (0.0f64, 0, 0.0f64, 0);
        for y in 0..w {
            for x in 0..w {
                let dx = (x as f64 + 0.5) / w as f64 * 2.0 - 1.0;
                let dy = (y as f64 + 0.5) / w as f64 * 2.0 - 1.0;
                let r = (dx * dx + dy * dy).sqrt();
                let v = f64::from(img.rgb[y * w + x][1]);
                if r < 0.4 {
                    centre += v;
                    nc += 1;
                } else if (0.75..0.88).contains(&r) {
                    rim += v;
                    nr += 1;
                }
            }
        }
        let (centre, rim) = (centre / f64::from(nc), rim / f64::from(nr));
        assert!((centre - 1.0).abs() < 0.01, "{name}: centre of the glass sphere reads {centre:.4}, expected 1");
        assert!((rim - 1.0).abs() < 0.01, "{name}: rim of the glass sphere reads {rim:.4}, expected 1");
    }
}

/// pbrt's analytic scene: a point light of intensity I at the centre of a Lambertian sphere of
/// radius R: L = rho / pi * I / R^2 / (1 - rho). 32 x 32 x 128 spp, seed 2, within 1%.
#[test]
fn furnace_point_light_matches_analytic_answer() {
    for rho in [0.3f32, 0.5, 0.9] {
        let (i, r) = (3.0f32, 2.0f32);
        let scene = glb_scene(&point_furnace_glb(i, rho, r));
        let img = render(&scene, &settings(32, 128, path(0, 3), 2));
        let expected = f64::from(rho / std::f32::consts::PI * i / (r * r) / (1.0 - rho));
        let m = mean_rgb(&img)[1];
        let rel = (m - expected).abs() / expected;
        assert!(rel < 0.01, "rho {rho}: mean {m:.5}, expected {expected:.5} ({:.2}% off)", rel * 100.0);
    }
}

/// `path --max-depth 2` equals `direct` in expectation (Cornell demo box with Blinn and
/// Ashikhmin-Shirley boxes; 64 x 64 x 64 spp, different seeds; |difference| < 4 standard errors).
#[test]
fn path_with_two_segments_equals_direct() {
    let scene = glb_scene(&cornell_demo_glb());
    let direct = IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: LightSampling::SolidAngle };
    let (a, sa) = mean_luminance_and_stderr(&render(&scene, &settings(64, 64, direct, 3)));
    let (b, sb) = mean_luminance_and_stderr(&render(&scene, &settings(64, 64, path(2, 3), 4)));
    let bound = 4.0 * (sa * sa + sb * sb).sqrt();
    assert!((a - b).abs() < bound, "direct {a:.5} vs path(2) {b:.5}, bound {bound:.5}");
}

/// Russian roulette changes noise, not the mean: roulette from the first bounce vs. none, both
/// with max depth 8 (64 x 64 x 64 spp, 4 standard errors).
#[test]
fn russian_roulette_is_unbiased() {
    let scene = glb_scene(&cornell_demo_glb());
    let (a, sa) = mean_luminance_and_stderr(&render(&scene, &settings(64, 64, path(8, 1), 5)));
    let (b, sb) = mean_luminance_and_stderr(&render(&scene, &settings(64, 64, path(8, u32::MAX), 6)));
    let bound = 4.0 * (sa * sa + sb * sb).sqrt();
    assert!((a - b).abs() < bound, "rr {a:.5} vs no rr {b:.5}, bound {bound:.5}");
    assert!(sa > sb, "roulette should add noise: {sa} vs {sb}");
}

/// Area and solid-angle light sampling agree in the mean (direct, 64 x 64 x 64 spp).
#[test]
fn light_sampling_modes_agree() {
    let scene = glb_scene(&cornell_demo_glb());
    let run = |ls, seed| {
        let i = IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: ls };
        mean_luminance_and_stderr(&render(&scene, &settings(64, 64, i, seed)))
    };
    let (a, sa) = run(LightSampling::Area, 7);
    let (b, sb) = run(LightSampling::SolidAngle, 8);
    let bound = 4.0 * (sa * sa + sb * sb).sqrt();
    assert!((a - b).abs() < bound, "area {a:.5} vs solid angle {b:.5}, bound {bound:.5}");
}

/// The lecture's MIS scene (strips from rough to near-mirror, a small bright and a large dim
/// light): all four strategies agree in the mean on every strip (4 standard errors), and on
/// every strip MIS (balance and power) has lower variance than the worse single strategy.
#[test]
fn mis_strategies_agree_and_mis_beats_the_worse_strategy() {
    let scene = glb_scene(&pathfarm_common::scene::demo::mis_glb());
    let mut results = Vec::new();
    for (k, mis) in
        [MisHeuristic::Balance, MisHeuristic::Power, MisHeuristic::Light, MisHeuristic::Bsdf].into_iter().enumerate()
    {
        let i = IntegratorSettings::Direct { mis, light_sampling: LightSampling::SolidAngle };
        let img = render(&scene, &settings(96, 32, i, 20 + k as u64));
        // Per strip (tagged by the albedo layer's red channel): mean luminance, its standard
        // error, and the mean per-pixel variance.
        let mut strips = Vec::new();
        for tag in [0.5f32, 0.6, 0.7, 0.8] {
            let px: Vec<usize> = (0..img.rgb.len())
                .filter(|&p| (img.albedo[p][0] / img.albedo[p][1].max(1e-6) * 0.7 - tag).abs() < 0.02)
                .collect();
            assert!(px.len() > 100, "strip {tag} covers only {} pixels", px.len());
            let n = px.len() as f64;
            let lum = |p: usize| luminance([img.rgb[p][0].into(), img.rgb[p][1].into(), img.rgb[p][2].into()]);
            let mean = px.iter().map(|&p| lum(p)).sum::<f64>() / n;
            let var_sum = px.iter().map(|&p| f64::from(img.variance[p])).sum::<f64>();
            strips.push((mean, (var_sum / (n * n)).sqrt(), var_sum / n));
        }
        results.push((mis, strips));
    }
    for s in 0..4 {
        let (_, base) = &results[0];
        for (mis, strips) in &results[1..] {
            let (a, sa, _) = base[s];
            let (b, sb, _) = strips[s];
            let bound = 4.0 * (sa * sa + sb * sb).sqrt();
            assert!((a - b).abs() < bound, "strip {s}: balance {a:.5} vs {mis:?} {b:.5} (bound {bound:.5})");
        }
        let worse = results[2].1[s].2.max(results[3].1[s].2);
        for (mis, strips) in &results[..2] {
            assert!(
                strips[s].2 < worse,
                "strip {s}: {mis:?} variance {} not below the worse single strategy {worse}",
                strips[s].2
            );
        }
    }
}

/// The Cornell box against Mitsuba 3 (reference/, made by scripts/make-reference.py: 16,384 spp, box filter, path,
/// max_depth 8). Ours: 256 x 256 x 64 spp, seed 9. Per-channel image means within 0.5%; the
/// 16 x 16 block means of luminance agree within the noise: |ours - ref| < 5 sigma for every
/// block, sigma^2 = our block variance (from the variance layer) + (0.06% of the image mean)^2
/// for the reference's own noise (its README: a 1,024 spp render is 0.23% off, 16x more samples
/// -> about 0.06%).
#[test]
fn cornell_box_matches_mitsuba_reference() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let img = render(&scene, &settings(256, 64, path(8, 5), 9));
    let reference =
        pathfarm_common::film::read_exr(&reference().join("cornell_mitsuba_box_16384spp.exr")).expect("reference exr");
    assert_eq!((reference.width, reference.height), (256, 256));
    let ref_rgb: Vec<&[f32]> = ["R", "G", "B"].iter().map(|c| reference.get(c).expect("channel")).collect();
    let ours = mean_rgb(&img);
    for c in 0..3 {
        let r = ref_rgb[c].iter().map(|&v| f64::from(v)).sum::<f64>() / 65536.0;
        let rel = (ours[c] - r).abs() / r;
        assert!(rel < 0.005, "channel {c}: ours {:.5}, Mitsuba {r:.5} ({:.3}% off)", ours[c], rel * 100.0);
    }
    let image_mean = luminance(ours);
    let mut worst = 0.0f64;
    for by in 0..16 {
        for bx in 0..16 {
            let (mut a, mut b, mut var) = (0.0, 0.0, 0.0);
            for y in by * 16..by * 16 + 16 {
                for x in bx * 16..bx * 16 + 16 {
                    let i = y * 256 + x;
                    let p = img.rgb[i];
                    a += luminance([p[0].into(), p[1].into(), p[2].into()]) / 256.0;
                    b += luminance([ref_rgb[0][i].into(), ref_rgb[1][i].into(), ref_rgb[2][i].into()]) / 256.0;
                    var += f64::from(img.variance[i]) / (256.0 * 256.0);
                }
            }
            let sigma = (var + (0.0006 * image_mean).powi(2)).sqrt();
            let z = (a - b).abs() / sigma;
            worst = worst.max(z);
            assert!(z < 5.0, "block ({bx}, {by}): ours {a:.5}, Mitsuba {b:.5}, {z:.1} sigma");
        }
    }
    eprintln!("worst block: {worst:.2} sigma");
}

/// Vertex colours multiply the base colour: a white quad whose vertices are all (1, 0.5, 0.25)
/// has that albedo in the albedo layer (camera framing the quad, 8 x 8 x 4 spp).
#[test]
fn vertex_colors_multiply_the_base_color() {
    use glam::Vec3;
    let mut b = pathfarm_common::scene::demo::GltfBuilder::new();
    let white = b.material(pathfarm_common::scene::demo::lambert("white", Vec3::splat(0.8)));
    let p = [Vec3::new(-1., -1., 0.), Vec3::new(1., -1., 0.), Vec3::new(1., 1., 0.), Vec3::new(-1., 1., 0.)];
    let node = b.mesh("quad", &p, &[Vec3::Z; 4], &[0, 1, 2, 0, 2, 3], white);
    b.vertex_colors(node, &[Vec3::new(1.0, 0.5, 0.25); 4]);
    b.camera(Vec3::new(0.0, 0.0, 2.0), Vec3::ZERO, Vec3::Y, 0.5, 1.0);
    let scene = glb_scene(&b.to_glb());
    let img = render(&scene, &settings(8, 4, path(2, 3), 1));
    let a = img.albedo[4 * 8 + 4];
    let want = [0.8, 0.4, 0.2];
    for c in 0..3 {
        assert!((a[c] - want[c]).abs() < 1e-4, "albedo {a:?}, expected {want:?}");
    }
}
