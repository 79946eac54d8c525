//! Renderer benchmark (prints figures; not a timed test). Run:
//!
//! ```sh
//! cargo bench -p pathfarm-worker --bench render            # everything
//! cargo bench -p pathfarm-worker --bench render -- quick   # skip the Mitsuba comparison
//! cargo bench -p pathfarm-worker --bench render -- sse2    # baseline kernels, not AVX2
//! cargo bench -p pathfarm-worker --bench render -- avx2    # AVX2 kernels where the CPU has AVX-512
//! cargo bench -p pathfarm-worker --bench render -- scalar  # path: one path at a time, not the wavefront
//! ```
//!
//! 1. BVH build time and Mrays/s for primary and diffuse (cosine) rays on
//!    01_vertex_count_32bit of the corpus (`PATHFARM_CORPUS`, default ../shared/scenes; 130k triangles), closest hit with full hit data.
//! 2. Direct-lighting samples/s on the reference Cornell box.
//! 3. Path tracing on the Cornell box at 256 x 256, max depth 8, 64 spp, 2 threads, in samples/s;
//!    when the `mitsuba` Python package is installed, the same scene with Mitsuba 3's
//!    `scalar_rgb` and `llvm_ad_rgb` variants (scripts/make-reference.py) and the
//!    ratios, of wall-clock throughput and of throughput per CPU-second (all threads' CPU time:
//!    less disturbed by other load on the machine); and the equal-time error: RMSE against the
//!    16k-spp reference of our render given the wall time of Mitsuba's llvm render of 64 spp,
//!    and of Mitsuba's. Then 5 rounds of ours and Mitsuba's llvm one right after the other,
//!    and the median of the rounds' ratios (a shared machine's speed drifts less within a
//!    round). Each timing, ours and Mitsuba's, is the median of several renders (3 of the
//!    Cornell box, 7 of the 130k scene). The comparisons render in one pass, as Mitsuba does;
//!    the figure for the farm's default progressive passes is printed beside it.
//!    Then both at max depth 1, 2 and 3 (the same settings otherwise): the time per sample of
//!    the first segment (camera ray, first hit, the film), what the second adds (one light
//!    sample and BSDF ray) and what each further bounce adds, ours against Mitsuba's.
//! 4. Path tracing on 01_vertex_count_32bit (64 spp) under a constant environment, and
//!    Mitsuba's throughput on the same view when installed; the equal-time error there, each
//!    renderer against its own 1,024-spp image (Mitsuba renders the glTF material with its
//!    `principled` BSDF, so the two images differ).

#![allow(clippy::print_stdout)] // a benchmark prints its figures

use glam::{UVec2, Vec2, Vec3A};
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::{LoadOptions, load_scene};
use pathfarm_worker::render::accel::RayQuery;
use pathfarm_worker::render::camera::Camera;
use pathfarm_worker::render::geometry::Frame;
use pathfarm_worker::render::scene::RenderScene;
use pathfarm_worker::render::wavefront::PathKernel;
use pathfarm_worker::render::wide::SimdLevel;
use pathfarm_worker::render::{Renderer, render_local};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// The repository's root (`reference/`, `scripts/`).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The third-party scenes: `PATHFARM_CORPUS`, else `../shared/scenes` beside the repository.
fn corpus() -> PathBuf {
    std::env::var_os("PATHFARM_CORPUS").map_or_else(|| repo().join("../shared/scenes"), PathBuf::from)
}

fn hash(mut x: u64) -> u64 {
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^ (x >> 33)
}

fn unit(x: u64) -> f32 {
    (hash(x) >> 40) as f32 / (1u64 << 24) as f32
}

/// The SIMD level the renders use: the CPU's best, or the baseline with the `sse2` argument, or
/// at most AVX2 with `avx2`.
fn simd_level() -> SimdLevel {
    if std::env::args().any(|a| a == "sse2") {
        SimdLevel::Baseline
    } else if std::env::args().any(|a| a == "avx2") {
        SimdLevel::Avx2.min(SimdLevel::detect())
    } else {
        SimdLevel::detect()
    }
}

/// The path kernel the renders use: the wavefront, or one path at a time with `scalar`.
fn path_kernel() -> PathKernel {
    if std::env::args().any(|a| a == "scalar") { PathKernel::Scalar } else { PathKernel::Wavefront }
}

