//! Film assembly: the one merge of units into a frame's film, used by the local renderer, the
//! farm (results in any order) and restore (a checkpoint's film and merged passes).
//!
//! A unit is (pass, tile). Each tile folds its passes in order: a unit that arrives before its
//! tile's earlier passes waits. The film's radiance sums are exact integers, for which the order
//! does not matter; its AOV means are bit-identical across renders only because of it, and it
//! makes every intermediate film a prefix of the final one (each pixel holds samples `[0, s)`).
//!
//! Adaptive sampling: after a tile folds a pass, its converged blocks are judged from the film's
//! merged sums ([`adaptive::converged_blocks`]); the next pass samples only the others, and a
//! tile whose every block converged leaves the schedule. The masks are a pure function of the
//! film, so a checkpoint does not store them: [`FilmAssembly::resume`] judges them again.

use crate::adaptive::{self, AdaptiveSettings, BlockMask};
use crate::film::{Film, PixelSums, SplatBuffer, TileAccum};
use crate::job::{Plan, TileRect, UnitKey};
use crate::protocol::TileSums;
use std::collections::{BTreeSet, HashMap};

/// A frame's film being assembled from units.
///
/// The film may be elsewhere for a while (the farm writes films beyond its memory limits to
/// disk, [`FilmAssembly::take_film`]): units offered meanwhile wait, and
/// [`FilmAssembly::put_film`] folds those that are then in order. The assembly's own state is
/// O(tiles + units waiting), whatever the pass count.
#[derive(Clone, Debug)]
pub struct FilmAssembly {
    /// `None` while the film is elsewhere: nothing folds, offers only wait.
    film: Option<Film>,
    /// Per tile: the next pass to fold (the passes before it are in the film).
    next_pass: Vec<u32>,
    /// Units that arrived before their tile's earlier passes (or while the film was away), by
    /// (tile, pass).
    waiting: HashMap<(u32, u32), (TileAccum, Option<SplatBuffer>)>,
    /// Adaptive sampling: per tile, the converged blocks after its last folded pass (`None`
    /// before the first, and without adaptive sampling).
    masks: Vec<Option<BlockMask>>,
    /// Resumed from a checkpoint before its film was here: the masks are judged when it comes.
    judge_on_put: bool,
}

/// A unit folded into the film by [`FilmAssembly::offer`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Folded {
    pub tile: u32,
    pub pass: u32,
    /// Samples the unit held (the weights of its pixels).
    pub samples: u64,
    /// Adaptive sampling: what judging the tile after this pass changed.
    pub judged: Option<Judged>,
}

impl Folded {
    /// The tile's next pass after this fold: the passes it skipped (converged) count as folded.
    pub fn next_pass(&self) -> u32 {
        self.pass + 1 + self.judged.map_or(0, |j| j.passes_skipped)
    }
}

/// What judging a tile's blocks after a pass changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Judged {
    /// Every block converged: the tile's later passes (if any) will not be rendered; the
    /// assembly counts them as folded.
    pub tile_done: bool,
    /// The passes after this one that the tile skips (0 unless `tile_done`).
    pub passes_skipped: u32,
    /// Samples that newly converged pixels will not get (of the job's spp per pixel).
    pub samples_skipped: u64,
}

/// What [`FilmAssembly::put_film`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PutFilm {
    /// Resumed from a checkpoint with adaptive sampling: each tile judged from the film's sums,
    /// in tile order (its next pass moved to the end when it had converged).
    pub judged: Vec<(u32, Judged)>,
    /// The waiting units that were in order, folded.
    pub folded: Vec<Folded>,
}

impl FilmAssembly {
    /// An empty film of `width` x `height` for `plan`.
    pub fn new(plan: &Plan, width: u32, height: u32) -> Self {
        let mut asm = Self::without_film(plan, vec![0; plan.tiles.len()]);
        asm.film = Some(Film::new(width, height));
        asm.judge_on_put = false;
        asm
    }

