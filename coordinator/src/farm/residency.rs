//! Which films are in memory: at most `max_resident_films` and `film_budget_bytes`; the rest
//! live on disk as their frames' checkpoints.
//!
//! The farm does no I/O: [`Farm::residency_plan`] says which films to write out and which to
//! read back, and the service does it: [`Farm::take_film`] moves a film out (the frame's
//! results wait in memory meanwhile, so nothing in flight is lost), the service writes it as
//! the frame's checkpoint and reports [`Farm::film_spilled`] (or gives it back with
//! [`Farm::return_film`]); a film read back is [`Farm::attach_film`]ed, which folds the results
//! that waited. A paused job's films go to disk at once; a job that wants its frames leased
//! loads them, writing out the least recently used films of jobs of no higher priority first
//! when the limits are reached.

use super::job::{Checkpoint, Job};
use super::{Farm, FarmError, MergeOutcome};
use pathfarm_common::assembly::Folded;
use pathfarm_common::film::Film;
use pathfarm_common::protocol::{FrameOrder, JobId, JobState};
use std::collections::HashSet;

/// A frame of a job: the job, the frame's index in its frame set and its number.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct FrameRef {
    pub job: JobId,
    pub index: usize,
    pub frame: i32,
    /// The job is a sequence (its checkpoint lives under `frames/NNNN/`).
    pub sequence: bool,
}

/// What the service is to do: films to write to disk (then drop), films to read back.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ResidencyPlan {
    pub spill: Vec<FrameRef>,
    pub load: Vec<FrameRef>,
}

impl ResidencyPlan {
    pub fn is_empty(&self) -> bool {
        self.spill.is_empty() && self.load.is_empty()
    }
}

fn frame_ref(job: &Job, index: usize) -> FrameRef {
    FrameRef { job: job.id, index, frame: job.frames.frames()[index], sequence: job.sequence }
}

impl Farm {
    /// Films in memory now (frames in progress, frames being written), and their bytes.
    pub fn films_in_memory(&self) -> (u64, u64) {
        self.jobs.values().fold((0, 0), |(n, b), j| (n + j.films_resident(), b + j.film_bytes()))
    }

    /// Decides which films go to disk and which come back (see the module doc).
    pub fn residency_plan(&self, now_ms: u64) -> ResidencyPlan {
        let max_films = self.cfg.max_resident_films.max(1) as u64;
        let budget = self.cfg.film_budget_bytes.unwrap_or(u64::MAX);
        let (mut films, mut bytes) = self.films_in_memory();
        let mut plan = ResidencyPlan::default();
        let mut chosen: HashSet<(JobId, usize)> = HashSet::new();
        let film_of = |j: &Job| Film::bytes_for(j.settings.width, j.settings.height);
        // A paused job's films go to disk.
        for job in self.jobs.values().filter(|j| j.state == JobState::Paused) {
            for &i in job.open.iter().filter(|(_, r)| r.resident && !r.spilling).map(|(i, _)| i) {
                plan.spill.push(frame_ref(job, i));
                chosen.insert((job.id, i));
                films -= 1;
                bytes = bytes.saturating_sub(film_of(job));
            }
        }
        // Jobs in lease order; each that cannot be leased for want of a film asks for it.
        let mut ranked: Vec<&Job> = self
            .jobs
            .values()
            .filter(|j| j.accepts_work() || (j.state.is_finished() && j.output_dirty && !j.sequence))
            .collect();
        ranked.sort_by_key(|j| (std::cmp::Reverse(j.priority), j.leased, j.served, j.id));
        let mut served: HashSet<JobId> = HashSet::new();
        for job in ranked {
            // A job with units to hand out keeps its films against the jobs ranked after it.
            if job.has_pending() {
                served.insert(job.id);
                continue;
            }
            let spilled = job.open.iter().find(|(_, r)| !r.resident && !r.spilling).map(|(&i, _)| i);
            let (load, n) = match spilled {
                Some(i) => (Some(i), 1),
                None if job.accepts_work()
                    && job.unstarted > 0
                    && job.open.values().all(|r| r.resident)
                    && (job.order == FrameOrder::SequencePreview
                        || job.films_held() < self.cfg.max_open_frames.max(1) as u64) =>
                {
                    (None, job.films_to_start())
                }
                None => continue,
            };
            let need = n.saturating_mul(film_of(job));
            if need > budget || n > max_films {
                continue;
            }
            // Room: the least recently used films of jobs of no higher priority that are not
            // served before this one (nor this one), and were not loaded moments ago.
            while films + n > max_films || bytes.saturating_add(need) > budget {
                let victim = self
                    .jobs
                    .values()
                    .filter(|v| v.id != job.id && !served.contains(&v.id) && v.priority <= job.priority)
                    .flat_map(|v| v.open.iter().map(move |(&i, r)| (v, i, r)))
                    .filter(|(v, i, r)| {
                        r.resident
                            && !r.spilling
                            && !chosen.contains(&(v.id, *i))
                            && now_ms.saturating_sub(r.loaded_ms) >= self.cfg.min_resident_ms
                    })
                    .min_by_key(|(v, i, r)| (r.last_used, v.id, *i));
                let Some((v, i, _)) = victim else { break };
                plan.spill.push(frame_ref(v, i));
                chosen.insert((v.id, i));
                films -= 1;
                bytes = bytes.saturating_sub(film_of(v));
            }
            if films + n > max_films || bytes.saturating_add(need) > budget {
                // No room for this job: those ranked after it may not take room before it (and
                // the plan stays O(jobs) per want met).
                break;
            }
            served.insert(job.id);
            films += n;
            bytes += need;
            if let Some(i) = load {
                plan.load.push(frame_ref(job, i));
            }
        }
        plan
    }