fn bvh_figures() {
    let path = corpus().join("01_vertex_count_32bit/01_vertex_count_32bit.gltf");
    let scene = match load_scene(&path, &LoadOptions::default()) {
        Ok(s) => s,
        Err(e) => {
            println!("bvh: cannot load {}: {e}", path.display());
            return;
        }
    };
    let t0 = Instant::now();
    let mut rs = RenderScene::new(&scene);
    rs.set_simd_level(simd_level());
    let build = t0.elapsed().as_secs_f64();
    println!("bvh: {} triangles, scene + BVH build {:.1} ms", rs.triangle_count(), build * 1e3);
    let (w, h) = (512u32, 512u32);
    let cam = Camera::framing(scene.bounds(), w, h);
    let t1 = Instant::now();
    let mut hits = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let r = cam.generate_ray(UVec2::new(x, y), Vec2::splat(0.5));
            if let Some(si) = rs.intersect(r.o, r.d, f32::INFINITY) {
                hits.push(si);
            }
        }
    }
    let primary = t1.elapsed().as_secs_f64();
    println!(
        "bvh: primary rays {:.2} Mrays/s (1 thread, {} of {} hit)",
        f64::from(w * h) / primary / 1e6,
        hits.len(),
        w * h
    );
    // A pixel's 8 camera rays (jittered), one by one and as batches of 256 (the wavefront's
    // query, where a pixel's rays go through the BVH as a packet).
    let (w8, h8) = (256u32, 256u32);
    let cam8 = Camera::framing(scene.bounds(), w8, h8);
    let mut rays = Vec::with_capacity((w8 * h8 * 8) as usize);
    for y in 0..h8 {
        for x in 0..w8 {
            for k in 0..8u32 {
                let u = Vec2::new((k % 4) as f32 * 0.25 + 0.125, (k / 4) as f32 * 0.5 + 0.25);
                let r = cam8.generate_ray(UVec2::new(x, y), u);
                rays.push(RayQuery { o: r.o, d: r.d, t_max: f32::INFINITY, time: 0.0 });
            }
        }
    }
    let t = Instant::now();
    let mut one_hits = 0usize;
    for r in &rays {
        one_hits += usize::from(rs.intersect(r.o, r.d, r.t_max).is_some());
    }
    let one = t.elapsed().as_secs_f64();
    let (mut hit_buf, mut surfaces) = (Vec::new(), Vec::new());
    let t = Instant::now();
    let mut batch_hits = 0usize;
    for batch in rays.chunks(256) {
        rs.intersect_many(batch, &mut hit_buf, &mut surfaces);
        batch_hits += surfaces.iter().filter(|s| s.is_some()).count();
    }
    let batched = t.elapsed().as_secs_f64();
    assert_eq!(one_hits, batch_hits);
    println!(
        "bvh: primary rays, 8 per pixel: {:.2} Mrays/s one by one, {:.2} Mrays/s in batches (packets) (1 thread)",
        rays.len() as f64 / one / 1e6,
        rays.len() as f64 / batched / 1e6
    );
    let t2 = Instant::now();
    let mut n = 0u64;
    for (i, si) in hits.iter().enumerate() {
        for k in 0..4u64 {
            let (u1, u2) = (unit(i as u64 * 8 + k), unit(i as u64 * 8 + k + 4));
            let r = u1.sqrt();
            let phi = 2.0 * std::f32::consts::PI * u2;
            let local = Vec3A::new(r * phi.cos(), r * phi.sin(), (1.0 - u1).max(0.0).sqrt());
            let n_f = if si.ng.dot(Vec3A::Z) > 0.0 { si.ng } else { -si.ng };
            let d = Frame::from_z(n_f).from_local(local);
            let o = pathfarm_worker::render::geometry::offset_ray_origin(si.p, n_f, d);
            std::hint::black_box(rs.intersect(o, d, f32::INFINITY));
            n += 1;
        }
    }
    let diffuse = t2.elapsed().as_secs_f64();
    println!("bvh: diffuse rays {:.2} Mrays/s (1 thread, {n} rays)", n as f64 / diffuse / 1e6);
}

/// `s` rendered in one pass of all its samples, as Mitsuba renders them (the comparisons with
/// it use this). A job's default schedule is progressive (passes of 1, 2, 4, ... spp, for
/// images that refine as they come): each pass goes over the whole image again, which costs
/// cache locality (17% of the 130k scene's time at 64 spp, measured).
fn one_pass(mut s: RenderSettings) -> RenderSettings {
    s.passes = pathfarm_common::job::PassSchedule::Fixed { spp: s.spp };
    s
}

fn settings(spp: u32, integrator: IntegratorSettings) -> RenderSettings {
    let mut s = RenderSettings::new(256, 256, spp);
    s.integrator = integrator;
    s
}

