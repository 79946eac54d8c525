//! One frame in progress: its scheduling state (units derived from the plan, never stored per
//! unit) and its [`FilmAssembly`], the one merge of units into a film (`common/src/assembly.rs`,
//! shared with `render_local`).

use parking_lot::{MappedMutexGuard, Mutex, MutexGuard};
use pathfarm_common::adaptive::{self, BlockMask};
use pathfarm_common::assembly::FilmAssembly;
use pathfarm_common::film::Film;
use pathfarm_common::job::{Plan, TileRect};
use pathfarm_common::protocol::LeaseId;
use pathfarm_common::protocol::TileSums;
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::sync::Arc;

/// Why a tile's sums (`rect`) do not hold exactly `spp` samples per pixel (each sample adds
/// weight 1 and at most one hit), as `Err`; else the samples they hold. A result claiming 1,000
/// samples for a 1-sample pass was merged. With adaptive sampling, pixels in the converged
/// blocks of `mask` must hold no sample.
pub(super) fn sample_count_mismatch(
    sums: &TileSums<'_>,
    rect: TileRect,
    spp: u32,
    mask: Option<&BlockMask>,
) -> Result<u64, String> {
    // Row by row (no division per pixel: this runs for every result).
    let w = rect.width().max(1) as usize;
    let mut samples = 0u64;
    for ly in 0..rect.height() {
        for lx in 0..w as u32 {
            let (weight, hits) = sums.weight_hits(ly as usize * w + lx as usize);
            let expected = adaptive::expected_samples(mask, lx, ly, spp);
            if weight != expected || hits > expected {
                let (x, y) = (rect.x0 + lx, rect.y0 + ly);
                let why = if expected == spp {
                    format!("the pass has {spp} samples per pixel")
                } else {
                    "its block has converged (adaptive sampling): it gets no samples".to_string()
                };
                return Err(format!("pixel ({x}, {y}) holds {weight} samples and {hits} hits; {why}"));
            }
            samples += u64::from(weight);
        }
    }
    Ok(samples)
}

/// One frame in progress: its scheduling state and its [`FilmAssembly`] (the film, each
/// tile's next pass, the results waiting, the adaptive masks: the same merge as
/// `render_local`'s), behind the frame's own lock. Frames not started have none of this;
/// finished ones are written and dropped.
///
/// Locking: the farm's state (this struct) changes under the farm lock; the assembly changes
/// under its frame lock. A result is folded under the frame lock alone (the farm lock is free
/// meanwhile: leases and other frames' merges go on), then recorded here under the farm lock
/// (`FrameRun::advance`, monotone, so two records of one tile in either order give the same
/// state). The lock order is farm, then frame: nothing takes the farm lock holding a frame lock.
///
/// Units are not stored: a unit is an index `pass * tiles + tile` (canonical, pass-major order)
/// and its state follows from the tile's recorded next pass (passes before it are merged) and
/// the units in flight (`leased`, `received`). Pending
/// units are found by a cursor that moves forward over the index space, plus `requeued` (units
/// before the cursor that came back). Memory: O(tiles + units in flight), whatever the pass
/// count.
#[derive(Debug)]
pub struct FrameRun {
    tiles: usize,
    passes: usize,
    /// Adaptive sampling: a tile's pass p+1 is pending only once its pass p is merged.
    adaptive: bool,
    /// Units at or after `cursor` are pending unless merged or in flight; pending units
    /// before it are in `requeued`.
    cursor: usize,
    pub(super) requeued: BTreeSet<usize>,
    /// Units leased and not yet received.
    leased: HashMap<usize, LeaseId>,
    /// Units whose result was taken: being folded, or waiting in the assembly for an earlier
    /// pass of their tile (or for the film). They leave when recorded as merged.
    received: HashSet<usize>,
    /// Per tile: the next pass as recorded (the assembly's is ahead by the folds not yet
    /// recorded).
    next_pass: Vec<u32>,
    /// Tiles per value of their next pass (the least key is the passes every tile merged).
    at_pass: BTreeMap<u32, u32>,
    /// The merge, behind the frame lock. Its film is `None` while on disk (its checkpoint):
    /// results then wait in it and nothing is leased until it is loaded
    /// ([`super::Farm::attach_film`]).
    pub(super) asm: Arc<Mutex<FilmAssembly>>,
    /// The assembly holds its film (changed with it, under the farm lock, so that scheduling
    /// never waits for the frame lock).
    pub(super) resident: bool,
    /// The film is being written to disk: it must not be loaded until that is done.
    pub(super) spilling: bool,
    /// Restored without its film (adaptive jobs: the samples the film holds are counted when
    /// it is loaded; the assembly judges the masks then).
    pub(super) restored: bool,
    /// When the frame was last leased from or merged into (the least recently used film is
    /// written to disk first), and when its film was last loaded.
    pub(super) last_used: u64,
    pub(super) loaded_ms: u64,
    pub passes_done: u32,
    pub(super) units_merged: u64,
    /// Merged units since the last checkpoint snapshot.
    pub(super) checkpoint_dirty: bool,
}

