//! `pathfarm-worker render`: render a scene locally, with the same plan and merge as the farm.

use crate::render::{Renderer, render_local};
use anyhow::Context;
use clap::{Args, ValueEnum};
use pathfarm_common::frames::{FrameSet, frame_path};
use pathfarm_common::job::{
    EnvironmentSettings, IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings, SamplerKind,
};
use pathfarm_common::scene::{LoadOptions, load_job_environment, load_scene};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum IntegratorArg {
    Direct,
    Path,
    Bdpt,
    Igi,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum MisArg {
    Balance,
    Power,
    Light,
    Bsdf,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum LightSamplingArg {
    Area,
    SolidAngle,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum SamplerArg {
    Sobol,
    Independent,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq, Eq)]
pub enum OnOff {
    On,
    Off,
}

/// Job settings shared by `render` and the client CLI.
#[derive(Args, Debug, Clone)]
pub struct SettingsArgs {
    #[arg(long, default_value_t = 256)]
    pub width: u32,
    #[arg(long, default_value_t = 256)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    #[arg(long, value_enum, default_value = "path")]
    pub integrator: IntegratorArg,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Scene camera index (default: camera 0, or a camera framing the scene).
    #[arg(long)]
    pub camera: Option<usize>,
    #[arg(long, value_enum, default_value = "power")]
    pub mis: MisArg,
    /// Path segments (Mitsuba's convention: 1 = emitters only, 2 = direct); 0 = no limit.
    #[arg(long, default_value_t = 8)]
    pub max_depth: u32,
    /// Scattering events before Russian roulette starts.
    #[arg(long, default_value_t = 3)]
    pub rr_depth: u32,
    #[arg(long, value_enum, default_value = "solid-angle")]
    pub light_sampling: LightSamplingArg,
    #[arg(long, value_enum, default_value = "sobol")]
    pub sampler: SamplerArg,
    #[arg(long, default_value_t = 64)]
    pub tile_size: u32,
    /// Samples per pass; 0 = doubling passes (1, 2, 4, ... up to 64).
    #[arg(long, default_value_t = 0)]
    pub pass_spp: u32,
    /// IGI: virtual point lights per set.
    #[arg(long, default_value_t = 64)]
    pub vpls: u32,
    /// IGI: independent VPL sets per pass.
    #[arg(long, default_value_t = 4)]
    pub vpl_sets: u32,
    /// IGI: clamp of the geometry term.
    #[arg(long, default_value_t = 10.0)]
    pub g_limit: f32,
    /// IGI: add back the clamped-away energy by BSDF sampling.
    #[arg(long, value_enum, default_value = "off")]
    pub bias_compensation: OnOff,
    /// BDPT: render only the MIS-weighted strategy `s,t` (s light vertices, t camera vertices).
    #[arg(long, value_parser = parse_strategy)]
    pub bdpt_strategy: Option<[u32; 2]>,
    /// Environment light: an equirectangular .exr/.hdr beside the scene file (in the bundle),
    /// or a constant linear colour `r,g,b`.
    #[arg(long)]
    pub environment: Option<String>,
    /// Multiplies the environment's image or colour.
    #[arg(long, default_value_t = 1.0)]
    pub environment_intensity: f32,
    /// Turns the environment about +Y (degrees, counter-clockwise seen from above).
    #[arg(long, default_value_t = 0.0)]
    pub environment_rotation: f32,
    /// Thin lens: aperture radius in scene units (0 = pinhole).
    #[arg(long, default_value_t = 0.0)]
    pub aperture_radius: f32,
    /// Thin lens: distance in focus along the view axis (scene units).
    #[arg(long)]
    pub focus_distance: Option<f32>,
    /// Preview (PNG) exposure in stops (EV); the EXR keeps the true radiance.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub exposure: f32,
    /// Previews expose automatically (log-average luminance to middle grey 0.18); `--exposure`
    /// adds to it.
    #[arg(long)]
    pub auto_exposure: bool,
    /// Adaptive sampling: after each pass, 8x8 pixel blocks whose relative error (standard
    /// error of the mean luminance over the mean) is at most this get no more samples.
    #[arg(long)]
    pub adaptive_threshold: Option<f32>,
    /// Adaptive sampling: samples every pixel gets before a block may stop (default: 16, or
    /// spp if smaller).
    #[arg(long, requires = "adaptive_threshold")]
    pub min_spp: Option<u32>,
    /// Also write a `denoised` layer (Intel Open Image Denoise, from colour, albedo and normal);
    /// the PNG shows it. A local render needs a binary built with the `denoise` feature; a farm
    /// job asks for it (`"denoise": true`).
    #[arg(long)]
    pub denoise: bool,
    /// With `--denoise`, on a farm (`pathfarm submit`): also denoise after every completed pass,
    /// for the preview. A local render denoises the final frame only.
    #[arg(long, requires = "denoise")]
    pub denoise_preview: bool,
}

/// `--min-spp`'s default: 16 samples, or the job's spp if it has fewer.
pub const DEFAULT_MIN_SPP: u32 = 16;

/// `--environment`: `r,g,b` is a colour, anything else a file.
fn environment_arg(v: &str, intensity: f32, rotation_deg: f32) -> EnvironmentSettings {
    let rgb: Vec<f32> = v.split(',').filter_map(|x| x.trim().parse().ok()).collect();
    let (file, color) = match rgb[..] {
        [r, g, b] if v.split(',').count() == 3 => (None, Some([r, g, b])),
        _ => (Some(v.to_string()), None),
    };
    EnvironmentSettings { file, color, intensity, rotation_deg }
}

/// Parses `s,t` for `--bdpt-strategy`.
fn parse_strategy(v: &str) -> Result<[u32; 2], String> {
    let (s, t) = v.split_once(',').ok_or_else(|| format!("expected s,t (e.g. 1,2), got {v:?}"))?;
    let parse = |x: &str| x.trim().parse::<u32>().map_err(|e| format!("{x:?} in {v:?}: {e}"));
    Ok([parse(s)?, parse(t)?])
}

impl SettingsArgs {
    pub fn to_settings(&self) -> RenderSettings {
        let mis = match self.mis {
            MisArg::Balance => MisHeuristic::Balance,
            MisArg::Power => MisHeuristic::Power,
            MisArg::Light => MisHeuristic::Light,
            MisArg::Bsdf => MisHeuristic::Bsdf,
        };
        let light_sampling = match self.light_sampling {
            LightSamplingArg::Area => LightSampling::Area,
            LightSamplingArg::SolidAngle => LightSampling::SolidAngle,
        };
        let integrator = match self.integrator {
            IntegratorArg::Direct => IntegratorSettings::Direct { mis, light_sampling },
            IntegratorArg::Path => {
                IntegratorSettings::Path { max_depth: self.max_depth, rr_depth: self.rr_depth, mis, light_sampling }
            }
            IntegratorArg::Bdpt => IntegratorSettings::Bdpt {
                max_depth: self.max_depth,
                mis,
                rr_depth: self.rr_depth,
                strategy: self.bdpt_strategy,
            },
            IntegratorArg::Igi => IntegratorSettings::Igi {
                vpls: self.vpls,
                vpl_sets: self.vpl_sets,
                g_limit: self.g_limit,
                bias_compensation: self.bias_compensation == OnOff::On,
                max_depth: self.max_depth,
            },
        };
        let mut s = RenderSettings::new(self.width, self.height, self.spp);
        s.seed = self.seed;
        s.camera = self.camera;
        s.integrator = integrator;
        s.sampler = match self.sampler {
            SamplerArg::Sobol => SamplerKind::Sobol,
            SamplerArg::Independent => SamplerKind::Independent,
        };
        s.tile_size = self.tile_size;
        if self.pass_spp > 0 {
            s.passes = PassSchedule::Fixed { spp: self.pass_spp };
        }
        s.environment = self
            .environment
            .as_deref()
            .map(|v| environment_arg(v, self.environment_intensity, self.environment_rotation));
        s.aperture_radius = self.aperture_radius;
        s.focus_distance = self.focus_distance;
        s.exposure = self.exposure;
        s.auto_exposure = self.auto_exposure;
        s.adaptive = self.adaptive_threshold.map(|threshold| pathfarm_common::adaptive::AdaptiveSettings {
            threshold,
            min_spp: self.min_spp.unwrap_or(DEFAULT_MIN_SPP.min(self.spp)),
        });
        s.denoise = self.denoise;
        s.denoise_preview = self.denoise_preview;
        s
    }
}

/// Which animation frame(s) `render` draws.
#[derive(Args, Debug, Clone)]
pub struct FrameArgs {
    /// Animation frame: the scene is posed at time frame / fps seconds.
    #[arg(long, default_value_t = 0, allow_hyphen_values = true, conflicts_with = "frames")]
    pub frame: i32,
    /// A sequence ("1-24", "1-100x5", "1,5,10-20"): one image per frame, named by `--out` with
    /// its `#` run replaced by the zero-padded frame (`out/shot.####.exr`).
    #[arg(long)]
    pub frames: Option<String>,
    /// Frames per second (frame numbers -> animation time).
    #[arg(long, default_value_t = 24.0)]
    pub fps: f32,
    /// Motion blur: the fraction of a frame the shutter stays open (0 = off).
    #[arg(long, default_value_t = 0.0)]
    pub shutter: f32,
    /// The animations that play, comma-separated (default: all of them).
    #[arg(long, value_delimiter = ',')]
    pub animations: Option<Vec<String>>,
}

impl FrameArgs {
    /// Writes frame, fps, shutter and animations into `s`.
    pub fn apply(&self, s: &mut RenderSettings) {
        s.frame = self.frame;
        s.fps = self.fps;
        s.shutter = self.shutter;
        s.animations = self.animations.clone();
    }
}

/// `pathfarm-worker render` arguments.
#[derive(Args, Debug, Clone)]
pub struct RenderArgs {
    /// A .glb or .gltf file.
    pub scene: PathBuf,
    #[command(flatten)]
    pub settings: SettingsArgs,
    #[command(flatten)]
    pub frames: FrameArgs,
    /// Output OpenEXR file (with `--frames`: a pattern whose `#` run becomes the frame number).
    #[arg(long, default_value = "out.exr")]
    pub out: PathBuf,
    /// Also write an sRGB PNG preview (with `--frames`: a pattern like `--out`).
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// Runs `pathfarm-worker render`.
pub fn render(args: RenderArgs) -> anyhow::Result<()> {
    if let Some(n) = args.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n.max(1)).build_global().context("thread pool")?;
    }
    if args.settings.denoise {
        // Before the render, not after it.
        crate::denoise::ensure_available()?;
    }
    let mut settings = args.settings.to_settings();
    args.frames.apply(&mut settings);
    settings.validate(&pathfarm_common::job::Limits::default()).context("invalid settings")?;
    let frames = match &args.frames.frames {
        Some(spec) => Some(FrameSet::parse(spec)?),
        None => None,
    };
    // The scene is loaded once; each frame poses it and builds its own BVH.
    let scene = load_scene(&args.scene, &LoadOptions::default())?;
    for w in &scene.warnings {
        tracing::warn!(scene = %args.scene.display(), "{w}");
    }
    // The job's environment image (if it names one) is decoded once for every frame.
    let folder = args.scene.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let environment = load_job_environment(folder, &settings, &LoadOptions::default())?;
    let env = environment.as_ref();
    let Some(frames) = frames else {
        return render_frame(&args, &scene, &settings, env, &args.out, args.png.as_deref());
    };
    let (out, png) =
        (args.out.to_string_lossy().into_owned(), args.png.as_ref().map(|p| p.to_string_lossy().into_owned()));
    for &frame in frames.frames() {
        settings.frame = frame;
        settings.validate(&pathfarm_common::job::Limits::default()).context("invalid settings")?;
        let exr = PathBuf::from(frame_path(&out, frame));
        let png = png.as_deref().map(|p| PathBuf::from(frame_path(p, frame)));
        if let Some(dir) = exr.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        render_frame(&args, &scene, &settings, env, &exr, png.as_deref()).with_context(|| format!("frame {frame}"))?;
    }
    Ok(())
}

/// Renders one frame of `scene` and writes its EXR (and PNG).
fn render_frame(
    args: &RenderArgs,
    scene: &pathfarm_common::scene::Scene,
    settings: &RenderSettings,
    environment: Option<&pathfarm_common::scene::EnvironmentImage>,
    out: &Path,
    png: Option<&Path>,
) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let renderer = Renderer::with_environment(scene, settings, environment.cloned())?;
    let prep = t0.elapsed();
    let bar = if args.quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(0) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} units, eta {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let t1 = Instant::now();
    let film = render_local(&renderer, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let secs = t1.elapsed().as_secs_f64();
    let mut image = film.resolve();
    // Adaptive sampling takes fewer than width x height x spp.
    let samples: f64 = image.samples.iter().map(|&n| f64::from(n)).sum();
    let uniform = f64::from(settings.width) * f64::from(settings.height) * f64::from(settings.spp);
    if settings.denoise {
        let t = Instant::now();
        image.denoised = Some(crate::denoise::denoise(&image)?);
        tracing::info!(denoise_s = t.elapsed().as_secs_f64(), "denoised (OIDN)");
    }
    image.write_exr(out)?;
    if let Some(png) = png {
        let ev = image.preview_ev(pathfarm_common::film::PreviewExposure::of(settings));
        image.write_png(png, ev)?;
        tracing::info!(png = %png.display(), preview_ev = ev, auto = settings.auto_exposure, "preview written");
    }
    tracing::info!(
        out = %out.display(),
        frame = settings.frame,
        prepare_s = prep.as_secs_f64(),
        render_s = secs,
        msamples_per_s = samples / secs / 1e6,
        samples_of_uniform = samples / uniform,
        "rendered"
    );
    Ok(())
}
