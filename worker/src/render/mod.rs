//! The renderer. Pure: no async, no I/O, no global state. Everything a unit computes is a
//! function of (scene, settings, tile, sample range).

pub mod accel;
pub mod bsdf;
pub mod camera;
#[cfg(test)]
pub mod chi2;
pub mod geometry;
pub mod light;
pub mod microfacet;
pub mod sampler;
pub mod sampling;
pub mod scene;

use pathfarm_common::film::{Film, SplatBuffer, TileAccum};
use pathfarm_common::job::{Pass, RenderSettings, TileRect};
use pathfarm_common::scene::Scene;

/// Errors preparing a scene for rendering.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error("scene: {0}")]
    Scene(String),
}

/// What one work unit (tile x pass) produces.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnitResult {
    pub accum: TileAccum,
    /// Light-tracing splats anywhere on the image (BDPT only).
    pub splats: Option<SplatBuffer>,
}

/// A scene prepared for rendering (BVH, lights, materials, camera) with fixed settings.
pub struct Renderer {
    settings: RenderSettings,
}

impl Renderer {
    /// Prepares `scene` for rendering with `settings`.
    pub fn new(_scene: &Scene, settings: &RenderSettings) -> Result<Self, RenderError> {
        Ok(Self { settings: settings.clone() })
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Renders the sample indices of `pass` for every pixel of `tile`.
    /// (Placeholder pattern until the integrators land.)
    pub fn render_unit(&self, tile: TileRect, pass: Pass) -> UnitResult {
        let mut accum = TileAccum::new(tile);
        for y in tile.y0..tile.y1 {
            for x in tile.x0..tile.x1 {
                for s in pass.samples() {
                    let v = ((x * 31 + y * 17 + s * 7) % 97) as f32 / 97.0;
                    pathfarm_common::film::add_sample(
                        accum.pixel_mut(x - tile.x0, y - tile.y0),
                        &pathfarm_common::film::SampleValue { radiance: [v, v, v], ..Default::default() },
                    );
                }
            }
        }
        UnitResult { accum, splats: None }
    }
}

/// Renders a whole job locally, unit by unit in canonical order, exactly as the farm does.
/// `progress(done, total)` is called after each unit.
pub fn render_local(renderer: &Renderer, mut progress: impl FnMut(usize, usize)) -> Film {
    let settings = renderer.settings();
    let plan = settings.plan();
    let mut film = Film::new(settings.width, settings.height);
    let total = plan.unit_count();
    for (done, key) in plan.units().enumerate() {
        let r = renderer.render_unit(plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
        film.add_tile(&r.accum);
        if let Some(s) = &r.splats {
            film.splats.merge(s);
        }
        progress(done + 1, total);
    }
    film.splat_spp = settings.spp;
    film
}
