//! The state machine's unit tests.

use super::*;
use pathfarm_common::adaptive::{self, AdaptiveSettings, BlockMask};
use pathfarm_common::assembly::FilmAssembly;
use pathfarm_common::film::SampleValue;
use pathfarm_common::film::TileAccum;
use pathfarm_common::job::PassSchedule;
use pathfarm_common::job::TileRect;
use pathfarm_common::protocol::{Codec, LeaseGrant, TileSums, UnitResultFrame, WorkerState};
use std::collections::HashMap;

fn settings() -> RenderSettings {
    let mut s = RenderSettings::new(20, 12, 7);
    s.tile_size = 8;
    s.passes = PassSchedule::Doubling { first: 1, max: 4 };
    s
}

/// A fake render: every sample of every pixel adds (x, y, pass) so the result depends on the unit.
pub(crate) fn fake_result(g: &LeaseGrant) -> UnitResultFrame {
    let mut accum = TileAccum::new(g.tile);
    for y in g.tile.y0..g.tile.y1 {
        for x in g.tile.x0..g.tile.x1 {
            for s in g.pass.samples() {
                let v = SampleValue { radiance: [x as f32, y as f32, s as f32], ..Default::default() };
                pathfarm_common::film::add_sample(accum.pixel_mut(x - g.tile.x0, y - g.tile.y0), &v);
            }
        }
    }
    UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None }
}

fn reference_film(s: &RenderSettings) -> Film {
    let plan = s.plan();
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    for _ in 0..plan.unit_count() {
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
    }
    assert_eq!(farm.job(id).expect("job").state, JobState::Completed);
    farm.job(id).expect("job").film().expect("film").clone()
}

fn sequence(frames: &str, order: FrameOrder) -> JobSpec {
    JobSpec { frames: Some(FrameSet::parse(frames).expect("frames")), order, ..JobSpec::new("x".into(), settings()) }
}

/// Frame order: a frame's units go out before the next frame's, the next frame starts only
/// when the frames in progress have nothing pending, at most `max_open_frames` are held at
/// once; grants carry the unit's frame; every frame's film equals a single-frame job's;
/// a written frame's film is dropped.
#[test]
fn frame_order_bounds_the_frames_in_progress() {
    let s = settings();
    let reference = reference_film(&s);
    let per_frame = s.plan().unit_count();
    let mut farm = Farm::new(FarmConfig { max_open_frames: 2, ..FarmConfig::default() });
    let id = farm.submit_job(sequence("10-14", FrameOrder::Frame), 0).expect("submit");
    assert_eq!(farm.job(id).expect("job").films_held(), 0, "a queued job holds no film");
    let w = farm.register("w".into(), 1, 0);
    let mut grants = Vec::new();
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        assert_eq!(g.settings.frame, g.unit.frame);
        grants.push(g);
    }
    // Two frames in progress, nothing returned: the third does not start.
    assert_eq!(grants.len(), 2 * per_frame);
    assert!(grants[..per_frame].iter().all(|g| g.unit.frame == 10));
    assert!(grants[per_frame..].iter().all(|g| g.unit.frame == 11));
    let info = farm.job(id).expect("job").info(0);
    assert_eq!((info.frames.total, info.frames.in_progress, info.frames.done), (5, 2, 0));
    assert_eq!(info.units_total, 5 * per_frame as u64);
    // Frame 10 merges: it waits to be written (still holding its film) and nothing starts.
    for g in &grants[..per_frame] {
        let out = farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
        assert!(!out.job_completed);
    }
    assert_eq!(farm.lease(w, 0).expect("lease"), None, "two films are held");
    let to_write = farm.job(id).expect("job").frames_to_write();
    assert_eq!(to_write.len(), 1);
    assert_eq!((to_write[0].1, &*to_write[0].2), (10, &reference));
    assert_eq!(farm.job(id).expect("job").frame_info(0).map(|f| f.state), Some(FrameState::Writing));
    assert_eq!(farm.frame_written(id, to_write[0].0), Some(10));
    assert_eq!(farm.frame_written(id, to_write[0].0), None, "once");
    assert_eq!(farm.job(id).expect("job").frame_info(0).map(|f| f.state), Some(FrameState::Done));
    // Room again: frame 12 starts.
    let g = farm.lease(w, 0).expect("lease").expect("work");
    assert_eq!(g.unit.frame, 12);
    grants = grants[per_frame..].to_vec();
    grants.push(g);
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        grants.push(g);
    }
    // Deliver everything, writing frames as they finish; the job completes with the last.
    let mut completed = false;
    while !completed {
        for g in std::mem::take(&mut grants) {
            completed |= farm.accept(g.lease_id, fake_result(&g), 0).expect("accept").job_completed;
        }
        for (i, frame, film) in farm.job(id).expect("job").frames_to_write() {
            assert_eq!(*film, reference, "frame {frame}");
            farm.frame_written(id, i);
        }
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            assert!(farm.job(id).expect("job").films_held() <= 2);
            grants.push(g);
        }
    }
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Completed);
    assert_eq!(job.films_held(), 0);
    assert_eq!(
        job.frames_page(None, 10).iter().map(|f| (f.frame, f.state)).collect::<Vec<_>>(),
        (10..15).map(|f| (f, FrameState::Done)).collect::<Vec<_>>()
    );
    assert_eq!(job.frames_page(Some(2), 10).first().map(|f| f.frame), Some(13));
    assert_eq!(job.info(0).passes_done, s.plan().passes.len() as u32);
}

/// Sequence preview: every frame's first pass is handed out before any frame's second.
#[test]
fn sequence_preview_hands_out_passes_across_frames() {
    let s = settings();
    let (tiles, passes) = (s.plan().tiles.len(), s.plan().passes.len());
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit_job(sequence("1-3", FrameOrder::SequencePreview), 0).expect("submit");
    assert_eq!(farm.job(id).expect("job").films_held(), 0, "a queued job holds no film");
    let w = farm.register("w".into(), 1, 0);
    let mut keys = Vec::new();
    let mut first = None;
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        assert_eq!(farm.job(id).expect("job").films_held(), 3, "the first lease starts every frame");
        keys.push(g.unit);
        // A result comes back now and then, out of order: requeues keep the order too.
        if keys.len() == 5 {
            first = Some(g);
        }
    }
    assert_eq!(keys.len(), 3 * tiles * passes);
    let order: Vec<(u32, i32)> = keys.iter().map(|k| (k.pass, k.frame)).collect();
    let mut sorted = order.clone();
    sorted.sort();
    assert_eq!(order, sorted, "pass-major, then frame");
    // An expired unit of pass 0 goes out before anything else pending.
    let g = first.expect("fifth grant");
    farm.release(g.lease_id, false, "shutdown", 0).expect("release");
    assert_eq!(farm.lease(w, 0).expect("lease").map(|g| g.unit), Some(g.unit));
    let _ = id;
}

/// Budgets and limits are checked before anything is allocated, with messages that say why.
#[test]
fn sequences_are_checked_against_budgets() {
    let s = settings();
    let film = Film::bytes_for(s.width, s.height);
    let units = s.plan().unit_count() as u64;
    let mut farm = Farm::new(FarmConfig { film_budget_bytes: Some(film * 2), ..FarmConfig::default() });
    // Frame order needs one film at a time: 100 frames fit a two-film budget.
    let id = farm.submit_job(sequence("1-100", FrameOrder::Frame), 0).expect("frame order fits");
    match farm.submit_job(sequence("1-3", FrameOrder::SequencePreview), 0) {
        Err(FarmError::OverBudget(m)) => {
            assert!(m.contains("sequence_preview holds every frame's film at once: 3 frames"), "{m}")
        }
        r => panic!("admitted: {r:?}"),
    }
    // The sequence holds one film; a second frame starts only while it fits.
    let w = farm.register("w".into(), 1, 0);
    let mut n = 0;
    while farm.lease(w, 0).expect("lease").is_some() {
        n += 1;
    }
    assert_eq!(n as u64, 2 * units, "two frames fit the budget");
    let mut small = Farm::new(FarmConfig {
        limits: Limits { max_units: units * 10, ..Limits::default() },
        ..FarmConfig::default()
    });
    small.submit_job(sequence("1-10", FrameOrder::Frame), 0).expect("10 frames fit");
    match small.submit_job(sequence("1-11", FrameOrder::Frame), 0) {
        Err(FarmError::InvalidJob(m)) => {
            assert!(m.contains("units (frames x tiles x passes)") && m.contains("11 x"), "{m}")
        }
        r => panic!("admitted: {r:?}"),
    }
    let _ = id;
}

