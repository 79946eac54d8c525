//! Sequences end to end: a job of several frames on real coordinator and worker processes.
//! Every frame is bit-identical to a local render of the job's settings with `frame` set to it,
//! whatever the workers do: an animated scene with motion blur, and still scenes.

mod support;

use pathfarm_common::frames::FrameSet;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{API, FrameInfo, FrameOrder, FrameState, JobId, JobInfo, JobRequest, JobState};
use pathfarm_common::scene::demo::{cornell_animated_glb, cornell_demo_glb};
use pathfarm_coordinator::client::Client;
use pathfarm_tests::procs::expect_error;
use std::time::Duration;
use support::*;

fn settings(width: u32, height: u32, spp: u32, tile: u32) -> RenderSettings {
    let mut s = RenderSettings::new(width, height, spp);
    s.tile_size = tile;
    s.seed = 11;
    s.integrator = IntegratorSettings::Path {
        max_depth: 5,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s
}

fn submit(client: &Client, scene: &[u8], s: &RenderSettings, frames: &str, order: FrameOrder) -> JobId {
    let created = client.upload_scene(scene.to_vec()).expect("upload");
    client
        .submit(&JobRequest {
            scene_id: created.scene_id,
            name: Some(format!("frames {frames}")),
            priority: 0,
            requires: Vec::new(),
            notify: None,
            frames: Some(FrameSet::parse(frames).expect("frames")),
            order,
            settings: s.clone(),
        })
        .expect("submit")
}

/// Waits until the job is completed and every frame is written.
fn wait_written(client: &Client, id: JobId, timeout: Duration) -> JobInfo {
    wait_for(&format!("job {id}'s frames to be written"), timeout, || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed && info.frames.done == info.frames.total).then_some(info)
    })
}

fn at_frame(s: &RenderSettings, frame: i32) -> RenderSettings {
    let mut s = s.clone();
    s.frame = frame;
    s
}

/// Frames 1-3 of an animated scene (a sliding and a turning box, motion blur over half a frame)
/// with two workers, submitted and fetched with the `pathfarm` CLI: each frame's EXR (served, on
/// disk, and written by `--out 'shot.####.exr'`) is the local render at that frame, and the
/// frames differ from each other.
#[test]
fn frames_of_a_sequence_are_bit_identical_to_local_renders() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_animated_glb();
    let scene_path = dir.path().join("cornell.glb");
    std::fs::write(&scene_path, &scene).expect("scene file");
    let out = dir.path().join("out");
    let pattern = out.join("shot.####.exr");
    let submitted = std::process::Command::new(bin("pathfarm"))
        .args(["--server", &coord.url, "submit"])
        .arg(&scene_path)
        .args(["--width", "40", "--height", "32", "--spp", "8", "--tile-size", "16", "--seed", "5"])
        .args(["--frames", "1-3", "--fps", "24", "--shutter", "0.5", "--wait", "--out"])
        .arg(&pattern)
        .output()
        .expect("pathfarm submit");
    assert!(submitted.status.success(), "{}", String::from_utf8_lossy(&submitted.stderr));
    let id: JobId = String::from_utf8_lossy(&submitted.stdout).trim().parse().expect("job id");
    let info = wait_written(&client, id, Duration::from_secs(120));
    assert_eq!((info.frames.total, info.frames.spec.as_str(), info.frames.sequence), (3, "1-3", true));
    assert_eq!(info.units_merged, info.units_total);
    assert_eq!(info.units_total, 3 * u64::from(info.tiles) * u64::from(info.passes_total));
    let fetched = dir.path().join("fetched");
    let fetch = std::process::Command::new(bin("pathfarm"))
        .args(["--server", &coord.url, "fetch", &id.to_string(), "--out"])
        .arg(fetched.join("f.##.exr"))
        .output()
        .expect("pathfarm fetch");
    assert!(fetch.status.success(), "{}", String::from_utf8_lossy(&fetch.stderr));
    assert_eq!(info.settings.shutter, 0.5);
    let mut frames_seen: Vec<Vec<u8>> = Vec::new();
    for f in 1..=3 {
        let local = local_exr(&scene, &at_frame(&info.settings, f));
        assert!(!frames_seen.contains(&local), "frame {f} looks like an earlier frame: the scene did not move");
        frames_seen.push(local.clone());
        let served = client.frame_exr(id, f).expect("frame exr");
        assert!(served == local, "frame {f}: the farm's EXR differs from the local render");
        let on_disk = std::fs::read(coord.data_dir.join(format!("jobs/{id}/frames/{f:04}/image.exr"))).expect("disk");
        assert!(on_disk == local, "frame {f}: the EXR on disk differs");
        assert!(coord.data_dir.join(format!("jobs/{id}/frames/{f:04}/preview.png")).is_file());
        let submitted = std::fs::read(out.join(format!("shot.{f:04}.exr"))).expect("--wait --out file");
        assert!(submitted == local, "frame {f}: submit --out wrote something else");
        let fetched = std::fs::read(fetched.join(format!("f.{f:02}.exr"))).expect("fetch --out file");
        assert!(fetched == local, "frame {f}: fetch --out wrote something else");
    }
    // The job's own image is no single frame: 409 pointing at the frame URLs.
    let resp = reqwest::blocking::get(format!("{}{API}/jobs/{id}/image.exr", coord.url)).expect("get");
    expect_error(resp, reqwest::StatusCode::CONFLICT, &["sequence of 3 frames", "/frames/{frame}/image.exr"]);
    let resp = reqwest::blocking::get(format!("{}{API}/jobs/{id}/frames/9/image.exr", coord.url)).expect("get");
    expect_error(resp, reqwest::StatusCode::NOT_FOUND, &["frame 9 is not in job"]);
    let frames = client.frames(id).expect("frames");
    assert_eq!(
        frames.iter().map(|f| (f.frame, f.state)).collect::<Vec<_>>(),
        (1..=3).map(|f| (f, FrameState::Done)).collect::<Vec<_>>()
    );
    // The log says when each frame started, merged and was written.
    let log: Vec<String> =
        reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").json().expect("json");
    for f in 1..=3 {
        assert!(log.iter().any(|l| l.starts_with(&format!("frame {f} written"))), "{log:?}");
    }
}

