//! Issue 14 through the farm: adaptive sampling with real coordinator and worker processes,
//! bit-identical to a local render.

mod support;

use pathfarm_common::adaptive::AdaptiveSettings;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_common::protocol::{JobRequest, JobState};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use std::time::Duration;
use support::*;

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
