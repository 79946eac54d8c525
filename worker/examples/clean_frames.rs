//! Benchmark for issue 14 ("clean frames sooner"): uniform vs adaptive sampling, each with and
//! without OIDN, on the Mitsuba Cornell box and the caustics scene (`common::scene::demo`).
//!
//! ```sh
//! export OIDN_DIR=<site-packages>/pyoidn/oidn
//! export LD_LIBRARY_PATH=$OIDN_DIR/lib RAYON_NUM_THREADS=2
//! cargo run --release -p pathfarm-worker --features denoise --example clean_frames -- \
//!     --size 64 --ref-spp 16384 --budget-s 2 --threshold 0.03 --target 1e-3 --out target/clean_frames
//! ```
//!
//! `scripts/bench-cycles.py` then measures Cycles on the GLB written here (README, Benchmark).
//!
//! For each scene it renders (or reuses) a reference of `--ref-spp` uniform samples, then:
//!
//! - **equal time**: each configuration renders passes of `--pass-spp` samples while the next
//!   pass is predicted to fit in `--budget-s` seconds (the OIDN configurations' budget is less
//!   the measured denoising time), and reports its relative MSE against the reference;
//! - **time to quality**: each configuration renders pass after pass until its image (denoised
//!   for the OIDN ones) has relMSE below `--target` (judged whenever the sample count grew by 5%,
//!   so the time is up to 5% late); the time is preparation (BVH) + rendering + one denoise, the
//!   evaluation itself is off the clock.
//!
//! relMSE = mean over pixels and channels of (x - r)^2 / (r^2 + 1e-2). Writes the scenes' GLBs
//! (for `scripts/bench-cycles.py`, which does the same for Cycles) and `results.json` in `--out`.
//! Adaptive decisions happen at pass ends exactly as in `render_local` (and the farm).

use anyhow::Context;
use pathfarm_common::adaptive::{AdaptiveSettings, BlockMask, converged_blocks};
use pathfarm_common::film::{Film, ImageLayers};
use pathfarm_common::job::{PassSchedule, RenderSettings};
use pathfarm_common::scene::demo::{caustics_glb, cornell_mitsuba_glb};
use pathfarm_common::scene::{LoadOptions, Scene, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};
use std::path::PathBuf;
use std::time::{Duration, Instant};

struct Args {
    size: u32,
    ref_spp: u32,
    budget_s: f64,
    threshold: f32,
    min_spp: u32,
    pass_spp: u32,
    target: f64,
    max_s: f64,
    out: PathBuf,
    scenes: Vec<String>,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut a = Args {
        size: 64,
        ref_spp: 4096,
        budget_s: 2.0,
        threshold: 0.03,
        min_spp: 16,
        pass_spp: 8,
        target: 1e-3,
        max_s: 120.0,
        out: PathBuf::from("target/clean_frames"),
        scenes: vec!["cornell".into(), "caustics".into()],
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--size" => a.size = value()?.parse()?,
            "--ref-spp" => a.ref_spp = value()?.parse()?,
            "--budget-s" => a.budget_s = value()?.parse()?,
            "--threshold" => a.threshold = value()?.parse()?,
            "--min-spp" => a.min_spp = value()?.parse()?,
            "--pass-spp" => a.pass_spp = value()?.parse()?,
            "--target" => a.target = value()?.parse()?,
            "--max-s" => a.max_s = value()?.parse()?,
            "--out" => a.out = PathBuf::from(value()?),
            "--scenes" => a.scenes = value()?.split(',').map(str::to_string).collect(),
            other => anyhow::bail!("unknown argument {other:?}"),
        }
    }
    Ok(a)
}

/// Relative MSE over pixels and channels: (x - r)^2 / (r^2 + 1e-2).
fn rel_mse(x: &[[f32; 3]], r: &[[f32; 3]]) -> f64 {
    let sum: f64 = x
        .iter()
        .zip(r)
        .flat_map(|(a, b)| (0..3).map(move |c| (f64::from(a[c]), f64::from(b[c]))))
        .map(|(a, b)| if a.is_finite() { (a - b).powi(2) / (b * b + 1e-2) } else { 1e6 })
        .sum();
    sum / (3 * x.len()) as f64
}

#[derive(Clone, Copy, Debug)]
struct Config {
    adaptive: bool,
    denoise: bool,
}

