//! Adaptive sampling: which 8 x 8 pixel blocks of a tile have converged after a pass.
//!
//! A job with `adaptive: {"threshold": T, "min_spp": N}` renders its passes in order. At the end
//! of every pass whose sample count so far is at least `min_spp`, [`converged_blocks`] looks at
//! the merged sums of each tile and marks the blocks whose estimated relative error is at most
//! `T`; those blocks get no further samples (the renderer skips their pixels, so their sums stay
//! as they are), and a tile whose blocks have all converged leaves the schedule. Decisions are a
//! pure function of the merged sums at pass boundaries, and the sums are exact, so the farm and
//! a local render make the same decisions and produce the same bits.
//!
//! ## The error estimate
//!
//! For a pixel with `n` samples of luminance `L_i` ([`PixelSums`]: `weight` counts `n`, `lum`
//! sums the camera samples' `L_i`, `lum_sq` sums `L_i^2`):
//!
//! - mean `m = sum L_i / n`;
//! - unbiased sample variance `s^2 = (sum L_i^2 - n m^2) / (n - 1)` (Bessel's `1/(n-1)`), clamped
//!   at 0 against rounding;
//! - variance of the mean `s^2 / n`, so the standard error is `sqrt(s^2 / n)`;
//! - relative error `e = sqrt(s^2 / n) / max(m, DARK_EPS)`.
//!
//! This is the per-pixel variance of the mean that pbrt-v4's `VarianceEstimator` (Welford's
//! running mean and variance; `RelativeVariance` divides by the mean) computes for its
//! `GBufferFilm` variance channels. Cycles' adaptive sampler estimates the same standard error
//! differently (the difference between the full image and an image of every other sample,
//! over `sqrt(I)`), and filters the decision over neighbouring pixels; here a block plays that
//! role: a block has converged when **every** pixel in it has `e <= T` (the maximum over the
//! block), so a single noisy pixel keeps its 63 neighbours sampling, which guards against a
//! pixel whose few samples happened to agree. `DARK_EPS` keeps near-black pixels from asking
//! for endless samples to pin down a tiny absolute error. A pixel needs two samples to have a
//! variance: with fewer it has not converged. A pixel whose samples were all equal (a black
//! background, a constant environment) has `e = 0` and converges at `min_spp`.
//!
//! Resolution: `lum_sq` holds `L_i^2` to 2^-20 (about 1e-6), so the variance of pixels whose
//! samples are darker than about 1e-3 is not resolved; `DARK_EPS` (1e-3) sits at that floor.
//!
//! Stopping on the samples' own estimate is a (small) biased stopping rule, as in every
//! renderer that samples adaptively; `min_spp` bounds how early it can act.
//!
//! ## Blocks
//!
//! Blocks are [`BLOCK`] x [`BLOCK`] pixels counted from the tile's corner (row-major; the last
//! row and column of blocks may be partial). When the tile size is a multiple of 8 (64, the
//! default, is), tiles start on multiples of 8 and the blocks lie on the image's 8-pixel grid,
//! so the decisions (and the image) are the same whatever the tile size.

use crate::film::PixelSums;
use crate::job::{SettingsError, TileRect};
use serde::{Deserialize, Serialize};

/// Side of a block in pixels.
pub const BLOCK: u32 = 8;

/// The floor of the mean luminance in the relative error (linear radiance units): darker pixels
/// are judged by their absolute error over this.
pub const DARK_EPS: f64 = 1e-3;

/// Adaptive sampling settings of a job (JSON `{"threshold": 0.01, "min_spp": 16}`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AdaptiveSettings {
    /// Largest relative standard error of a pixel's mean luminance (`sqrt(var / n) / mean`) at
    /// which its block stops sampling, e.g. 0.01 for 1%.
    pub threshold: f32,
    /// Samples every pixel gets before any block may stop (at least 1, at most the job's spp).
    pub min_spp: u32,
}