/// `sequence_preview` gives every frame its first pass before any frame gets its second: the
/// per-frame progress, polled while one worker renders, never shows a frame at pass 2 beside a
/// frame at pass 0, and does show every frame at one pass. The frames are the local renders.
#[test]
fn sequence_preview_gives_every_frame_its_first_pass_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let mut s = settings(64, 64, 64, 32);
    s.passes = PassSchedule::Fixed { spp: 32 };
    let id = submit(&client, &scene, &s, "1-3", FrameOrder::SequencePreview);
    // One worker: units are merged in the order they are handed out.
    let _worker = start_worker(&coord.url, "only", &dir.path().join("c"), &[]);
    let mut saw_preview = false;
    let http = reqwest::blocking::Client::new();
    loop {
        let frames: Vec<FrameInfo> =
            http.get(format!("{}{API}/jobs/{id}/frames", coord.url)).send().expect("frames").json().expect("json");
        let passes: Vec<u32> = frames.iter().map(|f| f.passes_done).collect();
        let (lo, hi) = (passes.iter().min().copied().unwrap_or(0), passes.iter().max().copied().unwrap_or(0));
        assert!(!(lo == 0 && hi >= 2), "a frame got its second pass before another got its first: {frames:?}");
        saw_preview |= lo == 1 && hi == 1;
        if frames.iter().all(|f| f.state == FrameState::Done) {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(saw_preview, "never saw every frame at its first pass");
    let info = wait_written(&client, id, Duration::from_secs(60));
    assert_eq!(info.frames.order, FrameOrder::SequencePreview);
    for f in [1, 3] {
        assert!(client.frame_exr(id, f).expect("exr") == local_exr(&scene, &at_frame(&s, f)), "frame {f} differs");
    }
}

/// A worker SIGKILLed in the middle of a sequence: its lease expires, the other worker renders
/// the unit again, every frame is still the local render.
#[test]
fn a_worker_killed_mid_sequence_loses_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &["--lease-timeout-ms", "1500", "--heartbeat-ms", "300"]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    // Units of about a second on one thread, so the kill lands inside a render.
    let mut s = settings(128, 64, 320, 64);
    s.passes = PassSchedule::Fixed { spp: 160 };
    let id = submit(&client, &scene, &s, "4,7", FrameOrder::Frame);
    let mut victim = start_worker(&coord.url, "victim", &dir.path().join("c1"), &[]);
    let workers = || -> Option<Vec<pathfarm_common::protocol::WorkerInfo>> {
        reqwest::blocking::get(format!("{}{API}/workers", coord.url)).ok()?.json().ok()
    };
    // Kill it while it renders a unit of the second frame (the first is partly merged).
    wait_for("the victim to hold a unit of frame 7", Duration::from_secs(120), || {
        workers()?.iter().any(|w| w.name == "victim" && w.current.is_some_and(|(_, k)| k.frame == 7)).then_some(())
    });
    victim.kill();
    let _survivor = start_worker(&coord.url, "survivor", &dir.path().join("c2"), &[]);
    let info = wait_written(&client, id, Duration::from_secs(180));
    assert_eq!(info.units_merged, info.units_total);
    let log: Vec<String> =
        reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").json().expect("json");
    assert!(log.iter().any(|l| l.contains("expired: unit frame 7")), "the victim's lease should have expired: {log:?}");
    for f in [4, 7] {
        assert!(client.frame_exr(id, f).expect("exr") == local_exr(&scene, &at_frame(&s, f)), "frame {f} differs");
    }
}