/// A restored sequence keeps its written frames and resumes its frame in progress from its
/// checkpoint; the result equals an uninterrupted render.
#[test]
fn a_restored_sequence_resumes_its_frames() {
    let s = settings();
    let reference = reference_film(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit_job(sequence("1-3", FrameOrder::Frame), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let per_frame = s.plan().unit_count();
    // Frame 1 completes and is written; frame 2 merges a few units.
    for _ in 0..per_frame + 5 {
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
    }
    for (i, _, _) in farm.job(id).expect("job").frames_to_write() {
        farm.frame_written(id, i);
    }
    let cps = farm.job_mut(id).expect("job").take_checkpoints(true, usize::MAX);
    assert_eq!(cps.iter().map(|c| c.frame).collect::<Vec<_>>(), vec![2]);
    assert!(farm.job_mut(id).expect("job").take_checkpoints(false, 1).is_empty(), "nothing merged since");
    let rec = farm.job(id).expect("job").record(0);
    let mut again = Farm::new(FarmConfig::default());
    again.restore(rec, cps, &[0], 0).expect("restore");
    let job = again.job(id).expect("job");
    assert_eq!(job.units_merged, per_frame as u64 + 5);
    assert_eq!(job.frame_info(0).map(|f| f.state), Some(FrameState::Done));
    assert_eq!(job.frame_info(1).map(|f| f.state), Some(FrameState::Rendering));
    let w = again.register("w".into(), 1, 0);
    let mut done = false;
    while !done {
        let Some(g) = again.lease(w, 0).expect("lease") else {
            for (i, frame, film) in again.job(id).expect("job").frames_to_write() {
                assert_eq!(*film, reference, "frame {frame}");
                again.frame_written(id, i);
            }
            continue;
        };
        assert_ne!(g.unit.frame, 1, "frame 1 is written");
        done = again.accept(g.lease_id, fake_result(&g), 0).expect("accept").job_completed;
    }
    assert_eq!(again.job(id).expect("job").units_merged, 3 * per_frame as u64);
    // A checkpoint of another job, or of a frame not in the set, is refused.
    let mut bad = farm.job_mut(id).expect("job").take_checkpoints(true, 1);
    bad[0].frame = 9;
    let rec = farm.job(id).expect("job").record(0);
    assert!(Farm::new(FarmConfig::default()).restore(rec, bad, &[], 0).is_err());
}

/// A single-frame job whose row says completed but whose last checkpoint holds only some units
/// (the coordinator was killed after the job completed, before its last checkpoint and its final
/// image): the restore renders the missing units again instead of finishing a partial film, and
/// the result is the uninterrupted film. With its final image on disk (`done`) it stays completed.
#[test]
fn a_completed_job_checkpointed_before_completion_renders_its_last_units_again() {
    let s = settings();
    let reference = reference_film(&s);
    let units = s.plan().unit_count();
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let mut cps = Vec::new();
    let mut completed = false;
    for n in 0..units {
        if n == units - 2 {
            cps = farm.job_mut(id).expect("job").take_checkpoints(true, 1);
        }
        let g = farm.lease(w, 0).expect("lease").expect("work");
        completed = farm.accept(g.lease_id, fake_result(&g), 0).expect("accept").job_completed;
    }
    assert!(completed);
    let rec = farm.job(id).expect("job").record(0);
    assert_eq!(rec.state, JobState::Completed);
    let mut final_on_disk = Farm::new(FarmConfig::default());
    final_on_disk.restore(rec.clone(), cps.clone(), &[0], 0).expect("restore");
    assert_eq!(final_on_disk.job(id).expect("job").state, JobState::Completed);
    let mut again = Farm::new(FarmConfig::default());
    again.restore(rec, cps, &[], 0).expect("restore");
    let job = again.job(id).expect("job");
    assert_eq!((job.state, job.units_merged, job.finished_ms), (JobState::Queued, units as u64 - 2, None));
    let w = again.register("w".into(), 1, 0);
    let mut leased = 0;
    while let Some(g) = again.lease(w, 0).expect("lease") {
        leased += 1;
        again.accept(g.lease_id, fake_result(&g), 0).expect("accept");
    }
    assert_eq!(leased, 2);
    let job = again.job(id).expect("job");
    assert_eq!(job.state, JobState::Completed);
    assert_eq!(job.film().as_deref(), Some(&reference));
}

/// Webhook events are queued once, only for the events a job asked for, in order.
#[test]
fn notifications_are_queued_for_the_events_asked_for() {
    let mut farm = Farm::new(FarmConfig::default());
    let hooked = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let url = "https://example.com/h".to_string();
    let events = vec![NotifyEvent::Started, NotifyEvent::Completed, NotifyEvent::Cancelled];
    farm.set_notify(hooked, Some(Notify { url, events })).expect("notify");
    let quiet = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let first = farm.lease(w, 0).expect("lease").expect("work");
    assert_eq!(first.job_id, hooked);
    farm.lease(w, 0).expect("lease").expect("work");
    assert_eq!(farm.take_notifications(), vec![(hooked, NotifyEvent::Started)]);
    assert!(farm.take_notifications().is_empty(), "drained");
    farm.pause(hooked, 1).expect("pause");
    farm.resume(hooked, 2).expect("resume");
    while farm.lease(w, 3).expect("lease").is_some() {}
    farm.cancel(quiet, 4).expect("cancel");
    farm.cancel(hooked, 4).expect("cancel");
    // Started is not sent again after a resume; the job without notify sends nothing.
    assert_eq!(farm.take_notifications(), vec![(hooked, NotifyEvent::Cancelled)]);
    farm.log_job(hooked, "notified cancelled: 200".into());
    assert_eq!(farm.job(hooked).expect("job").log.last().map(String::as_str), Some("notified cancelled: 200"));
}

#[test]
fn out_of_order_results_merge_to_the_same_film() {
    let s = settings();
    let reference = reference_film(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let mut grants = Vec::new();
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        grants.push(g);
    }
    assert_eq!(grants.len(), s.plan().unit_count());
    // Deliver in reverse: everything waits until pass 0 of each tile arrives.
    grants.reverse();
    let mut completed = Vec::new();
    for g in &grants {
        let out = farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
        completed.extend(out.passes_completed);
    }
    assert_eq!(completed, (0..s.plan().passes.len() as u32).collect::<Vec<_>>());
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Completed);
    assert_eq!(job.film().as_deref(), Some(&reference));
}

/// A result claiming more samples than its pass (1,000 for 1: R = 1000 was merged) or
/// fewer is refused and its unit handed out again; the honest result then merges.
#[test]
fn results_with_the_wrong_sample_count_are_refused() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig::default());
    farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let g = farm.lease(w, 0).expect("lease").expect("work");
    assert_eq!(g.pass.spp(), 1);
    let mut inflated = fake_result(&g);
    let v = SampleValue { radiance: [1.0; 3], ..Default::default() };
    for _ in 0..999 {
        pathfarm_common::film::add_sample(inflated.accum.pixel_mut(0, 0), &v);
    }
    match farm.accept(g.lease_id, inflated, 0) {
        Err(FarmError::ResultMismatch { reason, .. }) => {
            assert!(reason.contains("holds 1000 samples") && reason.contains("1 samples per pixel"), "{reason}")
        }
        r => panic!("accepted: {r:?}"),
    }
    // A pixel inside the tile: the reason names its image coordinates.
    let g = farm.lease(w, 0).expect("lease").expect("requeued");
    let mut off = fake_result(&g);
    let (lx, ly) = (g.tile.width() - 1, g.tile.height() - 1);
    pathfarm_common::film::add_sample(off.accum.pixel_mut(lx, ly), &v);
    match farm.accept(g.lease_id, off, 0) {
        Err(FarmError::ResultMismatch { reason, .. }) => {
            let at = format!("pixel ({}, {}) holds 2 samples", g.tile.x0 + lx, g.tile.y0 + ly);
            assert!(reason.contains(&at), "{reason}");
        }
        r => panic!("accepted: {r:?}"),
    }
    let mut empty = fake_result(&g);
    empty.accum = TileAccum::new(g.tile);
    let g = farm.lease(w, 0).expect("lease").expect("requeued");
    empty.lease_id = g.lease_id;
    assert!(matches!(farm.accept(g.lease_id, empty, 0), Err(FarmError::ResultMismatch { .. })));
    let g = farm.lease(w, 0).expect("lease").expect("requeued again");
    farm.accept(g.lease_id, fake_result(&g), 0).expect("the honest result merges");
}

