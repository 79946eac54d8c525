//! The farm end to end: a real coordinator and real worker processes on 127.0.0.1, talking HTTP.
//! Every test compares the farm's EXR with a local render of the same job, bit for bit.

mod support;

use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{
    API, JobId, JobRequest, JobState, LeaseGrant, Registered, UnitResultFrame, WORKER_SECRET_HEADER,
};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use std::time::Duration;
use support::*;

fn settings(width: u32, height: u32, spp: u32, tile: u32) -> RenderSettings {
    let mut s = RenderSettings::new(width, height, spp);
    s.tile_size = tile;
    s.seed = 7;
    s.integrator = IntegratorSettings::Path {
        max_depth: 6,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    s
}

fn submit(client: &Client, scene: &[u8], s: &RenderSettings, priority: i32, name: &str) -> JobId {
    let created = client.upload_scene(scene.to_vec()).expect("upload");
    let req = JobRequest {
        frames: None,
        order: Default::default(),
        scene_id: created.scene_id,
        name: Some(name.into()),
        priority,
        requires: Vec::new(),
        notify: None,
        settings: s.clone(),
    };
    client.submit(&req).expect("submit")
}

fn wait_done(client: &Client, id: JobId, timeout: Duration) -> pathfarm_common::protocol::JobInfo {
    wait_for(&format!("job {id} to complete"), timeout, || {
        let info = client.job(id).expect("job");
        assert_ne!(info.state, JobState::Failed, "job failed: {:?}", info.error);
        (info.state == JobState::Completed).then_some(info)
    })
}

#[test]
fn three_workers_render_the_same_bits_as_a_local_render() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "cache", 3);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let s = settings(64, 48, 24, 16);
    let id = submit(&client, &scene, &s, 0, "bits");
    let info = wait_done(&client, id, Duration::from_secs(120));
    assert_eq!(info.units_merged, info.units_total);
    assert_eq!(info.spp_done, 24);
    let farm = client.image_exr(id).expect("exr");
    assert!(farm == local_exr(&scene, &s), "the farm's EXR differs from the local render");
    // Every worker took part (units are small and plenty).
    let per_worker: Vec<u64> = reqwest::blocking::get(format!("{}{API}/workers", coord.url))
        .expect("workers")
        .json::<Vec<pathfarm_common::protocol::WorkerInfo>>()
        .expect("json")
        .iter()
        .map(|w| w.units_done)
        .collect();
    assert_eq!(per_worker.iter().sum::<u64>(), info.units_total, "{per_worker:?}");
    // The progressive output on disk is the final image once the job is done.
    let on_disk = wait_for("image.exr on disk", Duration::from_secs(10), || {
        let b = std::fs::read(coord.data_dir.join("jobs").join(id.to_string()).join("image.exr")).ok()?;
        (b == farm).then_some(b)
    });
    assert!(!on_disk.is_empty());
    drop(workers);
}

fn workers(url: &str) -> Vec<pathfarm_common::protocol::WorkerInfo> {
    reqwest::blocking::get(format!("{url}{API}/workers")).expect("workers").json().expect("json")
}

