//! The film: per-pixel sums in exact fixed point, their merge, and EXR / PNG encoding.
//!
//! Every sample's contribution is rounded once to a 96.32 fixed-point number ([`Fixed`]).
//! Integer addition is associative and commutative, so the sum over a pixel's samples is the
//! same bits however the samples were split into tiles, passes, workers or threads, and in
//! whatever order the parts arrive. That is what makes the farm's image bit-identical to a local
//! render (DESIGN.md, "Work units and the merge"). The rounding error is 2^-33 per sample,
//! far below f32 precision for any visible value.

use crate::job::TileRect;
use std::path::Path;

/// A fixed-point sum with [`FRAC_BITS`] fractional bits.
pub type Fixed = i128;

/// Fractional bits of [`Fixed`].
pub const FRAC_BITS: u32 = 32;
const SCALE: f64 = (1u64 << FRAC_BITS) as f64;

/// Converts one sample value to fixed point. Non-finite values become 0 (the caller counts them).
#[inline]
pub fn to_fixed(v: f32) -> Fixed {
    if v.is_finite() { (f64::from(v) * SCALE).round() as Fixed } else { 0 }
}

/// Converts a fixed-point sum back to a float.
#[inline]
pub fn from_fixed(v: Fixed) -> f64 {
    v as f64 / SCALE
}

/// Channels of a pixel's sums.
pub mod ch {
    pub const R: usize = 0;
    pub const G: usize = 1;
    pub const B: usize = 2;
    /// Sum of squared luminance of the radiance samples (for `variance.Y`).
    pub const LUM_SQ: usize = 3;
    pub const ALBEDO_R: usize = 4;
    pub const ALBEDO_G: usize = 5;
    pub const ALBEDO_B: usize = 6;
    pub const NORMAL_X: usize = 7;
    pub const NORMAL_Y: usize = 8;
    pub const NORMAL_Z: usize = 9;
    /// Sum of first-hit distances over the samples that hit something.
    pub const DEPTH: usize = 10;
    /// Number of samples that hit something.
    pub const HITS: usize = 11;
    /// Sample weight (box filter: 1 per sample).
    pub const WEIGHT: usize = 12;
    pub const COUNT: usize = 13;
}

/// What one camera sample contributes to its pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SampleValue {
    pub radiance: [f32; 3],
    pub albedo: [f32; 3],
    pub normal: [f32; 3],
    /// Distance to the first hit, `None` for a miss.
    pub depth: Option<f32>,
}

/// Relative luminance of linear sRGB primaries (Rec. 709).
#[inline]
pub fn luminance(rgb: [f32; 3]) -> f32 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// Sums of a rectangle of pixels, channel-interleaved (`pixel * ch::COUNT + channel`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileAccum {
    pub rect: TileRect,
    pub sums: Vec<Fixed>,
}

impl TileAccum {
    pub fn new(rect: TileRect) -> Self {
        Self { rect, sums: vec![0; rect.pixel_count() * ch::COUNT] }
    }

    /// The sums of pixel `(x, y)` in tile-local coordinates.
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [Fixed] {
        let i = (y * self.rect.width() + x) as usize * ch::COUNT;
        &mut self.sums[i..i + ch::COUNT]
    }

    /// Adds another accumulator of the same rectangle.
    pub fn merge(&mut self, other: &TileAccum) {
        assert_eq!(self.rect, other.rect, "merging tiles of different rectangles");
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            *a = a.wrapping_add(*b);
        }
    }
}

/// Adds one sample to a pixel's sums.
#[inline]
pub fn add_sample(pixel: &mut [Fixed], s: &SampleValue) {
    let lum = luminance(s.radiance);
    let vals = [
        s.radiance[0],
        s.radiance[1],
        s.radiance[2],
        lum * lum,
        s.albedo[0],
        s.albedo[1],
        s.albedo[2],
        s.normal[0],
        s.normal[1],
        s.normal[2],
    ];
    for (p, v) in pixel.iter_mut().zip(vals) {
        *p = p.wrapping_add(to_fixed(v));
    }
    if let Some(d) = s.depth {
        pixel[ch::DEPTH] = pixel[ch::DEPTH].wrapping_add(to_fixed(d));
        pixel[ch::HITS] = pixel[ch::HITS].wrapping_add(to_fixed(1.0));
    }
    pixel[ch::WEIGHT] = pixel[ch::WEIGHT].wrapping_add(to_fixed(1.0));
}

