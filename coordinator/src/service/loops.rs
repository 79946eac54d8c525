//! Background loops: lease expiry and maintenance, checkpoints.

use super::*;

/// Expires leases every `expiry_tick_ms` (a quarter second), prunes workers, wakes lease waiters
/// when units came back, collects old scenes and queues the jobs' webhook events.
pub async fn maintenance_loop(state: Arc<AppState>) {
    let mut tick = tokio::time::interval(Duration::from_millis(state.config.farm.expiry_tick_ms.max(1)));
    loop {
        tick.tick().await;
        // Also applies any change an earlier caller took no care of. Denoise steps given up:
        // their frames go on (images written, jobs completed).
        let ((expired, _, _), changes) = state.locked(|farm| {
            let now = now_ms();
            (farm.expire(now), farm.prune_workers(now), farm.expire_denoise(now))
        });
        if expired > 0 {
            tracing::warn!(expired, "leases expired; units are pending again");
        }
        state.apply_logged(changes, "the maintenance");
        if let Some(after) = state.config.scene_gc_after_ms {
            collect_scenes(&state, now_ms().saturating_sub(after));
        }
        super::webhook::enqueue_pending(&state);
    }
}

/// Checkpoints every job whose merged units or state changed: the film with its merged set
/// (atomically, one file), then the job's row.
pub async fn checkpoint_loop(state: Arc<AppState>) {
    // Per job: what the last checkpoint held, and when the next one may start. A checkpoint
    // copies the film under the farm lock and compresses it; for big films that is costly, so
    // the next one waits at least nine times as long as the last took (at most ~10% of a core),
    // unless the job's state or priority changed, or the job went quiet: a job that merged
    // nothing since the last tick gets its last merges saved now (when work stops, nothing merged
    // waits out a back-off that only exists to bound the cost while results flow).
    let mut seen: HashMap<JobId, ((u64, JobState, i32), Instant)> = HashMap::new();
    let mut last_tick: HashMap<JobId, u64> = HashMap::new();
    loop {
        tokio::time::sleep(state.config.checkpoint_interval).await;
        let due: Vec<JobId> = {
            let farm = state.farm.lock();
            let now = Instant::now();
            let due = farm
                .jobs()
                .filter(|j| match seen.get(&j.id) {
                    None => true,
                    Some(((merged, st, prio), next)) => {
                        let quiet = last_tick.get(&j.id) == Some(&j.units_merged);
                        (*st, *prio) != (j.state, j.priority) || (*merged != j.units_merged && (quiet || now >= *next))
                    }
                })
                .map(|j| j.id)
                .collect();
            last_tick = farm.jobs().map(|j| (j.id, j.units_merged)).collect();
            seen.retain(|id, _| last_tick.contains_key(id));
            due
        };
        for id in due {
            let t0 = Instant::now();
            let st = state.clone();
            match tokio::task::spawn_blocking(move || checkpoint_job(&st, id)).await {
                Ok(Ok(Some(key))) => {
                    let took = t0.elapsed();
                    seen.insert(id, (key, Instant::now() + took * 9));
                }
                Ok(Ok(None)) => {}
                Ok(Err(e)) => tracing::error!(job = id, "checkpoint failed: {e:#}"),
                Err(e) => tracing::error!(job = id, "checkpoint task failed: {e}"),
            }
        }
    }
}

/// What a job's checkpoint held: units merged, state, priority.
pub type CheckpointKey = (u64, JobState, i32);

/// Checkpoints job `id` now (blocking): the films of its frames in progress that merged units
/// since their last checkpoint, each with its merged set in one atomic file, and the job's row
/// with each. One film copy at a time, made under its frame lock after the farm lock is
/// released (merges of other frames and leases go on meanwhile). Returns what was written,
/// `None` when the job is gone.
pub fn checkpoint_job(state: &AppState, id: JobId) -> anyhow::Result<Option<CheckpointKey>> {
    let mut written = None;
    loop {
        let snapshot = {
            let mut farm = state.farm.lock();
            farm.job_mut(id).ok().map(|j| {
                let key = (j.units_merged, j.state, j.priority);
                (key, j.record(now_ms()), j.sequence, j.checkpoint_sources(false, 1))
            })
        };
        let Some((key, rec, sequence, sources)) = snapshot else { return Ok(written) };
        let more = sequence && !sources.is_empty();
        let cps: Vec<_> = sources.iter().filter_map(crate::farm::CheckpointSource::copy).collect();
        for cp in &cps {
            let path = if sequence {
                state.store().frame_checkpoint_path(id, cp.frame)
            } else {
                state.store().checkpoint_path(id)
            };
            write_checkpoint(&path, cp)?;
        }
        // Only a job that still exists gets its row written back: a DELETE that ran during the
        // snapshot or the write must not be undone (it came back after a restart). Lock order:
        // store, then farm (as in persist_job).
        let store = state.store();
        if state.farm.lock().job(id).is_ok() {
            store.put_job(&rec)?;
        } else {
            drop(store);
            let _ = std::fs::remove_dir_all(state.job_dir(id));
        }
        written = Some(key);
        if !more {
            return Ok(written);
        }
    }
}

/// Checkpoints every job (blocking); run at shutdown, once the loops have stopped, so that
/// nothing merged is lost. Returns the number of jobs written.
pub fn checkpoint_all(state: &AppState) -> usize {
    let ids: Vec<JobId> = state.farm.lock().jobs().map(|j| j.id).collect();
    let mut n = 0;
    for id in ids {
        match checkpoint_job(state, id) {
            Ok(Some(_)) => n += 1,
            Ok(None) => {}
            Err(e) => tracing::error!(job = id, "final checkpoint failed: {e:#}"),
        }
    }
    n
}