/// The CPU's model name, family and model (`/proc/cpuinfo`), and the threads available;
/// "unknown" where there is no such file.
fn cpu_name() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |key: &str| {
        info.lines().find_map(|l| l.split_once(':').filter(|(k, _)| k.trim() == key).map(|(_, v)| v.trim().to_string()))
    };
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    match (field("model name"), field("cpu family"), field("model")) {
        (Some(name), Some(family), Some(model)) => {
            format!("{name} (family {family}, model {model}), {threads} threads")
        }
        _ => format!("unknown, {threads} threads"),
    }
}

/// CPU time of every thread of this process so far, in seconds (`/proc/self/stat`'s utime and
/// stime, in Linux's 100 Hz clock ticks); `None` where there is no such file.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The fields after the command name (which is in parentheses and may hold spaces).
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks = |i: usize| fields.get(i)?.parse::<u64>().ok();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    Some((ticks(11)? + ticks(12)?) as f64 / 100.0)
}

/// Renders `s` and returns the wall seconds, the CPU seconds (all threads) and the image.
fn time_render_cpu(
    scene: &pathfarm_common::scene::Scene,
    s: &RenderSettings,
) -> (f64, Option<f64>, pathfarm_common::film::ImageLayers) {
    let mut r = Renderer::new(scene, s).expect("renderer");
    r.set_simd_level(simd_level());
    r.set_path_kernel(path_kernel());
    let c = cpu_seconds();
    let t = Instant::now();
    let film = render_local(&r, |_, _| {});
    let wall = t.elapsed().as_secs_f64();
    (wall, c.zip(cpu_seconds()).map(|(a, b)| b - a), film.resolve())
}

/// [`time_render_cpu`] `repeats` times: the median wall and CPU seconds (as the Mitsuba script
/// reports its renders), and the image of the last.
fn time_render_median(
    scene: &pathfarm_common::scene::Scene,
    s: &RenderSettings,
    repeats: usize,
) -> (f64, Option<f64>, pathfarm_common::film::ImageLayers) {
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (mut walls, mut cpus) = (Vec::new(), Vec::new());
    let mut img = None;
    for _ in 0..repeats.max(1) {
        let (wall, cpu, i) = time_render_cpu(scene, s);
        walls.push(wall);
        cpus.extend(cpu);
        img = Some(i);
    }
    let cpu = (cpus.len() == walls.len()).then(|| median(cpus));
    (median(walls), cpu, img.expect("at least one render"))
}

fn time_render(scene: &pathfarm_common::scene::Scene, s: &RenderSettings) -> (f64, pathfarm_common::film::ImageLayers) {
    let (wall, _, img) = time_render_cpu(scene, s);
    (wall, img)
}

/// Our render in `budget` seconds (Mitsuba's time for its image): the spp that `samples_per_s`
/// (ours, measured before) affords at 256 x 256, rendered by `settings(spp)`; where the machine's
/// speed drifted and the render overran the budget, again with proportionally fewer spp (at most
/// twice), so that the comparison never gives us more time than Mitsuba had.
fn equal_time_render(
    scene: &pathfarm_common::scene::Scene,
    settings: impl Fn(u32) -> RenderSettings,
    budget: f64,
    samples_per_s: f64,
) -> (u32, f64, pathfarm_common::film::ImageLayers) {
    let mut spp = ((budget * samples_per_s / (256.0 * 256.0)).floor() as u32).max(1);
    let mut tries = 0;
    loop {
        let (t, img) = time_render(scene, &settings(spp));
        tries += 1;
        if t <= budget || spp == 1 || tries == 3 {
            return (spp, t, img);
        }
        spp = ((f64::from(spp) * budget / t).floor() as u32).clamp(1, spp - 1);
    }
}

/// How much more efficient ours is than Mitsuba's (1 / (MSE x seconds) of each, ours over
/// theirs): the equal-time comparison made independent of the two times' small difference.
fn efficiency_ratio(ours_rmse: f64, ours_s: f64, theirs_rmse: f64, theirs_s: f64) -> f64 {
    (theirs_rmse * theirs_rmse * theirs_s) / (ours_rmse * ours_rmse * ours_s)
}

fn rmse(a: &[[f32; 3]], r: &[f32], g: &[f32], b: &[f32]) -> f64 {
    let mut sum = 0.0;
    for (i, p) in a.iter().enumerate() {
        for (c, reference) in [r, g, b].iter().enumerate() {
            let d = f64::from(p[c]) - f64::from(reference[i]);
            sum += d * d;
        }
    }
    (sum / (a.len() * 3) as f64).sqrt()
}

/// What the reference script measured: samples/s and render seconds (medians of wall time),
/// samples per CPU-second (median), and the image it wrote.
struct MitsubaRun {
    samples_per_s: f64,
    seconds: f64,
    samples_per_cpu_s: Option<f64>,
    exr: PathBuf,
}

