//! Instant global illumination and bidirectional path tracing, side by side.
//!
//! 1. The Mitsuba Cornell box: direct lighting only, IGI with 4 and with 64 light paths per VPL
//!    set (one set per sample index, 4 spp, `g_limit` 10), the 64-path image clamped hard
//!    (`g_limit` 0.25, dark corners) and the same clamp with bias compensation.
//! 2. The caustics scene (glass sphere, small bright light): path tracing and BDPT at equal time.
//! 3. A table of luminance RMSE and mean absolute error (pixels that see a light, and
//!    their neighbours, left out)
//!    against render time for path, bdpt and igi (clamped `g_limit` 1, and compensated) on both
//!    scenes: against Mitsuba's 16,384-spp render (box-downsampled) for the Cornell box and a
//!    long BDPT render (4 seeds, whose spread is taken out of the RMSE) for the caustics.
//!
//! ```sh
//! cargo run --release -p pathfarm-worker --example igi_sequence -- [OUT_DIR] [SIZE] [REF_SPP]
//! ```
//! Writes `OUT_DIR` (default `target/igi`): `cornell_{direct,vpl4,vpl64,clamped,compensated}.png`,
//! `cornell_sheet.png`, `caustics_{path,bdpt}_equal_time.png`, `caustics_sheet.png`, and prints
//! the table. SIZE (default 128) must divide 256; REF_SPP (default 1024) is the caustics
//! reference's sample count.

use anyhow::Context;
use pathfarm_common::film::{ImageLayers, read_exr};
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::caustics_glb;
use pathfarm_common::scene::{LoadOptions, Scene, load_scene, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};
use std::path::{Path, PathBuf};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "target/igi".into()));
    let size: u32 = args.next().map(|s| s.parse()).transpose().context("SIZE must be a number")?.unwrap_or(128);
    let ref_spp: u32 = args.next().map(|s| s.parse()).transpose().context("REF_SPP must be a number")?.unwrap_or(1024);
    anyhow::ensure!(size > 0 && 256 % size == 0, "SIZE must divide 256 (the Mitsuba reference's size)");
    std::fs::create_dir_all(&out)?;
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../reference");
    let cornell = load_scene(&shared.join("cornell_mitsuba.glb"), &LoadOptions::default())?;
    let caustics = load_scene_from_slice(&caustics_glb(), "caustics.glb", None, &LoadOptions::default())?;

    // 1. The IGI sequence.
    let igi = |vpls: u32, g_limit: f32, bias_compensation: bool| IntegratorSettings::Igi {
        vpls,
        vpl_sets: 1,
        g_limit,
        bias_compensation,
        max_depth: 8,
    };
    let direct = IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: LightSampling::SolidAngle };
    let mut sheet_imgs = Vec::new();
    for (name, integrator) in [
        ("direct", direct),
        ("vpl4", igi(4, 10.0, false)),
        ("vpl64", igi(64, 10.0, false)),
        ("clamped", igi(64, 0.25, false)),
        ("compensated", igi(64, 0.25, true)),
    ] {
        let (img, secs) = render(&cornell, size, 4, integrator, 1)?;
        let path = out.join(format!("cornell_{name}.png"));
        img.write_png(&path, 0.0)?;
        eprintln!("wrote {} ({secs:.1} s)", path.display());
        sheet_imgs.push(img.preview_rgb8(0.0));
    }
    sheet(&sheet_imgs).save(out.join("cornell_sheet.png"))?;

    // 2. Path vs bdpt at equal time on the caustics.
    let (b, t_bdpt) = render(&caustics, size, 16, bdpt(), 2)?;
    let (_, t_path16) = render(&caustics, size, 16, path(), 3)?;
    let path_spp = ((16.0 * t_bdpt / t_path16).round() as u32).max(1);
    let (p, t_path) = render(&caustics, size, path_spp, path(), 4)?;
    b.write_png(&out.join("caustics_bdpt_equal_time.png"), 0.0)?;
    p.write_png(&out.join("caustics_path_equal_time.png"), 0.0)?;
    sheet(&[p.preview_rgb8(0.0), b.preview_rgb8(0.0)]).save(out.join("caustics_sheet.png"))?;
    eprintln!("caustics at equal time: path {path_spp} spp ({t_path:.1} s), bdpt 16 spp ({t_bdpt:.1} s)");

    // 3. RMSE against time.
    // Mitsuba's 16,384 spp are noise-free at this scale; the caustics reference is the mean of 4
    // BDPT renders (seeds 99 to 102), whose spread gives its own noise, which is taken out of the
    // mean squared errors (RMSE column; MAE is as measured).
    let cornell_ref = (mitsuba_reference(&shared, size as usize)?, vec![0.0; (size * size) as usize]);
    eprintln!("caustics reference: bdpt 4 x {} spp ...", ref_spp / 4);
    let t = Instant::now();
    let refs: Vec<Vec<f64>> = (99..103)
        .map(|seed| {
            Ok(render(&caustics, size, (ref_spp / 4).max(1), bdpt(), seed)?.0.rgb.iter().map(|&p| lum(p)).collect())
        })
        .collect::<anyhow::Result<_>>()?;
    let mean: Vec<f64> = (0..refs[0].len()).map(|i| refs.iter().map(|r| r[i]).sum::<f64>() / 4.0).collect();
    let var: Vec<f64> =
        (0..mean.len()).map(|i| refs.iter().map(|r| (r[i] - mean[i]).powi(2)).sum::<f64>() / 3.0 / 4.0).collect();
    eprintln!("  {:.1} s", t.elapsed().as_secs_f64());
    let caustics_ref = (mean, var);
    let integrators = [
        ("path", path()),
        ("bdpt", bdpt()),
        (
            "igi clamped (g 1)",
            IntegratorSettings::Igi { vpls: 64, vpl_sets: 4, g_limit: 1.0, bias_compensation: false, max_depth: 8 },
        ),
        (
            "igi compensated (g 1)",
            IntegratorSettings::Igi { vpls: 64, vpl_sets: 4, g_limit: 1.0, bias_compensation: true, max_depth: 8 },
        ),
    ];
    let mut table = String::from("| scene | integrator | spp | time (s) | RMSE | MAE |\n|---|---|---|---|---|---|\n");
    for (scene_name, scene, reference) in [("cornell", &cornell, &cornell_ref), ("caustics", &caustics, &caustics_ref)]
    {
        let (reference, ref_var) = (&reference.0, &reference.1);
        let mask = emitter_mask(scene, size);
        let kept = mask.iter().filter(|&&m| !m).count().max(1) as f64;
        let ref_mse = ref_var.iter().zip(&mask).filter(|(_, m)| !**m).map(|(v, _)| v).sum::<f64>() / kept;
        eprintln!("{scene_name}: reference noise (RMS) {:.4}", ref_mse.sqrt());
        for (name, integrator) in &integrators {
            for spp in [1u32, 4, 16, 64] {
                let (img, secs) = render(scene, size, spp, integrator.clone(), 7)?;
                let e = (rmse(&img, reference, &mask).powi(2) - ref_mse).max(0.0).sqrt();
                let a = mae(&img, reference, &mask);
                table += &format!("| {scene_name} | {name} | {spp} | {secs:.2} | {e:.4} | {a:.4} |\n");
                eprintln!("{scene_name} {name} {spp} spp: {secs:.2} s, RMSE {e:.4}, MAE {a:.4}");
            }
        }
    }
    std::fs::write(out.join("rmse_table.md"), &table)?;
    eprintln!("\n{table}");
    Ok(())
}