/// Full-frame RGB sums of light-tracing splats (BDPT `t = 1`), divided by the sample count at
/// resolve time.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplatBuffer {
    pub width: u32,
    pub height: u32,
    /// `(y * width + x) * 3 + c`.
    pub sums: Vec<Fixed>,
}

impl SplatBuffer {
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, sums: vec![0; width as usize * height as usize * 3] }
    }

    #[inline]
    pub fn add(&mut self, x: u32, y: u32, rgb: [f32; 3]) {
        if x < self.width && y < self.height {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            for (sum, v) in self.sums[i..i + 3].iter_mut().zip(rgb) {
                *sum = sum.wrapping_add(to_fixed(v));
            }
        }
    }

    pub fn merge(&mut self, other: &SplatBuffer) {
        assert_eq!((self.width, self.height), (other.width, other.height), "splat buffer size");
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            *a = a.wrapping_add(*b);
        }
    }

    pub fn is_empty(&self) -> bool {
        self.sums.iter().all(|&v| v == 0)
    }
}

/// A whole image's sums.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    pub sums: Vec<Fixed>,
    pub splats: SplatBuffer,
    /// Samples per pixel that the splats are divided by (the pass-complete sample count).
    pub splat_spp: u32,
}

/// How previews (PNG) are exposed: `ev` stops, added to the automatic exposure when `auto`.
/// From a job's `exposure` and `auto_exposure`; the EXR is never affected.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PreviewExposure {
    pub ev: f32,
    pub auto: bool,
}

impl PreviewExposure {
    pub fn of(settings: &crate::job::RenderSettings) -> Self {
        Self { ev: settings.exposure, auto: settings.auto_exposure }
    }
}

/// Float layers of a resolved image, each `width * height` (or x3 for RGB), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageLayers {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    pub depth: Vec<f32>,
    pub samples: Vec<f32>,
    pub variance: Vec<f32>,
    /// The colour denoised (OIDN, from colour, albedo and normal), when asked for: written as
    /// the EXR layer `denoised` and shown by the PNG preview.
    pub denoised: Option<Vec<[f32; 3]>>,
}