/// Rounds of ours then Mitsuba's llvm_ad_rgb on one scene (each the median of its renders),
/// one right after the other: a shared machine's speed drifts over the minutes a bench takes,
/// so the ratio within a round, and the median of the rounds' ratios, is the steadier figure.
/// Five rounds, not three: on an AMD EPYC whose speed varied by 10-15% from render to render,
/// one run's three Cornell rounds gave 1.33, 1.29 and 1.10; the median of five is the steadier
/// estimate (it stands while two rounds are disturbed).
fn paired_rounds(
    name: &str,
    scene: &pathfarm_common::scene::Scene,
    s: &RenderSettings,
    repeats: usize,
    llvm: impl Fn() -> Option<MitsubaRun>,
) {
    const ROUNDS: usize = 5;
    let samples = f64::from(s.width) * f64::from(s.height) * f64::from(s.spp);
    // Per wall-clock second, and per CPU-second where both sides measured it.
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for round in 1..=ROUNDS {
        let (t, ours_cpu, _) = time_render_median(scene, s, repeats);
        let Some(llvm) = llvm() else { return };
        let ratio = samples / t / llvm.samples_per_s;
        let cpu_ratio = ours_cpu.zip(llvm.samples_per_cpu_s).map(|(c, m)| samples / c / m);
        println!(
            "{name} round {round}: ours {:.2} M samples/s, mitsuba llvm_ad_rgb {:.2} M samples/s: {ratio:.2}{}",
            samples / t / 1e6,
            llvm.samples_per_s / 1e6,
            cpu_ratio.map_or(String::new(), |r| format!(" (per CPU-second {r:.2})"))
        );
        wall.push(ratio);
        cpu.extend(cpu_ratio);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        format!("{:.2} ({:.2} - {:.2})", v[v.len() / 2], v[0], v[v.len() - 1])
    };
    let cpu = if cpu.len() == ROUNDS { format!("; per CPU-second {}", median(&mut cpu)) } else { String::new() };
    println!("ours / llvm_ad_rgb on {name}, median of {ROUNDS} interleaved rounds: {}{cpu}", median(&mut wall));
}

/// Runs the reference script.
fn mitsuba(variant: &str, spp: u32) -> Option<MitsubaRun> {
    mitsuba_with(variant, spp, spp, 8, "cornell", CORNELL_REPEATS, &[])
}

/// Renders per timing (ours and Mitsuba's, each the median): the Cornell box's take about 2 s
/// each, the 130k scene's about 0.2 s (so more of them).
const CORNELL_REPEATS: usize = 3;
const LARGE_REPEATS: usize = 7;

/// [`mitsuba`] with more arguments for the script (another scene); `tag` names its output.
#[allow(clippy::too_many_arguments)]
fn mitsuba_with(
    variant: &str,
    spp: u32,
    spp_per_pass: u32,
    max_depth: u32,
    tag: &str,
    repeats: usize,
    extra: &[&std::ffi::OsStr],
) -> Option<MitsubaRun> {
    let out = std::env::temp_dir().join(format!("pathfarm_bench_mitsuba_{tag}_{variant}_{spp}.exr"));
    let script = repo().join("scripts/make-reference.py");
    let mut cmd = Command::new("python3");
    // drjit's LLVM backend needs a recent libLLVM (Debian's default 14 fails with "Cannot select
    // fminimum"): point it at the newest one installed (`apt-get install libllvm19`).
    if let (None, Some(lib)) = (std::env::var_os("DRJIT_LIBLLVM_PATH"), newest_libllvm()) {
        cmd.env("DRJIT_LIBLLVM_PATH", lib);
    }
    let o = cmd
        .arg(script)
        .args(["--variant", variant, "--spp", &spp.to_string(), "--spp-per-pass", &spp_per_pass.to_string()])
        .args(["--res", "256", "--repeats", &repeats.to_string(), "--threads", "2"])
        .args(["--max-depth", &max_depth.to_string(), "--out"])
        .arg(&out)
        .args(extra)
        .output()
        .ok()?;
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text.lines().find_map(|l| l.strip_prefix("RESULT "))?;
    let v: serde_json::Value = serde_json::from_str(line).ok()?;
    Some(MitsubaRun {
        samples_per_s: v["samples_per_s_median"].as_f64()?,
        seconds: v["render_median_s"].as_f64()?,
        samples_per_cpu_s: v["samples_per_cpu_s_median"].as_f64(),
        exr: out,
    })
}

