//! Helpers for the renderer's integration tests.
#![allow(dead_code)]

use pathfarm_common::film::ImageLayers;
use pathfarm_common::job::RenderSettings;
use pathfarm_common::scene::{LoadOptions, Scene, load_scene, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};
use std::path::{Path, PathBuf};

/// The repository's `reference/` folder: Mitsuba 3's Cornell box as our exporter writes it and
/// the Mitsuba render of it made by `scripts/make-reference.py`.
pub fn reference() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../reference")
}

pub fn glb_scene(bytes: &[u8]) -> Scene {
    load_scene_from_slice(bytes, "test.glb", None, &LoadOptions::default()).expect("our scene loads")
}

pub fn file_scene(path: &Path) -> Scene {
    load_scene(path, &LoadOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn render(scene: &Scene, settings: &RenderSettings) -> ImageLayers {
    let r = Renderer::new(scene, settings).expect("renderer");
    render_local(&r, |_, _| {}).resolve()
}

/// Mean of each RGB channel.
pub fn mean_rgb(img: &ImageLayers) -> [f64; 3] {
    let n = img.rgb.len() as f64;
    let mut m = [0.0; 3];
    for p in &img.rgb {
        for c in 0..3 {
            m[c] += f64::from(p[c]) / n;
        }
    }
    m
}

pub fn luminance(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// Mean luminance of the image and the standard error of that mean, from the variance layer
/// (the pixels' estimates are independent).
pub fn mean_luminance_and_stderr(img: &ImageLayers) -> (f64, f64) {
    let n = img.rgb.len() as f64;
    let mean = img.rgb.iter().map(|p| luminance([p[0].into(), p[1].into(), p[2].into()])).sum::<f64>() / n;
    let var = img.variance.iter().map(|&v| f64::from(v)).sum::<f64>() / (n * n);
    (mean, var.sqrt())
}