impl Film {
    /// Bytes a film of this size holds: the channel sums and the splat sums, 128 bits each.
    pub fn bytes_for(width: u32, height: u32) -> u64 {
        u64::from(width) * u64::from(height) * (ch::COUNT as u64 + 3) * std::mem::size_of::<Fixed>() as u64
    }

    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            sums: vec![0; width as usize * height as usize * ch::COUNT],
            splats: SplatBuffer::new(width, height),
            splat_spp: 0,
        }
    }

    /// Adds a tile's sums (any order: the sums are exact).
    pub fn add_tile(&mut self, tile: &TileAccum) {
        let r = tile.rect;
        assert!(r.x1 <= self.width && r.y1 <= self.height, "tile outside the film");
        let row = r.width() as usize * ch::COUNT;
        for y in r.y0..r.y1 {
            let src = (y - r.y0) as usize * row;
            let dst = (y as usize * self.width as usize + r.x0 as usize) * ch::COUNT;
            for (a, b) in self.sums[dst..dst + row].iter_mut().zip(&tile.sums[src..src + row]) {
                *a = a.wrapping_add(*b);
            }
        }
    }

    /// Copies the film's sums of `rect` into a tile accumulator.
    pub fn tile(&self, rect: TileRect) -> TileAccum {
        let mut t = TileAccum::new(rect);
        let row = rect.width() as usize * ch::COUNT;
        for y in rect.y0..rect.y1 {
            let src = (y as usize * self.width as usize + rect.x0 as usize) * ch::COUNT;
            let dst = (y - rect.y0) as usize * row;
            t.sums[dst..dst + row].copy_from_slice(&self.sums[src..src + row]);
        }
        t
    }

    /// Per-pixel means and AOVs as floats.
    pub fn resolve(&self) -> ImageLayers {
        let n = self.width as usize * self.height as usize;
        let mut out = ImageLayers {
            width: self.width,
            height: self.height,
            rgb: vec![[0.0; 3]; n],
            albedo: vec![[0.0; 3]; n],
            normal: vec![[0.0; 3]; n],
            depth: vec![f32::INFINITY; n],
            samples: vec![0.0; n],
            variance: vec![0.0; n],
            denoised: None,
        };
        let splat_scale = if self.splat_spp > 0 { 1.0 / f64::from(self.splat_spp) } else { 0.0 };
        for i in 0..n {
            let p = &self.sums[i * ch::COUNT..(i + 1) * ch::COUNT];
            let w = from_fixed(p[ch::WEIGHT]);
            let splat = |c: usize| from_fixed(self.splats.sums[i * 3 + c]) * splat_scale;
            out.samples[i] = w as f32;
            if w > 0.0 {
                let mean = |c: usize| from_fixed(p[c]) / w;
                out.rgb[i] =
                    [(mean(ch::R) + splat(0)) as f32, (mean(ch::G) + splat(1)) as f32, (mean(ch::B) + splat(2)) as f32];
                out.albedo[i] = [mean(ch::ALBEDO_R) as f32, mean(ch::ALBEDO_G) as f32, mean(ch::ALBEDO_B) as f32];
                out.normal[i] = [mean(ch::NORMAL_X) as f32, mean(ch::NORMAL_Y) as f32, mean(ch::NORMAL_Z) as f32];
                let hits = from_fixed(p[ch::HITS]);
                if hits > 0.0 {
                    out.depth[i] = (from_fixed(p[ch::DEPTH]) / hits) as f32;
                }
                let lum = f64::from(luminance([mean(ch::R) as f32, mean(ch::G) as f32, mean(ch::B) as f32]));
                // Variance of the pixel mean: sample variance / n.
                let var = if w > 1.0 {
                    ((from_fixed(p[ch::LUM_SQ]) / w - lum * lum).max(0.0) * w / (w - 1.0)) / w
                } else {
                    0.0
                };
                out.variance[i] = var as f32;
            } else {
                out.rgb[i] = [splat(0) as f32, splat(1) as f32, splat(2) as f32];
            }
        }
        out
    }
}

/// Errors writing or reading images.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("EXR {path}: {source}")]
    Exr { path: String, source: exr::error::Error },
    #[error("PNG {path}: {source}")]
    Png { path: String, source: image::ImageError },
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("EXR {path}: {message}")]
    Format { path: String, message: String },
}

impl ImageLayers {
    /// The EXR channel list, as (name, values) pairs.
    pub fn exr_channels(&self) -> Vec<(&'static str, Vec<f32>)> {
        let c3 = |v: &[[f32; 3]], c: usize| v.iter().map(|p| p[c]).collect::<Vec<f32>>();
        vec![
            ("R", c3(&self.rgb, 0)),
            ("G", c3(&self.rgb, 1)),
            ("B", c3(&self.rgb, 2)),
            ("albedo.R", c3(&self.albedo, 0)),
            ("albedo.G", c3(&self.albedo, 1)),
            ("albedo.B", c3(&self.albedo, 2)),
            ("normal.X", c3(&self.normal, 0)),
            ("normal.Y", c3(&self.normal, 1)),
            ("normal.Z", c3(&self.normal, 2)),
            ("depth.Z", self.depth.clone()),
            ("samples.Y", self.samples.clone()),
            ("variance.Y", self.variance.clone()),
        ]
        .into_iter()
        .chain(
            self.denoised
                .iter()
                .flat_map(|d| [("denoised.R", c3(d, 0)), ("denoised.G", c3(d, 1)), ("denoised.B", c3(d, 2))]),
        )
        .collect()
    }