/// Two real workers, one started with `--tags highmem`: a job requiring `highmem` waits (and
/// says why) while only the untagged worker is up, then is rendered by the tagged worker
/// alone, bit-identical to a local render.
#[test]
fn a_job_requiring_a_tag_is_rendered_only_by_workers_having_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let plain = start_worker(&coord.url, "plain", &dir.path().join("c0"), &[]);
    wait_for("the plain worker", Duration::from_secs(30), || (!workers(&coord.url).is_empty()).then_some(()));
    let scene = cornell_demo_glb();
    let s = settings(48, 32, 8, 16);
    let created = client.upload_scene(scene.clone()).expect("upload");
    let req = JobRequest {
        frames: None,
        order: Default::default(),
        scene_id: created.scene_id,
        name: Some("highmem".into()),
        priority: 0,
        requires: vec!["highmem".into()],
        notify: None,
        settings: s.clone(),
    };
    let id = client.submit(&req).expect("submit");
    std::thread::sleep(Duration::from_millis(1500));
    let info = client.job(id).expect("job");
    assert_eq!(info.state, JobState::Queued, "{info:?}");
    assert_eq!(info.requires, vec!["highmem".to_string()]);
    assert_eq!(info.waiting.as_deref(), Some("no live worker has tags [highmem]"));
    let log = reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").text().expect("text");
    assert!(log.contains("no live worker has tags [highmem]"), "{log}");

    let tagged = start_worker(&coord.url, "tagged", &dir.path().join("c1"), &["--tags", "highmem"]);
    let info = wait_done(&client, id, Duration::from_secs(120));
    assert_eq!(info.waiting, None);
    assert!(
        client.image_exr(id).expect("exr") == local_exr(&scene, &s),
        "the farm's EXR differs from the local render"
    );
    let ws = workers(&coord.url);
    let by_name = |n: &str| ws.iter().find(|w| w.name == n).unwrap_or_else(|| panic!("worker {n}: {ws:?}"));
    assert_eq!(by_name("tagged").units_done, info.units_total, "{ws:?}");
    assert_eq!(by_name("plain").units_done, 0, "{ws:?}");
    assert!(by_name("tagged").tags.contains(&"highmem".to_string()), "{ws:?}");
    assert!(
        by_name("plain").tags.contains(&"cpu".to_string()) && !by_name("plain").tags.contains(&"highmem".to_string())
    );
    drop((plain, tagged));
}

#[test]
fn a_worker_killed_mid_unit_loses_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &["--lease-timeout-ms", "1500", "--heartbeat-ms", "300"]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    // Big units (one 64x64 tile, 160 spp per pass: about a second on one thread) so the kill
    // lands inside a render (16-spp units took ~65 ms and a busy machine let one finish first).
    let mut s = settings(128, 64, 480, 64);
    s.passes = PassSchedule::Fixed { spp: 160 };
    let id = submit(&client, &scene, &s, 0, "kill");
    let mut victim = start_worker(&coord.url, "victim", &dir.path().join("c1"), &[]);
    // Wait until the victim holds a lease, then SIGKILL it in the middle of rendering.
    wait_for("the victim to hold a unit", Duration::from_secs(60), || {
        let ws: Vec<pathfarm_common::protocol::WorkerInfo> =
            reqwest::blocking::get(format!("{}{API}/workers", coord.url)).ok()?.json().ok()?;
        ws.iter().any(|w| w.name == "victim" && w.current.is_some()).then_some(())
    });
    victim.kill();
    let _survivor = start_worker(&coord.url, "survivor", &dir.path().join("c2"), &[]);
    let info = wait_done(&client, id, Duration::from_secs(180));
    assert_eq!(info.units_merged, info.units_total);
    let log: Vec<String> =
        reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").json().expect("json");
    assert!(log.iter().any(|l| l.contains("expired")), "the victim's lease should have expired: {log:?}");
    assert!(client.image_exr(id).expect("exr") == local_exr(&scene, &s), "image differs after a worker death");
}

#[test]
fn the_higher_priority_job_finishes_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let s = settings(64, 64, 16, 16);
    let low = submit(&client, &scene, &s, 0, "low");
    let high = submit(&client, &scene, &s, 10, "high");
    let _workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    let high_info = wait_done(&client, high, Duration::from_secs(120));
    let low_now = client.job(low).expect("low");
    assert_ne!(low_now.state, JobState::Completed, "the low-priority job finished first");
    let low_info = wait_done(&client, low, Duration::from_secs(120));
    assert!(high_info.finished_ms <= low_info.finished_ms);
    assert!(client.image_exr(high).expect("exr") == local_exr(&scene, &s));
    assert!(client.image_exr(low).expect("exr") == client.image_exr(high).expect("exr"));
}

