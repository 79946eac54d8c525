//! One frame in progress: its merge state (units derived from the plan, never stored per
//! unit), film and adaptive decisions.

use pathfarm_common::adaptive::{self, AdaptiveSettings, BlockMask};
use pathfarm_common::assembly::skipped_samples;
use pathfarm_common::film::{Film, SplatBuffer, TileAccum};
use pathfarm_common::job::Plan;
use pathfarm_common::protocol::LeaseId;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// at most one hit), or `None`. A result claiming 1,000 samples for a 1-sample pass was merged.
/// With adaptive sampling, pixels in the converged blocks of `mask` must hold no sample.
pub(super) fn sample_count_mismatch(accum: &TileAccum, spp: u32, mask: Option<&BlockMask>) -> Option<String> {
    let w = accum.rect.width();
    accum.sums.iter().enumerate().find_map(|(i, p)| {
        let (lx, ly) = (i as u32 % w, i as u32 / w);
        let expected = adaptive::expected_samples(mask, lx, ly, spp);
        (p.weight != expected || p.hits > expected).then(|| {
            let (x, y) = (accum.rect.x0 + lx, accum.rect.y0 + ly);
            let why = if expected == spp {
                format!("the pass has {spp} samples per pixel")
            } else {
                "its block has converged (adaptive sampling): it gets no samples".to_string()
            };
            format!("pixel ({x}, {y}) holds {:.3} samples and {:.3} hits; {why}", p.weight(), f64::from(p.hits))
        })
    })
}

