//! One frame in progress: its unit states, merge order and film; adaptive decisions.

use pathfarm_common::adaptive::{self, AdaptiveSettings, BlockMask};
use pathfarm_common::film::{Film, SplatBuffer, TileAccum};
use pathfarm_common::job::{Plan, TileRect};
use pathfarm_common::protocol::LeaseId;
use std::collections::{BTreeSet, HashMap};

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

/// Samples a tile's converged pixels will not get: per pixel in a converged block of `mask`,
/// the job's spp less the samples it holds (they stop changing once their block converged).
pub(super) fn skipped_samples(
    mask: Option<&BlockMask>,
    sums: &[pathfarm_common::film::PixelSums],
    rect: TileRect,
    spp: u32,
) -> u64 {
    let Some(mask) = mask else { return 0 };
    let w = rect.width();
    sums.iter()
        .enumerate()
        .filter(|(i, _)| mask.pixel_converged(*i as u32 % w, *i as u32 / w))
        .map(|(_, p)| u64::from(spp.saturating_sub(p.weight)))
        .sum()
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum UnitState {
    Pending,
    Leased(LeaseId),
    /// Result held in `waiting` until the tile's earlier passes are merged.
    Received,
    Merged,
    /// Adaptive sampling: the tile's previous pass is not merged yet, so the blocks this unit
    /// samples are not known; it becomes pending when that pass merges.
    Blocked,
}

/// One frame whose film exists: its units (pass-major: `pass * tiles + tile`), merge state and
/// film. Frames not started have none of this; finished ones are written and dropped.
#[derive(Debug)]
pub struct FrameRun {
    pub(super) units: Vec<UnitState>,
    /// Pending units before `cursor` are in `requeued`; at or after it, units are scanned.
    pub(super) cursor: usize,
    pub(super) pending: usize,
    pub(super) requeued: BTreeSet<usize>,
    /// Per tile: the next pass to fold.
    pub(super) next_pass: Vec<u32>,
    pub(super) waiting: HashMap<usize, (TileAccum, Option<SplatBuffer>)>,
    /// Tiles merged, per pass.
    pub(super) pass_merged: Vec<u32>,
    /// Adaptive sampling: per tile, the converged blocks after its last merged pass (`None`
    /// before the first, and for jobs without `adaptive`). A pure function of the film, so
    /// checkpoints do not hold it: restore computes it again.
    pub(super) masks: Vec<Option<BlockMask>>,
    pub film: Film,
    pub passes_done: u32,
    pub(super) units_merged: u64,
    /// Merged units since the last checkpoint snapshot.
    pub(super) checkpoint_dirty: bool,
}

impl FrameRun {
    /// A frame with nothing merged. `adaptive`: only the first pass is pending; each tile's
    /// later passes wait for its previous one ([`UnitState::Blocked`]).
    pub(super) fn new(plan: &Plan, width: u32, height: u32, adaptive: bool) -> Self {
        let units = plan.unit_count();
        let tiles = plan.tiles.len();
        let pending = if adaptive { tiles.min(units) } else { units };
        let mut states = vec![UnitState::Pending; units];
        states[pending..].fill(UnitState::Blocked);
        FrameRun {
            units: states,
            cursor: 0,
            pending,
            requeued: BTreeSet::new(),
            next_pass: vec![0; tiles],
            waiting: HashMap::new(),
            pass_merged: vec![0; plan.passes.len()],
            masks: vec![None; tiles],
            film: Film::new(width, height),
            passes_done: 0,
            units_merged: 0,
            checkpoint_dirty: true,
        }
    }

    /// The first pending unit in canonical order, without taking it.
    pub(super) fn peek_pending(&mut self) -> Option<usize> {
        while self.cursor < self.units.len() && self.units[self.cursor] != UnitState::Pending {
            self.cursor += 1;
        }
        let scanned = (self.cursor < self.units.len()).then_some(self.cursor);
        match (self.requeued.first().copied(), scanned) {
            (Some(r), Some(s)) => Some(r.min(s)),
            (r, s) => r.or(s),
        }
    }

    /// The first pending unit in canonical order (returned units come first: they are earlier).
    pub(super) fn take_pending(&mut self) -> Option<usize> {
        let i = self.peek_pending()?;
        if self.requeued.first() == Some(&i) {
            self.requeued.pop_first();
        } else {
            self.cursor = i + 1;
        }
        self.pending -= 1;
        Some(i)
    }

    pub(super) fn requeue(&mut self, index: usize) {
        if self.units[index] != UnitState::Pending {
            self.units[index] = UnitState::Pending;
            self.pending += 1;
            if index < self.cursor {
                self.requeued.insert(index);
            }
        }
    }

    pub(super) fn is_complete(&self) -> bool {
        self.units_merged == self.units.len() as u64
    }

    /// Adaptive sampling, once `tile` has merged its passes before `next_pass[tile]`: its
    /// converged blocks from the film's merged sums (exactly as `render_local` decides), then
    /// either its next pass becomes pending with the mask, or, when every block has converged,
    /// its remaining passes count as merged with nothing (the tile leaves the schedule).
    pub(super) fn decide(&mut self, plan: &Plan, a: &AdaptiveSettings, spp: u32, tile: usize) -> Decision {
        let (tiles, passes) = (plan.tiles.len(), plan.passes.len());
        let np = self.next_pass[tile] as usize;
        let mut out = Decision::default();
        if np == 0 {
            return out;
        }
        let rect = plan.tiles[tile];
        let sums = self.film.tile(rect).sums;
        let mask = adaptive::converged_blocks(&sums, rect, a, plan.passes[np - 1].s1);
        let before = skipped_samples(self.masks[tile].as_ref(), &sums, rect, spp);
        out.samples_skipped = skipped_samples(Some(&mask), &sums, rect, spp).saturating_sub(before);
        let all = mask.all_converged();
        self.masks[tile] = Some(mask);
        if np >= passes {
            return out;
        }
        if all {
            for q in np..passes {
                let i = q * tiles + tile;
                if self.units[i] == UnitState::Pending {
                    self.pending -= 1;
                    self.requeued.remove(&i);
                }
                self.units[i] = UnitState::Merged;
                self.units_merged += 1;
                self.pass_merged[q] += 1;
                out.units_skipped += 1;
            }
            self.next_pass[tile] = passes as u32;
        } else if self.units[np * tiles + tile] == UnitState::Blocked {
            self.requeue(np * tiles + tile);
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