impl AdaptiveSettings {
    /// Checks the fields against the job's sample count.
    pub fn validate(&self, spp: u32) -> Result<(), SettingsError> {
        if !(self.threshold.is_finite() && self.threshold > 0.0) {
            return Err(SettingsError::Invalid(format!(
                "adaptive.threshold must be a finite number > 0 (a relative error, e.g. 0.01), got {}",
                self.threshold
            )));
        }
        if self.min_spp < 1 || self.min_spp > spp {
            return Err(SettingsError::Invalid(format!(
                "adaptive.min_spp must be between 1 and the job's spp ({spp}), got {}",
                self.min_spp
            )));
        }
        Ok(())
    }

    /// Whether blocks are judged at the end of a pass that leaves every active pixel with
    /// `samples_so_far` samples (the pass's `s1`): only once `min_spp` is reached.
    pub fn decides_after(&self, samples_so_far: u32) -> bool {
        samples_so_far >= self.min_spp
    }
}

/// The converged blocks of one tile: 1 bit per [`BLOCK`] x [`BLOCK`] block, row-major from the
/// tile's corner; a set bit means "converged: no more samples".
///
/// On the wire (a lease) it is `{"blocks_x": 8, "blocks_y": 8, "converged": "<base64>"}`, the
/// bits little-endian in `ceil(blocks / 8)` bytes (12 characters for a 64-pixel tile).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "BlockMaskWire", into = "BlockMaskWire")]
pub struct BlockMask {
    blocks_x: u32,
    blocks_y: u32,
    bits: Vec<u64>,
}

/// [`BlockMask`] as JSON.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct BlockMaskWire {
    pub blocks_x: u32,
    pub blocks_y: u32,
    /// Base64 (standard, padded) of the bits, little-endian, `ceil(blocks_x * blocks_y / 8)` bytes.
    pub converged: String,
}

/// Most blocks along a side: a 1024-pixel tile (the largest allowed).
const MAX_BLOCKS_PER_SIDE: u32 = 1024 / BLOCK;

impl From<BlockMask> for BlockMaskWire {
    fn from(m: BlockMask) -> Self {
        use base64::Engine as _;
        let n = m.block_count().div_ceil(8);
        let bytes: Vec<u8> = m.bits.iter().flat_map(|w| w.to_le_bytes()).take(n).collect();
        Self {
            blocks_x: m.blocks_x,
            blocks_y: m.blocks_y,
            converged: base64::engine::general_purpose::STANDARD.encode(bytes),
        }
    }
}

impl TryFrom<BlockMaskWire> for BlockMask {
    type Error = String;
    fn try_from(w: BlockMaskWire) -> Result<Self, String> {
        use base64::Engine as _;
        if w.blocks_x == 0 || w.blocks_y == 0 || w.blocks_x > MAX_BLOCKS_PER_SIDE || w.blocks_y > MAX_BLOCKS_PER_SIDE {
            return Err(format!(
                "block mask of {} x {} blocks: each side must be 1 to {MAX_BLOCKS_PER_SIDE}",
                w.blocks_x, w.blocks_y
            ));
        }
        let mut mask = BlockMask { blocks_x: w.blocks_x, blocks_y: w.blocks_y, bits: Vec::new() };
        let n = mask.block_count();
        // Refuse before decoding something huge.
        if w.converged.len() > n.div_ceil(8).div_ceil(3) * 4 {
            return Err(format!("block mask: `converged` is longer than {n} bits"));
        }
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(&w.converged)
            .map_err(|e| format!("block mask: `converged` is not base64: {e}"))?;
        if bytes.len() != n.div_ceil(8) {
            return Err(format!("block mask: {} bytes for {n} blocks (expected {})", bytes.len(), n.div_ceil(8)));
        }
        mask.bits = bytes
            .chunks(8)
            .map(|c| {
                let mut b = [0u8; 8];
                b[..c.len()].copy_from_slice(c);
                u64::from_le_bytes(b)
            })
            .collect();
        if !n.is_multiple_of(64) && mask.bits.last().is_some_and(|w| w >> (n % 64) != 0) {
            return Err(format!("block mask: bits beyond block {n} are set"));
        }
        Ok(mask)
    }
}