/// Path tracing on the 130k-triangle 01_vertex_count_32bit at 256 x 256, 64 spp, max depth 8,
/// 2 threads, from the default camera under a constant environment of radiance 1 (the scene has
/// neither camera nor lights); without `quick`, the same scene in Mitsuba (the script's
/// `--gltf`: PLY meshes, its `principled` BSDF for the glTF material, so only the throughput
/// compares).
fn large_scene_figures(quick: bool) {
    let path = corpus().join("01_vertex_count_32bit/01_vertex_count_32bit.gltf");
    let Ok(scene) = load_scene(&path, &LoadOptions::default()) else {
        println!("path 130k: cannot load {}", path.display());
        return;
    };
    let spp = 64;
    let s = large_scene_settings(spp);
    let samples = 256.0 * 256.0 * f64::from(spp);
    let (t_prog, cpu_prog, _) = time_render_median(&scene, &s, LARGE_REPEATS);
    let (t, cpu, _) = time_render_median(&scene, &one_pass(s), LARGE_REPEATS);
    let ours = samples / t;
    let ours_cpu = cpu.map(|c| samples / c);
    println!(
        "path: 01_vertex_count_32bit 256x256x{spp} max_depth 8, 2 threads, constant environment, one pass: {:.2} M samples/s ({t:.2} s); {}; progressive passes: {:.2} M samples/s ({t_prog:.2} s); {}",
        ours / 1e6,
        per_cpu_second(ours_cpu),
        samples / t_prog / 1e6,
        per_cpu_second(cpu_prog.map(|c| samples / c))
    );
    if quick {
        return;
    }
    let gltf = ["--gltf".as_ref(), path.as_os_str()];
    let mut llvm = None;
    for variant in ["scalar_rgb", "llvm_ad_rgb"] {
        let Some(m) = mitsuba_with(variant, spp, spp, 8, "vertex_count", LARGE_REPEATS, &gltf) else {
            println!("mitsuba {variant} on 01_vertex_count_32bit: no result");
            continue;
        };
        let cpu =
            ours_cpu.zip(m.samples_per_cpu_s).map_or(String::new(), |(o, m)| format!(", per CPU-second {:.2}", o / m));
        println!(
            "mitsuba {variant} on 01_vertex_count_32bit: {:.2} M samples/s; {}; ours / {variant} = {:.2}{cpu}",
            m.samples_per_s / 1e6,
            per_cpu_second(m.samples_per_cpu_s),
            ours / m.samples_per_s
        );
        if variant == "llvm_ad_rgb" {
            llvm = Some(m);
        }
    }
    let s_one = one_pass(large_scene_settings(spp));
    paired_rounds("01_vertex_count_32bit", &scene, &s_one, LARGE_REPEATS, || {
        mitsuba_with("llvm_ad_rgb", spp, spp, 8, "vertex_count", LARGE_REPEATS, &gltf)
    });
    // Equal-time error. Each renderer is compared with its own converged image (1,024 spp):
    // Mitsuba renders the glTF material with its `principled` BSDF, so the images differ.
    let Some(llvm) = llvm else { return };
    // The references use other seeds than the timed renders: a sample sequence's prefix would
    // share its errors with the whole.
    let reference_spp = 1024;
    let mut reference = one_pass(large_scene_settings(reference_spp));
    reference.seed = 1000;
    let (_, _, ours_ref) = time_render_median(&scene, &reference, 1);
    let seeded = [gltf[0], gltf[1], "--seed".as_ref(), "1000".as_ref()];
    let Some(m_ref) = mitsuba_with("llvm_ad_rgb", reference_spp, spp, 8, "vertex_count_ref", 1, &seeded) else {
        println!("mitsuba llvm_ad_rgb on 01_vertex_count_32bit, {reference_spp} spp: no result");
        return;
    };
    let channels = |img: &[[f32; 3]]| -> [Vec<f32>; 3] { std::array::from_fn(|c| img.iter().map(|p| p[c]).collect()) };
    let [r, g, b] = channels(&ours_ref.rgb);
    let (spp_eq, t_eq, img) = equal_time_render(&scene, |spp| one_pass(large_scene_settings(spp)), llvm.seconds, ours);
    let ours_rmse = rmse(&img.rgb, &r, &g, &b);
    let (Ok(m), Ok(m_ref)) = (pathfarm_common::film::read_exr(&llvm.exr), pathfarm_common::film::read_exr(&m_ref.exr))
    else {
        println!("mitsuba on 01_vertex_count_32bit: cannot read its images");
        return;
    };
    let pixel = |e: &pathfarm_common::film::ExrChannels, i: usize| {
        [e.get("R").map_or(0.0, |c| c[i]), e.get("G").map_or(0.0, |c| c[i]), e.get("B").map_or(0.0, |c| c[i])]
    };
    let mi: Vec<[f32; 3]> = (0..65536).map(|i| pixel(&m, i)).collect();
    let [mr, mg, mb] = channels(&(0..65536).map(|i| pixel(&m_ref, i)).collect::<Vec<_>>());
    let m_rmse = rmse(&mi, &mr, &mg, &mb);
    println!(
        "equal time on 01_vertex_count_32bit ({:.2} s), each against its own {reference_spp}-spp image: ours {spp_eq} spp in {t_eq:.2} s RMSE {ours_rmse:.5}; mitsuba llvm {spp} spp RMSE {m_rmse:.5}; efficiency (1 / (MSE x s)) ours / mitsuba {:.1}",
        llvm.seconds,
        efficiency_ratio(ours_rmse, t_eq, m_rmse, llvm.seconds)
    );
}

