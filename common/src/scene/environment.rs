//! Environment images: the equirectangular `.exr`/`.hdr` a job names (see
//! [`EnvironmentSettings`](crate::job::EnvironmentSettings)), read from the scene's folder with
//! the scene's image budgets checked before decoding.

use super::{LoadOptions, SceneError};
use glam::Vec3;
use std::path::{Component, Path};
use std::sync::Arc;

/// A decoded equirectangular environment image, linear RGB.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvironmentImage {
    pub width: u32,
    pub height: u32,
    /// Row-major, top row (straight up) first. Negative and non-finite texels read as 0.
    pub texels: Arc<Vec<Vec3>>,
}

impl EnvironmentImage {
    /// An image from texels (tests and generated skies); `None` if the sizes disagree.
    pub fn new(width: u32, height: u32, texels: Vec<Vec3>) -> Option<Self> {
        let ok = width > 0 && height > 0 && texels.len() as u64 == u64::from(width) * u64::from(height);
        ok.then(|| Self { width, height, texels: Arc::new(texels.into_iter().map(clean).collect()) })
    }

    /// Texel `(x, y)`, clamped to the image.
    #[inline]
    pub fn texel(&self, x: u32, y: u32) -> Vec3 {
        let (x, y) = (x.min(self.width - 1), y.min(self.height - 1));
        self.texels.get(y as usize * self.width as usize + x as usize).copied().unwrap_or(Vec3::ZERO)
    }
}

fn clean(c: Vec3) -> Vec3 {
    let f = |v: f32| if v.is_finite() && v > 0.0 { v } else { 0.0 };
    Vec3::new(f(c.x), f(c.y), f(c.z))
}

/// Most pixels of an environment image, whatever the options say (16k x 8k, the largest
/// HDRIs in common use; 2 GiB of texels).
pub const MAX_ENVIRONMENT_PIXELS: u64 = 16384 * 8192;

/// The image of a job's environment, if its settings name one (`scene_dir`: the folder of the
/// scene's `.gltf`/`.glb`).
pub fn load_job_environment(
    scene_dir: &Path,
    settings: &crate::job::RenderSettings,
    opts: &LoadOptions,
) -> Result<Option<EnvironmentImage>, SceneError> {
    match settings.environment.as_ref().and_then(|e| e.file.as_deref()) {
        Some(file) => load_environment(scene_dir, file, opts).map(Some),
        None => Ok(None),
    }
}

