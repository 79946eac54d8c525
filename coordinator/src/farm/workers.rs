//! Workers: registration, heartbeats, liveness, pruning.

use super::{Farm, FarmError, missing_secret};
use pathfarm_common::protocol::{LeaseId, WorkerId, WorkerInfo, WorkerState};
use std::collections::BTreeSet;

#[derive(Debug)]
pub(super) struct Worker {
    /// Issued at registration; every lease, heartbeat, result and release of this worker must
    /// carry it. Empty: nothing authenticates as this worker (farms built in tests).
    pub(super) secret: String,
    pub(super) name: String,
    pub(super) threads: u32,
    /// What it offers (registration); jobs' `requires` must be a subset.
    pub(super) tags: BTreeSet<String>,
    pub(super) leases: BTreeSet<LeaseId>,
    pub(super) last_seen_ms: u64,
    pub(super) registered_ms: u64,
    pub(super) units_done: u64,
    pub(super) samples_done: u64,
    pub(super) offline: bool,
}

impl Farm {
    /// Registers a worker that no request can authenticate as (see [`Farm::register_with_secret`]).
    pub fn register(&mut self, name: String, threads: u32, now_ms: u64) -> WorkerId {
        self.register_with_secret(name, threads, String::new(), now_ms)
    }

    /// Registers a worker whose requests must carry `secret` (an empty one never matches).
    pub fn register_with_secret(&mut self, name: String, threads: u32, secret: String, now_ms: u64) -> WorkerId {
        self.register_tagged(name, threads, secret, Vec::new(), now_ms)
    }

    /// Registers a worker offering `tags` (validated by the caller).
    pub fn register_tagged(
        &mut self,
        name: String,
        threads: u32,
        secret: String,
        tags: Vec<String>,
        now_ms: u64,
    ) -> WorkerId {
        let id = self.next_worker;
        self.next_worker += 1;
        tracing::info!(worker = id, %name, threads, ?tags, "worker registered");
        self.changes.registered.push((id, name.clone(), threads));
        self.changes.workers.insert(id);
        self.changes.work_ready = true;
        self.workers.insert(
            id,
            Worker {
                secret,
                name,
                threads,
                tags: tags.into_iter().collect(),
                leases: BTreeSet::new(),
                last_seen_ms: now_ms,
                registered_ms: now_ms,
                units_done: 0,
                samples_done: 0,
                offline: false,
            },
        );
        self.note_unservable();
        id
    }

    /// Marks the jobs with pending units whose `requires` no live (not offline) worker meets,
    /// logging once when a job becomes unservable, and clears the mark of the others. Runs
    /// when jobs or workers come and go (submit, registration, `expire`, pruning).
    pub fn note_unservable(&mut self) {
        let workers = &self.workers;
        for job in self.jobs.values_mut() {
            let stuck = !job.requires.is_empty()
                && job.accepts_work()
                && job.has_work()
                && !workers.values().any(|w| !w.offline && job.requires.iter().all(|t| w.tags.contains(t)));
            match (stuck, job.unservable.is_some()) {
                (true, false) => {
                    let why = format!("no live worker has tags [{}]", job.requires.join(", "));
                    job.log(format!("waiting: {why}"));
                    job.unservable = Some(why);
                }
                (false, true) => {
                    job.unservable = None;
                    if job.accepts_work() && job.has_work() {
                        job.log("a live worker has the required tags now".into());
                    }
                }
                _ => {}
            }
        }
    }

    /// Checks that `secret` is worker `worker`'s own: `NoWorker` if it is not registered,
    /// `WrongWorker` if the secret is missing or another's (compared in constant time).
    pub fn check_worker(&self, worker: WorkerId, secret: Option<&str>) -> Result<(), FarmError> {
        let w = self.workers.get(&worker).ok_or(FarmError::NoWorker(worker))?;
        match secret {
            Some(s) if crate::farm::token_matches(s, &w.secret) => Ok(()),
            Some(_) => Err(FarmError::WrongWorker(format!(
                "the worker secret is not worker {worker}'s: a worker may only act for itself"
            ))),
            None => Err(missing_secret()),
        }
    }

    /// Checks that lease `lease_id` is held and that `secret` belongs to the worker holding it:
    /// `LeaseLost` if it is not held, `WrongWorker` if the secret is missing or another's.
    pub fn check_lease(&self, lease_id: LeaseId, secret: Option<&str>) -> Result<(), FarmError> {
        let secret = secret.ok_or_else(missing_secret)?;
        let l = self.leases.get(&lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
        match self.workers.get(&l.worker) {
            Some(w) if crate::farm::token_matches(secret, &w.secret) => Ok(()),
            _ => Err(FarmError::WrongWorker(format!(
                "lease {lease_id} is held by another worker: only the worker it was granted to may deliver, \
                 release or renew it"
            ))),
        }
    }

    /// Marks the worker alive and extends its leases.
    pub fn heartbeat(&mut self, worker: WorkerId, now_ms: u64) -> Result<(), FarmError> {
        let w = self.workers.get_mut(&worker).ok_or(FarmError::NoWorker(worker))?;
        w.last_seen_ms = now_ms;
        if std::mem::replace(&mut w.offline, false) {
            self.changes.workers.insert(worker);
        }
        let deadline = now_ms + self.cfg.lease_timeout_ms;
        for id in &w.leases {
            if let Some(l) = self.leases.get_mut(id) {
                l.deadline_ms = deadline;
            }
        }
        Ok(())
    }

    /// Forgets workers that have not been seen for longer than `worker_prune_ms` and hold no
    /// lease; returns their ids (the store deletes their rows). A pruned worker that comes back
    /// gets 404 and registers again.
    pub fn prune_workers(&mut self, now_ms: u64) -> Vec<WorkerId> {
        let Some(after) = self.cfg.worker_prune_ms else { return Vec::new() };
        if now_ms < self.grace_until_ms {
            return Vec::new();
        }
        let gone: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.leases.is_empty() && now_ms.saturating_sub(w.last_seen_ms) > after)
            .map(|(id, _)| *id)
            .collect();
        for id in &gone {
            if let Some(w) = self.workers.remove(id) {
                tracing::info!(worker = id, name = %w.name, last_seen_ms = w.last_seen_ms, "offline worker pruned");
            }
        }
        if !gone.is_empty() {
            self.note_unservable();
            self.changes.pruned.extend(&gone);
            self.changes.workers.extend(&gone);
        }
        gone
    }

    pub fn workers(&self, now_ms: u64) -> Vec<WorkerInfo> {
        self.workers
            .iter()
            .map(|(&id, w)| {
                let current = w
                    .leases
                    .iter()
                    .next()
                    .and_then(|l| self.leases.get(l))
                    .and_then(|l| self.jobs.get(&l.job).map(|j| (l.job, j.unit_key(l.frame, l.unit))));
                let secs = now_ms.saturating_sub(w.registered_ms) as f64 / 1000.0;
                WorkerInfo {
                    id,
                    name: w.name.clone(),
                    threads: w.threads,
                    state: if w.offline {
                        WorkerState::Offline
                    } else if w.leases.is_empty() {
                        WorkerState::Idle
                    } else {
                        WorkerState::Busy
                    },
                    current,
                    units_done: w.units_done,
                    samples_done: w.samples_done,
                    samples_per_sec: if secs > 0.0 { w.samples_done as f64 / secs } else { 0.0 },
                    last_seen_ms: w.last_seen_ms,
                    tags: w.tags.iter().cloned().collect(),
                }
            })
            .collect()
    }
}