    /// Resumes from a checkpoint whose film is not here yet: the film will hold, per tile,
    /// exactly the passes before `next_pass[tile]`. Offers wait until [`FilmAssembly::put_film`]
    /// brings the film, which judges the adaptive masks. The caller checked `next_pass.len()` =
    /// tiles, each at most the pass count.
    pub fn without_film(plan: &Plan, next_pass: Vec<u32>) -> Self {
        let tiles = plan.tiles.len();
        FilmAssembly { film: None, next_pass, waiting: HashMap::new(), masks: vec![None; tiles], judge_on_put: true }
    }

    /// Resumes from a film holding, per tile, exactly the passes before `next_pass[tile]` (a
    /// checkpoint). Adaptive masks are judged again from the film; a tile that had converged
    /// is done again. The caller checked the shapes (`next_pass.len()` = tiles, each at most the
    /// pass count, the film the job's size).
    pub fn resume(plan: &Plan, film: Film, next_pass: Vec<u32>, adaptive: Option<(&AdaptiveSettings, u32)>) -> Self {
        let mut asm = Self::without_film(plan, next_pass);
        asm.put_film(plan, adaptive, film);
        asm
    }

    /// The film, unless it is elsewhere ([`FilmAssembly::take_film`]).
    pub fn film(&self) -> Option<&Film> {
        self.film.as_ref()
    }

    /// The film to write into directly (tests and tools that fabricate sums); folding adds to
    /// what it then holds.
    pub fn film_mut(&mut self) -> Option<&mut Film> {
        self.film.as_mut()
    }

    pub fn has_film(&self) -> bool {
        self.film.is_some()
    }

    pub fn into_film(self) -> Option<Film> {
        self.film
    }

    /// Moves the film out (to be written to disk): until [`FilmAssembly::put_film`], offered
    /// units only wait. `None` when it is already out.
    pub fn take_film(&mut self) -> Option<Film> {
        self.film.take()
    }

    /// Brings the film back: it must hold exactly the passes before [`FilmAssembly::next_passes`]
    /// (the caller checked it, and its size). Resumed from a checkpoint, each tile is judged
    /// first (adaptive sampling); then every waiting unit now in order folds, tile by tile. A
    /// film already here stays, and the one given is dropped.
    pub fn put_film(&mut self, plan: &Plan, adaptive: Option<(&AdaptiveSettings, u32)>, film: Film) -> PutFilm {
        let mut out = PutFilm::default();
        if self.film.is_some() {
            return out;
        }
        self.film = Some(film);
        if std::mem::replace(&mut self.judge_on_put, false)
            && let Some((a, spp)) = adaptive
        {
            for tile in 0..plan.tiles.len() {
                let judged = self.judge(plan, a, spp, tile);
                out.judged.push((tile as u32, judged));
            }
            let next_pass = &self.next_pass;
            self.waiting.retain(|&(t, p), _| p >= next_pass[t as usize]);
        }
        let tiles: BTreeSet<u32> = self.waiting.keys().map(|&(t, _)| t).collect();
        for tile in tiles {
            self.fold_in_order(plan, adaptive, tile, &mut out.folded);
        }
        out
    }

    /// Per tile, the next pass to fold.
    pub fn next_passes(&self) -> &[u32] {
        &self.next_pass
    }

    pub fn next_pass(&self, tile: usize) -> u32 {
        self.next_pass[tile]
    }

    /// The tile's converged blocks: the mask its next pass renders with.
    pub fn mask(&self, tile: usize) -> Option<&BlockMask> {
        self.masks[tile].as_ref()
    }