    /// Encodes the layers as a float32 OpenEXR file in memory (ZIP compression, lossless).
    pub fn encode_exr(&self) -> Result<Vec<u8>, exr::error::Error> {
        use exr::prelude::*;
        let size = (self.width as usize, self.height as usize);
        let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> =
            self.exr_channels().into_iter().map(|(name, v)| AnyChannel::new(name, FlatSamples::F32(v))).collect();
        let attrs = LayerAttributes { software_name: Some(Text::from("pathfarm")), ..Default::default() };
        let layer = Layer::new(size, attrs, Encoding::SMALL_LOSSLESS, AnyChannels::sort(channels));
        let mut buf = std::io::Cursor::new(Vec::new());
        Image::from_layer(layer).write().to_buffered(&mut buf)?;
        Ok(buf.into_inner())
    }

    /// Writes the EXR atomically: a temporary file beside `path`, then a rename.
    pub fn write_exr(&self, path: &Path) -> Result<(), ImageError> {
        let bytes = self.encode_exr().map_err(|source| ImageError::Exr { path: path.display().to_string(), source })?;
        write_atomic(path, &bytes)
    }

    /// The exposure (EV) that brings the log-average luminance of the shown colour (denoised if
    /// there is one) to middle grey, 0.18 (Reinhard's key value): `log2(0.18 / exp(mean(ln(1e-4
    /// + L))))` over the finite pixels, within +-20 EV; 0 for an all-black image.
    pub fn auto_exposure(&self) -> f32 {
        let shown = self.denoised.as_deref().unwrap_or(&self.rgb);
        let (mut sum, mut n, mut max) = (0.0f64, 0usize, 0.0f32);
        for c in shown {
            let l = 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
            if l.is_finite() && l >= 0.0 {
                sum += f64::from(1e-4 + l).ln();
                n += 1;
                max = max.max(l);
            }
        }
        if n == 0 || max <= 0.0 {
            return 0.0;
        }
        let log_average = (sum / n as f64).exp();
        ((0.18 / log_average).log2() as f32).clamp(-20.0, 20.0)
    }

    /// The EV a preview uses: `exposure.ev`, plus [`ImageLayers::auto_exposure`] when
    /// `exposure.auto`.
    pub fn preview_ev(&self, exposure: PreviewExposure) -> f32 {
        if exposure.auto { exposure.ev + self.auto_exposure() } else { exposure.ev }
    }

    /// An 8-bit sRGB preview of the denoised colour if there is one, else of the colour:
    /// `exposure` in stops, clamped, sRGB-encoded.
    pub fn preview_rgb8(&self, exposure: f32) -> image::RgbImage {
        let scale = exposure.exp2();
        let mut img = image::RgbImage::new(self.width, self.height);
        let shown = self.denoised.as_deref().unwrap_or(&self.rgb);
        for (i, px) in img.pixels_mut().enumerate() {
            let c = shown[i];
            *px = image::Rgb([encode_srgb8(c[0] * scale), encode_srgb8(c[1] * scale), encode_srgb8(c[2] * scale)]);
        }
        img
    }

    /// PNG bytes of [`ImageLayers::preview_rgb8`].
    pub fn encode_png(&self, exposure: f32) -> Result<Vec<u8>, image::ImageError> {
        let mut buf = std::io::Cursor::new(Vec::new());
        self.preview_rgb8(exposure).write_to(&mut buf, image::ImageFormat::Png)?;
        Ok(buf.into_inner())
    }

    /// Writes the PNG preview atomically.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), ImageError> {
        let bytes =
            self.encode_png(exposure).map_err(|source| ImageError::Png { path: path.display().to_string(), source })?;
        write_atomic(path, &bytes)
    }
}

/// sRGB transfer function, linear [0, 1] -> 8-bit code.
pub fn encode_srgb8(v: f32) -> u8 {
    let v = if v.is_finite() { v.clamp(0.0, 1.0) } else { 0.0 };
    let s = if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0 + 0.5) as u8
}

