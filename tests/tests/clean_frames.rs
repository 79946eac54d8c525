//! Issue 14 through the farm: adaptive sampling and denoise steps with real coordinator and
//! worker processes, bit-identical to a local render.

mod support;

use pathfarm_common::adaptive::AdaptiveSettings;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{JobRequest, JobState};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use std::path::Path;
use std::time::Duration;
use support::*;

/// GET `path` of the API; (status, body).
fn get(url: &str, path: &str) -> (u16, Vec<u8>) {
    let r = reqwest::blocking::get(format!("{url}/api/v1{path}")).expect("request");
    (r.status().as_u16(), r.bytes().expect("body").to_vec())
}

/// A channel of an EXR held in memory, as bits (so equality is bit equality).
fn channel_bits(exr: &[u8], name: &str, dir: &Path) -> Option<Vec<u32>> {
    let path = dir.join("read.exr");
    std::fs::write(&path, exr).expect("write exr");
    let channels = pathfarm_common::film::read_exr(&path).expect("read exr");
    channels.get(name).map(|v| v.iter().map(|x| x.to_bits()).collect())
}

fn job_request(scene_id: String, name: &str, settings: RenderSettings) -> JobRequest {
    JobRequest {
        frames: None,
        order: Default::default(),
        scene_id,
        name: Some(name.into()),
        priority: 0,
        requires: Vec::new(),
        notify: None,
        settings,
    }
}

/// Three workers render an adaptive job (pass by pass, the converged blocks sent with the
/// leases): the EXR is the local render's bit for bit, and adaptive sampling really acted
/// (fewer samples than width x height x spp, progress 1).
#[test]
fn adaptive_sampling_on_three_workers_gives_the_local_render_bits() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "cache", 3);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let mut s = RenderSettings::new(64, 48, 32);
    s.tile_size = 16;
    s.seed = 7;
    s.passes = PassSchedule::Doubling { first: 4, max: 8 };
    s.integrator = IntegratorSettings::Path {
        max_depth: 6,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s.adaptive = Some(AdaptiveSettings { threshold: 0.25, min_spp: 4 });
    let created = client.upload_scene(scene.to_vec()).expect("upload");
    let req = JobRequest {
        frames: None,
        order: Default::default(),
        scene_id: created.scene_id,
        name: Some("adaptive".into()),
        priority: 0,
        requires: Vec::new(),
        notify: None,
        settings: s.clone(),
    };
    let id = client.submit(&req).expect("submit");
    let info = wait_for("the adaptive job to complete", Duration::from_secs(180), || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed).then_some(info)
    });
    assert_eq!(info.units_merged, info.units_total);
    assert_eq!(info.progress, 1.0);
    let full = 64 * 48 * 32;
    assert!(
        info.samples_total < full && info.samples_done == info.samples_total,
        "adaptive sampling did not act: {} of {full} samples",
        info.samples_done
    );
    let farm = client.image_exr(id).expect("exr");
    assert!(farm == local_exr(&scene, &s), "the farm's adaptive EXR differs from the local render");
    drop(workers);
}