/// The settings of [`large_scene_figures`]: path tracing at 256 x 256, max depth 8, under a
/// constant environment of radiance 1.
fn large_scene_settings(spp: u32) -> RenderSettings {
    let mut s = settings(
        spp,
        IntegratorSettings::Path {
            max_depth: 8,
            rr_depth: 5,
            mis: MisHeuristic::Power,
            light_sampling: LightSampling::Area,
        },
    );
    s.environment = Some(pathfarm_common::job::EnvironmentSettings {
        file: None,
        color: Some([1.0; 3]),
        intensity: 1.0,
        rotation_deg: 0.0,
    });
    s
}

/// "x M samples per CPU-second" (the render's throughput per busy core, which the machine's
/// load disturbs less than wall time), or nothing where it was not measured.
fn per_cpu_second(samples_per_cpu_s: Option<f64>) -> String {
    samples_per_cpu_s
        .map_or_else(|| "CPU time not measured".into(), |s| format!("{:.2} M samples per CPU-second", s / 1e6))
}

/// The newest `libLLVM-N.so` in the system library directory.
fn newest_libllvm() -> Option<PathBuf> {
    let dir = Path::new("/usr/lib/x86_64-linux-gnu");
    std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| {
            let name = e.ok()?.file_name().into_string().ok()?;
            let version: u32 = name.strip_prefix("libLLVM-")?.strip_suffix(".so")?.parse().ok()?;
            Some((version, dir.join(name)))
        })
        .max()
        .map(|(_, p)| p)
}

/// `tiny`: one small path-traced render on one thread, for instruction counts under
/// `valgrind --tool=callgrind` (repeatable whatever the machine's load); `tiny solid`: with
/// solid-angle light sampling; `tiny igi` and `tiny bdpt`: the same with those integrators;
/// `tiny long`: 16x the pixels (for sampling profilers such as perf); `tiny large`: the
/// 130k-triangle scene of [`large_scene_figures`] at 16 spp (`tiny large long`: 256 spp); with
/// `onepass`, any of them in one pass ([`one_pass`]); with `threads2`, on 2 threads.
fn tiny() {
    let scene = load_scene(&repo().join("reference/cornell_mitsuba.glb"), &LoadOptions::default()).expect("cornell");
    let mut s = RenderSettings::new(64, 64, 16);
    s.integrator = IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::Area,
    };
    let mut name = "path (area)";
    if std::env::args().any(|a| a == "solid") {
        s.integrator = IntegratorSettings::Path {
            max_depth: 8,
            rr_depth: 5,
            mis: MisHeuristic::Power,
            light_sampling: LightSampling::SolidAngle,
        };
        name = "path (solid angle)";
    }
    if std::env::args().any(|a| a == "igi") {
        s = RenderSettings::new(32, 32, 8);
        s.integrator =
            IntegratorSettings::Igi { vpls: 64, vpl_sets: 4, g_limit: 10.0, bias_compensation: true, max_depth: 8 };
        name = "igi (64 VPLs, compensation)";
    }
    if std::env::args().any(|a| a == "bdpt") {
        s = RenderSettings::new(32, 32, 16);
        s.integrator = IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 5, strategy: None };
        name = "bdpt";
    }
    if std::env::args().any(|a| a == "large") {
        let path = corpus().join("01_vertex_count_32bit/01_vertex_count_32bit.gltf");
        let Ok(large) = load_scene(&path, &LoadOptions::default()) else {
            println!("tiny large: cannot load {}", path.display());
            return;
        };
        // `tiny large long`: 16x the samples (for sampling profilers).
        let long = std::env::args().any(|a| a == "long");
        let mut s = large_scene_settings(if long { 256 } else { 16 });
        if std::env::args().any(|a| a == "onepass") {
            s = one_pass(s);
        }
        let (t, _) = time_render(&large, &s);
        println!("tiny: 01_vertex_count_32bit {}x{}x{} path in {t:.3} s", s.width, s.height, s.spp);
        return;
    }
    // `depth2`, `depth3`, ...: the path integrator at that max depth (where per-sample costs
    // dominate: the camera stage, the first hit, one light sample, the film).
    if let Some(depth) = std::env::args().find_map(|a| a.strip_prefix("depth").and_then(|d| d.parse::<u32>().ok()))
        && let IntegratorSettings::Path { max_depth, .. } = &mut s.integrator
    {
        *max_depth = depth;
        name = "path (max depth from the arguments)";
    }
    if std::env::args().any(|a| a == "onepass") {
        s = one_pass(s);
    }
    if std::env::args().any(|a| a == "long") {
        // For sampling profilers (perf): 16x the pixels, same settings otherwise.
        s.width *= 4;
        s.height *= 4;
    }
    let (t, img) = time_render(&scene, &s);
    println!(
        "tiny: {}x{}x{} {name} in {t:.3} s, mean R {:.4}",
        s.width,
        s.height,
        s.spp,
        img.rgb.iter().map(|p| p[0]).sum::<f32>() / img.rgb.len() as f32
    );
}