impl BlockMask {
    /// Blocks along x and y of a tile.
    pub fn blocks_of(rect: TileRect) -> (u32, u32) {
        (rect.width().div_ceil(BLOCK), rect.height().div_ceil(BLOCK))
    }

    /// A mask of `rect` with no block converged.
    pub fn none_converged(rect: TileRect) -> Self {
        let (blocks_x, blocks_y) = Self::blocks_of(rect);
        let n = blocks_x as usize * blocks_y as usize;
        Self { blocks_x, blocks_y, bits: vec![0; n.div_ceil(64)] }
    }

    /// Whether the mask has the block layout of `rect`.
    pub fn fits(&self, rect: TileRect) -> bool {
        Self::blocks_of(rect) == (self.blocks_x, self.blocks_y)
    }

    /// Blocks along x and y.
    pub fn blocks(&self) -> (u32, u32) {
        (self.blocks_x, self.blocks_y)
    }

    fn block_count(&self) -> usize {
        self.blocks_x as usize * self.blocks_y as usize
    }

    /// Whether block `(bx, by)` has converged.
    pub fn is_converged(&self, bx: u32, by: u32) -> bool {
        let i = (by * self.blocks_x + bx) as usize;
        bx < self.blocks_x && by < self.blocks_y && self.bits[i / 64] >> (i % 64) & 1 == 1
    }

    /// Marks block `(bx, by)` converged.
    pub fn set_converged(&mut self, bx: u32, by: u32) {
        assert!(bx < self.blocks_x && by < self.blocks_y, "block ({bx}, {by}) outside the mask");
        let i = (by * self.blocks_x + bx) as usize;
        self.bits[i / 64] |= 1 << (i % 64);
    }

    /// Whether the pixel `(x, y)` (tile-local) lies in a converged block.
    pub fn pixel_converged(&self, x: u32, y: u32) -> bool {
        self.is_converged(x / BLOCK, y / BLOCK)
    }

    /// Number of converged blocks.
    pub fn converged_count(&self) -> usize {
        self.bits.iter().map(|w| w.count_ones() as usize).sum()
    }

    /// True when every block has converged: the tile leaves the schedule.
    pub fn all_converged(&self) -> bool {
        self.converged_count() == self.block_count()
    }

    /// True when no block has converged (the mask changes nothing).
    pub fn none(&self) -> bool {
        self.converged_count() == 0
    }

    /// Pixels of `rect` that still get samples.
    pub fn active_pixels(&self, rect: TileRect) -> usize {
        (0..rect.height()).map(|y| (0..rect.width()).filter(|&x| !self.pixel_converged(x, y)).count()).sum()
    }
}

/// Relative standard error of a pixel's mean luminance (see the module docs); infinite with
/// fewer than two samples.
pub fn relative_error(pixel: &PixelSums) -> f64 {
    let n = pixel.weight();
    if !(n >= 2.0) {
        return f64::INFINITY;
    }
    let m = pixel.luminance_sum() / n;
    pixel.variance_of_mean().sqrt() / m.max(DARK_EPS)
}

/// The blocks of a tile that have converged, from the tile's merged sums after a pass
/// (`sums` in [`crate::film::TileAccum`] layout over `rect`). `samples_so_far` is the pass's
/// `s1`: before `min_spp` nothing has converged. Pure: the same sums give the same mask.
pub fn converged_blocks(
    sums: &[PixelSums],
    rect: TileRect,
    settings: &AdaptiveSettings,
    samples_so_far: u32,
) -> BlockMask {
    assert_eq!(sums.len(), rect.pixel_count(), "tile sums do not match the rectangle");
    let mut mask = BlockMask::none_converged(rect);
    if !settings.decides_after(samples_so_far) {
        return mask;
    }
    let threshold = f64::from(settings.threshold);
    let (w, h) = (rect.width(), rect.height());
    for by in 0..mask.blocks_y {
        for bx in 0..mask.blocks_x {
            let converged = (by * BLOCK..((by + 1) * BLOCK).min(h)).all(|y| {
                (bx * BLOCK..((bx + 1) * BLOCK).min(w))
                    .all(|x| relative_error(&sums[(y * w + x) as usize]) <= threshold)
            });
            if converged {
                mask.set_converged(bx, by);
            }
        }
    }
    mask
}

