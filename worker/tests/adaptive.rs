//! Adaptive sampling (`common::adaptive`, `Renderer::render_unit_masked`, `render_local`) and the
//! local `--denoise` with it: unbiased in expectation, fewer samples where the image is flat,
//! the same decisions whatever the tile split or unit order, and deterministic.

mod common;

use common::*;
use pathfarm_common::adaptive::{AdaptiveSettings, BlockMask, converged_blocks};
use pathfarm_common::film::{Film, TileAccum, read_exr};
use pathfarm_common::job::{IntegratorSettings, MisHeuristic, PassSchedule, RenderSettings, SamplerKind};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_worker::render::{Renderer, render_local};
use std::process::Command;

fn worker() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pathfarm-worker"))
}

fn adaptive_settings(w: u32, spp: u32, seed: u64, threshold: f32, min_spp: u32) -> RenderSettings {
    let mut s = RenderSettings::new(w, w, spp);
    s.seed = seed;
    s.sampler = SamplerKind::Independent;
    s.passes = PassSchedule::Fixed { spp: 8 };
    s.tile_size = 32;
    s.adaptive = Some(AdaptiveSettings { threshold, min_spp });
    s
}

/// Adaptive and uniform sampling agree in expectation. The Mitsuba Cornell box at 64 x 64: an
/// adaptive render (128 spp, threshold 0.2, min 8, independent sampler, seed 11) against a
/// uniform one (128 spp, seed 12), in 16 regions of 16 x 16 pixels. Each region's mean
/// luminance has a standard error from the variance layers (the variance of each pixel's mean,
/// with its own sample count; pixels are independent), and z = difference / sqrt(var_a + var_u).
/// Significance level 1e-3 over the 16 regions and the whole image (Bonferroni: |z| < 4.03 for
/// each of 17 two-sided tests). The adaptive render must also have taken fewer samples.
#[test]
fn adaptive_and_uniform_agree_in_expectation() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let a = render(&scene, &adaptive_settings(64, 128, 11, 0.2, 8));
    let mut u = adaptive_settings(64, 128, 12, 0.2, 8);
    u.adaptive = None;
    let u = render(&scene, &u);
    let taken: f64 = a.samples.iter().map(|&n| f64::from(n)).sum();
    let fraction = taken / (64.0 * 64.0 * 128.0);
    eprintln!("adaptive took {:.1}% of the uniform samples", 100.0 * fraction);
    assert!(fraction < 0.9, "adaptive sampling saved almost nothing: {fraction:.3}");
    assert!(a.samples.iter().all(|&n| (8.0..=128.0).contains(&n)), "a pixel outside [min_spp, spp]");
    let lum = |p: &[f32; 3]| luminance([p[0].into(), p[1].into(), p[2].into()]);
    let region = |img: &pathfarm_common::film::ImageLayers, x0: usize, y0: usize, size: usize| {
        let (mut m, mut v, n) = (0.0, 0.0, (size * size) as f64);
        for y in y0..y0 + size {
            for x in x0..x0 + size {
                m += lum(&img.rgb[y * 64 + x]) / n;
                v += f64::from(img.variance[y * 64 + x]) / (n * n);
            }
        }
        (m, v)
    };
    let z_limit = 4.03;
    let mut worst = 0.0f64;
    let regions = (0..4).flat_map(|j| (0..4).map(move |i| (i * 16, j * 16, 16))).chain([(0, 0, 64)]);
    for (x0, y0, size) in regions {
        let ((ma, va), (mu, vu)) = (region(&a, x0, y0, size), region(&u, x0, y0, size));
        if va + vu == 0.0 {
            assert_eq!(ma, mu, "a noiseless region differs at ({x0}, {y0})");
            continue;
        }
        let z = (ma - mu) / (va + vu).sqrt();
        worst = worst.max(z.abs());
        assert!(z.abs() < z_limit, "region ({x0}, {y0}) size {size}: adaptive {ma:.5} vs uniform {mu:.5}, z = {z:.2}");
    }
    eprintln!("largest |z| over 17 regions: {worst:.2}");
}