#[test]
fn a_result_replayed_after_its_lease_expired_is_refused_and_not_merged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &["--lease-timeout-ms", "800", "--heartbeat-ms", "200"]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let s = settings(32, 32, 8, 16);
    let id = submit(&client, &scene, &s, 0, "replay");
    // Play a worker by hand: register, lease a unit, render it correctly, then stay silent.
    let http = reqwest::blocking::Client::new();
    let reg: Registered = http
        .post(format!("{}{API}/workers/register", coord.url))
        .json(&serde_json::json!({"name": "slow", "threads": 1}))
        .send()
        .expect("register")
        .json()
        .expect("json");
    let grant: LeaseGrant = http
        .post(format!("{}{API}/workers/{}/lease?wait_ms=5000", coord.url, reg.worker_id))
        .header(WORKER_SECRET_HEADER, &reg.worker_secret)
        .send()
        .expect("lease")
        .json()
        .expect("grant");
    let tmp = tempfile::tempdir().expect("tempdir");
    let loaded = pathfarm_common::scene::bundle::load_bundle(&scene, tmp.path(), &Default::default()).expect("scene");
    let renderer = pathfarm_worker::render::Renderer::new(&loaded, &grant.settings).expect("renderer");
    let r = renderer.render_unit(grant.tile, grant.pass);
    let body = UnitResultFrame {
        lease_id: grant.lease_id,
        job_id: grant.job_id,
        unit: grant.unit,
        accum: r.accum,
        splats: r.splats,
    }
    .encode();
    // Let the lease expire (no heartbeats), then deliver: 409, not merged.
    std::thread::sleep(Duration::from_millis(1500));
    let resp = http
        .put(format!("{}{API}/leases/{}/result", coord.url, grant.lease_id))
        .header(WORKER_SECRET_HEADER, &reg.worker_secret)
        .body(body.clone())
        .send()
        .expect("upload");
    assert_eq!(resp.status().as_u16(), 409, "{}", resp.text().unwrap_or_default());
    assert_eq!(client.job(id).expect("job").units_merged, 0);
    // A real worker finishes the job; the replay again after completion is refused too.
    let _w = start_worker(&coord.url, "w", &dir.path().join("c"), &[]);
    wait_done(&client, id, Duration::from_secs(120));
    let resp = http
        .put(format!("{}{API}/leases/{}/result", coord.url, grant.lease_id))
        .header(WORKER_SECRET_HEADER, &reg.worker_secret)
        .body(body)
        .send()
        .expect("upload");
    assert_eq!(resp.status().as_u16(), 409);
    let info = client.job(id).expect("job");
    assert_eq!(info.units_merged, info.units_total);
    assert!(client.image_exr(id).expect("exr") == local_exr(&scene, &s), "image differs after a replay");
}

#[test]
fn a_sigtermed_worker_finishes_its_unit_and_exits() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let mut s = settings(64, 64, 32, 64);
    s.passes = PassSchedule::Fixed { spp: 16 };
    let id = submit(&client, &scene, &s, 0, "drain");
    let mut w = start_worker(&coord.url, "drainer", &dir.path().join("c"), &[]);
    wait_for("a merged unit or a held lease", Duration::from_secs(60), || {
        let ws: Vec<pathfarm_common::protocol::WorkerInfo> =
            reqwest::blocking::get(format!("{}{API}/workers", coord.url)).ok()?.json().ok()?;
        ws.iter().any(|w| w.current.is_some()).then_some(())
    });
    let status = w.terminate(Duration::from_secs(60)).expect("the worker exits after SIGTERM");
    assert!(status.success(), "{status:?}");
    // Its unit was delivered (not left to expire): nothing is leased any more.
    let info = client.job(id).expect("job");
    assert!(info.units_merged >= 1, "the unit in progress should have been uploaded");
    let ws: Vec<pathfarm_common::protocol::WorkerInfo> =
        reqwest::blocking::get(format!("{}{API}/workers", coord.url)).expect("workers").json().expect("json");
    assert!(ws.iter().all(|w| w.current.is_none()), "{ws:?}");
}

#[test]
fn bdpt_and_igi_jobs_are_bit_identical_through_the_farm() {
    // BDPT units carry full-frame light-tracing splats; IGI units share per-sample VPL sets.
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _workers: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let mut bdpt = settings(40, 32, 12, 16);
    bdpt.integrator =
        IntegratorSettings::Bdpt { max_depth: 5, mis: MisHeuristic::Balance, rr_depth: 3, strategy: None };
    let mut igi = settings(40, 32, 8, 16);
    igi.integrator =
        IntegratorSettings::Igi { vpls: 16, vpl_sets: 2, g_limit: 5.0, bias_compensation: true, max_depth: 5 };
    for (name, s) in [("bdpt", bdpt), ("igi", igi)] {
        let id = submit(&client, &scene, &s, 0, name);
        wait_done(&client, id, Duration::from_secs(120));
        assert!(client.image_exr(id).expect("exr") == local_exr(&scene, &s), "{name}: farm image differs from local");
    }
}