/// Samples a pixel (tile-local `(x, y)`) of a unit must hold: the pass's spp, or 0 in a
/// converged block. For the coordinator's check of a result against its lease.
#[inline]
pub fn expected_samples(mask: Option<&BlockMask>, x: u32, y: u32, pass_spp: u32) -> u32 {
    if mask.is_some_and(|m| m.pixel_converged(x, y)) { 0 } else { pass_spp }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::film::{SampleValue, TileAccum, add_sample};

    fn grey(v: f32) -> SampleValue {
        SampleValue { radiance: [v; 3], ..Default::default() }
    }

    #[test]
    fn settings_are_validated_with_clear_messages() {
        let ok = AdaptiveSettings { threshold: 0.01, min_spp: 16 };
        assert_eq!(ok.validate(64), Ok(()));
        for (bad, spp, words) in [
            (AdaptiveSettings { threshold: 0.0, min_spp: 4 }, 64, "adaptive.threshold"),
            (AdaptiveSettings { threshold: -1.0, min_spp: 4 }, 64, "adaptive.threshold"),
            (AdaptiveSettings { threshold: f32::NAN, min_spp: 4 }, 64, "adaptive.threshold"),
            (AdaptiveSettings { threshold: f32::INFINITY, min_spp: 4 }, 64, "adaptive.threshold"),
            (AdaptiveSettings { threshold: 0.1, min_spp: 0 }, 64, "adaptive.min_spp"),
            (AdaptiveSettings { threshold: 0.1, min_spp: 65 }, 64, "the job's spp (64)"),
        ] {
            let e = bad.validate(spp).expect_err("invalid").to_string();
            assert!(e.contains(words), "{bad:?}: {e}");
        }
        assert!(serde_json::from_str::<AdaptiveSettings>(r#"{"threshold": 0.1}"#).is_err());
        assert!(serde_json::from_str::<AdaptiveSettings>(r#"{"threshold": 0.1, "min_spp": 2, "x": 1}"#).is_err());
    }

    /// The estimator: samples {1, 3} have mean 2, sample variance 2 (1/(n-1)), variance of the
    /// mean 1, relative error 1/2; equal samples have error 0; one sample has no estimate; a
    /// black pixel with noise is judged against DARK_EPS.
    #[test]
    fn relative_error_is_the_standard_error_over_the_mean() {
        let rect = TileRect { x0: 0, y0: 0, x1: 1, y1: 1 };
        let px = |vals: &[f32]| {
            let mut t = TileAccum::new(rect);
            for &v in vals {
                add_sample(t.pixel_mut(0, 0), &grey(v));
            }
            t.sums[0]
        };
        assert!((relative_error(&px(&[1.0, 3.0])) - 0.5).abs() < 1e-9);
        // Equal samples: zero up to the f32 luminance of LUM_SQ vs the f64 one of the mean.
        assert!(relative_error(&px(&[0.7; 5])) < 1e-6);
        assert_eq!(relative_error(&px(&[0.0; 5])), 0.0);
        assert!(relative_error(&px(&[1.0])).is_infinite());
        assert!(relative_error(&px(&[])).is_infinite());
        // Mean 5e-4, sd of the mean 5e-4: judged as 5e-4 / DARK_EPS = 0.5.
        let e = relative_error(&px(&[0.0, 1e-3]));
        // (L^2 = 1e-6 is held to 2^-20 in the sums: about 5% here, see the module docs.)
        assert!((e - 0.5).abs() < 0.05, "{e}");
    }

    /// A 20 x 12 tile (3 x 2 blocks, partial at the right and bottom): flat pixels converge,
    /// one noisy pixel keeps its whole block (and only it) sampling; before min_spp nothing
    /// converges; the same sums give the same mask.
    #[test]
    fn a_noisy_pixel_keeps_its_block_and_only_it() {
        let rect = TileRect { x0: 8, y0: 16, x1: 28, y1: 28 };
        let mut t = TileAccum::new(rect);
        for y in 0..12 {
            for x in 0..20 {
                for s in 0..8 {
                    let v = if (x, y) == (17, 9) { if s % 2 == 0 { 0.1 } else { 2.0 } } else { 0.5 };
                    add_sample(t.pixel_mut(x, y), &grey(v));
                }
            }
        }
        let settings = AdaptiveSettings { threshold: 0.05, min_spp: 8 };
        let mask = converged_blocks(&t.sums, rect, &settings, 8);
        assert_eq!(mask.blocks(), (3, 2));
        assert!(!mask.is_converged(2, 1));
        assert_eq!(mask.converged_count(), 5);
        assert!(!mask.all_converged() && !mask.none());
        assert!(mask.pixel_converged(16, 7) && !mask.pixel_converged(16, 8) && !mask.pixel_converged(19, 11));
        assert_eq!(mask.active_pixels(rect), 4 * 4);
        assert_eq!(expected_samples(Some(&mask), 0, 0, 8), 0);
        assert_eq!(expected_samples(Some(&mask), 17, 9, 8), 8);
        assert_eq!(expected_samples(None, 0, 0, 8), 8);
        assert!(converged_blocks(&t.sums, rect, &AdaptiveSettings { min_spp: 16, ..settings }, 8).none());
        assert_eq!(converged_blocks(&t.sums, rect, &settings, 8), mask);
        // A threshold above the noisy pixel's error (0.34) takes its block too.
        assert!(converged_blocks(&t.sums, rect, &AdaptiveSettings { threshold: 10.0, ..settings }, 8).all_converged());
    }

    #[test]
    fn masks_roundtrip_compactly_and_bad_ones_are_refused() {
        let rect = TileRect { x0: 0, y0: 0, x1: 64, y1: 64 };
        let mut m = BlockMask::none_converged(rect);
        for (bx, by) in [(0, 0), (7, 7), (3, 5)] {
            m.set_converged(bx, by);
        }
        let json = serde_json::to_string(&m).expect("json");
        assert_eq!(json.len(), r#"{"blocks_x":8,"blocks_y":8,"converged":"AAAAAAAAAAA="}"#.len(), "{json}");
        let back: BlockMask = serde_json::from_str(&json).expect("parse");
        assert_eq!(back, m);
        assert!(back.fits(rect) && !back.fits(TileRect { x0: 0, y0: 0, x1: 56, y1: 64 }));
        // 13 x 3 blocks: 39 bits in 5 bytes.
        let odd = TileRect { x0: 0, y0: 0, x1: 100, y1: 20 };
        let mut m = BlockMask::none_converged(odd);
        m.set_converged(12, 2);
        let back: BlockMask = serde_json::from_str(&serde_json::to_string(&m).expect("json")).expect("parse");
        assert_eq!(back, m);
        for (bad, words) in [
            (r#"{"blocks_x":0,"blocks_y":8,"converged":""}"#, "each side"),
            (r#"{"blocks_x":200,"blocks_y":8,"converged":""}"#, "each side"),
            (r#"{"blocks_x":8,"blocks_y":8,"converged":"!!"}"#, "base64"),
            (r#"{"blocks_x":8,"blocks_y":8,"converged":"AAAA"}"#, "3 bytes for 64 blocks"),
            (r#"{"blocks_x":3,"blocks_y":1,"converged":"/w=="}"#, "beyond block 3"),
            (r#"{"blocks_x":1,"blocks_y":1,"converged":"AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA"}"#, "longer"),
        ] {
            let e = serde_json::from_str::<BlockMask>(bad).expect_err(bad).to_string();
            assert!(e.contains(words), "{bad}: {e}");
        }
    }
}