/// Writes `bytes` to `path` through a temporary file in the same directory and a rename, so
/// readers never see a half-written file.
/// Writes `bytes` to `path` atomically and durably: a unique temporary file in the same
/// directory, fsynced, renamed over `path`, then the directory fsynced. On failure the temporary
/// file is removed and `path` keeps its old contents.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ImageError> {
    let io = |source| ImageError::Io { path: path.display().to_string(), source };
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io)?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    // Unique per write: threads of one process (local workers) may write the same file at once.
    static SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let seq = SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.{}.{seq}.tmp", std::process::id()));
    let written = (|| {
        use std::io::Write;
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        // Durable before it replaces the old file: a crash leaves the old or the new bytes.
        f.sync_all()?;
        std::fs::rename(&tmp, path)?;
        // The rename itself is durable once the directory is synced.
        std::fs::File::open(dir).and_then(|d| d.sync_all())
    })();
    if written.is_err() {
        // A failed write (e.g. a full disk) leaves no temporary file behind.
        let _ = std::fs::remove_file(&tmp);
    }
    written.map_err(io)
}

/// Named float channels of an EXR file (first layer), for tests and tools.
#[derive(Clone, Debug)]
pub struct ExrChannels {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }
}

/// Reads all channels of the first layer of an EXR file as f32.
pub fn read_exr(path: &Path) -> Result<ExrChannels, ImageError> {
    use exr::prelude::*;
    let err = |source| ImageError::Exr { path: path.display().to_string(), source };
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(err)?;
    let layer = image.layer_data;
    let channels =
        layer.channel_data.list.iter().map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect())).collect();
    Ok(ExrChannels { width: layer.size.0, height: layer.size.1, channels })
}

#[cfg(test)]
mod tests {