#[test]
fn duplicate_and_expired_results_are_refused() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, ..FarmConfig::default() });
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let g = farm.lease(w, 0).expect("lease").expect("work");
    farm.accept(g.lease_id, fake_result(&g), 10).expect("first");
    assert_eq!(farm.accept(g.lease_id, fake_result(&g), 10), Err(FarmError::LeaseLost(g.lease_id)));
    // A lease renewed by heartbeats survives; an abandoned one expires.
    let g2 = farm.lease(w, 20).expect("lease").expect("work");
    farm.heartbeat(w, 90).expect("hb");
    assert_eq!(farm.expire(150), 0);
    assert_eq!(farm.expire(191), 1);
    assert_eq!(farm.accept(g2.lease_id, fake_result(&g2), 200), Err(FarmError::LeaseLost(g2.lease_id)));
    // The unit is handed out again, first, and merges once.
    let w2 = farm.register("w2".into(), 1, 200);
    let g3 = farm.lease(w2, 200).expect("lease").expect("work");
    assert_eq!((g3.unit, g3.tile), (g2.unit, g2.tile));
    farm.accept(g3.lease_id, fake_result(&g3), 200).expect("accept");
    assert_eq!(farm.job(id).expect("job").units_merged, 2);
}

#[test]
fn leases_and_workers_are_bound_to_their_secret() {
    let mut farm = Farm::new(FarmConfig::default());
    farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let a = farm.register_with_secret("a".into(), 1, "secret-a".into(), 0);
    let b = farm.register_with_secret("b".into(), 1, "secret-b".into(), 0);
    let nobody = farm.register("n".into(), 1, 0);
    let g = farm.lease(a, 0).expect("lease").expect("work");
    assert_eq!(farm.check_lease(g.lease_id, Some("secret-a")), Ok(()));
    for bad in [Some("secret-b"), Some(""), Some("secret-"), None] {
        assert!(matches!(farm.check_lease(g.lease_id, bad), Err(FarmError::WrongWorker(_))), "{bad:?}");
        assert!(matches!(farm.check_worker(a, bad), Err(FarmError::WrongWorker(_))), "{bad:?}");
    }
    assert_eq!(farm.check_worker(a, Some("secret-a")), Ok(()));
    assert_eq!(farm.check_worker(b, Some("secret-b")), Ok(()));
    assert!(matches!(farm.check_worker(nobody, Some("")), Err(FarmError::WrongWorker(_))));
    assert_eq!(farm.check_worker(999, Some("secret-a")), Err(FarmError::NoWorker(999)));
    assert_eq!(farm.check_lease(g.lease_id + 100, Some("secret-a")), Err(FarmError::LeaseLost(g.lease_id + 100)));
}

/// A job requiring `gpu` is not leased to a cpu-only worker (which still gets untagged
/// work); while no live worker has the tag the job stays queued and says why; a worker with
/// the tag gets it.
#[test]
fn required_tags_decide_which_worker_gets_a_job() {
    let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, ..FarmConfig::default() });
    let tags = |t: &[&str]| t.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let cpu = farm.register_tagged("cpu".into(), 1, String::new(), tags(&["cpu", "avx2"]), 0);
    let id = farm.submit_requiring("x".into(), None, 5, settings(), tags(&["gpu"]), 0).expect("submit");
    assert_eq!(farm.lease(cpu, 0).expect("lease"), None, "a cpu-only worker got a gpu unit");
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Queued);
    let info = job.info(0);
    assert_eq!(info.requires, tags(&["gpu"]));
    assert_eq!(info.waiting.as_deref(), Some("no live worker has tags [gpu]"));
    assert!(job.log.iter().any(|l| l.contains("no live worker has tags [gpu]")), "{:?}", job.log);
    // Untagged work still goes to the cpu worker, after the higher-priority gpu job.
    let plain = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    assert_eq!(farm.lease(cpu, 0).expect("lease").map(|g| g.job_id), Some(plain));
    let gpu = farm.register_tagged("gpu".into(), 1, String::new(), tags(&["cpu", "gpu"]), 0);
    assert_eq!(farm.job(id).expect("job").info(0).waiting, None);
    assert_eq!(farm.lease(gpu, 0).expect("lease").map(|g| g.job_id), Some(id));
    assert_eq!(farm.job(id).expect("job").state, JobState::Running);
    assert_eq!(farm.workers(0).iter().find(|w| w.id == gpu).map(|w| w.tags.clone()), Some(tags(&["cpu", "gpu"])));
    // The gpu worker goes silent: the job says so again.
    farm.heartbeat(cpu, 150).expect("hb");
    farm.expire(150);
    assert_eq!(farm.job(id).expect("job").info(150).waiting.as_deref(), Some("no live worker has tags [gpu]"));
    assert!(matches!(
        farm.submit_requiring("x".into(), None, 0, settings(), tags(&["GPU"]), 0),
        Err(FarmError::InvalidJob(_))
    ));
}

#[test]
fn offline_workers_are_pruned() {
    let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, worker_prune_ms: Some(1000), ..Default::default() });
    farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let quiet = farm.register("quiet".into(), 1, 0);
    let busy = farm.register("busy".into(), 1, 0);
    let alive = farm.register("alive".into(), 1, 0);
    farm.lease(busy, 0).expect("lease").expect("work");
    farm.heartbeat(alive, 900).expect("hb");
    assert_eq!(farm.prune_workers(1000), Vec::<WorkerId>::new());
    // The busy worker's lease expires (it is then silent too): pruned with the quiet one.
    farm.expire(1001);
    assert_eq!(farm.prune_workers(1001), vec![quiet, busy]);
    assert_eq!(farm.workers(1001).iter().map(|w| w.id).collect::<Vec<_>>(), vec![alive]);
    assert_eq!(farm.heartbeat(quiet, 1002), Err(FarmError::NoWorker(quiet)));
    let mut never = Farm::new(FarmConfig { worker_prune_ms: None, ..Default::default() });
    never.register("w".into(), 1, 0);
    assert!(never.prune_workers(u64::MAX).is_empty());
}