#[test]
fn a_tar_bundle_renders_and_a_job_no_worker_can_render_fails_with_the_reason() {
    // A "glTF Separate" export (.gltf + .bin + .png) with a perspective and an orthographic
    // camera, uploaded as a tar bundle; bdpt cannot use the orthographic camera.
    let files = pathfarm_common::scene::demo::cornell_separate_files();
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let bundle = pathfarm_common::scene::bundle::tar_bundle(&refs).expect("tar");
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _w = start_worker(&coord.url, "only", &dir.path().join("c"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let mut ok = settings(32, 32, 4, 16);
    ok.camera = Some(1);
    ok.integrator = IntegratorSettings::Direct { mis: MisHeuristic::Power, light_sampling: LightSampling::Area };
    let id = submit(&client, &bundle, &ok, 0, "ortho direct");
    wait_done(&client, id, Duration::from_secs(60));
    assert!(client.image_exr(id).expect("exr") == local_exr(&bundle, &ok), "tar bundle render differs from local");

    let mut bad = ok.clone();
    bad.integrator = IntegratorSettings::Bdpt { max_depth: 4, mis: MisHeuristic::Balance, rr_depth: 3, strategy: None };
    let id = submit(&client, &bundle, &bad, 0, "ortho bdpt");
    let info = wait_for("the job to fail", Duration::from_secs(60), || {
        let info = client.job(id).ok()?;
        info.state.is_finished().then_some(info)
    });
    assert_eq!(info.state, JobState::Failed);
    let error = info.error.unwrap_or_default();
    assert!(error.contains("perspective"), "the job's error should carry the worker's reason: {error}");
    assert!(!info.blocklist.is_empty(), "the failing worker should be blocklisted");
}

#[test]
fn an_environment_image_in_the_bundle_and_a_thin_lens_render_the_same_bits_through_the_farm() {
    // The Cornell box export plus an equirectangular .hdr in a subfolder, as a tar bundle; the
    // job names it (relative to the .gltf) and adds depth of field. A job naming a file the
    // bundle lacks fails with the file's name.
    let mut files = pathfarm_common::scene::demo::cornell_separate_files();
    let mut hdr = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8 +X 16\n".to_vec();
    for i in 0..128u32 {
        hdr.extend_from_slice(&[128, 64 + (i % 16) as u8 * 8, 32, 129]);
    }
    files.push(("env/sky.hdr".into(), hdr));
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let bundle = pathfarm_common::scene::bundle::tar_bundle(&refs).expect("tar");
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _w: Vec<Proc> = start_workers(&coord.url, "w", dir.path(), "c", 2);
    let client = Client::new(&coord.url, None).expect("client");
    let mut s = settings(32, 32, 8, 16);
    s.camera = Some(0);
    s.environment = Some(pathfarm_common::job::EnvironmentSettings {
        file: Some("env/sky.hdr".into()),
        color: None,
        intensity: 2.0,
        rotation_deg: 30.0,
    });
    s.aperture_radius = 0.05;
    s.focus_distance = Some(3.0);
    let id = submit(&client, &bundle, &s, 0, "sky");
    wait_done(&client, id, Duration::from_secs(120));
    assert!(client.image_exr(id).expect("exr") == local_exr(&bundle, &s), "environment job differs from local");

    let mut missing = s.clone();
    missing.environment.as_mut().expect("set").file = Some("env/none.exr".into());
    let id = submit(&client, &bundle, &missing, 0, "no sky");
    let info = wait_for("the job to fail", Duration::from_secs(60), || {
        let info = client.job(id).ok()?;
        info.state.is_finished().then_some(info)
    });
    assert_eq!(info.state, JobState::Failed);
    let error = info.error.unwrap_or_default();
    assert!(error.contains("env/none.exr"), "the job's error should name the missing file: {error}");
}

/// Preview exposure: a job with `auto_exposure` and `exposure` 0.5 gets previews at the automatic
/// EV of its image plus 0.5 (said in the PNG's header; the PNG is exactly that exposure of the
/// local render), while its EXR holds the true radiance, bit-identical to a render without them.
#[test]
fn previews_use_the_jobs_exposure_and_the_exr_keeps_radiance() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _w = start_worker(&coord.url, "w", &dir.path().join("c"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let scene = cornell_demo_glb();
    let mut s = settings(32, 24, 4, 16);
    s.exposure = 0.5;
    s.auto_exposure = true;
    let id = submit(&client, &scene, &s, 0, "exposure");
    wait_done(&client, id, Duration::from_secs(120));
    let mut plain = s.clone();
    (plain.exposure, plain.auto_exposure) = (0.0, false);
    assert!(client.image_exr(id).expect("exr") == local_exr(&scene, &plain), "the EXR changed with the exposure");
    let resp = reqwest::blocking::get(format!("{}{API}/jobs/{id}/preview.png", coord.url)).expect("png");
    let ev: f32 = resp
        .headers()
        .get("x-pathfarm-preview-ev")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("the preview says its exposure");
    let png = resp.bytes().expect("body");
    let tmp = tempfile::tempdir().expect("tempdir");
    let local = pathfarm_common::scene::bundle::load_bundle(&scene, tmp.path(), &Default::default()).expect("scene");
    let layers = pathfarm_worker::render::render_local(
        &pathfarm_worker::render::Renderer::new(&local, &s).expect("renderer"),
        |_, _| {},
    )
    .resolve();
    let expected = layers.auto_exposure() + 0.5;
    assert!((ev - expected).abs() < 1e-3, "preview EV {ev}, expected {expected}");
    assert!(expected.abs() > 0.6, "the automatic part should matter here: {expected}");
    assert!(png.as_ref() == layers.encode_png(expected).expect("png").as_slice(), "the PNG is not that exposure");
}

/// A scene without lights: a job without an environment is accepted with a warning (in the 201
/// answer and the job's log) that it renders black; with a constant environment there is none.
#[test]
fn a_dark_job_is_warned_about() {
    use pathfarm_common::scene::demo::{GltfBuilder, lambert};
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let client = Client::new(&coord.url, None).expect("client");
    let mut b = GltfBuilder::new();
    let grey = b.material(lambert("grey", glam::Vec3::splat(0.5)));
    let v = glam::Vec3::new;
    pathfarm_common::scene::demo::quad(
        &mut b,
        "floor",
        [v(-1.0, 0.0, 1.0), v(1.0, 0.0, 1.0), v(1.0, 0.0, -1.0), v(-1.0, 0.0, -1.0)],
        grey,
    );
    let created = client.upload_scene(b.to_glb()).expect("upload");
    let submit = |environment: Option<serde_json::Value>| -> serde_json::Value {
        let mut body = JobRequest {
            scene_id: created.scene_id.clone(),
            name: None,
            priority: 0,
            requires: Vec::new(),
            notify: None,
            frames: None,
            order: Default::default(),
            settings: settings(16, 16, 1, 16),
        }
        .to_json();
        if let Some(e) = environment {
            body["environment"] = e;
        }
        let resp = reqwest::blocking::Client::new()
            .post(format!("{}{API}/jobs", coord.url))
            .json(&body)
            .send()
            .expect("submit");
        assert_eq!(resp.status().as_u16(), 201);
        resp.json().expect("json")
    };
    let dark = submit(None);
    let warning = pathfarm_common::scene::DARK_JOB_WARNING;
    assert_eq!(dark["warnings"], serde_json::json!([warning]), "{dark}");
    let id = dark["id"].as_u64().expect("id");
    let log = reqwest::blocking::get(format!("{}{API}/jobs/{id}/log", coord.url)).expect("log").text().expect("text");
    assert!(log.contains(warning), "{log}");
    let lit = submit(Some(serde_json::json!({"color": [1.0, 1.0, 1.0]})));
    assert!(lit.get("warnings").is_none(), "{lit}");
}