    #[test]
    fn a_failed_atomic_write_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let target = dir.path().join("image.exr");
        write_atomic(&target, b"one").expect("first write");
        assert_eq!(std::fs::read(&target).expect("read"), b"one");
        // A directory in the way: the rename fails, the temporary file is removed.
        let blocked = dir.path().join("blocked");
        std::fs::create_dir_all(blocked.join("inside")).expect("dir");
        assert!(write_atomic(&blocked, b"two").is_err());
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .expect("list")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        assert!(left.iter().all(|n| !n.ends_with(".tmp")), "temporary files left: {left:?}");
        assert_eq!(std::fs::read(&target).expect("read"), b"one");
    }

    use super::*;

    fn uniform(width: u32, height: u32, rgb: [f32; 3]) -> ImageLayers {
        let n = (width * height) as usize;
        ImageLayers {
            width,
            height,
            rgb: vec![rgb; n],
            albedo: vec![[0.0; 3]; n],
            normal: vec![[0.0; 3]; n],
            depth: vec![0.0; n],
            samples: vec![1.0; n],
            variance: vec![0.0; n],
            denoised: None,
        }
    }

    /// Auto exposure brings the log-average luminance to 0.18: a uniform grey of 0.045 gets
    /// log2(0.18 / 0.0451) = +1.997 EV, so its preview shows middle grey (sRGB 118); a manual EV
    /// adds to it; a black image keeps 0; the EXR does not change.
    #[test]
    fn auto_exposure_maps_the_log_average_to_middle_grey() {
        let img = uniform(4, 2, [0.045; 3]);
        let ev = img.auto_exposure();
        assert!((ev - (0.18f32 / 0.0451).log2()).abs() < 1e-4, "{ev}");
        let auto = PreviewExposure { ev: 0.0, auto: true };
        let px = img.preview_rgb8(img.preview_ev(auto));
        assert_eq!(px.get_pixel(0, 0).0, [encode_srgb8(0.18 * 0.045 / 0.0451); 3]);
        assert_eq!(img.preview_ev(PreviewExposure { ev: -1.0, auto: true }), ev - 1.0);
        assert_eq!(img.preview_ev(PreviewExposure { ev: 1.5, auto: false }), 1.5);
        assert_eq!(uniform(2, 2, [0.0; 3]).auto_exposure(), 0.0);
        // A bright image is exposed down: 100x brighter is log2(100) = 6.6 EV less.
        let bright = uniform(2, 2, [4.5; 3]);
        assert!((ev - bright.auto_exposure() - 100f32.log2()).abs() < 0.01);
    }

    #[test]
    fn fixed_point_merge_is_order_independent() {
        let rect = TileRect { x0: 0, y0: 0, x1: 2, y1: 1 };
        let samples: Vec<SampleValue> = (0..50)
            .map(|i| SampleValue {
                radiance: [(i as f32 * 0.37).sin().abs() * 10.0, 1e-7 * i as f32, 3.3],
                depth: Some(i as f32),
                ..Default::default()
            })
            .collect();
        let mut whole = TileAccum::new(rect);
        for s in &samples {
            add_sample(whole.pixel_mut(1, 0), s);
        }
        // Split in three parts, merged in reverse order.
        let mut parts: Vec<TileAccum> = samples
            .chunks(17)
            .map(|c| {
                let mut t = TileAccum::new(rect);
                for s in c {
                    add_sample(t.pixel_mut(1, 0), s);
                }
                t
            })
            .collect();
        parts.reverse();
        let mut merged = TileAccum::new(rect);
        for p in &parts {
            merged.merge(p);
        }
        assert_eq!(whole, merged);
    }

    #[test]
    fn resolve_mean_and_variance() {
        let mut film = Film::new(1, 1);
        let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 1, y1: 1 });
        for v in [1.0f32, 3.0] {
            add_sample(t.pixel_mut(0, 0), &SampleValue { radiance: [v, v, v], ..Default::default() });
        }
        film.add_tile(&t);
        let img = film.resolve();
        assert!((img.rgb[0][0] - 2.0).abs() < 1e-6);
        assert_eq!(img.samples[0], 2.0);
        // Sample variance of {1, 3} is 2; variance of the mean is 1.
        assert!((img.variance[0] - 1.0).abs() < 1e-5, "{}", img.variance[0]);
        assert!(img.depth[0].is_infinite());
    }

    #[test]
    fn exr_roundtrip_through_our_reader() {
        let mut film = Film::new(3, 2);
        let mut t = TileAccum::new(TileRect { x0: 0, y0: 0, x1: 3, y1: 2 });
        add_sample(
            t.pixel_mut(2, 1),
            &SampleValue {
                radiance: [0.5, 0.25, 0.125],
                albedo: [1.0, 0.0, 0.0],
                normal: [0.0, 1.0, 0.0],
                depth: Some(2.5),
            },
        );
        film.add_tile(&t);
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("x.exr");
        film.resolve().write_exr(&path).expect("write");
        let back = read_exr(&path).expect("read");
        assert_eq!((back.width, back.height), (3, 2));
        let r = back.get("R").expect("R");
        assert_eq!(r[5], 0.5);
        assert_eq!(back.get("depth.Z").expect("depth")[5], 2.5);
        assert_eq!(back.get("normal.Y").expect("normal")[5], 1.0);
        assert_eq!(back.channels.len(), 12);
    }
}

/// What adaptive sampling reads of a pixel's sums (`crate::adaptive`): the sample weight, the
/// mean colour and the sum of squared luminance, as floats.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelStats {
    /// Samples (box filter: weight 1 each).
    pub weight: f64,
    /// Mean radiance (0 without samples).
    pub mean_rgb: [f64; 3],
    /// Sum over the samples of their squared luminance.
    pub lum_sq_sum: f64,
}

/// [`PixelStats`] of one pixel's sums (`ch::COUNT` values).
pub fn pixel_stats(p: &[Fixed]) -> PixelStats {
    let weight = from_fixed(p[ch::WEIGHT]);
    let mean = |c: usize| if weight > 0.0 { from_fixed(p[c]) / weight } else { 0.0 };
    PixelStats { weight, mean_rgb: [mean(ch::R), mean(ch::G), mean(ch::B)], lum_sq_sum: from_fixed(p[ch::LUM_SQ]) }
}