/// A coordinator stall longer than the lease timeout does not expire live workers' leases:
/// the expiry after it gives every lease one more lease timeout.
#[test]
fn leases_get_a_grace_period_after_a_stall() {
    let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 1000, ..FarmConfig::default() });
    let id = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let g = farm.lease(w, 0).expect("lease").expect("work");
    let g2 = farm.lease(w, 0).expect("lease").expect("work");
    for t in (250..=750).step_by(250) {
        assert_eq!(farm.expire(t), 0);
    }
    // Stalled from 750 to 5000: nothing expires, the worker is not offline.
    assert_eq!(farm.expire(5000), 0);
    assert!(farm.workers(5000).iter().all(|i| i.state != WorkerState::Offline));
    // The worker's result, sent during the stall, is heard and merged.
    farm.accept(g.lease_id, fake_result(&g), 5100).expect("merged after the stall");
    assert_eq!(farm.job(id).expect("job").units_merged, 1);
    // The grace is one lease timeout: a lease nobody renews expires after it.
    for t in (5250..=6000).step_by(250) {
        assert_eq!(farm.expire(t), 0, "{t}");
    }
    assert_eq!(farm.expire(6001), 1);
    assert_eq!(farm.accept(g2.lease_id, fake_result(&g2), 6002), Err(FarmError::LeaseLost(g2.lease_id)));
    // Without a stall, leases expire on time.
    let h = farm.lease(w, 6002).expect("lease").expect("work");
    let mut t = 6002;
    while t <= 7002 {
        t += 250;
        farm.expire(t);
    }
    assert_eq!(farm.accept(h.lease_id, fake_result(&h), t), Err(FarmError::LeaseLost(h.lease_id)));
}

#[test]
fn mismatched_result_is_refused_and_requeued() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig::default());
    farm.submit("x".into(), None, 0, s, 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let g = farm.lease(w, 0).expect("lease").expect("work");
    let g2 = farm.lease(w, 0).expect("lease").expect("work");
    let mut wrong = fake_result(&g2);
    wrong.lease_id = g.lease_id;
    assert!(matches!(farm.accept(g.lease_id, wrong, 0), Err(FarmError::ResultMismatch { .. })));
    let again = farm.lease(w, 0).expect("lease").expect("work");
    assert_eq!(again.unit, g.unit);
}

#[test]
fn higher_priority_first_and_fair_share_among_equals() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig::default());
    let low = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let low2 = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let high = farm.submit("x".into(), None, 5, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let units = s.plan().unit_count();
    for _ in 0..units {
        assert_eq!(farm.lease(w, 0).expect("lease").expect("work").job_id, high);
    }
    let mut counts = HashMap::new();
    for _ in 0..10 {
        *counts.entry(farm.lease(w, 0).expect("lease").expect("work").job_id).or_insert(0) += 1;
    }
    assert_eq!(counts.get(&low), Some(&5));
    assert_eq!(counts.get(&low2), Some(&5));
}

#[test]
fn repeated_failures_blocklist_the_worker_and_fail_the_job() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
    let a = farm.register("a".into(), 1, 0);
    let b = farm.register("b".into(), 1, 0);
    for _ in 0..2 {
        let g = farm.lease(a, 0).expect("lease").expect("work");
        farm.release(g.lease_id, true, "boom", 0).expect("release");
    }
    assert!(farm.job(id).expect("job").blocklist.contains(&a));
    assert_eq!(farm.lease(a, 0).expect("lease"), None);
    let g = farm.lease(b, 0).expect("lease").expect("work");
    farm.release(g.lease_id, true, "boom again", 0).expect("release");
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Failed);
    assert!(job.error.as_deref().is_some_and(|e| e.contains("boom again")), "{:?}", job.error);
}

#[test]
fn a_job_every_worker_fails_fails_instead_of_waiting_forever() {
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
    let only = farm.register("only".into(), 1, 0);
    // Two different units fail on the only worker: it is blocklisted, no unit failed 3 times.
    for _ in 0..2 {
        let g = farm.lease(only, 0).expect("lease").expect("work");
        farm.release(g.lease_id, true, "scene does not load", 0).expect("release");
    }
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Failed);
    assert!(job.error.as_deref().is_some_and(|e| e.contains("every worker")), "{:?}", job.error);
}

#[test]
fn cancel_pause_resume() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let g = farm.lease(w, 0).expect("lease").expect("work");
    farm.pause(id, 1).expect("pause");
    assert_eq!(farm.lease(w, 1).expect("lease"), None);
    // In-flight work still merges while paused.
    farm.accept(g.lease_id, fake_result(&g), 2).expect("accept");
    farm.resume(id, 3).expect("resume");
    let g = farm.lease(w, 3).expect("lease").expect("work");
    farm.cancel(id, 4).expect("cancel");
    assert_eq!(farm.accept(g.lease_id, fake_result(&g), 5), Err(FarmError::LeaseLost(g.lease_id)));
    assert!(farm.cancel(id, 6).is_err());
    farm.delete(id).expect("delete");
    assert_eq!(farm.job(id).err(), Some(FarmError::NoJob(id)));
}

/// Each operation says what it changed (what the service persists, wakes and publishes), and
/// taking the changes empties them.
#[test]
fn operations_report_their_changes() {
    let s = settings();
    let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, worker_prune_ms: Some(1000), ..Default::default() });
    let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
    let c = farm.take_changes();
    assert!(c.records.contains(&id) && c.work_ready, "{c:?}");
    assert!(farm.take_changes().is_empty());
    let w = farm.register("w".into(), 1, 0);
    let c = farm.take_changes();
    assert_eq!(c.registered, vec![(w, "w".to_string(), 1)]);
    assert!(c.workers.contains(&w));
    // The first lease starts the job: its record changes (state running).
    let g = farm.lease(w, 0).expect("lease").expect("work");
    let c = farm.take_changes();
    assert!(c.records.contains(&id) && c.progress.contains(&id) && c.workers.contains(&w), "{c:?}");
    // A result that completes no pass: progress only, nothing to write, nobody to wake.
    farm.accept(g.lease_id, fake_result(&g), 1).expect("accept");
    let c = farm.take_changes();
    assert!(c.progress.contains(&id) && c.records.is_empty() && !c.work_ready, "{c:?}");
    let g = farm.lease(w, 2).expect("lease").expect("work");
    farm.take_changes();
    farm.release(g.lease_id, false, "shutdown", 3).expect("release");
    let c = farm.take_changes();
    assert!(c.work_ready && c.progress.contains(&id), "{c:?}");
    // Leases expire and the silent worker goes offline, then is pruned.
    farm.lease(w, 4).expect("lease").expect("work");
    farm.take_changes();
    farm.expire(200);
    let c = farm.take_changes();
    assert!(c.work_ready && c.workers.contains(&w), "{c:?}");
    farm.prune_workers(2000);
    assert_eq!(farm.take_changes().pruned, vec![w]);
    farm.pause(id, 2001).expect("pause");
    assert!(farm.take_changes().records.contains(&id));
    farm.cancel(id, 2002).expect("cancel");
    assert!(farm.take_changes().outputs);
    farm.delete(id).expect("delete");
    assert!(farm.take_changes().removed.contains(&id));
    // A refused operation changes nothing.
    assert!(farm.pause(id, 2003).is_err());
    assert!(farm.take_changes().is_empty());
}

// ------------------------------------------------------------- adaptive sampling

/// 20 x 12 pixels in 16-pixel tiles (tile 0: 2 x 2 blocks), spp 7 in passes 1, 2, 4.
fn adaptive_settings() -> RenderSettings {
    let mut s = RenderSettings::new(20, 12, 7);
    s.tile_size = 16;
    s.passes = PassSchedule::Doubling { first: 1, max: 4 };
    s.adaptive = Some(AdaptiveSettings { threshold: 0.05, min_spp: 2 });
    s
}

/// A fake adaptive render: pixels left of x = 8 are flat (their blocks converge once they
/// have 2 samples), the others alternate 0.1 and 2.0 (never converge); pixels in the mask's
/// converged blocks get no samples (empty sums), as the renderer does.
fn adaptive_result(tile: TileRect, pass: pathfarm_common::job::Pass, mask: Option<&BlockMask>) -> TileAccum {
    let mut accum = TileAccum::new(tile);
    for y in tile.y0..tile.y1 {
        for x in tile.x0..tile.x1 {
            if mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0)) {
                continue;
            }
            for s in pass.samples() {
                let v = if x < 8 {
                    0.5
                } else if s % 2 == 0 {
                    0.1
                } else {
                    2.0
                };
                let v = SampleValue { radiance: [v, v * 0.5, x as f32 * 0.01 + y as f32], ..Default::default() };
                pathfarm_common::film::add_sample(accum.pixel_mut(x - tile.x0, y - tile.y0), &v);
            }
        }
    }
    accum
}