/// Adaptive sampling and denoising both on, through the farm: two workers built with OIDN
/// render, denoise a preview after every pass (`denoise_preview`) and the final frame; the
/// `denoised` layer of the farm's EXR is bit for bit that of `pathfarm-worker render --denoise`
/// of the same job (the same resolve of the same film into the same OIDN calls), the noisy
/// colour is too, and the preview toggles between the two layers.
#[test]
#[cfg_attr(
    not(oidn),
    ignore = "needs OIDN: OIDN_DIR=<site-packages>/pyoidn/oidn and workers built with \
              --features pathfarm-worker/denoise (scripts/test does both when pyoidn is installed)"
)]
fn farm_denoised_layer_is_the_local_denoise_bits_with_adaptive_on() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let workers: Vec<Proc> = start_workers(&coord.url, "d", dir.path(), "cache", 2);
    let client = Client::new(&coord.url, None).expect("client");
    let denoisers = wait_for("two workers to register", Duration::from_secs(30), || {
        let (_, body) = get(&coord.url, "/workers");
        let list: Vec<serde_json::Value> = serde_json::from_slice(&body).expect("worker list");
        (list.len() == 2).then(|| list.iter().filter(|w| w["tags"].to_string().contains("\"denoise\"")).count())
    });
    assert_eq!(
        denoisers, 2,
        "the worker binary cannot denoise: build it with `cargo build --release -p pathfarm-worker --features denoise`"
    );
    let scene = cornell_demo_glb();
    // Settings the CLI below can say too (its defaults: sobol, power MIS, solid-angle lights).
    let mut s = RenderSettings::new(64, 48, 32);
    s.tile_size = 16;
    s.seed = 7;
    s.integrator = IntegratorSettings::Path {
        max_depth: 6,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s.adaptive = Some(AdaptiveSettings { threshold: 0.25, min_spp: 4 });
    s.denoise = true;
    s.denoise_preview = true;
    let created = client.upload_scene(scene.to_vec()).expect("upload");
    let id = client.submit(&job_request(created.scene_id, "adaptive+denoise", s.clone())).expect("submit");
    let info = wait_for("the job to complete", Duration::from_secs(180), || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed).then_some(info)
    });
    assert!(info.samples_total < 64 * 48 * 32, "adaptive sampling did not act");
    let (_, log) = get(&coord.url, &format!("/jobs/{id}/log"));
    let log = String::from_utf8_lossy(&log);
    assert!(log.contains("denoised") && !log.contains("without the denoised layer"), "{log}");
    let farm = client.image_exr(id).expect("exr");

    let glb = dir.path().join("cornell.glb");
    std::fs::write(&glb, scene).expect("scene file");
    let local = dir.path().join("local.exr");
    let status = std::process::Command::new(bin("pathfarm-worker"))
        .arg("render")
        .arg(&glb)
        .args(["--width", "64", "--height", "48", "--spp", "32", "--seed", "7", "--tile-size", "16"])
        .args(["--max-depth", "6", "--rr-depth", "3", "--adaptive-threshold", "0.25", "--min-spp", "4"])
        .args(["--denoise", "--threads", "1", "--quiet", "--out"])
        .arg(&local)
        .env("RUST_LOG", "warn")
        .status()
        .expect("run pathfarm-worker render");
    assert!(status.success(), "pathfarm-worker render --denoise failed");
    let local = std::fs::read(&local).expect("local exr");
    for c in ["R", "G", "B", "denoised.R", "denoised.G", "denoised.B"] {
        let (f, l) = (channel_bits(&farm, c, dir.path()), channel_bits(&local, c, dir.path()));
        assert!(f.is_some() && l.is_some(), "channel {c} missing (farm {}, local {})", f.is_some(), l.is_some());
        assert!(f == l, "channel {c} of the farm's EXR differs from the local render's");
    }
    assert_ne!(channel_bits(&farm, "R", dir.path()), channel_bits(&farm, "denoised.R", dir.path()));
    // The preview shows the denoised layer; `?layer=noisy` the noisy one; anything else is a 400.
    let (ok, denoised) = get(&coord.url, &format!("/jobs/{id}/preview.png"));
    let (ok2, noisy) = get(&coord.url, &format!("/jobs/{id}/preview.png?layer=noisy"));
    let (ok3, asked) = get(&coord.url, &format!("/jobs/{id}/preview.png?layer=denoised"));
    assert_eq!((ok, ok2, ok3), (200, 200, 200));
    assert!(denoised == asked && denoised != noisy, "the preview does not toggle between the layers");
    assert_eq!(get(&coord.url, &format!("/jobs/{id}/preview.png?layer=both")).0, 400);
    // The files written at completion hold the layer too.
    let written = std::fs::read(coord.data_dir.join(format!("jobs/{id}/image.exr"))).expect("written exr");
    assert_eq!(channel_bits(&written, "denoised.G", dir.path()), channel_bits(&local, "denoised.G", dir.path()));
    drop(workers);
}