    /// Units waiting for an earlier pass of their tile (or for the film).
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }

    /// Whether unit (tile, pass) waits.
    pub fn is_waiting(&self, tile: u32, pass: u32) -> bool {
        self.waiting.contains_key(&(tile, pass))
    }

    /// Drops every waiting unit (its job ended: nothing more folds).
    pub fn drop_waiting(&mut self) {
        self.waiting = HashMap::new();
    }

    /// True once every tile folded (or skipped) every pass.
    pub fn is_complete(&self, plan: &Plan) -> bool {
        let passes = plan.passes.len() as u32;
        self.next_pass.iter().all(|&p| p >= passes)
    }

    /// Bytes of the assembly's state besides its film and the units waiting (O(tiles)).
    pub fn state_bytes(&self) -> usize {
        use std::mem::size_of;
        self.next_pass.capacity() * size_of::<u32>()
            + self.masks.capacity() * size_of::<Option<BlockMask>>()
            + self.waiting.len() * 2 * size_of::<u32>()
    }

    /// Takes a unit's sums (and its BDPT splats, which fold into the film's radiance with it) and
    /// folds every unit of its tile that is now in order, returning them in the order folded.
    /// While the film is away the unit only waits. A unit at or before a pass its tile already
    /// folded is ignored (the caller refuses duplicates before; this keeps the film exact
    /// whatever it does). `adaptive`: the job's settings and spp.
    pub fn offer(
        &mut self,
        plan: &Plan,
        adaptive: Option<(&AdaptiveSettings, u32)>,
        key: UnitKey,
        accum: TileAccum,
        splats: Option<SplatBuffer>,
    ) -> Vec<Folded> {
        let mut out = Vec::new();
        if key.pass < self.next_pass[key.tile as usize] {
            return out;
        }
        self.waiting.insert((key.tile, key.pass), (accum, splats));
        self.fold_in_order(plan, adaptive, key.tile, &mut out);
        out
    }

    /// [`FilmAssembly::offer`] of a result's sums as they come (`rect`: the unit's tile): a unit
    /// in order is merged as its sums are read (packed sums straight from the result body, with
    /// no tile of pixels in between); one that must wait is decoded to wait.
    pub fn offer_sums(
        &mut self,
        plan: &Plan,
        adaptive: Option<(&AdaptiveSettings, u32)>,
        key: UnitKey,
        rect: TileRect,
        sums: TileSums<'_>,
        splats: Option<SplatBuffer>,
    ) -> Vec<Folded> {
        let t = key.tile as usize;
        let in_order = key.pass == self.next_pass[t] && key.pass < plan.passes.len() as u32;
        let (true, Some(film)) = (in_order, self.film.as_mut()) else {
            let accum = TileAccum { rect, sums: sums.into_pixels() };
            return self.offer(plan, adaptive, key, accum, splats);
        };
        let samples = match &sums {
            TileSums::Pixels(p) => film.add_tile_with(rect, |i| p.get(i).copied().unwrap_or_default()),
            TileSums::Packed(p) => film.add_tile_with(rect, |i| p.get(i)),
        };
        if let Some(s) = &splats {
            film.add_splats(s);
        }
        let mut out = Vec::new();
        if !self.folded(plan, adaptive, key.tile, key.pass, samples, &mut out) {
            self.fold_in_order(plan, adaptive, key.tile, &mut out);
        }
        out
    }

    /// Records that `tile`'s pass `pass` (of `samples` samples) is in the film: the tile's next
    /// pass, and the tile judged (adaptive sampling). Returns whether the tile is now done (its
    /// waiting units are dropped).
    fn folded(
        &mut self,
        plan: &Plan,
        adaptive: Option<(&AdaptiveSettings, u32)>,
        tile: u32,
        pass: u32,
        samples: u64,
        out: &mut Vec<Folded>,
    ) -> bool {
        let t = tile as usize;
        self.next_pass[t] += 1;
        let judged = adaptive.map(|(a, spp)| self.judge(plan, a, spp, t));
        out.push(Folded { tile, pass, samples, judged });
        if judged.is_some_and(|j| j.tile_done) {
            // Later passes of a done tile can only be stale; drop any that waited.
            self.waiting.retain(|&(w, _), _| w != tile);
            return true;
        }
        false
    }

    /// Folds `tile`'s waiting units while the next is here (and the film is), judging the tile
    /// after each (adaptive sampling).
    fn fold_in_order(
        &mut self,
        plan: &Plan,
        adaptive: Option<(&AdaptiveSettings, u32)>,
        tile: u32,
        out: &mut Vec<Folded>,
    ) {
        let passes = plan.passes.len() as u32;
        let t = tile as usize;
        while self.next_pass[t] < passes {
            let Some(film) = self.film.as_mut() else { return };
            let pass = self.next_pass[t];
            let Some((accum, splats)) = self.waiting.remove(&(tile, pass)) else { return };
            let samples = film.add_tile(&accum);
            if let Some(s) = &splats {
                film.add_splats(s);
            }
            if self.folded(plan, adaptive, tile, pass, samples, out) {
                return;
            }
        }
    }

    /// Judges `tile` after its passes before `next_pass[tile]` folded: its mask from the film's
    /// sums; when every block converged, its remaining passes count as folded. Nothing changes
    /// while the film is away.
    fn judge(&mut self, plan: &Plan, a: &AdaptiveSettings, spp: u32, tile: usize) -> Judged {
        let np = self.next_pass[tile] as usize;
        let mut out = Judged { tile_done: false, passes_skipped: 0, samples_skipped: 0 };
        let Some(film) = &self.film else { return out };
        if np == 0 {
            return out;
        }
        let rect = plan.tiles[tile];
        let sums = film.tile(rect).sums;
        let mask = adaptive::converged_blocks(&sums, rect, a, plan.passes[np - 1].s1);
        let before = skipped_samples(self.masks[tile].as_ref(), &sums, rect, spp);
        out.samples_skipped = skipped_samples(Some(&mask), &sums, rect, spp).saturating_sub(before);
        let all = mask.all_converged();
        self.masks[tile] = Some(mask);
        let passes = plan.passes.len();
        if all && np < passes {
            out.tile_done = true;
            out.passes_skipped = (passes - np) as u32;
            self.next_pass[tile] = passes as u32;
        }
        out
    }
}