impl FrameRun {
    /// A frame merging into `asm` (a new film, or a checkpoint's passes). `adaptive`: each
    /// tile's later passes wait for its previous one.
    pub(super) fn new(plan: &Plan, asm: FilmAssembly, adaptive: bool) -> Self {
        let passes = plan.passes.len();
        let mut at_pass = BTreeMap::new();
        for &p in asm.next_passes() {
            *at_pass.entry(p).or_insert(0) += 1;
        }
        let units_merged = asm.next_passes().iter().map(|&p| u64::from(p)).sum();
        let next_pass = asm.next_passes().to_vec();
        FrameRun {
            tiles: plan.tiles.len(),
            passes,
            adaptive,
            cursor: 0,
            requeued: BTreeSet::new(),
            leased: HashMap::new(),
            received: HashSet::new(),
            next_pass,
            passes_done: at_pass.keys().next().copied().unwrap_or(passes as u32),
            at_pass,
            resident: asm.has_film(),
            asm: Arc::new(Mutex::new(asm)),
            spilling: false,
            restored: false,
            last_used: 0,
            loaded_ms: 0,
            units_merged,
            checkpoint_dirty: true,
        }
    }

    /// Units of the frame (tiles x passes).
    pub(super) fn unit_count(&self) -> u64 {
        self.tiles as u64 * self.passes as u64
    }

    /// (pass, tile) of unit `index`.
    fn split(&self, index: usize) -> (usize, usize) {
        (index / self.tiles.max(1), index % self.tiles.max(1))
    }

    fn in_flight(&self, index: usize) -> bool {
        self.leased.contains_key(&index) || self.received.contains(&index)
    }

    /// Whether unit `index` may be leased now (not merged, not in flight, and for adaptive
    /// jobs the next pass of its tile).
    fn is_pending(&self, index: usize) -> bool {
        let (pass, tile) = self.split(index);
        let next = self.next_pass[tile] as usize;
        pass < self.passes && pass >= next && (!self.adaptive || pass == next) && !self.in_flight(index)
    }

    /// Units that may be leased now (none while the film is on disk).
    pub(super) fn pending(&self) -> u64 {
        if !self.resident {
            return 0;
        }
        let in_flight = (self.leased.len() + self.received.len()) as u64;
        if self.adaptive {
            // One unit per tile that has passes left: its next pass.
            let finished = self.at_pass.get(&(self.passes as u32)).copied().unwrap_or(0);
            (self.tiles as u64 - u64::from(finished)).saturating_sub(in_flight)
        } else {
            self.unit_count().saturating_sub(self.units_merged).saturating_sub(in_flight)
        }
    }

    /// The cursor needs not look at or beyond this index: for adaptive jobs, no unit after
    /// the latest next pass of a tile with passes left may be pending.
    fn scan_end(&self) -> usize {
        if !self.adaptive {
            return self.tiles * self.passes;
        }
        match self.at_pass.range(..self.passes as u32).next_back() {
            Some((&p, _)) => (p as usize + 1) * self.tiles,
            None => 0,
        }
    }