/// A farm whose workers take no denoise steps (`--no-denoise`; builds without OIDN are the
/// same): a job asking for `denoise` completes without the `denoised` layer, its log says why,
/// and the denoised preview is a 409 saying there is none.
#[test]
fn without_a_denoise_worker_the_job_finishes_without_the_layer_and_says_why() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let worker = start_worker(&coord.url, "plain", &dir.path().join("cache"), &["--no-denoise"]);
    let client = Client::new(&coord.url, None).expect("client");
    let mut s = RenderSettings::new(32, 24, 4);
    s.tile_size = 16;
    s.denoise = true;
    let created = client.upload_scene(cornell_demo_glb().to_vec()).expect("upload");
    let id = client.submit(&job_request(created.scene_id, "denoise, nobody to", s)).expect("submit");
    wait_for("the job to complete", Duration::from_secs(120), || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed).then_some(())
    });
    let (_, log) = get(&coord.url, &format!("/jobs/{id}/log"));
    let log = String::from_utf8_lossy(&log);
    assert!(
        log.contains("the image is finished without the denoised layer: no live worker can denoise"),
        "the log does not say why: {log}"
    );
    let exr = client.image_exr(id).expect("exr");
    assert!(channel_bits(&exr, "R", dir.path()).is_some());
    assert!(channel_bits(&exr, "denoised.R", dir.path()).is_none(), "a denoised layer nobody made");
    let (status, body) = get(&coord.url, &format!("/jobs/{id}/preview.png?layer=denoised"));
    assert_eq!(status, 409);
    assert!(String::from_utf8_lossy(&body).contains("no_denoised"));
    assert_eq!(get(&coord.url, &format!("/jobs/{id}/preview.png?layer=noisy")).0, 200);
    drop(worker);
}

/// A sequence with denoise: each frame waits for its own denoise step and is written with its
/// `denoised` layer: the served EXR of every frame is, byte for byte, the local render of that
/// frame with `denoise` (render_local, resolve, OIDN on `DenoiseInput::of` it); the written
/// frame's preview shows the denoised layer and `?layer=noisy` the noisy one.
#[test]
#[cfg_attr(
    not(oidn),
    ignore = "needs OIDN: OIDN_DIR=<site-packages>/pyoidn/oidn and workers built with \
              --features pathfarm-worker/denoise (scripts/test does both when pyoidn is installed)"
)]
fn sequence_frames_are_written_with_their_denoised_layer() {
    use pathfarm_common::frames::FrameSet;
    use pathfarm_common::scene::demo::cornell_animated_glb;
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let workers: Vec<Proc> = start_workers(&coord.url, "d", dir.path(), "cache", 2);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_animated_glb();
    let mut s = RenderSettings::new(32, 24, 8);
    s.tile_size = 16;
    s.seed = 3;
    s.denoise = true;
    let created = client.upload_scene(scene.to_vec()).expect("upload");
    let mut req = job_request(created.scene_id, "denoised frames", s.clone());
    req.frames = Some(FrameSet::parse("1-2").expect("frames"));
    let id = client.submit(&req).expect("submit");
    wait_for("the frames to be written", Duration::from_secs(180), || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed && info.frames.done == info.frames.total).then_some(())
    });
    let bundle = tempfile::tempdir().expect("tempdir");
    let main = pathfarm_common::scene::bundle::unpack_bundle(&scene, bundle.path()).expect("bundle");
    let loaded = pathfarm_common::scene::load_scene(&main, &Default::default()).expect("scene");
    for frame in [1, 2] {
        let mut at = s.clone();
        at.frame = frame;
        let renderer = pathfarm_worker::render::Renderer::new(&loaded, &at).expect("renderer");
        let mut image = pathfarm_worker::render::render_local(&renderer, |_, _| {}).resolve();
        image.denoised = Some(pathfarm_worker::denoise::denoise(&image).expect("denoise"));
        let served = client.frame_exr(id, frame).expect("frame exr");
        assert!(served == image.encode_exr().expect("encode"), "frame {frame} differs from the local denoised render");
        let url = |q: &str| format!("{}/api/v1/jobs/{id}/frames/{frame}/preview.png{q}", coord.url);
        let layer = |q: &str| {
            let r = reqwest::blocking::get(url(q)).expect("preview");
            assert_eq!(r.status().as_u16(), 200);
            r.headers().get("x-pathfarm-preview-layer").map(|v| v.to_str().unwrap_or_default().to_string())
        };
        assert_eq!(layer("").as_deref(), Some("denoised"));
        assert_eq!(layer("?layer=noisy").as_deref(), Some("noisy"));
    }
    drop(workers);
}