/// Loads the environment image `file` (relative, inside `scene_dir`: the folder of the scene's
/// `.gltf`/`.glb`). `max_texture_pixels` is checked from the header before decoding, and
/// `max_texture_bytes` bounds the decoder's buffer plus the texels kept.
pub fn load_environment(scene_dir: &Path, file: &str, opts: &LoadOptions) -> Result<EnvironmentImage, SceneError> {
    let invalid = |message: String| SceneError::Invalid { file: file.to_string(), message };
    let rel = Path::new(file);
    if file.is_empty() || !rel.components().all(|c| matches!(c, Component::Normal(_))) {
        return Err(SceneError::ForbiddenUri {
            file: file.to_string(),
            element: "environment".into(),
            uri: file.to_string(),
            reason: "must be a relative path inside the scene bundle".into(),
        });
    }
    let path = scene_dir.join(rel);
    let reader = image::ImageReader::open(&path).map_err(|source| SceneError::Io {
        file: file.to_string(),
        element: "environment image (not found in the scene bundle?)".into(),
        source,
    })?;
    let reader = reader.with_guessed_format().map_err(|e| invalid(format!("environment image: {e}")))?;
    let decoder = reader.into_decoder().map_err(|e| invalid(format!("environment image: {e}")))?;
    let (w, h) = image::ImageDecoder::dimensions(&decoder);
    let pixels = u64::from(w) * u64::from(h);
    if pixels == 0 {
        return Err(invalid("environment image: has no pixels".into()));
    }
    let max_pixels = opts.max_texture_pixels.unwrap_or(MAX_ENVIRONMENT_PIXELS).min(MAX_ENVIRONMENT_PIXELS);
    if let Some(max) = Some(max_pixels).filter(|&m| pixels > m) {
        return Err(SceneError::LimitExceeded {
            file: file.to_string(),
            element: format!("environment image: {w}x{h} pixels"),
            limit: "max_texture_pixels",
            actual: pixels,
            max,
        });
    }
    // The decoder's buffer, its RGB f32 copy and the importance-sampling tables (a cdf entry
    // per texel) that the renderer builds.
    let bytes = image::ImageDecoder::total_bytes(&decoder).saturating_add(pixels.saturating_mul(12 + 4));
    if let Some(max) = opts.max_texture_bytes.filter(|&m| bytes > m) {
        return Err(SceneError::LimitExceeded {
            file: file.to_string(),
            element: "environment image: image memory".into(),
            limit: "max_texture_bytes",
            actual: bytes,
            max,
        });
    }
    let decoded = image::DynamicImage::from_decoder(decoder).map_err(|e| invalid(format!("environment image: {e}")))?;
    let rgb = decoded.to_rgb32f();
    let texels = rgb.into_raw().chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])).collect();
    EnvironmentImage::new(w, h, texels).ok_or_else(|| invalid("environment image: size mismatch".into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small Radiance `.hdr` (uncompressed flat RGBE scanlines).
    fn hdr_bytes(w: u32, h: u32, rgbe: [u8; 4]) -> Vec<u8> {
        let mut b = format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n").into_bytes();
        for _ in 0..w * h {
            b.extend_from_slice(&rgbe);
        }
        b
    }

    #[test]
    fn loads_hdr_and_checks_limits_and_paths() {
        let dir = tempfile::tempdir().expect("tempdir");
        // RGBE (128, 64, 32, 129): mantissas / 256 x 2^(129 - 128) = (1, 0.5, 0.25).
        std::fs::write(dir.path().join("sky.hdr"), hdr_bytes(8, 4, [128, 64, 32, 129])).expect("write");
        let img = load_environment(dir.path(), "sky.hdr", &LoadOptions::default()).expect("loads");
        assert_eq!((img.width, img.height), (8, 4));
        let t = img.texel(3, 2);
        assert!((t - Vec3::new(1.0, 0.5, 0.25)).abs().max_element() < 1e-2, "{t}");

        let small = LoadOptions { max_texture_pixels: Some(16), ..Default::default() };
        let e = load_environment(dir.path(), "sky.hdr", &small).expect_err("too many pixels");
        assert!(e.to_string().contains("max_texture_pixels") && e.to_string().contains("8x4"), "{e}");
        let tight = LoadOptions { max_texture_bytes: Some(100), ..Default::default() };
        let e = load_environment(dir.path(), "sky.hdr", &tight).expect_err("too much memory");
        assert!(e.to_string().contains("max_texture_bytes"), "{e}");

        let e = load_environment(dir.path(), "../sky.hdr", &LoadOptions::default()).expect_err("escape");
        assert!(e.to_string().contains("inside the scene bundle"), "{e}");
        let e = load_environment(dir.path(), "missing.exr", &LoadOptions::default()).expect_err("missing");
        assert!(e.to_string().contains("missing.exr") && e.to_string().contains("not found"), "{e}");
        std::fs::write(dir.path().join("bad.exr"), b"not an image").expect("write");
        let e = load_environment(dir.path(), "bad.exr", &LoadOptions::default()).expect_err("garbage");
        assert!(e.to_string().contains("bad.exr"), "{e}");
    }

    #[test]
    fn loads_exr() {
        use exr::prelude::*;
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("sky.exr");
        write_rgb_file(&path, 6, 3, |x, y| (x as f32, y as f32, 2.0)).expect("write exr");
        let img = load_environment(dir.path(), "sky.exr", &LoadOptions::default()).expect("loads");
        assert_eq!((img.width, img.height), (6, 3));
        assert_eq!(img.texel(4, 1), Vec3::new(4.0, 1.0, 2.0));
    }
}
