//! Nothing lost across coordinator crashes: SIGKILL the coordinator at several points of a job,
//! restart it on the same data dir and port each time; the workers ride it out, and the job's
//! EXR is still bit-identical to a local render.

mod support;

use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{API, JobRequest, JobState};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use std::time::{Duration, Instant};
use support::*;

/// Path tracing in 32-px tiles and 16-spp passes: units long enough for kills to land inside.
fn settings(width: u32, height: u32, spp: u32, seed: u64) -> RenderSettings {
    let mut s = RenderSettings::new(width, height, spp);
    s.seed = seed;
    s.tile_size = 32;
    s.passes = PassSchedule::Fixed { spp: 16 };
    s.integrator = IntegratorSettings::Path {
        max_depth: 5,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s
}

#[test]
fn a_job_survives_repeated_coordinator_kills() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let flags = ["--lease-timeout-ms", "1500", "--heartbeat-ms", "300"];
    let mut coord = start_coordinator(&data, &flags);
    let addr = coord.url.trim_start_matches("http://").to_string();
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let s = settings(96, 96, 192, 3);
    let created = client.upload_scene(scene.clone()).expect("upload");
    let id = client
        .submit(&JobRequest {
            frames: None,
            order: Default::default(),
            scene_id: created.scene_id,
            name: Some("crash".into()),
            priority: 0,
            requires: Vec::new(),
            notify: None,
            settings: s.clone(),
        })
        .expect("submit");
    let _workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    // Kill points: after these fractions of the job's units are merged (a fixed pseudo-random
    // choice, so the test is repeatable).
    let mut kills = 0;
    for fraction in [0.15, 0.4, 0.7] {
        let reached = wait_for("progress before the kill", Duration::from_secs(120), || {
            let info = client.job(id).ok()?;
            (info.state == JobState::Completed || info.progress >= fraction).then_some(info.state)
        });
        if reached == JobState::Completed {
            break;
        }
        // Land between checkpoints: the units merged since the last one must be redone.
        std::thread::sleep(Duration::from_millis(150 + 200 * kills));
        coord.proc.kill();
        kills += 1;
        coord = start_coordinator_at(&data, &addr, &flags);
        assert_eq!(coord.url, format!("http://{addr}"));
    }
    assert!(kills >= 2, "the job finished before the coordinator could be killed twice; make it longer");
    let t0 = Instant::now();
    let info = wait_for("the job to complete after the restarts", Duration::from_secs(180), || {
        let info = client.job(id).ok()?;
        assert_ne!(info.state, JobState::Failed, "{:?}", info.error);
        (info.state == JobState::Completed).then_some(info)
    });
    assert_eq!(info.units_merged, info.units_total);
    let log: Vec<String> =
        reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").json().expect("json");
    assert!(log.iter().any(|l| l.starts_with("restored")), "{log:?}");
    assert!(
        client.image_exr(id).expect("exr") == local_exr(&scene, &s),
        "the image differs from the local render after {kills} coordinator kills"
    );
    eprintln!("{kills} coordinator kills; completed {:.1} s after the last restart", t0.elapsed().as_secs_f64());
}

/// DELETE raced the checkpoint loop (a checkpoint snapshotted before the delete wrote the job's
/// row back: 4 of 8 deleted jobs returned after a restart), and ids of deleted jobs were given
/// again after a restart. Eight queued jobs (no workers) deleted while checkpoints run every
/// 100 ms, with priority changes to make each one due; after a restart none is back and the next
/// id is above all of them.
#[test]
fn deleted_jobs_stay_deleted_and_their_ids_are_not_reused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let flags = ["--checkpoint-ms", "100"];
    let mut coord = start_coordinator(&data, &flags);
    let addr = coord.url.trim_start_matches("http://").to_string();
    let client = Client::new(&coord.url, None).expect("client");
    let created = client.upload_scene(cornell_demo_glb()).expect("upload");
    let request = |name: &str| JobRequest {
        frames: None,
        order: Default::default(),
        scene_id: created.scene_id.clone(),
        name: Some(name.into()),
        priority: 0,
        requires: Vec::new(),
        notify: None,
        settings: RenderSettings::new(512, 512, 16),
    };
    let keep = client.submit(&request("kept")).expect("submit");
    let mut deleted = Vec::new();
    for i in 0..8 {
        let id = client.submit(&request(&format!("doomed {i}"))).expect("submit");
        // Cancel (a state change makes the job due for a checkpoint), give the loop a moment
        // to take its snapshot, then delete.
        client.cancel(id).expect("cancel");
        std::thread::sleep(Duration::from_millis(40 + 15 * i));
        let r =
            reqwest::blocking::Client::new().delete(format!("{}{API}/jobs/{id}", coord.url)).send().expect("DELETE");
        assert!(r.status().is_success(), "delete {id}: {}", r.status());
        deleted.push(id);
    }
    std::thread::sleep(Duration::from_millis(500));
    coord.proc.kill();
    let coord = start_coordinator_at(&data, &addr, &flags);
    let client = Client::new(&coord.url, None).expect("client");
    let ids: Vec<u64> = client.jobs().expect("jobs").iter().map(|j| j.id).collect();
    assert_eq!(ids, vec![keep], "deleted jobs came back after a restart");
    let next = client.submit(&request("after the restart")).expect("submit");
    let max = deleted.iter().copied().max().unwrap_or(keep);
    assert!(next > max, "job id {next} reused (deleted ids go up to {max})");
}