impl Config {
    fn name(&self) -> &'static str {
        match (self.adaptive, self.denoise) {
            (false, false) => "uniform",
            (true, false) => "adaptive",
            (false, true) => "uniform+oidn",
            (true, true) => "adaptive+oidn",
        }
    }
}

/// Renders pass after pass (pass-major, masks from the film after each pass as `render_local`
/// does) until `after_pass(film, render_seconds, samples)` says stop or the plan ends.
/// The callback's own time is off the clock.
fn progressive(renderer: &Renderer, mut after_pass: impl FnMut(&Film, f64, f64, f64) -> bool) -> anyhow::Result<()> {
    let settings = renderer.settings();
    let plan = settings.plan();
    let mut film = Film::new(settings.width, settings.height);
    let mut masks: Vec<Option<BlockMask>> = vec![None; plan.tiles.len()];
    let mut clock = Duration::ZERO;
    let mut samples = 0.0;
    for pass in &plan.passes {
        let t = Instant::now();
        for (i, &tile) in plan.tiles.iter().enumerate() {
            if masks[i].as_ref().is_some_and(BlockMask::all_converged) {
                continue;
            }
            let r = renderer.render_unit_masked(tile, *pass, masks[i].as_ref())?;
            film.add_tile(&r.accum);
            let active = masks[i].as_ref().map_or(tile.pixel_count(), |m| m.active_pixels(tile));
            samples += (active * pass.spp() as usize) as f64;
            if let Some(a) = &settings.adaptive {
                masks[i] = Some(converged_blocks(&film.tile(tile).sums, tile, a, pass.s1));
            }
        }
        let pass_s = t.elapsed().as_secs_f64();
        clock += t.elapsed();
        if after_pass(&film, clock.as_secs_f64(), pass_s, samples) {
            break;
        }
        if masks.iter().all(|m| m.as_ref().is_some_and(BlockMask::all_converged)) {
            break;
        }
    }
    Ok(())
}

fn denoised(img: &ImageLayers) -> anyhow::Result<(Vec<[f32; 3]>, f64)> {
    let t = Instant::now();
    let d = pathfarm_worker::denoise::denoise(img)?;
    Ok((d, t.elapsed().as_secs_f64()))
}

fn settings_for(a: &Args, config: Config, spp: u32) -> RenderSettings {
    let mut s = RenderSettings::new(a.size, a.size, spp);
    s.passes = PassSchedule::Fixed { spp: a.pass_spp };
    if config.adaptive {
        s.adaptive = Some(AdaptiveSettings { threshold: a.threshold, min_spp: a.min_spp.min(spp) });
    }
    s
}