fn adaptive_grant_result(g: &LeaseGrant) -> UnitResultFrame {
    let accum = adaptive_result(g.tile, g.pass, g.mask.as_ref());
    UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None }
}

/// The local render's loop (`pathfarm_worker::render::render_local`) over the fake renderer.
fn adaptive_local(s: &RenderSettings) -> Film {
    let (plan, a) = (s.plan(), s.adaptive.expect("adaptive"));
    let mut film = Film::new(s.width, s.height);
    let mut masks: Vec<Option<BlockMask>> = vec![None; plan.tiles.len()];
    for key in plan.units() {
        let (tile, pass) = (plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
        let mask = masks[key.tile as usize].as_ref();
        if !mask.is_some_and(BlockMask::all_converged) {
            film.add_tile(&adaptive_result(tile, pass, mask));
        }
        masks[key.tile as usize] = Some(adaptive::converged_blocks(&film.tile(tile).sums, tile, &a, pass.s1));
    }
    film
}

/// Adaptive: a tile's next pass is leased only after its previous pass merged; the grants
/// carry the converged blocks; a fully converged tile leaves the schedule (its last pass is
/// never leased) and the frame completes; results delivered out of order give the local
/// render's film; a result with samples in converged blocks is refused; progress ends at
/// 1 with the samples actually taken.
#[test]
fn adaptive_masks_gate_passes_and_match_the_local_render() {
    let s = adaptive_settings();
    let plan = s.plan();
    assert_eq!((plan.tiles.len(), plan.passes.len()), (2, 3));
    let reference = adaptive_local(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let round = |farm: &mut Farm| {
        let mut grants = Vec::new();
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            grants.push(g);
        }
        grants
    };
    // Only pass 0 is pending: pass 1 waits for it.
    let g0 = round(&mut farm);
    assert_eq!(g0.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(0, 0), (0, 1)]);
    assert!(g0.iter().all(|g| g.mask.is_none()), "nothing decided before the first pass");
    // Delivered in reverse order; 1 sample is below min_spp: no mask yet.
    for g in g0.iter().rev() {
        farm.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
    }
    let g1 = round(&mut farm);
    assert_eq!(g1.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(1, 0), (1, 1)]);
    assert!(g1.iter().all(|g| g.mask.is_none()), "one sample: no pixel has an error estimate");
    for g in g1.iter().rev() {
        farm.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
    }
    // After 3 samples tile 0's left blocks converged: its pass 2 carries the mask; tile 1
    // (x 16..20) is noisy everywhere: no converged block, no mask.
    let g2 = round(&mut farm);
    assert_eq!(g2.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(2, 0), (2, 1)]);
    let mask = g2[0].mask.as_ref().expect("tile 0 has a mask");
    assert!(mask.is_converged(0, 0) && mask.is_converged(0, 1) && !mask.is_converged(1, 0));
    assert_eq!(g2[1].mask, None);
    // A result that samples the converged blocks anyway is refused and the unit comes back.
    let mut wrong = fake_result(&g2[0]);
    wrong.accum = adaptive_result(g2[0].tile, g2[0].pass, None);
    let e = farm.accept(g2[0].lease_id, wrong, 0).expect_err("refused");
    assert!(e.to_string().contains("its block has converged"), "{e}");
    let again = farm.lease(w, 0).expect("lease").expect("the unit is pending again");
    assert_eq!(again.unit, g2[0].unit);
    assert_eq!(again.mask.as_ref(), Some(mask));
    let mut out = farm.accept(g2[1].lease_id, adaptive_grant_result(&g2[1]), 0).expect("accept");
    assert!(!out.job_completed);
    out = farm.accept(again.lease_id, adaptive_grant_result(&again), 0).expect("accept");
    assert!(out.job_completed);
    let job = farm.job(id).expect("job");
    assert_eq!(job.film().as_deref(), Some(&reference), "farm film differs from the local render");
    let info = job.info(0);
    assert_eq!(info.progress, 1.0);
    assert_eq!(info.units_merged, info.units_total);
    // Tile 0's left 8 x 12 pixels stopped at 3 of 7 samples.
    assert_eq!(info.samples_total, 20 * 12 * 7 - 8 * 12 * 4);
    assert_eq!(info.samples_done, info.samples_total);
}