fn path() -> IntegratorSettings {
    IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    }
}

fn bdpt() -> IntegratorSettings {
    IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 5, strategy: None }
}

/// Renders and times one image.
fn render(
    scene: &Scene,
    size: u32,
    spp: u32,
    integrator: IntegratorSettings,
    seed: u64,
) -> anyhow::Result<(ImageLayers, f64)> {
    let mut s = RenderSettings::new(size, size, spp);
    s.integrator = integrator;
    s.seed = seed;
    let t = Instant::now();
    let renderer = Renderer::new(scene, &s)?;
    let img = render_local(&renderer, |_, _| {}).resolve();
    Ok((img, t.elapsed().as_secs_f64()))
}

fn lum(p: [f32; 3]) -> f64 {
    0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2])
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

/// Mean absolute luminance error over the same pixels: robust to the rare fireflies that
/// dominate the RMSE of caustics at low sample counts.
fn mae(img: &ImageLayers, reference: &[f64], mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0.0f64);
    for ((&p, &r), &m) in img.rgb.iter().zip(reference).zip(mask) {
        if !m {
            sum += (lum(p) - r).abs();
            n += 1.0;
        }
    }
    sum / n.max(1.0)
}

/// Mitsuba's Cornell box render box-downsampled to `w x w`, as luminance.
fn mitsuba_reference(dir: &Path, w: usize) -> anyhow::Result<Vec<f64>> {
    let r = read_exr(&dir.join("cornell_mitsuba_box_16384spp.exr"))?;
    anyhow::ensure!((r.width, r.height) == (256, 256), "the reference is not 256 x 256");
    let ch: Vec<&[f32]> = ["R", "G", "B"]
        .iter()
        .map(|c| r.get(c).with_context(|| format!("reference channel {c}")))
        .collect::<anyhow::Result<_>>()?;
    let f = 256 / w;
    let mut out = vec![0.0; w * w];
    for y in 0..256 {
        for x in 0..256 {
            let i = y * 256 + x;
            out[(y / f) * w + x / f] += lum([ch[0][i], ch[1][i], ch[2][i]]) / (f * f) as f64;
        }
    }
    Ok(out)
}

/// Images side by side with a 4-pixel gap.
fn sheet(images: &[image::RgbImage]) -> image::RgbImage {
    let (w, h) = images.first().map_or((0, 0), |i| i.dimensions());
    let mut out = image::RgbImage::from_pixel((w + 4) * images.len() as u32 - 4, h, image::Rgb([255, 255, 255]));
    for (k, img) in images.iter().enumerate() {
        image::imageops::replace(&mut out, img, i64::from(k as u32 * (w + 4)), 0);
    }
    out
}