/// The Cornell box through `pathfarm-worker render --adaptive-threshold 0.2 --min-spp 8`:
/// `samples.Y` holds each pixel's count, from min_spp up to spp; the noisiest quarter of the
/// image (by the per-pixel relative error of a uniform 8-spp render) gets more than 1.5 times the
/// samples of the flattest quarter (measured: 119.8 vs 69.1).
#[test]
fn samples_layer_shows_fewer_samples_where_the_image_is_flat() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("a.exr");
    let glb = reference().join("cornell_mitsuba.glb");
    let status = worker()
        .arg("render")
        .arg(&glb)
        .args(["--width", "64", "--height", "64", "--spp", "128", "--pass-spp", "8", "--tile-size", "32"])
        .args(["--adaptive-threshold", "0.2", "--min-spp", "8", "--quiet", "--out"])
        .arg(&out)
        .status()
        .expect("run");
    assert!(status.success());
    let exr = read_exr(&out).expect("read");
    let samples = exr.get("samples.Y").expect("samples.Y");
    let (lo, hi) = samples.iter().fold((f32::MAX, 0.0f32), |(lo, hi), &n| (lo.min(n), hi.max(n)));
    eprintln!("samples per pixel from {lo} to {hi}");
    assert!(lo >= 8.0 && lo < hi && hi == 128.0, "per-pixel counts {lo} to {hi}");
    // Rank the pixels by the relative error of a uniform render at min_spp.
    let mut s = RenderSettings::new(64, 64, 8);
    s.tile_size = 32;
    let u = render(&file_scene(&glb), &s);
    let rel = |i: usize| {
        let m = luminance([u.rgb[i][0].into(), u.rgb[i][1].into(), u.rgb[i][2].into()]);
        f64::from(u.variance[i]).sqrt() / m.max(1e-3)
    };
    let mut order: Vec<usize> = (0..64 * 64).collect();
    order.sort_by(|&a, &b| rel(a).total_cmp(&rel(b)));
    let mean = |ix: &[usize]| ix.iter().map(|&i| f64::from(samples[i])).sum::<f64>() / ix.len() as f64;
    let (flat, noisy) = (mean(&order[..1024]), mean(&order[3072..]));
    eprintln!("mean samples: flattest quarter {flat:.1}, noisiest quarter {noisy:.1}");
    assert!(noisy > 1.5 * flat, "noisy pixels got {noisy:.1} samples, flat ones {flat:.1}");
}

/// The decision is per 8 x 8 block on the image's 8-pixel grid: tile sizes 16 and 32 (both
/// multiples of 8) give the same sums bit for bit, and so does rendering the units in a farm's
/// order (tile-major, each tile's mask from its own merged accumulator) instead of pass-major
/// over the film; rendering twice gives the same bits.
#[test]
fn decisions_do_not_depend_on_the_tile_split_or_unit_order() {
    let scene = glb_scene(&cornell_demo_glb());
    let s32 = adaptive_settings(48, 24, 5, 0.5, 4);
    let mut s16 = s32.clone();
    s16.tile_size = 16;
    let film32 = render_local(&Renderer::new(&scene, &s32).expect("renderer"), |_, _| {});
    let film16 = render_local(&Renderer::new(&scene, &s16).expect("renderer"), |_, _| {});
    let again = render_local(&Renderer::new(&scene, &s32).expect("renderer"), |_, _| {});
    assert!(film32.sums == again.sums, "two renders differ");
    assert!(film32.sums == film16.sums, "tile size 16 and 32 differ");
    let samples: Vec<f32> = film32.resolve().samples;
    assert!(samples.iter().any(|&n| n < 24.0), "nothing converged: the test shows nothing");

    // A farm: tiles in reverse order, each folding its passes in order in its own accumulator.
    let renderer = Renderer::new(&scene, &s32).expect("renderer");
    let plan = s32.plan();
    let a = s32.adaptive.expect("adaptive");
    let mut film = Film::new(48, 48);
    for &tile in plan.tiles.iter().rev() {
        let mut accum = TileAccum::new(tile);
        let mut mask: Option<BlockMask> = None;
        for pass in &plan.passes {
            if mask.as_ref().is_some_and(BlockMask::all_converged) {
                break;
            }
            let r = renderer.render_unit_masked(tile, *pass, mask.as_ref()).expect("unit");
            accum.merge(&r.accum);
            mask = Some(converged_blocks(&accum.sums, tile, &a, pass.s1));
        }
        film.add_tile(&accum);
    }
    assert!(film.sums == film32.sums, "farm order differs from the local render");
}

