//! Films on disk: carries out the farm's residency plan ([`crate::farm::Farm::residency_plan`]):
//! films of paused jobs and the least recently used films beyond `--max-resident-films` or
//! `--film-memory-mb` are written as their frames' checkpoints and dropped; films of frames
//! wanted again are read back.

use super::*;
use crate::farm::FrameRef;

/// Every `RESIDENCY_TICK`, carries out the farm's residency plan.
pub async fn residency_loop(state: Arc<AppState>) {
    let mut tick = tokio::time::interval(RESIDENCY_TICK);
    loop {
        tick.tick().await;
        let st = state.clone();
        if let Err(e) = tokio::task::spawn_blocking(move || apply_residency(&st)).await {
            tracing::error!("residency task failed: {e}");
        }
    }
}

/// How often the residency plan is carried out.
pub const RESIDENCY_TICK: Duration = Duration::from_millis(200);

fn checkpoint_path(state: &AppState, f: &FrameRef) -> PathBuf {
    let store = state.store();
    if f.sequence { store.frame_checkpoint_path(f.job, f.frame) } else { store.checkpoint_path(f.job) }
}

/// Carries out one residency plan (blocking): films written out first (their memory is free
/// before others are read), then films read back. Returns whether the plan did anything.
pub fn apply_residency(state: &AppState) -> bool {
    let plan = state.farm.lock().residency_plan(now_ms());
    if plan.is_empty() {
        return false;
    }
    for f in &plan.spill {
        let Some(cp) = state.farm.lock().take_film(*f) else { continue };
        let path = checkpoint_path(state, f);
        match write_checkpoint(&path, &cp) {
            Ok(()) => {
                drop(cp);
                let exists = {
                    let mut farm = state.farm.lock();
                    farm.film_spilled(*f);
                    farm.job(f.job).is_ok()
                };
                if exists {
                    tracing::debug!(job = f.job, frame = f.frame, "film written to disk and dropped");
                } else {
                    // Deleted meanwhile: no files may remain.
                    state.delete_job_files(f.job);
                }
            }
            Err(e) => {
                tracing::error!(job = f.job, frame = f.frame, "writing a film to disk failed, it stays in memory: {e:#}");
                let out = state.farm.lock().return_film(*f, cp.film, now_ms());
                publish_outcome(state, f.job, &out);
            }
        }
    }
    for f in &plan.load {
        let path = checkpoint_path(state, f);
        let cp = std::fs::read(&path)
            .map_err(|e| format!("reading {}: {e}", path.display()))
            .and_then(|b| store::decode_checkpoint(&b).map_err(|e| format!("{}: {e:#}", path.display())));
        let out = state.farm.lock().attach_film(*f, cp, now_ms());
        match out {
            Ok(out) => {
                tracing::debug!(job = f.job, frame = f.frame, folded = out.folded, "film read back from disk");
                publish_outcome(state, f.job, &out);
            }
            Err(e) => {
                tracing::error!(job = f.job, frame = f.frame, "{e}");
                state.publish(Event::Job { id: f.job });
            }
        }
    }
    state.work_ready.notify_waiters();
    true
}

/// Results folded when a film came back: progress, output and completion are announced.
fn publish_outcome(state: &AppState, id: JobId, out: &crate::farm::MergeOutcome) {
    if out.folded > 0 || !out.frames_completed.is_empty() {
        state.publish(Event::Job { id });
    }
    if !out.passes_completed.is_empty() || !out.frames_completed.is_empty() || out.job_completed {
        state.output_ready.notify_one();
    }
}