fn main() {
    if std::env::args().any(|a| a == "tiny") {
        println!("simd: {} kernels, {:?} path kernel", simd_level().name(), path_kernel());
        // `threads2`: on 2 threads (for how a render uses the pool, such as `render_local`'s
        // folds beside the renders).
        let threads = if std::env::args().any(|a| a == "threads2") { 2 } else { 1 };
        rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().ok();
        return tiny();
    }
    let quick = std::env::args().any(|a| a == "quick");
    println!("simd: {} kernels, {:?} path kernel", simd_level().name(), path_kernel());
    // Ratios against Mitsuba move with the CPU (its llvm variant runs 16 lanes where there is
    // AVX-512, 8 with AVX2): name the machine with its figures.
    println!("cpu: {}", cpu_name());
    rayon::ThreadPoolBuilder::new().num_threads(2).build_global().ok();
    bvh_figures();

    let reference = repo().join("reference");
    let scene = load_scene(&reference.join("cornell_mitsuba.glb"), &LoadOptions::default()).expect("cornell");
    let direct = IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: LightSampling::SolidAngle };
    let (t, _) = time_render(&scene, &settings(64, direct));
    println!("direct: cornell 256x256x64, 2 threads: {:.2} M samples/s", 256.0 * 256.0 * 64.0 / t / 1e6);

    // Mitsuba samples its rectangle emitter by area: that is the like-for-like comparison.
    // Our default, solid-angle sampling (Arvo), costs more per sample and lowers variance.
    let path_with = |light_sampling| IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling,
    };
    let (t_sa, _) = time_render(&scene, &settings(64, path_with(LightSampling::SolidAngle)));
    println!(
        "path: cornell 256x256x64 max_depth 8, 2 threads, solid-angle light sampling: {:.2} M samples/s ({t_sa:.2} s)",
        256.0 * 256.0 * 64.0 / t_sa / 1e6
    );
    let path = path_with(LightSampling::Area);
    let samples = 256.0 * 256.0 * 64.0;
    let (t_prog, cpu_prog, _) = time_render_median(&scene, &settings(64, path.clone()), CORNELL_REPEATS);
    let (t, cpu, _) = time_render_median(&scene, &one_pass(settings(64, path.clone())), CORNELL_REPEATS);
    let ours = samples / t;
    let ours_cpu = cpu.map(|c| samples / c);
    println!(
        "path: cornell 256x256x64 max_depth 8, 2 threads, area light sampling, one pass: {:.2} M samples/s ({t:.2} s); {}; progressive passes: {:.2} M samples/s ({t_prog:.2} s); {}",
        ours / 1e6,
        per_cpu_second(ours_cpu),
        samples / t_prog / 1e6,
        per_cpu_second(cpu_prog.map(|c| samples / c))
    );
    large_scene_figures(quick);
    if quick {
        return;
    }
    let exr = pathfarm_common::film::read_exr(&reference.join("cornell_mitsuba_box_16384spp.exr")).expect("reference");
    let (r, g, b) = (exr.get("R").expect("R"), exr.get("G").expect("G"), exr.get("B").expect("B"));
    let Some(scalar) = mitsuba("scalar_rgb", 64) else {
        println!("mitsuba: not installed (pip install mitsuba) - no comparison");
        return;
    };
    let ratios = |m: &MitsubaRun| {
        let cpu =
            ours_cpu.zip(m.samples_per_cpu_s).map_or(String::new(), |(o, m)| format!(", per CPU-second {:.2}", o / m));
        format!("{:.2}{cpu}", ours / m.samples_per_s)
    };
    println!(
        "mitsuba scalar_rgb: {:.2} M samples/s; {}; ours / scalar_rgb = {}",
        scalar.samples_per_s / 1e6,
        per_cpu_second(scalar.samples_per_cpu_s),
        ratios(&scalar)
    );
    let Some(llvm) = mitsuba("llvm_ad_rgb", 64) else { return };
    println!(
        "mitsuba llvm_ad_rgb: {:.2} M samples/s; {}; ours / llvm_ad_rgb = {}",
        llvm.samples_per_s / 1e6,
        per_cpu_second(llvm.samples_per_cpu_s),
        ratios(&llvm)
    );
    paired_rounds("the Cornell box", &scene, &one_pass(settings(64, path.clone())), CORNELL_REPEATS, || {
        mitsuba("llvm_ad_rgb", 64)
    });
    let (llvm_s, llvm_exr) = (llvm.seconds, llvm.exr);
    // Equal time: our spp for Mitsuba llvm's 64-spp wall time.
    let (spp, t_eq, img) = equal_time_render(&scene, |spp| one_pass(settings(spp, path.clone())), llvm_s, ours);
    let ours_rmse = rmse(&img.rgb, r, g, b);
    if let Ok(m) = pathfarm_common::film::read_exr(&llvm_exr) {
        let mi: Vec<[f32; 3]> = (0..65536)
            .map(|i| {
                [m.get("R").map_or(0.0, |c| c[i]), m.get("G").map_or(0.0, |c| c[i]), m.get("B").map_or(0.0, |c| c[i])]
            })
            .collect();
        let m_rmse = rmse(&mi, r, g, b);
        println!(
            "equal time ({llvm_s:.2} s): ours {spp} spp in {t_eq:.2} s RMSE {ours_rmse:.5}; mitsuba llvm 64 spp RMSE {m_rmse:.5}; efficiency (1 / (MSE x s)) ours / mitsuba {:.1}",
            efficiency_ratio(ours_rmse, t_eq, m_rmse, llvm_s)
        );
    }
    depth_figures(&scene, &settings(64, path), ours, llvm.samples_per_s);
}