fn main() -> anyhow::Result<()> {
    let a = parse_args()?;
    std::fs::create_dir_all(&a.out)?;
    let configs: Vec<Config> = [(false, false), (true, false), (false, true), (true, true)]
        .into_iter()
        .map(|(adaptive, denoise)| Config { adaptive, denoise })
        .filter(|c| {
            let ok = !c.denoise || pathfarm_worker::denoise::AVAILABLE;
            if !ok {
                eprintln!("{}: skipped (build with --features denoise)", c.name());
            }
            ok
        })
        .collect();
    let mut results = Vec::new();
    for name in &a.scenes {
        let glb = match name.as_str() {
            "cornell" => cornell_mitsuba_glb(),
            "caustics" => caustics_glb(),
            other => anyhow::bail!("unknown scene {other:?} (cornell, caustics)"),
        };
        std::fs::write(a.out.join(format!("{name}.glb")), &glb)?;
        let scene: Scene = load_scene_from_slice(&glb, "scene.glb", None, &LoadOptions::default())?;

        // The reference: uniform, cached by size and spp.
        let ref_path = a.out.join(format!("{name}_{}px_{}spp.exr", a.size, a.ref_spp));
        let reference: Vec<[f32; 3]> = match pathfarm_common::film::read_exr(&ref_path) {
            Ok(exr) => {
                let c: Vec<&[f32]> = ["R", "G", "B"].iter().filter_map(|n| exr.get(n)).collect();
                anyhow::ensure!(c.len() == 3, "{}: no RGB", ref_path.display());
                (0..c[0].len()).map(|i| [c[0][i], c[1][i], c[2][i]]).collect()
            }
            Err(_) => {
                let mut s = RenderSettings::new(a.size, a.size, a.ref_spp);
                s.passes = PassSchedule::Fixed { spp: 256.min(a.ref_spp) };
                let t = Instant::now();
                let img = render_local(&Renderer::new(&scene, &s)?, |_, _| {}).resolve();
                eprintln!("{name}: reference {} spp in {:.1} s", a.ref_spp, t.elapsed().as_secs_f64());
                img.write_exr(&ref_path)?;
                img.rgb
            }
        };

        // The denoiser's cost at this size, for the equal-time budget.
        let denoise_s = if pathfarm_worker::denoise::AVAILABLE {
            let mut s = RenderSettings::new(a.size, a.size, 1);
            s.passes = PassSchedule::Fixed { spp: 1 };
            let img = render_local(&Renderer::new(&scene, &s)?, |_, _| {}).resolve();
            denoised(&img)?;
            (0..3)
                .map(|_| denoised(&img).map(|d| d.1))
                .collect::<anyhow::Result<Vec<f64>>>()?
                .into_iter()
                .fold(0.0, f64::max)
        } else {
            0.0
        };

        for &config in &configs {
            // Equal time.
            let t = Instant::now();
            let renderer = Renderer::new(&scene, &settings_for(&a, config, 1 << 16))?;
            let prep_s = t.elapsed().as_secs_f64();
            let budget = a.budget_s - prep_s - if config.denoise { denoise_s } else { 0.0 };
            let mut last: Option<(ImageLayers, f64, f64)> = None;
            progressive(&renderer, |film, clock, pass_s, samples| {
                last = Some((film.resolve(), clock, samples));
                clock + pass_s > budget
            })?;
            let (mut img, clock, samples) = last.context("no pass rendered")?;
            if config.denoise {
                img.rgb = denoised(&img)?.0;
            }
            let equal_time = rel_mse(&img.rgb, &reference);
            let spp = samples / f64::from(a.size * a.size);

            // Time to quality.
            let t = Instant::now();
            let renderer = Renderer::new(&scene, &settings_for(&a, config, 1 << 16))?;
            let prep_s = t.elapsed().as_secs_f64();
            let mut reached: Option<(f64, f64, f64)> = None;
            let mut error: anyhow::Result<()> = Ok(());
            let mut evaluated_at = 0.0;
            progressive(&renderer, |film, clock, _, samples| {
                // Judged when the samples grew by 5% (a denoise per pass would dominate the run).
                if samples < 1.05 * evaluated_at {
                    return clock > a.max_s;
                }
                evaluated_at = samples;
                let mut img = film.resolve();
                let mut extra = 0.0;
                if config.denoise {
                    match denoised(&img) {
                        Ok((d, s)) => (img.rgb, extra) = (d, s),
                        Err(e) => {
                            error = Err(e);
                            return true;
                        }
                    }
                }
                let e = rel_mse(&img.rgb, &reference);
                if e < a.target {
                    reached = Some((prep_s + clock + extra, e, samples / f64::from(a.size * a.size)));
                }
                reached.is_some() || clock > a.max_s
            })?;
            error?;
            let line = serde_json::json!({
                "scene": name, "config": config.name(), "size": a.size, "ref_spp": a.ref_spp,
                "budget_s": a.budget_s, "render_s": clock, "mean_spp": spp, "rel_mse_equal_time": equal_time,
                "threshold": config.adaptive.then_some(a.threshold), "min_spp": config.adaptive.then_some(a.min_spp),
                "target": a.target,
                "time_to_quality_s": reached.map(|r| r.0), "spp_at_quality": reached.map(|r| r.2),
            });
            eprintln!(
                "{name:9} {:14} equal time {:.1} s: relMSE {equal_time:.5} at {spp:.1} spp | relMSE < {:e}: {}",
                config.name(),
                a.budget_s,
                a.target,
                reached.map_or(format!("not within {} s", a.max_s), |r| format!("{:.2} s at {:.1} spp", r.0, r.2))
            );
            results.push(line);
        }
    }
    let path = a.out.join("results.json");
    std::fs::write(&path, serde_json::to_string_pretty(&results)?)?;
    eprintln!("wrote {}", path.display());
    Ok(())
}
