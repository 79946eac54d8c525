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
                tracing::error!(
                    job = f.job,
                    frame = f.frame,
                    "writing a film to disk failed, it stays in memory: {e:#}"
                );
                let (_, changes) = state.locked(|farm| farm.return_film(*f, cp.film, now_ms()));
                state.apply_logged(changes, "a film kept in memory");
            }
        }
    }
    for f in &plan.load {
        let path = checkpoint_path(state, f);
        let cp = store::load_checkpoint(&path).map_err(|e| format!("{}: {e:#}", path.display()));
        let (out, changes) = state.locked(|farm| farm.attach_film(*f, cp, now_ms()));
        state.apply_logged(changes, "a film's read-back");
        match out {
            Ok(out) => tracing::debug!(job = f.job, frame = f.frame, folded = out.folded, "film read back from disk"),
            Err(e) => tracing::error!(job = f.job, frame = f.frame, "{e}"),
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_common::job::RenderSettings;

    /// A restart reads no film: 50 queued jobs (none was checkpointed) and a running one
    /// whose checkpoint holds its film; the running one's film is read by the first residency
    /// plan, when its job wants leasing, and a paused job's film goes back to disk.
    #[test]
    fn a_restart_reads_films_only_when_wanted() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), dir.path().into());
        let running = {
            let state = AppState::new(cfg.clone()).expect("state");
            let running = {
                let mut farm = state.farm.lock();
                let id = farm.submit("s".into(), None, 1, RenderSettings::new(64, 32, 4), 0).expect("submit");
                for _ in 0..50 {
                    farm.submit("s".into(), None, 0, RenderSettings::new(64, 32, 4), 0).expect("submit");
                }
                let w = farm.register("w".into(), 1, 0);
                assert_eq!(farm.lease(w, 0).expect("lease").map(|g| g.job_id), Some(id));
                id
            };
            assert_eq!(super::super::loops::checkpoint_all(&state), 51);
            running
        };
        let files: Vec<_> = std::fs::read_dir(dir.path().join("jobs"))
            .expect("jobs dir")
            .flatten()
            .filter(|e| e.path().join("checkpoint.bin").is_file())
            .map(|e| e.file_name())
            .collect();
        assert_eq!(files, vec![std::ffi::OsString::from(running.to_string())], "queued jobs have no checkpoint");
        let state = AppState::new(cfg).expect("restart");
        assert_eq!(state.farm.lock().films_in_memory(), (0, 0), "no film is read at restart");
        assert!(apply_residency(&state));
        assert_eq!(state.farm.lock().films_in_memory().0, 1, "the running job's film is read back");
        let w = state.farm.lock().register("w".into(), 1, 0);
        assert_eq!(state.farm.lock().lease(w, 0).expect("lease").map(|g| g.job_id), Some(running));
        state.farm.lock().pause(running, 0).expect("pause");
        assert!(apply_residency(&state));
        assert_eq!(state.farm.lock().films_in_memory(), (0, 0), "a paused job's film is on disk");
    }
}