    /// Moves frame `f`'s film out for the service to write to disk, with its merged set (the
    /// frame's checkpoint); `None` when it is not in memory. Until [`Farm::film_spilled`] or
    /// [`Farm::return_film`], the frame is neither leased nor loaded; results wait.
    pub fn take_film(&mut self, f: FrameRef) -> Option<Checkpoint> {
        let job = self.jobs.get_mut(&f.job)?;
        let run = job.open.get_mut(&f.index)?;
        if run.spilling {
            return None;
        }
        // Under the frame lock (a fold in progress finishes first): the film and the passes it
        // holds together.
        let (film, next_pass) = {
            let mut asm = run.asm.lock();
            let film = asm.take_film()?;
            (film, asm.next_passes().to_vec())
        };
        run.resident = false;
        run.spilling = true;
        run.checkpoint_dirty = false;
        Some(Checkpoint { job_id: f.job, frame: f.frame, next_pass, film })
    }

    /// The film taken by [`Farm::take_film`] is on disk.
    pub fn film_spilled(&mut self, f: FrameRef) {
        if let Some(run) = self.jobs.get_mut(&f.job).and_then(|j| j.open.get_mut(&f.index)) {
            run.spilling = false;
        }
    }

    /// Writing the film taken by [`Farm::take_film`] failed: it is in memory again.
    pub fn return_film(&mut self, f: FrameRef, film: Film, now_ms: u64) -> MergeOutcome {
        let Some(job) = self.jobs.get_mut(&f.job) else { return MergeOutcome::default() };
        let Some(run) = job.open.get_mut(&f.index) else { return MergeOutcome::default() };
        run.spilling = false;
        if run.resident {
            return MergeOutcome::default();
        }
        run.checkpoint_dirty = true;
        let folded = job.put_film(f.index, film);
        self.film_back(f, &folded, now_ms)
    }

    /// Frame `f`'s film read back from its checkpoint: it must hold exactly the merged set the
    /// farm has for the frame. The results that waited are folded (which may complete the frame
    /// and the job). A checkpoint that cannot be read or does not match fails the job: the
    /// merged units it held are gone.
    pub fn attach_film(
        &mut self,
        f: FrameRef,
        cp: Result<Checkpoint, String>,
        now_ms: u64,
    ) -> Result<MergeOutcome, FarmError> {
        let job = self.jobs.get_mut(&f.job).ok_or(FarmError::NoJob(f.job))?;
        let Some(run) = job.open.get_mut(&f.index) else { return Ok(MergeOutcome::default()) };
        if run.resident || run.spilling {
            return Ok(MergeOutcome::default());
        }
        let (w, h) = (job.settings.width, job.settings.height);
        let held = run.asm.lock().next_passes().to_vec();
        let film = cp.and_then(|cp| {
            if cp.job_id != f.job || cp.frame != f.frame || cp.next_pass != held {
                Err(format!("its checkpoint holds passes {:?}, the farm {held:?}", cp.next_pass))
            } else if (cp.film.width, cp.film.height) != (w, h) {
                Err(format!("its checkpoint is {}x{}, the job {w}x{h}", cp.film.width, cp.film.height))
            } else {
                Ok(cp.film)
            }
        });
        match film {
            Ok(film) => {
                run.loaded_ms = now_ms;
                run.last_used = now_ms;
                let folded = job.put_film(f.index, film);
                if job.state.is_finished() && !job.sequence {
                    job.output_dirty = true;
                    self.changes.outputs = true;
                }
                Ok(self.film_back(f, &folded, now_ms))
            }
            Err(e) => {
                let msg = format!("frame {} could not be read back from disk: {e}", f.frame);
                job.log(format!("job failed: {msg}"));
                self.changes.progress(f.job);
                // Nothing is left to read back (or to try again).
                job.open.remove(&f.index);
                if job.state.is_finished() {
                    job.output_dirty = job.sequence;
                } else {
                    self.finish(f.job, JobState::Failed, Some(msg.clone()), now_ms);
                }
                Err(FarmError::InvalidJob(msg))
            }
        }
    }

    /// Frame `f`'s film is back: records the results that waited and folded (which may
    /// complete the frame and the job).
    fn film_back(&mut self, f: FrameRef, folded: &[Folded], now_ms: u64) -> MergeOutcome {
        // The frame's film is back: its units may be leased again.
        self.changes.work_ready = true;
        self.changes.progress(f.job);
        self.settle(f.job, f.index, folded, now_ms)
    }
}