    /// The first pending unit in canonical order, without taking it.
    pub(super) fn peek_pending(&mut self) -> Option<usize> {
        // Every unit before the passes all tiles merged is merged (a restored frame starts there).
        self.cursor = self.cursor.max(self.passes_done as usize * self.tiles);
        let end = self.scan_end();
        while self.cursor < end && !self.is_pending(self.cursor) {
            self.cursor += 1;
        }
        let scanned = (self.cursor < end).then_some(self.cursor);
        match (self.requeued.first().copied(), scanned) {
            (Some(r), Some(s)) => Some(r.min(s)),
            (r, s) => r.or(s),
        }
    }

    /// Leases the first pending unit in canonical order (returned units come first: they are
    /// earlier).
    pub(super) fn take_pending(&mut self, lease: LeaseId) -> Option<usize> {
        let i = self.peek_pending()?;
        if self.requeued.first() == Some(&i) {
            self.requeued.pop_first();
        } else {
            self.cursor = i + 1;
        }
        self.leased.insert(i, lease);
        Some(i)
    }

    /// A leased unit comes back (lease expired, released, result refused): pending again.
    pub(super) fn requeue(&mut self, index: usize) {
        if self.leased.remove(&index).is_some() && index < self.cursor && self.is_pending(index) {
            self.requeued.insert(index);
        }
    }

    /// The unit's result was taken: no longer leased, in flight until recorded as merged.
    pub(super) fn receive(&mut self, index: usize) {
        self.leased.remove(&index);
        self.received.insert(index);
    }

    /// The job ended: the results waiting will not be folded.
    pub(super) fn drop_received(&mut self) {
        self.received = HashSet::new();
        self.asm.lock().drop_waiting();
    }

    /// The film under the frame lock (held while the guard lives), unless it is on disk.
    pub(super) fn film(&self) -> Option<MappedMutexGuard<'_, Film>> {
        MutexGuard::try_map(self.asm.lock(), FilmAssembly::film_mut).ok()
    }

    /// Per tile, the next pass as recorded.
    pub(super) fn next_passes(&self) -> &[u32] {
        &self.next_pass
    }

    /// Records that the assembly moved `tile`'s next pass to `to` (a fold, or passes skipped
    /// because the tile converged). Monotone: a record behind the tile's is ignored, so records
    /// of one tile give the same state in any order. Keeps `at_pass`, `units_merged` and
    /// `passes_done` in step; for adaptive jobs the tile's new next pass becomes pending
    /// (before the cursor: requeued).
    pub(super) fn advance(&mut self, tile: usize, to: u32) {
        let from = self.next_pass[tile];
        if to <= from {
            return;
        }
        self.next_pass[tile] = to;
        self.units_merged += u64::from(to - from);
        if let Some(n) = self.at_pass.get_mut(&from) {
            *n -= 1;
            if *n == 0 {
                self.at_pass.remove(&from);
            }
        }
        *self.at_pass.entry(to).or_insert(0) += 1;
        // Units of the tile's merged or skipped passes are no longer pending.
        for p in from..to {
            let index = p as usize * self.tiles + tile;
            self.requeued.remove(&index);
            self.received.remove(&index);
        }
        let index = to as usize * self.tiles + tile;
        if self.adaptive && (to as usize) < self.passes && index < self.cursor && self.is_pending(index) {
            self.requeued.insert(index);
        }
        self.passes_done = self.at_pass.keys().next().copied().unwrap_or(self.passes as u32);
    }

    pub(super) fn is_complete(&self) -> bool {
        self.units_merged == self.unit_count()
    }

    /// Bytes this frame holds besides its film and the results waiting (tests: memory must not
    /// grow with the pass count).
    pub fn state_bytes(&self) -> usize {
        use std::mem::size_of;
        self.asm.lock().state_bytes()
            + self.next_pass.capacity() * size_of::<u32>()
            + self.at_pass.len() * 2 * size_of::<u32>()
            + (self.requeued.len() + self.leased.len() + self.received.len()) * 4 * size_of::<usize>()
    }
}