/// A mask of another tile's layout and a mask with bdpt are refused with an error, and bdpt with
/// adaptive settings is refused by the settings and by the CLI.
#[test]
fn bad_masks_and_bdpt_are_refused() {
    let scene = glb_scene(&cornell_demo_glb());
    let s = adaptive_settings(32, 8, 1, 0.1, 2);
    let r = Renderer::new(&scene, &s).expect("renderer");
    let plan = s.plan();
    let wrong = BlockMask::none_converged(pathfarm_common::job::TileRect { x0: 0, y0: 0, x1: 16, y1: 16 });
    let mut wrong_set = wrong.clone();
    wrong_set.set_converged(0, 0);
    let e = r.render_unit_masked(plan.tiles[0], plan.passes[0], Some(&wrong_set)).expect_err("mismatch");
    assert!(e.to_string().contains("block mask"), "{e}");
    let mut b = s.clone();
    b.integrator = IntegratorSettings::Bdpt { max_depth: 5, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
    let e = Renderer::new(&scene, &b).err().expect("bdpt + adaptive").to_string();
    assert!(e.contains("bdpt"), "{e}");
    let out = worker()
        .args(["render", "x.glb", "--integrator", "bdpt", "--adaptive-threshold", "0.1", "--spp", "4"])
        .output()
        .expect("run");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("adaptive sampling is not available with the bdpt integrator"), "{stderr}");
    let out = worker().args(["render", "x.glb", "--min-spp", "4"]).output().expect("run");
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--adaptive-threshold"));
}

/// Relative MSE over pixels and channels: (x - r)^2 / (r^2 + 1e-2).
#[cfg(feature = "denoise")]
fn rel_mse(x: &[[f32; 3]], r: &[[f32; 3]]) -> f64 {
    let sum: f64 = x
        .iter()
        .zip(r)
        .flat_map(|(a, b)| (0..3).map(move |c| (f64::from(a[c]), f64::from(b[c]))))
        .map(|(a, b)| (a - b).powi(2) / (b * b + 1e-2))
        .sum();
    sum / (3 * x.len()) as f64
}

/// `render --adaptive-threshold --denoise` on the Cornell box at 64 x 64: the EXR holds the
/// `denoised` layer beside the noisy colour, the denoised colour is closer to the Mitsuba
/// reference (16384 spp, 256 x 256, box-filtered down 4 x 4) than the noisy one by relMSE, and
/// two runs give the same bits in every channel.
#[cfg(feature = "denoise")]
#[test]
fn adaptive_denoised_render_is_closer_to_the_reference_and_deterministic() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |name: &str| {
        let out = dir.path().join(name);
        let status = worker()
            .arg("render")
            .arg(reference().join("cornell_mitsuba.glb"))
            .args(["--width", "64", "--height", "64", "--spp", "16", "--pass-spp", "4", "--tile-size", "32"])
            .args(["--adaptive-threshold", "0.1", "--min-spp", "4", "--denoise", "--quiet", "--out"])
            .arg(&out)
            .status()
            .expect("run");
        assert!(status.success());
        read_exr(&out).expect("read")
    };
    let (one, two) = (run("1.exr"), run("2.exr"));
    for ((n1, v1), (n2, v2)) in one.channels.iter().zip(&two.channels) {
        assert_eq!(n1, n2);
        assert!(v1.iter().zip(v2).all(|(a, b)| a.to_bits() == b.to_bits()), "channel {n1} differs between runs");
    }
    let reference = read_exr(&reference().join("cornell_mitsuba_box_16384spp.exr")).expect("reference");
    let rgb: Vec<&[f32]> = ["R", "G", "B"].iter().map(|c| reference.get(c).expect("channel")).collect();
    // 256 -> 64: the mean of each 4 x 4 block (a box filter, as our pixels are).
    let down: Vec<[f32; 3]> = (0..64 * 64)
        .map(|i| {
            let (x, y) = (i % 64, i / 64);
            let mut m = [0.0f32; 3];
            for dy in 0..4 {
                for dx in 0..4 {
                    for c in 0..3 {
                        m[c] += rgb[c][(4 * y + dy) * 256 + 4 * x + dx] / 16.0;
                    }
                }
            }
            m
        })
        .collect();
    let layer = |prefix: &str| -> Vec<[f32; 3]> {
        let ch: Vec<&[f32]> = ["R", "G", "B"]
            .iter()
            .map(|c| one.get(&format!("{prefix}{c}")).unwrap_or_else(|| panic!("no {prefix}{c}")))
            .collect();
        (0..64 * 64).map(|i| [ch[0][i], ch[1][i], ch[2][i]]).collect()
    };
    let (noisy, denoised) = (rel_mse(&layer(""), &down), rel_mse(&layer("denoised."), &down));
    eprintln!("relMSE vs Mitsuba: noisy {noisy:.5}, denoised {denoised:.5}");
    assert!(denoised < noisy, "denoised relMSE {denoised:.5} vs noisy {noisy:.5}");
}
