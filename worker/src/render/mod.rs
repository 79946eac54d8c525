//! The renderer. Pure: no async, no I/O, no global state. Everything a unit computes is a
//! function of (scene, settings, tile, sample range).

pub mod accel;
pub mod bsdf;
pub mod camera;
#[cfg(test)]
pub mod chi2;
pub mod geometry;
pub mod integrator;
pub mod light;
pub mod material;
pub mod microfacet;
pub mod sampler;
pub mod sampling;
pub mod scene;

use camera::Camera;
use glam::UVec2;
use integrator::{PathParams, li_path};
use pathfarm_common::film::{self, Film, SplatBuffer, TileAccum};
use pathfarm_common::job::{IntegratorSettings, Pass, RenderSettings, TileRect};
use pathfarm_common::scene::Scene;
use rayon::prelude::*;
use sampler::{AnySampler, Sampler};
use scene::RenderScene;

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
    scene: RenderScene,
    camera: Camera,
    params: PathParams,
}

impl Renderer {
    /// Prepares `scene` for rendering with `settings` (builds the BVH: do it once per job).
    pub fn new(scene: &Scene, settings: &RenderSettings) -> Result<Self, RenderError> {
        settings
            .validate(&pathfarm_common::job::Limits::default())
            .map_err(|e| RenderError::Settings(e.to_string()))?;
        let camera = match settings.camera {
            Some(i) => {
                let cam = scene.cameras.get(i).ok_or_else(|| {
                    RenderError::Settings(format!("camera {i} does not exist (the scene has {})", scene.cameras.len()))
                })?;
                Camera::new(cam, settings.width, settings.height)
            }
            None => match scene.cameras.first() {
                Some(cam) => Camera::new(cam, settings.width, settings.height),
                None => Camera::framing(scene.bounds(), settings.width, settings.height),
            },
        };
        let params = match settings.integrator {
            IntegratorSettings::Direct { mis, light_sampling } => {
                PathParams { max_depth: 2, rr_depth: u32::MAX, mis, light_sampling }
            }
            IntegratorSettings::Path { max_depth, rr_depth, mis, light_sampling } => {
                PathParams { max_depth, rr_depth, mis, light_sampling }
            }
            ref other => {
                return Err(RenderError::Settings(format!(
                    "integrator {:?} is not available yet in this build",
                    serde_json::to_value(other).ok().and_then(|v| v.get("type").cloned()).unwrap_or_default()
                )));
            }
        };
        Ok(Self { settings: settings.clone(), scene: RenderScene::new(scene), camera, params })
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    pub fn scene(&self) -> &RenderScene {
        &self.scene
    }

    /// Renders the sample indices of `pass` for every pixel of `tile`, in parallel over rows on
    /// the current rayon pool. The result does not depend on the thread count.
    pub fn render_unit(&self, tile: TileRect, pass: Pass) -> UnitResult {
        // One match per unit: the per-sample loop is monomorphized for the concrete sampler.
        let seed = self.settings.seed;
        let accum = match AnySampler::new(self.settings.sampler, seed) {
            AnySampler::Sobol(_) => self.render_tile(tile, pass, || sampler::SobolSampler::new(seed)),
            AnySampler::Independent(_) => self.render_tile(tile, pass, || sampler::IndependentSampler::new(seed)),
        };
        UnitResult { accum, splats: None }
    }

    fn render_tile<S: Sampler>(&self, tile: TileRect, pass: Pass, new_sampler: impl Fn() -> S + Sync) -> TileAccum {
        let row_len = tile.width() as usize * film::ch::COUNT;
        let rows: Vec<Vec<film::Fixed>> = (tile.y0..tile.y1)
            .into_par_iter()
            .map(|y| {
                let mut sampler = new_sampler();
                let mut row = vec![0; row_len];
                for x in tile.x0..tile.x1 {
                    let i = (x - tile.x0) as usize * film::ch::COUNT;
                    let pixel = UVec2::new(x, y);
                    for s in pass.samples() {
                        sampler.start_pixel_sample(pixel, s, 0);
                        let v = li_path(&self.scene, &self.camera, pixel, &mut sampler, &self.params);
                        film::add_sample(&mut row[i..i + film::ch::COUNT], &v);
                    }
                }
                row
            })
            .collect();
        let mut accum = TileAccum::new(tile);
        for (dst, src) in accum.sums.chunks_mut(row_len).zip(rows) {
            dst.copy_from_slice(&src);
        }
        accum
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