/// One frame whose film exists: its merge state and film. Frames not started have none of
/// this; finished ones are written and dropped.
///
/// Units are not stored: a unit is an index `pass * tiles + tile` (canonical, pass-major order)
/// and its state follows from the tile's `next_pass` (passes before it are merged) and the
/// units in flight (`leased`, `waiting`). Pending units are found by a cursor that moves
/// forward over the index space, plus `requeued` (units before the cursor that came back).
/// Memory: O(tiles + units in flight), whatever the pass count.
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
    /// Per tile: the next pass to fold (all passes before it are merged).
    pub(super) next_pass: Vec<u32>,
    /// Tiles per value of `next_pass` (the least key is the passes every tile merged).
    at_pass: BTreeMap<u32, u32>,
    /// Results received before their tile's earlier passes merged.
    pub(super) waiting: HashMap<usize, (TileAccum, Option<SplatBuffer>)>,
    /// Adaptive sampling: per tile, the converged blocks after its last merged pass (`None`
    /// before the first, and for jobs without `adaptive`). A pure function of the film, so
    /// checkpoints do not hold it: restore computes it again.
    pub(super) masks: Vec<Option<BlockMask>>,
    /// The merged sums; `None` while the film is on disk (its checkpoint): results then wait
    /// in `waiting` and nothing is leased until it is loaded ([`super::Farm::attach_film`]).
    pub film: Option<Film>,
    /// The film is being written to disk: it must not be loaded until that is done.
    pub(super) spilling: bool,
    /// Restored without its film (adaptive jobs: masks and samples are computed when loaded).
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
    /// A frame with nothing merged. `adaptive`: only the first pass is pending; each tile's
    /// later passes wait for its previous one.
    pub(super) fn new(plan: &Plan, film: Option<Film>, adaptive: bool) -> Self {
        let tiles = plan.tiles.len();
        FrameRun {
            tiles,
            passes: plan.passes.len(),
            adaptive,
            cursor: 0,
            requeued: BTreeSet::new(),
            leased: HashMap::new(),
            next_pass: vec![0; tiles],
            at_pass: BTreeMap::from([(0, tiles as u32)]),
            waiting: HashMap::new(),
            masks: if adaptive { vec![None; tiles] } else { Vec::new() },
            film,
            spilling: false,
            restored: false,
            last_used: 0,
            loaded_ms: 0,
            passes_done: 0,
            units_merged: 0,
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
        self.leased.contains_key(&index) || self.waiting.contains_key(&index)
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
        if self.film.is_none() {
            return 0;
        }
        let in_flight = (self.leased.len() + self.waiting.len()) as u64;
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

    /// The unit's result arrived: it waits in `waiting` until it is folded in tile order.
    pub(super) fn receive(&mut self, index: usize, accum: TileAccum, splats: Option<SplatBuffer>) {
        self.leased.remove(&index);
        self.waiting.insert(index, (accum, splats));
    }

    /// Tiles with results waiting, in order.
    pub(super) fn waiting_tiles(&self) -> Vec<usize> {
        let tiles: BTreeSet<usize> = self.waiting.keys().map(|&i| self.split(i).1).collect();
        tiles.into_iter().collect()
    }

    /// The next unit `tile` folds, if its result is here: taken out of `waiting`.
    pub(super) fn take_next_result(&mut self, tile: usize) -> Option<(usize, TileAccum, Option<SplatBuffer>)> {
        let next = self.next_pass[tile] as usize;
        if next >= self.passes {
            return None;
        }
        let index = next * self.tiles + tile;
        self.waiting.remove(&index).map(|(a, s)| (index, a, s))
    }

    /// Sets `tile`'s next pass (only forward) and keeps `at_pass` and `passes_done` in step;
    /// for adaptive jobs the tile's new next pass becomes pending (before the cursor: requeued).
    pub(super) fn advance(&mut self, tile: usize, to: u32) {
        let from = self.next_pass[tile];
        if to <= from {
            return;
        }
        self.units_merged += u64::from(to - from);
        self.next_pass[tile] = to;
        if let Some(n) = self.at_pass.get_mut(&from) {
            *n -= 1;
            if *n == 0 {
                self.at_pass.remove(&from);
            }
        }
        *self.at_pass.entry(to).or_insert(0) += 1;
        // Units of the tile's skipped passes are no longer pending (adaptive: converged).
        for p in from + 1..to {
            self.requeued.remove(&(p as usize * self.tiles + tile));
        }
        self.requeued.remove(&(from as usize * self.tiles + tile));
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
        self.next_pass.capacity() * size_of::<u32>()
            + self.at_pass.len() * 2 * size_of::<u32>()
            + self.masks.capacity() * size_of::<Option<BlockMask>>()
            + (self.requeued.len() + self.leased.len() + self.waiting.len()) * 4 * size_of::<usize>()
    }

    /// Adaptive sampling, once `tile` has merged its passes before `next_pass[tile]`: its
    /// converged blocks from the film's merged sums (exactly as `render_local` decides), then
    /// either its next pass becomes pending with the mask, or, when every block has converged,
    /// its remaining passes count as merged with nothing (the tile leaves the schedule).
    pub(super) fn decide(&mut self, plan: &Plan, a: &AdaptiveSettings, spp: u32, tile: usize) -> Decision {
        let passes = plan.passes.len();
        let np = self.next_pass[tile] as usize;
        let mut out = Decision::default();
        if np == 0 {
            return out;
        }
        let rect = plan.tiles[tile];
        let Some(film) = &self.film else { return out };
        let sums = film.tile(rect).sums;
        let mask = adaptive::converged_blocks(&sums, rect, a, plan.passes[np - 1].s1);
        let before = skipped_samples(self.masks[tile].as_ref(), &sums, rect, spp);
        out.samples_skipped = skipped_samples(Some(&mask), &sums, rect, spp).saturating_sub(before);
        let all = mask.all_converged();
        self.masks[tile] = Some(mask);
        if np >= passes {
            return out;
        }
        if all {
            out.units_skipped = (passes - np) as u64;
            self.advance(tile, passes as u32);
        }
        out
    }
}

/// What an adaptive decision for a tile changed.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Decision {
    /// Units (the tile's remaining passes) counted as merged because every block converged.
    pub(super) units_skipped: u64,
    /// Samples that newly converged pixels will not get (taken off the job's total).
    pub(super) samples_skipped: u64,
}