/// Where the Cornell box's time goes against Mitsuba's llvm_ad_rgb: both renderers with the
/// comparison's settings `s` (a path integrator, in one pass) but at max depth 1 (camera ray,
/// first hit, emission found there, the film: the per-sample costs; ours also makes the first
/// hit's albedo and normal), 2 (one light sample and one BSDF ray more) and 3 (one bounce
/// more); the time per sample of each, and what each depth adds to it, against `ours_8` and
/// `mitsuba_8` (the comparison's samples/s at its max depth, 8).
fn depth_figures(scene: &pathfarm_common::scene::Scene, s: &RenderSettings, ours_8: f64, mitsuba_8: f64) {
    let samples = f64::from(s.width) * f64::from(s.height) * f64::from(s.spp);
    let (mut ours_ns, mut mitsuba_ns) = (Vec::new(), Vec::new());
    for depth in [1, 2, 3] {
        let mut at_depth = one_pass(s.clone());
        if let IntegratorSettings::Path { max_depth, .. } = &mut at_depth.integrator {
            *max_depth = depth;
        }
        let (t, _, _) = time_render_median(scene, &at_depth, CORNELL_REPEATS);
        let Some(m) = mitsuba_with("llvm_ad_rgb", s.spp, s.spp, depth, "cornell_depth", CORNELL_REPEATS, &[]) else {
            println!("mitsuba llvm_ad_rgb at max depth {depth}: no result");
            return;
        };
        let ours = samples / t;
        println!(
            "the Cornell box at max depth {depth}: ours {:.2} M samples/s, mitsuba llvm_ad_rgb {:.2}: {:.2}",
            ours / 1e6,
            m.samples_per_s / 1e6,
            ours / m.samples_per_s
        );
        ours_ns.push(1e9 / ours);
        mitsuba_ns.push(1e9 / m.samples_per_s);
    }
    ours_ns.push(1e9 / ours_8);
    mitsuba_ns.push(1e9 / mitsuba_8);
    // Nanoseconds (wall, 2 threads) per sample: at depth 1, then what depths 2, 3 and 4-8 add.
    let parts = |ns: &[f64]| [ns[0], ns[1] - ns[0], ns[2] - ns[1], ns[3] - ns[2]];
    let (o, m) = (parts(&ours_ns), parts(&mitsuba_ns));
    let names = ["depth 1", "depth 2 adds", "depth 3 adds", "depths 4-8 add"];
    let figures: Vec<String> =
        (0..4).map(|i| format!("{} {:.0} / {:.0} ({:.2}x)", names[i], o[i], m[i], o[i] / m[i])).collect();
    println!("ns per sample, ours / mitsuba llvm_ad_rgb: {}", figures.join(", "));
}