/// Samples a tile's converged pixels will not get: per pixel in a converged block of `mask`,
/// the job's spp less the samples it holds (they stop changing once their block converged).
pub fn skipped_samples(mask: Option<&BlockMask>, sums: &[PixelSums], rect: TileRect, spp: u32) -> u64 {
    let Some(mask) = mask else { return 0 };
    let w = rect.width();
    sums.iter()
        .enumerate()
        .filter(|(i, _)| mask.pixel_converged(*i as u32 % w, *i as u32 / w))
        .map(|(_, p)| u64::from(spp.saturating_sub(p.weight)))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::film::{SampleValue, add_sample};
    use crate::job::{PassSchedule, RenderSettings};

    fn settings() -> RenderSettings {
        let mut s = RenderSettings::new(20, 12, 7);
        s.tile_size = 8;
        s.passes = PassSchedule::Doubling { first: 1, max: 4 };
        s
    }

    /// 32 spp in passes of 4 with adaptive sampling: tiles converge after different passes.
    fn adaptive_settings() -> RenderSettings {
        let mut s = settings();
        s.spp = 32;
        s.passes = PassSchedule::Fixed { spp: 4 };
        s.adaptive = Some(AdaptiveSettings { threshold: 0.05, min_spp: 4 });
        s
    }

    /// A unit's sums: a value per sample that depends on the pixel and the sample index, with
    /// AOVs, so a different merge order would change the AOV means' bits.
    fn unit(plan: &Plan, key: UnitKey, mask: Option<&BlockMask>) -> TileAccum {
        let (rect, pass) = (plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
        let mut accum = TileAccum::new(rect);
        for y in rect.y0..rect.y1 {
            for x in rect.x0..rect.x1 {
                let (lx, ly) = (x - rect.x0, y - rect.y0);
                if mask.is_some_and(|m| m.pixel_converged(lx, ly)) {
                    continue;
                }
                for s in pass.samples() {
                    // Bright, smooth pixels on the left converge; noisy ones on the right do not.
                    let noise = if x < 8 { 0.0 } else { ((s * 7919 + x * 31 + y) % 13) as f32 };
                    let v = SampleValue {
                        radiance: [1.0 + noise, 0.5, 0.25],
                        albedo: [0.1 * s as f32, 0.3, 0.7],
                        normal: [0.0, (s as f32).sin(), (s as f32).cos()],
                        depth: Some(1.0 + s as f32),
                    };
                    add_sample(accum.pixel_mut(lx, ly), &v);
                }
            }
        }
        accum
    }

    fn in_order(s: &RenderSettings) -> FilmAssembly {
        let plan = s.plan();
        let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        for key in plan.units() {
            if asm.next_pass(key.tile as usize) > key.pass {
                continue; // the tile left the schedule
            }
            let accum = unit(&plan, key, asm.mask(key.tile as usize));
            asm.offer(&plan, adaptive, key, accum, None);
        }
        asm
    }

    #[test]
    fn any_arrival_order_assembles_the_same_bits() {
        let s = settings();
        let plan = s.plan();
        let reference = in_order(&s).into_film().expect("film");
        let mut keys: Vec<UnitKey> = plan.units().collect();
        keys.reverse();
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        let mut folded = 0;
        for key in keys {
            let accum = unit(&plan, key, None);
            let f = asm.offer(&plan, None, key, accum, None);
            // A tile's last pass arrives first: nothing folds until its pass 0 does.
            folded += f.len();
        }
        assert_eq!(folded, plan.unit_count());
        assert!(asm.is_complete(&plan) && asm.waiting() == 0);
        assert!(asm.into_film() == Some(reference), "the reverse arrival order changed the film");
    }

    #[test]
    fn stale_units_are_ignored() {
        let s = settings();
        let plan = s.plan();
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        let key = UnitKey { frame: 0, pass: 0, tile: 1 };
        assert_eq!(asm.offer(&plan, None, key, unit(&plan, key, None), None).len(), 1);
        let film = asm.film().cloned();
        assert!(asm.offer(&plan, None, key, unit(&plan, key, None), None).is_empty());
        assert_eq!(asm.film(), film.as_ref());
    }

    #[test]
    fn adaptive_tiles_leave_the_schedule_and_resume_judges_the_same_masks() {
        let s = adaptive_settings();
        let plan = s.plan();
        let full = in_order(&s);
        let passes = plan.passes.len() as u32;
        // The smooth left tiles converge after their first pass; the noisy ones run to the end.
        assert!(full.is_complete(&plan));
        let smooth: Vec<usize> = (0..plan.tiles.len()).filter(|&t| plan.tiles[t].x1 <= 8).collect();
        assert!(!smooth.is_empty());
        for &t in &smooth {
            assert!(full.mask(t).is_some_and(BlockMask::all_converged), "tile {t}");
        }
        assert!((0..plan.tiles.len()).any(|t| !full.mask(t).is_some_and(BlockMask::all_converged)));
        // Stop halfway (pass 2 of every tile still in the schedule), resume, finish: same bits.
        let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        for key in plan.units().filter(|k| k.pass < 2) {
            if asm.next_pass(key.tile as usize) <= key.pass {
                let accum = unit(&plan, key, asm.mask(key.tile as usize));
                asm.offer(&plan, adaptive, key, accum, None);
            }
        }
        let mut resumed =
            FilmAssembly::resume(&plan, asm.film().expect("film").clone(), asm.next_passes().to_vec(), adaptive);
        for t in 0..plan.tiles.len() {
            assert_eq!(resumed.mask(t), asm.mask(t), "tile {t}");
            assert_eq!(resumed.next_pass(t), asm.next_pass(t), "tile {t}");
        }
        for key in plan.units().filter(|k| k.pass >= 2) {
            if resumed.next_pass(key.tile as usize) <= key.pass {
                let accum = unit(&plan, key, resumed.mask(key.tile as usize));
                resumed.offer(&plan, adaptive, key, accum, None);
            }
        }
        assert!(resumed.next_passes().iter().all(|&p| p == passes));
        assert!(resumed.into_film() == Some(full.into_film().expect("film")), "resuming changed the film");
    }

    /// The film goes away mid-frame (the farm writes it to disk) while units keep arriving in a
    /// scrambled order: they wait, and putting the film back folds them to the same bits and
    /// the same adaptive decisions as an assembly that never let its film go.
    #[test]
    fn a_film_taken_away_and_put_back_assembles_the_same_bits() {
        let s = adaptive_settings();
        let plan = s.plan();
        let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
        let full = in_order(&s);
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        let tiles = plan.tiles.len() as u32;
        // Rounds: every tile still in the schedule renders its next pass with its mask; the
        // results arrive in reverse tile order, the film away during every other round.
        for round in 0.. {
            let keys: Vec<UnitKey> = (0..tiles)
                .rev()
                .filter(|&t| asm.next_pass(t as usize) < plan.passes.len() as u32)
                .map(|t| UnitKey { frame: 0, pass: asm.next_pass(t as usize), tile: t })
                .collect();
            if keys.is_empty() {
                break;
            }
            let units: Vec<_> = keys.iter().map(|&k| (k, unit(&plan, k, asm.mask(k.tile as usize)))).collect();
            let away = (round % 2 == 1).then(|| asm.take_film().expect("the film is here"));
            let mut folded = 0;
            for (key, accum) in units {
                folded += asm.offer(&plan, adaptive, key, accum, None).len();
            }
            if let Some(film) = away {
                assert_eq!((folded, asm.waiting()), (0, keys.len()), "nothing folds while the film is away");
                assert!(asm.take_film().is_none());
                let put = asm.put_film(&plan, adaptive, film);
                assert!(put.judged.is_empty(), "masks are kept while the film is away");
                let mut got: Vec<(u32, u32)> = put.folded.iter().map(|f| (f.tile, f.pass)).collect();
                let mut want: Vec<(u32, u32)> = keys.iter().map(|k| (k.tile, k.pass)).collect();
                got.sort();
                want.sort();
                assert_eq!(got, want);
            } else {
                assert_eq!(folded, keys.len());
            }
        }
        assert_eq!(asm.waiting(), 0);
        for t in 0..plan.tiles.len() {
            assert_eq!(asm.mask(t), full.mask(t), "tile {t}");
        }
        assert!(asm.into_film() == full.into_film(), "taking the film away changed it");
    }

    /// A checkpoint resumed before its film is read: units wait, putting the film judges every
    /// tile (as `resume` does) and then folds them.
    #[test]
    fn resuming_without_the_film_judges_when_it_comes() {
        let s = adaptive_settings();
        let plan = s.plan();
        let adaptive = s.adaptive.as_ref().map(|a| (a, s.spp));
        let mut asm = FilmAssembly::new(&plan, s.width, s.height);
        for key in plan.units().filter(|k| k.pass < 1) {
            let accum = unit(&plan, key, None);
            asm.offer(&plan, adaptive, key, accum, None);
        }
        let film = asm.film().expect("film").clone();
        let next: Vec<u32> = vec![1; plan.tiles.len()];
        let resumed = FilmAssembly::resume(&plan, film.clone(), next.clone(), adaptive);
        let mut later = FilmAssembly::without_film(&plan, next);
        let open = (0..plan.tiles.len()).find(|&t| resumed.next_pass(t) == 1).expect("a tile goes on") as u32;
        let key = UnitKey { frame: 0, pass: 1, tile: open };
        let accum = unit(&plan, key, resumed.mask(open as usize));
        assert!(later.offer(&plan, adaptive, key, accum.clone(), None).is_empty());
        let put = later.put_film(&plan, adaptive, film);
        assert_eq!(put.judged.len(), plan.tiles.len());
        let done = put.judged.iter().filter(|(_, j)| j.tile_done).count();
        assert!(done > 0 && done < plan.tiles.len(), "some tiles converged after pass 0, not all");
        assert_eq!(put.folded.iter().map(|f| (f.tile, f.pass)).collect::<Vec<_>>(), vec![(open, 1)]);
        let mut resumed = resumed;
        resumed.offer(&plan, adaptive, key, accum, None);
        assert_eq!(later.next_passes(), resumed.next_passes());
        for t in 0..plan.tiles.len() {
            assert_eq!(later.mask(t), resumed.mask(t), "tile {t}");
        }
        assert!(later.into_film() == resumed.into_film());
    }
}
