//! What farm operations changed, for the service to apply in one place.
//!
//! Every operation of [`Farm`](super::Farm) that changes something the outside world keeps or
//! shows marks it here; the service takes the accumulated [`Changes`] after the operation (with
//! the farm lock still held, so none is lost or applied twice) and applies them after releasing
//! the lock: it persists job records, forgets removed jobs, saves and deletes worker rows, wakes
//! long-polling workers and the output writer, and publishes events. No route places those
//! calls by hand, and changes a caller did not take are applied by the next one that does (the
//! maintenance loop does every tick).

use pathfarm_common::protocol::{JobId, WorkerId};
use std::collections::BTreeSet;

/// Changes since the last [`Farm::take_changes`](super::Farm::take_changes).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Changes {
    /// Jobs whose durable record changed (submitted, state, priority, webhook): persisted, and
    /// published.
    pub records: BTreeSet<JobId>,
    /// Jobs whose progress or log changed: published.
    pub progress: BTreeSet<JobId>,
    /// Jobs deleted: their rows and files go, and a last event says so.
    pub removed: BTreeSet<JobId>,
    /// Frames of sequences written, `(job, frame number)`: published.
    pub frames: Vec<(JobId, i32)>,
    /// Workers registered, `(id, name, threads)`: saved.
    pub registered: Vec<(WorkerId, String, u32)>,
    /// Workers forgotten (offline too long): their rows are deleted.
    pub pruned: Vec<WorkerId>,
    /// Workers whose state changed (registered, leased, offline, back): published.
    pub workers: BTreeSet<WorkerId>,
    /// Units may have become pending: long-polling workers are woken.
    pub work_ready: bool,
    /// A pass completed or a frame or job ended: outputs are written.
    pub outputs: bool,
}

impl Changes {
    pub fn is_empty(&self) -> bool {
        *self == Changes::default()
    }

    pub(super) fn record(&mut self, id: JobId) {
        self.records.insert(id);
    }

    pub(super) fn progress(&mut self, id: JobId) {
        self.progress.insert(id);
    }

    /// Adds `other`'s changes to these (changes taken but not applied go back).
    pub fn merge(&mut self, other: Changes) {
        self.records.extend(other.records);
        self.progress.extend(other.progress);
        self.removed.extend(other.removed);
        self.frames.extend(other.frames);
        self.registered.extend(other.registered);
        self.pruned.extend(other.pruned);
        self.workers.extend(other.workers);
        self.work_ready |= other.work_ready;
        self.outputs |= other.outputs;
    }
}