/// A sequence across a coordinator SIGKILL: frames written before it stay written (their files
/// are not rewritten), the frame in progress resumes from its checkpoint (every unit merged
/// before the kill is still merged after it), and every frame is the local render at its frame.
#[test]
fn a_sequence_resumes_its_frames_after_a_coordinator_kill() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let flags = ["--lease-timeout-ms", "1500", "--heartbeat-ms", "300", "--checkpoint-ms", "100"];
    let mut coord = start_coordinator(&data, &flags);
    let addr = coord.url.trim_start_matches("http://").to_string();
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let s = settings(96, 64, 128, 5);
    let created = client.upload_scene(scene.clone()).expect("upload");
    let id = client
        .submit(&JobRequest {
            frames: Some(pathfarm_common::frames::FrameSet::parse("1-3").expect("frames")),
            order: Default::default(),
            scene_id: created.scene_id,
            name: Some("sequence crash".into()),
            priority: 0,
            requires: Vec::new(),
            notify: None,
            settings: s.clone(),
        })
        .expect("submit");
    let mut workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    // Frame 1 written, frame 2 under way: stop the workers, let the coordinator settle
    // (checkpoints, writes), then kill it.
    wait_for("frame 1 written and frame 2 under way", Duration::from_secs(120), || {
        let info = client.job(id).ok()?;
        (info.frames.done >= 1 && info.frames.current.iter().any(|f| f.frame == 2 && f.passes_done >= 1)).then_some(())
    });
    for w in &mut workers {
        w.kill();
    }
    let before = wait_for("the coordinator to settle", Duration::from_secs(30), || {
        let a = client.job(id).ok()?;
        // Longer than the checkpoint loop's back-off (nine times the last checkpoint's duration,
        // which on a loaded machine can pass 400 ms).
        std::thread::sleep(Duration::from_millis(2000));
        let b = client.job(id).ok()?;
        let settled = a.units_merged == b.units_merged
            && b.frames.current.iter().all(|f| f.state == pathfarm_common::protocol::FrameState::Rendering);
        settled.then_some(b)
    });
    assert!(before.frames.done < 3, "the sequence finished before the kill; make it longer");
    let frame1 = data.join(format!("jobs/{id}/frames/0001/image.exr"));
    let written = std::fs::metadata(&frame1).and_then(|m| m.modified()).expect("frame 1 on disk");
    coord.proc.kill();
    coord = start_coordinator_at(&data, &addr, &flags);
    let after = client.job(id).expect("job after the restart");
    assert_eq!(after.frames.done, before.frames.done, "written frames stay written");
    assert_eq!(after.units_merged, before.units_merged, "units merged before the kill are still merged");
    let log: Vec<String> =
        reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").json().expect("json");
    assert!(log.iter().any(|l| l.starts_with("restored") && l.contains("frames written")), "{log:?}");
    let _workers: Vec<Proc> = start_workers(&coord.url, "v", dir.path(), "c", 2);
    wait_for("the sequence to be written", Duration::from_secs(180), || {
        let info = client.job(id).ok()?;
        assert_ne!(info.state, JobState::Failed, "{:?}", info.error);
        (info.state == JobState::Completed && info.frames.done == 3).then_some(())
    });
    assert_eq!(std::fs::metadata(&frame1).and_then(|m| m.modified()).expect("frame 1"), written, "frame 1 rewritten");
    for f in 1..=3 {
        let mut at = s.clone();
        at.frame = f;
        assert!(client.frame_exr(id, f).expect("exr") == local_exr(&scene, &at), "frame {f} differs after the kill");
    }
}
