//! Scenes with specular transport against Mitsuba 3: `reference/cornell_spheres.glb` (our
//! exporter: Mitsuba's Cornell box walls with a perfect mirror sphere and a solid glass sphere,
//! both faceted) and its Mitsuba render `reference/cornell_spheres_8192spp.exr`
//! (`scripts/make-reference.py --glb`, which converts the same file to PLY meshes and Mitsuba
//! BSDFs: llvm_ad_rgb, path, max_depth 16, 8,192 spp, box filter).
//!
//! Ours: 128 x 128 (each pixel compared with the mean of the 2 x 2 reference pixels it covers),
//! path at 256 spp and bdpt at 64 spp, max_depth 16 and rr_depth 5 as Mitsuba. Checked: the
//! image mean of each channel within 1%; the mean of the pixels covering each sphere within
//! 5 sigma, where sigma^2 is our variance of that mean (the variance layer) plus the reference's
//! (ours scaled by our samples over its samples) plus (0.1% of the image mean)^2; and the mean of
//! each 16 x 16 block within 5 sigma where sigma^2 also has (2% of the block's mean)^2. That floor
//! is for caustics: light reaching the ceiling and floor through the mirror and the glass sphere
//! comes in rare, bright samples (fireflies), and a block that happened to draw none has a variance
//! layer that cannot see what it missed (measured: such blocks run 3-25% dark at 64 spp, 11-18
//! "sigma" without the floor, while their 256-spp ratio to Mitsuba is 0.94-1.09). Seeds fixed;
//! with the floors a correct renderer passes with margin (worst block printed), and a wrong
//! glass or mirror (the glass bug of issue 16 made the sphere seen in the mirror 20% dark) fails.

mod common;

use common::*;
use glam::Vec3;
use pathfarm_common::film::ImageLayers;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::{CORNELL_GLASS_SPHERE, CORNELL_MIRROR_SPHERE, cornell_spheres_glb};

const W: usize = 128;
const REFERENCE: &str = "cornell_spheres_8192spp.exr";
const REFERENCE_SPP: f64 = 8192.0;

fn settings(spp: u32, integrator: IntegratorSettings, seed: u64) -> RenderSettings {
    let mut s = RenderSettings::new(W as u32, W as u32, spp);
    s.integrator = integrator;
    s.seed = seed;
    s
}

/// The reference box-downsampled to W x W: per-pixel RGB.
fn mitsuba_reference() -> Vec<[f64; 3]> {
    let reference = pathfarm_common::film::read_exr(&reference().join(REFERENCE)).expect("reference exr");
    let r = reference.width as usize;
    assert_eq!((reference.width, reference.height), (256, 256));
    let ch: Vec<&[f32]> = ["R", "G", "B"].iter().map(|c| reference.get(c).expect("channel")).collect();
    let f = r / W;
    let mut out = vec![[0.0; 3]; W * W];
    for y in 0..r {
        for x in 0..r {
            for c in 0..3 {
                out[(y / f) * W + x / f][c] += f64::from(ch[c][y * r + x]) / (f * f) as f64;
            }
        }
    }
    out
}

/// Pixels whose centre sees the sphere `(c, r)` through the scene's pinhole camera (at (0, 0, 3.9)
/// looking down -Z, vertical field of view 0.6860488 rad, as `cornell_walls` places it), shrunk
/// by 15% of the radius so that edge pixels (half sphere, half wall) stay out.
fn sphere_pixels((c, r): (Vec3, f32)) -> Vec<usize> {
    let eye = Vec3::new(0.0, 0.0, 3.9);
    let tan = (0.686_048_8f32 / 2.0).tan();
    let mut out = Vec::new();
    for y in 0..W {
        for x in 0..W {
            let u = ((x as f32 + 0.5) / W as f32 * 2.0 - 1.0) * tan;
            let v = (1.0 - (y as f32 + 0.5) / W as f32 * 2.0) * tan;
            let d = Vec3::new(u, v, -1.0).normalize();
            // Distance of the sphere centre from the ray.
            let t = (c - eye).dot(d);
            if (eye + d * t - c).length() < 0.85 * r {
                out.push(y * W + x);
            }
        }
    }
    out
}

/// |ours - reference| / sigma of the luminance mean over `pixels`.
fn z_score(
    img: &ImageLayers,
    spp: u32,
    reference: &[[f64; 3]],
    pixels: &[usize],
    floor: f64,
    rel_floor: f64,
) -> (f64, f64, f64) {
    let n = pixels.len() as f64;
    let (mut a, mut b, mut var) = (0.0, 0.0, 0.0);
    for &i in pixels {
        let p = img.rgb[i];
        a += luminance([p[0].into(), p[1].into(), p[2].into()]) / n;
        b += luminance(reference[i]) / n;
        var += f64::from(img.variance[i]) / (n * n);
    }
    // The reference has 4 x 8192 samples per W x W pixel: its variance is ours scaled down.
    let var = var * (1.0 + f64::from(spp) / (4.0 * REFERENCE_SPP));
    ((a - b).abs() / (var + floor * floor + (rel_floor * b).powi(2)).sqrt(), a, b)
}

