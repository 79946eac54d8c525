//! The lecture's picture sequences on our demo Cornell box (Blinn and Ashikhmin-Shirley boxes):
//! path tracing with bounce limits 1, 2, 4, 8 (path segments, Mitsuba's convention) at 256 spp,
//! and 1, 4, 16, 256 spp at max depth 8; one PNG each plus a contact sheet per sequence.
//!
//! ```sh
//! cargo run --release -p pathfarm-worker --example lecture -- [OUT_DIR] [SIZE]
//! ```
//! Writes `OUT_DIR` (default `target/lecture`): `depth_{1,2,4,8}.png`, `spp_{1,4,16,256}.png`,
//! `depth_sheet.png`, `spp_sheet.png`.

use anyhow::Context;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_common::scene::{LoadOptions, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "target/lecture".into()));
    let size: u32 = args.next().map(|s| s.parse()).transpose().context("SIZE must be a number")?.unwrap_or(256);
    std::fs::create_dir_all(&out)?;
    let scene = load_scene_from_slice(&cornell_demo_glb(), "demo.glb", None, &LoadOptions::default())?;

    let render = |max_depth: u32, spp: u32, name: &str| -> anyhow::Result<image::RgbImage> {
        let mut s = RenderSettings::new(size, size, spp);
        s.integrator = IntegratorSettings::Path {
            max_depth,
            rr_depth: 5,
            mis: MisHeuristic::Power,
            light_sampling: LightSampling::SolidAngle,
        };
        let img = render_local(&Renderer::new(&scene, &s)?, |_, _| {}).resolve();
        let path = out.join(format!("{name}.png"));
        img.write_png(&path, 0.0)?;
        eprintln!("wrote {}", path.display());
        Ok(img.preview_rgb8(0.0))
    };

    let depth: Vec<_> =
        [1, 2, 4, 8].iter().map(|&d| render(d, 256, &format!("depth_{d}"))).collect::<anyhow::Result<_>>()?;
    sheet(&depth).save(out.join("depth_sheet.png"))?;
    let spp: Vec<_> =
        [1, 4, 16, 256].iter().map(|&n| render(8, n, &format!("spp_{n}"))).collect::<anyhow::Result<_>>()?;
    sheet(&spp).save(out.join("spp_sheet.png"))?;
    eprintln!("contact sheets: {}, {}", out.join("depth_sheet.png").display(), out.join("spp_sheet.png").display());
    Ok(())
}

/// Images side by side with a 4-pixel gap.
fn sheet(images: &[image::RgbImage]) -> image::RgbImage {
    let (w, h) = images.first().map_or((0, 0), |i| i.dimensions());
    let mut out = image::RgbImage::from_pixel((w + 4) * images.len() as u32 - 4, h, image::Rgb([255, 255, 255]));
    for (k, img) in images.iter().enumerate() {
        image::imageops::replace(&mut out, img, i64::from(k as u32 * (w + 4)), 0);
    }
    out
}