/// Adaptive with a tile that converges entirely: its remaining passes are never leased and
/// count as merged; a checkpoint restored mid-way recomputes the masks (they are not stored)
/// and finishes with the local render's film.
#[test]
fn adaptive_converged_tiles_leave_the_schedule_and_survive_a_restore() {
    let mut s = adaptive_settings();
    s.tile_size = 8; // tile (0, 0) and (0, 8) are flat: they converge after pass 1
    let plan = s.plan();
    let (tiles, passes) = (plan.tiles.len(), plan.passes.len());
    let flat = plan.tiles.iter().filter(|t| t.x1 <= 8).count();
    assert_eq!((tiles, flat), (6, 2));
    let reference = adaptive_local(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    // Passes 0 and 1 everywhere, then 1 unit of pass 2: checkpoint and restore.
    for _ in 0..2 * tiles + 1 {
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.accept(g.lease_id, adaptive_grant_result(&g), 0).expect("accept");
    }
    let cps = farm.job_mut(id).expect("job").take_checkpoints(true, 1);
    let rec = farm.job(id).expect("job").record(0);
    let before = farm.job(id).expect("job").info(0);
    let mut again = Farm::new(FarmConfig::default());
    again.restore(rec, cps, &[], 0).expect("restore");
    let after = again.job(id).expect("job").info(0);
    assert_eq!(
        (after.units_merged, after.samples_done, after.samples_total),
        (before.units_merged, before.samples_done, before.samples_total)
    );
    // Both flat tiles left the schedule: only the other tiles' pass 2 remains.
    assert_eq!(after.units_merged, (2 * tiles + 1 + flat) as u64);
    let w = again.register("w".into(), 1, 0);
    let mut left = Vec::new();
    while let Some(g) = again.lease(w, 0).expect("lease") {
        assert!(plan.tiles[g.unit.tile as usize].x1 > 8, "a converged tile was leased: {:?}", g.unit);
        left.push(g);
    }
    assert_eq!(left.len(), tiles * passes - (2 * tiles + 1) - flat);
    for g in left.iter().rev() {
        again.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
    }
    let job = again.job(id).expect("job");
    assert_eq!(job.state, JobState::Completed);
    assert_eq!(job.film().as_deref(), Some(&reference));
    assert_eq!(job.info(0).progress, 1.0);
}

/// `render_local`'s loop (worker/src/render/mod.rs) over the fake renderer of
/// [`adaptive_result`]: the film a local render of the job makes.
fn local_fold(s: &RenderSettings) -> Film {
    let plan = s.plan();
    let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
    let mut local = FilmAssembly::new(&plan, s.width, s.height);
    for key in plan.units() {
        let t = key.tile as usize;
        if local.next_pass(t) == key.pass {
            let accum = adaptive_result(plan.tiles[t], plan.passes[key.pass as usize], local.mask(t));
            local.offer(&plan, adaptive, key, accum, None);
        }
    }
    local.into_film().expect("film")
}

/// The farm folds through `FilmAssembly`, the fold of `render_local`: with and without
/// adaptive sampling, results delivered in a scrambled order, the film written to disk halfway
/// through every round (the rest of the round's results wait) and read back, give the film of
/// `render_local`'s loop over the same fake renderer, bit for bit, and of an assembly fed the
/// units in the farm's arrival order; each accept folds what that assembly folds. Half the
/// results come as packed bodies read in place, as the HTTP route takes them.
#[test]
fn the_farm_and_render_local_share_the_fold_in_any_order_and_across_a_spill() {
    for adaptive_on in [true, false] {
        let mut s = adaptive_settings();
        s.tile_size = 8;
        s.passes = PassSchedule::Fixed { spp: 1 }; // 7 passes of 1 sample
        if !adaptive_on {
            s.adaptive = None;
        }
        let plan = s.plan();
        let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
        let local = local_fold(&s);
        if adaptive_on {
            assert_eq!(local, adaptive_local(&s), "the assembly is the local render's adaptive loop");
        }
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let f = FrameRef { job: id, index: 0, frame: s.frame, sequence: false };
        let w = farm.register("w".into(), 1, 0);
        let mut fed = FilmAssembly::new(&plan, s.width, s.height);
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut rounds = 0;
        loop {
            let mut grants = Vec::new();
            while let Some(g) = farm.lease(w, 0).expect("lease") {
                grants.push(g);
            }
            if grants.is_empty() {
                break;
            }
            rounds += 1;
            // Fisher-Yates with xorshift64 (fixed seed): a scrambled arrival order.
            for i in (1..grants.len()).rev() {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                grants.swap(i, (x % (i as u64 + 1)) as usize);
            }
            let half = grants.len() / 2;
            let mut away = None;
            let mut folded_away = 0;
            for (n, g) in grants.iter().enumerate() {
                if n == half {
                    away = Some(farm.take_film(f).expect("the film is in memory"));
                    farm.film_spilled(f);
                }
                let r = adaptive_grant_result(g);
                let want = fed.offer(&plan, adaptive, g.unit, r.accum.clone(), None).len() as u32;
                // Every other result as the HTTP route takes it: packed sums read in place from
                // the body (merged as read when in order, decoded when they must wait).
                let body = r.encode_with(Codec::Packed);
                let out = if n % 2 == 0 {
                    let view = UnitResultFrame::decode_view(&body, g.tile, (s.width, s.height)).expect("decode");
                    assert!(matches!(view.sums, TileSums::Packed(_)));
                    farm.accept(g.lease_id, view, 0).expect("accept")
                } else {
                    farm.accept(g.lease_id, r, 0).expect("accept")
                };
                if away.is_some() {
                    assert_eq!(out.folded, 0, "nothing folds while the film is on disk");
                    folded_away += want;
                } else {
                    assert_eq!(out.folded, want, "the farm folds what the assembly folds");
                }
            }
            if let Some(cp) = away {
                assert_eq!(farm.job(id).expect("job").film().as_deref(), None);
                assert_eq!(farm.lease(w, 0).expect("lease"), None, "nothing is leased while the film is on disk");
                let out = farm.attach_film(f, Ok(cp), 0).expect("read back");
                assert_eq!(out.folded, folded_away, "the results that waited fold when it is back");
            }
        }
        assert!(rounds > 1 || !adaptive_on, "adaptive passes go out one at a time per tile");
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        assert!(
            job.film().as_deref() == Some(&local),
            "adaptive {adaptive_on}: the farm's film differs from render_local's"
        );
        assert!(fed.film() == Some(&local));
        let info = job.info(0);
        assert_eq!((info.units_merged, info.progress), (info.units_total, 1.0));
        let held: u64 = local.sums.iter().map(|p| u64::from(p.weight)).sum();
        assert_eq!((info.samples_done, info.samples_total), (held, held));
    }
}

/// Folds run outside the farm lock, under their frame's lock: a fold completes while another
/// thread holds the farm lock; four threads lease, fold and record units of two jobs at once
/// (one adaptive, one not; 7 passes of 1 sample), each leasing a few units and delivering them
/// in reverse after a pause drawn from a fixed-seed xorshift, so results of a tile fold out of
/// order and the records of one tile arrive in either order. Each job's film is the sequential
/// fold's (`render_local`'s) bit for bit, and its figures are complete.
#[test]
fn concurrent_folds_of_two_jobs_give_the_sequential_films() {
    use std::sync::{Arc, Mutex};
    let mut adaptive = adaptive_settings();
    adaptive.tile_size = 8;
    adaptive.passes = PassSchedule::Fixed { spp: 1 };
    let plain = RenderSettings { adaptive: None, ..adaptive.clone() };
    let farm = Arc::new(Mutex::new(Farm::new(FarmConfig::default())));
    let ids: Vec<JobId> = [&adaptive, &plain]
        .iter()
        .map(|s| farm.lock().expect("farm").submit("x".into(), None, 0, (*s).clone(), 0).expect("submit"))
        .collect();
    // A fold needs no farm lock.
    {
        let w = farm.lock().expect("farm").register("w".into(), 1, 0);
        let mut f = farm.lock().expect("farm");
        let g = f.lease(w, 0).expect("lease").expect("work");
        let fold = f.begin_accept(g.lease_id, adaptive_grant_result(&g), 0).expect("begin");
        let folding = std::thread::scope(|s| s.spawn(|| fold.fold()).join().expect("fold"));
        f.finish_accept(folding, 0);
        // Two folds of one tile recorded in reverse: the plain job's tile 0, passes 0 and 1.
        let mut grants = Vec::new();
        while grants.len() < 2 {
            let g = f.lease(w, 0).expect("lease").expect("work");
            if g.job_id == ids[1] && g.unit.tile == 0 {
                grants.push(g);
            } else {
                let fold = f.begin_accept(g.lease_id, adaptive_grant_result(&g), 0).expect("begin");
                f.finish_accept(fold.fold(), 0);
            }
        }
        let mut folds: Vec<Folding> = grants
            .iter()
            .map(|g| f.begin_accept(g.lease_id, adaptive_grant_result(g), 0).expect("begin").fold())
            .collect();
        let first = folds.remove(0);
        f.finish_accept(folds.remove(0), 0);
        assert_eq!(f.job(ids[1]).expect("job").open[&0].next_passes()[0], 2, "the later record moves the tile");
        f.finish_accept(first, 0);
        assert_eq!(f.job(ids[1]).expect("job").open[&0].next_passes()[0], 2, "the earlier record is behind it");
    }
    let done = |farm: &Farm| ids.iter().all(|&id| farm.job(id).expect("job").state == JobState::Completed);
    std::thread::scope(|scope| {
        for t in 0..4u64 {
            let farm = farm.clone();
            let done = &done;
            scope.spawn(move || {
                let w = farm.lock().expect("farm").register(format!("w{t}"), 1, 0);
                let mut x = 0x9e37_79b9_7f4a_7c15 ^ (t + 1);
                let mut next = move || {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x
                };
                // Bounded: a farm that lost track of its units fails the asserts, never hangs.
                for _ in 0..100_000 {
                    let mut grants = Vec::new();
                    {
                        let mut f = farm.lock().expect("farm");
                        if done(&f) {
                            return;
                        }
                        for _ in 0..1 + next() % 4 {
                            match f.lease(w, 0).expect("lease") {
                                Some(g) => grants.push(g),
                                None => break,
                            }
                        }
                    }
                    if grants.is_empty() {
                        std::thread::yield_now();
                        continue;
                    }
                    for g in grants.iter().rev() {
                        let fold = farm.lock().expect("farm").begin_accept(g.lease_id, adaptive_grant_result(g), 0);
                        let folding = fold.expect("begin").fold();
                        std::thread::sleep(std::time::Duration::from_micros(next() % 300));
                        farm.lock().expect("farm").finish_accept(folding, 0);
                    }
                }
            });
        }
    });
    let farm = farm.lock().expect("farm");
    for (id, s) in ids.iter().zip([&adaptive, &plain]) {
        let job = farm.job(*id).expect("job");
        let local = local_fold(s);
        assert!(job.film().as_deref() == Some(&local), "job {id}: concurrent folds changed the film");
        let info = job.info(0);
        assert_eq!((info.units_merged, info.progress), (info.units_total, 1.0), "job {id}");
        let held: u64 = local.sums.iter().map(|p| u64::from(p.weight)).sum();
        assert_eq!((info.samples_done, info.samples_total), (held, held), "job {id}");
        assert_eq!(job.leased, 0, "job {id}");
    }
}

/// Units are derived from the plan, never stored per (pass, tile): the job of issue 17
/// (8192 x 8192, spp 2^20, tile 8, 1-spp passes: 2^40 units, whose unit table aborted the
/// coordinator) is refused by the default unit limit with a message that says so; with the
/// limit lifted it is accepted holding no film and no unit table, and a frame's state with
/// 2^20 passes takes the same memory as with one pass.
#[test]
fn units_are_lazy_and_memory_does_not_grow_with_the_pass_count() {
    let mut huge = RenderSettings::new(8192, 8192, 1 << 20);
    huge.tile_size = 8;
    huge.passes = PassSchedule::Fixed { spp: 1 };
    let mut farm = Farm::new(FarmConfig::default());
    match farm.submit("x".into(), None, 0, huge.clone(), 0) {
        Err(FarmError::InvalidJob(m)) => assert!(m.contains("units (tiles x passes)"), "{m}"),
        r => panic!("admitted: {r:?}"),
    }
    let unlimited = FarmConfig {
        limits: Limits { max_units: u64::MAX, ..Limits::default() },
        film_budget_bytes: Some(Film::bytes_for(8192, 8192)),
        ..FarmConfig::default()
    };
    let mut farm = Farm::new(unlimited.clone());
    let id = farm.submit("x".into(), None, 0, huge, 0).expect("2^40 units are accepted without a unit table");
    assert_eq!(farm.job(id).expect("job").films_held(), 0, "a queued job holds no film");
    // Lease and merge a few units of a 2^20-pass frame (small image, 4096 tiles): canonical
    // order, pass 0 first; then compare its state with a 1-pass job's.
    let state_after = |spp: u32| {
        let mut s = RenderSettings::new(512, 512, spp);
        s.tile_size = 8;
        s.passes = PassSchedule::Fixed { spp: 1 };
        let mut farm = Farm::new(unlimited.clone());
        let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        for i in 0..10u32 {
            let g = farm.lease(w, 0).expect("lease").expect("work");
            assert_eq!((g.unit.pass, g.unit.tile), (0, i));
            farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
        }
        let job = farm.job(id).expect("job");
        job.open.values().map(FrameRun::state_bytes).sum::<usize>()
    };
    let (many, one) = (state_after(1 << 20), state_after(1));
    assert_eq!(many, one, "a frame's state must not depend on the pass count");
    assert!(many < 64 * 4096, "{many} bytes for 4096 tiles");
}

/// The canonical order survives returns: units handed back (expired, released, refused) go
/// out again before later ones, in (pass, tile) order, and every unit merges once.
#[test]
fn lazy_units_hand_out_returned_units_first_in_canonical_order() {
    let s = settings();
    let reference = reference_film(&s);
    let plan = s.plan();
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let mut out = Vec::new();
    for _ in 0..9 {
        out.push(farm.lease(w, 0).expect("lease").expect("work"));
    }
    // Units 7, 2 and 5 come back (in that order): they go out again sorted, before the
    // cursor's next unit.
    let key = |g: &LeaseGrant| (g.unit.pass, g.unit.tile);
    for i in [7, 2, 5] {
        farm.release(out[i].lease_id, false, "shutdown", 0).expect("release");
    }
    let again: Vec<_> = (0..4).map(|_| farm.lease(w, 0).expect("lease").expect("work")).collect();
    let tiles = plan.tiles.len() as u32;
    let next = (9 / tiles, 9 % tiles);
    assert_eq!(
        again.iter().map(key).collect::<Vec<_>>(),
        vec![key(&out[2]), key(&out[5]), key(&out[7]), next],
        "returned units first, then the cursor"
    );
    assert!(out.iter().map(key).collect::<Vec<_>>().is_sorted(), "pass-major order");
    // Everything else, delivered newest first.
    let mut grants: Vec<_> =
        out.iter().enumerate().filter(|(i, _)| ![2, 5, 7].contains(i)).map(|(_, g)| g.clone()).collect();
    grants.extend(again);
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        grants.push(g);
    }
    assert_eq!(grants.len(), plan.unit_count());
    for g in grants.iter().rev() {
        farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
    }
    let job = farm.job(id).expect("job");
    assert_eq!(job.state, JobState::Completed);
    assert_eq!(job.film().as_deref(), Some(&reference));
}