fn check_against_mitsuba(name: &str, img: &ImageLayers, spp: u32) {
    let reference = mitsuba_reference();
    let ours = mean_rgb(img);
    let theirs: Vec<f64> =
        (0..3).map(|c| reference.iter().map(|p| p[c]).sum::<f64>() / reference.len() as f64).collect();
    for c in 0..3 {
        let rel = (ours[c] - theirs[c]).abs() / theirs[c];
        eprintln!("{name} channel {c}: ours {:.5}, Mitsuba {:.5} ({:.3}% off)", ours[c], theirs[c], rel * 100.0);
        assert!(rel < 0.01, "{name} channel {c}: ours {:.5}, Mitsuba {:.5}", ours[c], theirs[c]);
    }
    let floor = 0.001 * luminance(ours);
    for (sphere, geometry) in [("mirror sphere", CORNELL_MIRROR_SPHERE), ("glass sphere", CORNELL_GLASS_SPHERE)] {
        let pixels = sphere_pixels(geometry);
        assert!(pixels.len() > 300, "{sphere}: only {} pixels", pixels.len());
        let (z, a, b) = z_score(img, spp, &reference, &pixels, floor, 0.0);
        eprintln!("{name} {sphere}: ours {a:.5}, Mitsuba {b:.5} ({:+.2}%), {z:.2} sigma", (a / b - 1.0) * 100.0);
        assert!(z < 5.0, "{name} {sphere}: ours {a:.5}, Mitsuba {b:.5}, {z:.1} sigma");
    }
    let mut worst = (0.0f64, 0, 0);
    const B: usize = 16;
    for by in 0..W / B {
        for bx in 0..W / B {
            let pixels: Vec<usize> =
                (by * B..by * B + B).flat_map(|y| (bx * B..bx * B + B).map(move |x| y * W + x)).collect();
            let (z, a, b) = z_score(img, spp, &reference, &pixels, floor, 0.02);
            if z > worst.0 {
                worst = (z, bx, by);
            }
            assert!(z < 5.0, "{name} block ({bx}, {by}): ours {a:.5}, Mitsuba {b:.5}, {z:.1} sigma");
        }
    }
    eprintln!("{name}: worst block ({}, {}) at {:.2} sigma", worst.1, worst.2, worst.0);
}

#[test]
fn committed_scene_is_what_the_reference_shows() {
    // The reference was rendered from the committed file; the test renders from our exporter.
    let committed = std::fs::read(reference().join("cornell_spheres.glb")).expect("reference/cornell_spheres.glb");
    assert!(committed == cornell_spheres_glb(), "reference/cornell_spheres.glb is stale: run make_reference_scene");
}

#[test]
fn path_tracing_matches_mitsuba_on_mirror_and_glass() {
    let scene = glb_scene(&cornell_spheres_glb());
    let integrator = IntegratorSettings::Path {
        max_depth: 16,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    let img = render(&scene, &settings(256, integrator, 21));
    check_against_mitsuba("path", &img, 256);
}

#[test]
fn bdpt_matches_mitsuba_on_mirror_and_glass() {
    let scene = glb_scene(&cornell_spheres_glb());
    let integrator = IntegratorSettings::Bdpt { max_depth: 16, mis: MisHeuristic::Power, rr_depth: 5, strategy: None };
    let img = render(&scene, &settings(64, integrator, 22));
    check_against_mitsuba("bdpt", &img, 64);
}

/// igi's stated bias (`render::igi` module documentation): light that reaches the first
/// non-specular surface seen from the camera straight from a specular one (a caustic seen
/// directly, or through the mirror or glass) is beyond VPLs. In this scene the spheres throw much
/// light onto the ceiling and the walls that way, so igi is dark there by design. Checked: igi
/// is never brighter than Mitsuba (every 16 x 16 block at most 5 sigma above, sigma as in
/// `check_against_mitsuba` without the caustic floor), and each channel's image mean is at most
/// 12% darker. Measured (128 x 128, 64 spp, 32 VPLs x 4 sets, g_limit 1, compensated, seed 23):
/// channels -9.37%, -7.14%, -6.24%; the ceiling's blocks 15-35% dark, the floor under the glass
/// sphere 85%, the emitter's blocks -0.7%; the mirror sphere -5.6%, the glass sphere -9.3%. A
/// bound that checks igi against a caustic-free reference is not written (see the report).
#[test]
fn igi_is_darker_than_mitsuba_only_by_its_caustics() {
    let scene = glb_scene(&cornell_spheres_glb());
    let integrator =
        IntegratorSettings::Igi { vpls: 32, vpl_sets: 4, g_limit: 1.0, bias_compensation: true, max_depth: 16 };
    let spp = 64;
    let img = render(&scene, &settings(spp, integrator, 23));
    let reference = mitsuba_reference();
    let ours = mean_rgb(&img);
    for c in 0..3 {
        let theirs = reference.iter().map(|p| p[c]).sum::<f64>() / reference.len() as f64;
        let rel = ours[c] / theirs - 1.0;
        eprintln!("igi channel {c}: ours {:.5}, Mitsuba {theirs:.5} ({:+.3}%)", ours[c], rel * 100.0);
        assert!((-0.12..=0.0).contains(&rel), "igi channel {c}: {:+.3}% off Mitsuba", rel * 100.0);
    }
    let floor = 0.001 * luminance(ours);
    const B: usize = 16;
    for by in 0..W / B {
        for bx in 0..W / B {
            let pixels: Vec<usize> =
                (by * B..by * B + B).flat_map(|y| (bx * B..bx * B + B).map(move |x| y * W + x)).collect();
            let (z, a, b) = z_score(&img, spp, &reference, &pixels, floor, 0.0);
            assert!(a <= b || z < 5.0, "igi block ({bx}, {by}): ours {a:.5} above Mitsuba {b:.5}, {z:.1} sigma");
        }
    }
}