/// Films follow the jobs in progress: queued jobs hold none and are admitted while their film
/// alone fits the budget; they start when leased, once their film fits beside those held; a
/// finished job's film is dropped once its image is written, making room for the next.
#[test]
fn queued_jobs_hold_no_film_and_start_when_their_film_fits() {
    let s = settings();
    let film = Film::bytes_for(s.width, s.height);
    let mut farm = Farm::new(FarmConfig { film_budget_bytes: Some(film * 2), ..FarmConfig::default() });
    let ids: Vec<JobId> = (0..5).map(|_| farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit")).collect();
    assert_eq!(farm.film_bytes_held(), 0);
    let mut big = s.clone();
    big.width *= 3;
    match farm.submit("x".into(), None, 0, big, 0) {
        Err(FarmError::OverBudget(m)) => assert!(m.contains("--film-memory-mb") && m.contains("64 bytes"), "{m}"),
        r => panic!("admitted: {r:?}"),
    }
    let w = farm.register("w".into(), 1, 0);
    let mut grants = Vec::new();
    while let Some(g) = farm.lease(w, 0).expect("lease") {
        grants.push(g);
    }
    let started: std::collections::BTreeSet<JobId> = grants.iter().map(|g| g.job_id).collect();
    assert_eq!(started.len(), 2, "two films fit");
    assert_eq!(farm.film_bytes_held(), 2 * film);
    for g in &grants {
        farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
    }
    let done: Vec<JobId> = started.iter().copied().collect();
    assert!(done.iter().all(|&id| farm.job(id).expect("job").state == JobState::Completed));
    assert_eq!(farm.lease(w, 0).expect("lease"), None, "finished films are held until written");
    // The output loop wrote one job's final image: its film is dropped, the next job starts.
    farm.job_mut(done[0]).expect("job").output_dirty = false;
    assert!(farm.final_image_written(done[0], Some(0.5)).is_some());
    let job = farm.job(done[0]).expect("job");
    assert_eq!((job.film().as_deref(), job.image_on_disk()), (None, Some(Some(0.5))));
    assert_eq!(job.info(0).progress, 1.0);
    assert_eq!(farm.film_bytes_held(), film);
    let g = farm.lease(w, 0).expect("lease").expect("the third job starts");
    assert!(!started.contains(&g.job_id) && ids.contains(&g.job_id));
}

/// A restart loads no film for queued jobs (none was checkpointed) nor for finished jobs
/// whose image is on disk; a completed one keeps its figures; frames with a checkpoint resume.
#[test]
fn a_restart_loads_no_film_for_queued_or_written_jobs() {
    let s = settings();
    let units = s.plan().unit_count();
    let mut farm = Farm::new(FarmConfig::default());
    let done = farm.submit("x".into(), None, 1, s.clone(), 0).expect("submit");
    let queued: Vec<JobId> = (0..50).map(|_| farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit")).collect();
    // Nothing to checkpoint: a queued job holds no frame.
    for &id in &queued {
        assert!(farm.job_mut(id).expect("job").take_checkpoints(true, usize::MAX).is_empty());
    }
    let w = farm.register("w".into(), 1, 0);
    for _ in 0..units {
        let g = farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(g.job_id, done, "the higher priority first");
        farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
    }
    assert_eq!(farm.job(done).expect("job").state, JobState::Completed);
    let mut again = Farm::new(FarmConfig::default());
    for job in farm.jobs() {
        let written: &[usize] = if job.id == done { &[0] } else { &[] };
        // The store would find no checkpoint for the queued jobs and read none for the written one.
        again.restore(job.record(0), Vec::<Checkpoint>::new(), written, 0).expect("restore");
    }
    assert_eq!(again.film_bytes_held(), 0, "no film is loaded at restore");
    let info = again.job(done).expect("job").info(0);
    assert_eq!((info.state, info.units_merged, info.progress), (JobState::Completed, units as u64, 1.0));
    assert_eq!(again.job(done).expect("job").image_on_disk(), Some(None));
    assert!(queued.iter().all(|&id| again.job(id).expect("job").state == JobState::Queued));
}

/// The service's side of residency with a map for a disk: carries out one plan.
fn run_residency(farm: &mut Farm, disk: &mut HashMap<(JobId, i32), Checkpoint>, now: u64) -> ResidencyPlan {
    let plan = farm.residency_plan(now);
    for f in &plan.spill {
        let cp = farm.take_film(*f).expect("a film to write");
        disk.insert((f.job, f.frame), cp);
        farm.film_spilled(*f);
    }
    for f in &plan.load {
        let cp = disk.get(&(f.job, f.frame)).cloned().ok_or_else(|| "not on disk".to_string());
        farm.attach_film(*f, cp, now).expect("attach");
    }
    plan
}

/// A job's film, from memory or from the disk map.
fn film_of(farm: &Farm, disk: &HashMap<(JobId, i32), Checkpoint>, id: JobId) -> Film {
    let job = farm.job(id).expect("job");
    job.film().as_deref().cloned().unwrap_or_else(|| disk[&(id, job.settings.frame)].film.clone())
}

/// At most one film in memory (`max_resident_films` 1) and two jobs of equal priority: they
/// take turns, each film written to disk and read back many times, results that arrive while
/// their film is on disk wait and fold when it is back; both end bit-identical to an
/// uninterrupted render.
#[test]
fn lru_residency_with_one_film_alternates_two_jobs_bit_identically() {
    let s = settings();
    let reference = reference_film(&s);
    let mut farm = Farm::new(FarmConfig { max_resident_films: 1, min_resident_ms: 0, ..FarmConfig::default() });
    let a = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let b = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let mut disk = HashMap::new();
    let (mut held, mut spills, mut loads, mut served): (Vec<LeaseGrant>, _, _, Vec<JobId>) =
        (Vec::new(), 0, 0, Vec::new());
    for step in 0..10_000 {
        let plan = run_residency(&mut farm, &mut disk, step);
        (spills, loads) = (spills + plan.spill.len(), loads + plan.load.len());
        assert!(farm.films_in_memory().0 <= 1, "step {step}: {:?}", farm.films_in_memory());
        // Results leased before the plan arrive now, their film perhaps on disk.
        for g in std::mem::take(&mut held) {
            farm.accept(g.lease_id, fake_result(&g), step).expect("accept");
        }
        for _ in 0..3 {
            if let Some(g) = farm.lease(w, step).expect("lease") {
                served.push(g.job_id);
                held.push(g);
            }
        }
        assert!(farm.films_in_memory().0 <= 1);
        let done = |id| farm.job(id).expect("job").state == JobState::Completed;
        if held.is_empty() && done(a) && done(b) {
            break;
        }
    }
    assert!(
        farm.job(a).expect("job").state == JobState::Completed
            && farm.job(b).expect("job").state == JobState::Completed
    );
    let turns = served.windows(2).filter(|p| p[0] != p[1]).count();
    assert!(turns >= 4 && spills >= 4 && loads >= 3, "turns {turns}, spills {spills}, loads {loads}");
    assert_eq!(film_of(&farm, &disk, a), reference);
    assert_eq!(film_of(&farm, &disk, b), reference);
}

/// A paused job's film goes to disk (results in flight wait); resumed, it is read back at
/// the next plan and the job finishes bit-identical.
#[test]
fn a_paused_jobs_film_lives_on_disk() {
    let s = settings();
    let reference = reference_film(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
    let w = farm.register("w".into(), 1, 0);
    let mut disk = HashMap::new();
    let g1 = farm.lease(w, 0).expect("lease").expect("work");
    let g2 = farm.lease(w, 0).expect("lease").expect("work");
    farm.accept(g1.lease_id, fake_result(&g1), 0).expect("accept");
    farm.pause(id, 1).expect("pause");
    let plan = run_residency(&mut farm, &mut disk, 1);
    assert_eq!(plan.spill.len(), 1);
    assert_eq!(farm.film_bytes_held(), 0, "a paused job's film is on disk");
    assert_eq!(disk[&(id, 0)].next_pass.iter().sum::<u32>(), 1);
    // The unit in flight arrives: it waits in memory, nothing is folded.
    assert_eq!(farm.accept(g2.lease_id, fake_result(&g2), 2).expect("accept").folded, 0);
    assert!(run_residency(&mut farm, &mut disk, 2).is_empty(), "paused: stays on disk");
    farm.resume(id, 3).expect("resume");
    assert_eq!(farm.lease(w, 3).expect("lease"), None, "nothing is leased before the film is back");
    let plan = run_residency(&mut farm, &mut disk, 3);
    assert_eq!(plan.load.len(), 1);
    assert_eq!(farm.job(id).expect("job").units_merged, 2, "the waiting result folded");
    while let Some(g) = farm.lease(w, 4).expect("lease") {
        farm.accept(g.lease_id, fake_result(&g), 4).expect("accept");
    }
    assert_eq!(farm.job(id).expect("job").state, JobState::Completed);
    assert_eq!(film_of(&farm, &disk, id), reference);
}

/// A restart with checkpoint heads only: no film is in memory; a frame's film is read when its
/// job wants leasing, and the job finishes bit-identical. A checkpoint that does not match
/// what the farm restored fails the job with a message, never merges wrong sums.
#[test]
fn a_restart_reads_films_when_their_frames_are_leased() {
    let s = settings();
    let reference = reference_film(&s);
    let mut farm = Farm::new(FarmConfig::default());
    let ids: Vec<JobId> = (0..3).map(|_| farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit")).collect();
    let w = farm.register("w".into(), 1, 0);
    for _ in 0..12 {
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
    }
    let mut disk = HashMap::new();
    let mut again = Farm::new(FarmConfig::default());
    for &id in &ids {
        let cps = farm.job_mut(id).expect("job").take_checkpoints(true, usize::MAX);
        let heads: Vec<CheckpointHead> = cps.iter().map(Checkpoint::head).collect();
        for cp in cps {
            disk.insert((id, cp.frame), cp);
        }
        again.restore(farm.job(id).expect("job").record(0), heads, &[], 0).expect("restore");
    }
    assert_eq!(again.films_in_memory(), (0, 0), "no film is read at restore");
    let before = again.job(ids[0]).expect("job").info(0);
    assert_eq!(before.units_merged, farm.job(ids[0]).expect("job").units_merged);
    let w = again.register("w".into(), 1, 0);
    assert_eq!(again.lease(w, 0).expect("lease"), None, "films first");
    // The third job's checkpoint on disk is not the one restored: it fails, saying why.
    disk.get_mut(&(ids[2], 0)).expect("cp").next_pass[0] += 1;
    let plan = again.residency_plan(0);
    assert_eq!(plan.load.len(), 3);
    for f in &plan.load {
        let r = again.attach_film(*f, Ok(disk[&(f.job, f.frame)].clone()), 0);
        assert_eq!(r.is_err(), f.job == ids[2], "{r:?}");
    }
    let failed = again.job(ids[2]).expect("job");
    assert_eq!(failed.state, JobState::Failed);
    assert!(failed.error.as_deref().is_some_and(|e| e.contains("could not be read back")), "{:?}", failed.error);
    while let Some(g) = again.lease(w, 1).expect("lease") {
        again.accept(g.lease_id, fake_result(&g), 1).expect("accept");
    }
    for &id in &ids[..2] {
        assert_eq!(again.job(id).expect("job").state, JobState::Completed);
        assert_eq!(again.job(id).expect("job").film().as_deref(), Some(&reference));
    }
}
