//! Integrators: `direct` (emission + direct lighting with MIS) and `path` (path tracing with
//! next-event estimation, MIS and Russian roulette). Both trace one camera sample; the renderer
//! schedules samples over pixels (Tungsten's split between scheduling and `trace_sample`).

use super::bsdf::{Bsdf, BsdfSample};
use super::camera::Camera;
use super::geometry::{Ray, offset_ray_origin};
use super::light::{LightLiSample, LightSampleContext};
use super::material::{Shading, shade};
use super::sampler::Sampler;
use super::sampling::{CosineSample, balance_heuristic, power_heuristic};
use super::scene::RenderScene;
use glam::{UVec2, Vec2, Vec3A};
use pathfarm_common::film::SampleValue;
use pathfarm_common::job::{LightSampling, MisHeuristic};

/// Path-tracing parameters (`direct` is `path` with two segments and no roulette).
#[derive(Clone, Copy, Debug)]
pub struct PathParams {
    /// Path segments, as Mitsuba counts them: 1 = emitters seen directly, 2 = direct lighting;
    /// 0 = no limit (Russian roulette only).
    pub max_depth: u32,
    /// Scattering events before Russian roulette starts; `u32::MAX` disables it.
    pub rr_depth: u32,
    pub mis: MisHeuristic,
    pub light_sampling: LightSampling,
}

/// Survival probability cap of Russian roulette (Mitsuba's 0.95): even bright paths end.
pub(crate) const RR_MAX_SURVIVAL: f32 = 0.95;

#[inline]
pub(crate) fn mis_weight(mis: MisHeuristic, pdf_this: f32, pdf_other: f32) -> f32 {
    match mis {
        MisHeuristic::Power => power_heuristic(1.0, pdf_this, 1.0, pdf_other),
        MisHeuristic::Balance => balance_heuristic(1.0, pdf_this, 1.0, pdf_other),
        MisHeuristic::Light | MisHeuristic::Bsdf => 1.0,
    }
}

/// The weight of emission found by BSDF sampling (after a bounce of density `prev_bsdf_pdf`),
/// given the light's density for it; emission after a specular bounce (or seen by a camera
/// ray) counts in full.
#[inline]
pub(crate) fn emission_weight(
    specular_bounce: bool,
    mis: MisHeuristic,
    prev_bsdf_pdf: f32,
    light_pdf: impl FnOnce() -> f32,
) -> f32 {
    if specular_bounce {
        return 1.0;
    }
    match mis {
        MisHeuristic::Bsdf => 1.0,
        MisHeuristic::Light => 0.0,
        mis => mis_weight(mis, prev_bsdf_pdf, light_pdf()),
    }
}

/// Next-event estimation at a non-delta vertex: one light sample, weighted against BSDF
/// sampling, at the path's shutter time `time`. Returns the contribution without the path
/// throughput.
pub fn sample_ld(
    scene: &RenderScene,
    p: Vec3A,
    sh: &Shading,
    wo: Vec3A,
    sampler: &mut impl Sampler,
    params: &PathParams,
    time: f32,
) -> Vec3A {
    let u_select = sampler.get_1d();
    let u = sampler.get_2d();
    let Some(nee) = nee_sample(scene, p, sh, wo, u_select, u, params, time) else { return Vec3A::ZERO };
    if !scene.unoccluded_at(p, sh.ng, &nee.ls, time) {
        return Vec3A::ZERO;
    }
    nee.contribution(params)
}

/// A light sample of next-event estimation that can contribute (BSDF value nonzero), before
/// its shadow ray.
#[derive(Clone, Copy, Debug)]
pub struct NeeSample {
    pub ls: LightLiSample,
    /// `f |cos|` toward the light.
    pub f: Vec3A,
    /// Probability of the light's selection.
    pub pmf: f32,
    pub delta: bool,
    /// The BSDF's density toward the light (for the MIS weight; 0 for a delta light, which
    /// has none).
    pub bsdf_pdf: f32,
}

impl NeeSample {
    /// The contribution (without the path throughput) if the shadow ray is unoccluded.
    #[inline]
    pub fn contribution(&self, params: &PathParams) -> Vec3A {
        let (f, ls, pmf) = (self.f, &self.ls, self.pmf);
        let light_pdf = pmf * ls.pdf;
        if self.delta {
            return f * ls.l / pmf;
        }
        let w = mis_weight(params.mis, light_pdf, self.bsdf_pdf);
        f * ls.l * (w / light_pdf)
    }
}

/// The light sample of [`sample_ld`] from its random numbers (`u_select` picks the light, `u`
/// the point on it): `None` where it contributes nothing whatever the shadow ray finds.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn nee_sample(
    scene: &RenderScene,
    p: Vec3A,
    sh: &Shading,
    wo: Vec3A,
    u_select: f32,
    u: Vec2,
    params: &PathParams,
    time: f32,
) -> Option<NeeSample> {
    sh.bsdf.as_ref()?;
    let ctx = LightSampleContext { p, n: sh.ng };
    let light = scene.sample_light_at(&ctx, u_select, u, params.light_sampling, time)?;
    nee_with_light(scene, sh, wo, light, params)
}

/// [`nee_sample`] from its light sample (`RenderScene::sample_light_at`: light index, sample,
/// selection pmf), taken apart so that the wavefront can sample a batch's lights in lanes.
#[inline]
pub fn nee_with_light(
    scene: &RenderScene,
    sh: &Shading,
    wo: Vec3A,
    (index, ls, pmf): (usize, LightLiSample, f32),
    params: &PathParams,
) -> Option<NeeSample> {
    let bsdf = sh.bsdf.as_ref()?;
    let light = &scene.lights[index];
    let delta = light.is_delta();
    // BSDF-only: area lights are found by BSDF sampling instead; delta lights can only be
    // reached by light sampling, so they stay.
    if params.mis == MisHeuristic::Bsdf && !delta {
        return None;
    }
    // Reflection stays on the viewer's side of the geometric surface (no leaks through shading
    // normals); a transmitting BSDF also takes light from the other side.
    let same_side = ls.wi.dot(sh.ng) * wo.dot(sh.ng) > 0.0;
    if ls.l == Vec3A::ZERO || !(same_side || bsdf.bxdf.has_transmission() && ls.wi.dot(sh.ng) != 0.0) {
        return None;
    }
    // The BSDF's density too, where the MIS weight will need it (what the two share is made
    // once).
    let (f, bsdf_pdf) = if delta { (bsdf.f(wo, ls.wi), 0.0) } else { bsdf.f_pdf(wo, ls.wi) };
    let f = f * ls.wi.dot(bsdf.frame.z).abs();
    if f == Vec3A::ZERO {
        return None;
    }
    Some(NeeSample { ls, f, pmf, delta, bsdf_pdf })
}

/// Samples the BSDF for the next path segment (one 1D and one 2D sample, in that order) and
/// returns the sample with its throughput weight `f |cos| / pdf`. A reflection that crosses the
/// geometric surface (wi and wo on different sides of `ng`) is refused, so shading normals cannot
/// leak light; `ng` need not face `wo` (glass keeps its true orientation, and light inside it
/// reflects below `ng`). Shared by every integrator that extends a path by BSDF sampling.
#[inline]
pub fn sample_scatter(bsdf: &Bsdf, ng: Vec3A, wo: Vec3A, sampler: &mut impl Sampler) -> Option<(BsdfSample, Vec3A)> {
    sample_scatter_ahead(bsdf, ng, wo, sampler, None)
}

/// [`sample_scatter`] with a cosine-hemisphere direction computed ahead ([`Bsdf::sample_f_ahead`]).
#[inline]
pub fn sample_scatter_ahead(
    bsdf: &Bsdf,
    ng: Vec3A,
    wo: Vec3A,
    sampler: &mut impl Sampler,
    ahead: Option<&CosineSample>,
) -> Option<(BsdfSample, Vec3A)> {
    let uc = sampler.get_1d();
    let u = sampler.get_2d();
    let bs = bsdf.sample_f_ahead(wo, uc, u, ahead)?;
    // Reflection must stay on the viewer's side of the geometric surface.
    if !bs.is_transmission() && bs.wi.dot(ng) * wo.dot(ng) <= 0.0 {
        return None;
    }
    let weight = bs.f * (bs.wi.dot(bsdf.frame.z).abs() / bs.pdf);
    Some((bs, weight))
}

/// Traces one camera sample through `pixel` at shutter time `time` in [0, 1] (every ray of
/// the path sees the scene at that time; 0 without motion blur) and returns its radiance and
/// AOVs.
pub fn li_path(
    scene: &RenderScene,
    camera: &Camera,
    pixel: UVec2,
    sampler: &mut impl Sampler,
    params: &PathParams,
    time: f32,
) -> SampleValue {
    let mut out = SampleValue::default();
    let mut ray: Ray = camera.sample_ray(pixel, sampler);
    let mut l = Vec3A::ZERO;
    let mut beta = Vec3A::ONE;
    let mut eta_scale = 1.0f32;
    // Emission found by a camera ray or after a specular bounce is counted in full.
    let mut specular_bounce = true;
    let mut prev_bsdf_pdf = 0.0f32;
    let mut prev_ctx = LightSampleContext { p: ray.o, n: Vec3A::ZERO };
    let mut depth = 0u32;
    loop {
        let Some(si) = scene.intersect_at(ray.o, ray.d, f32::INFINITY, time) else {
            // The ray left the scene: the environment is its emitter.
            if let Some((i, env)) = scene.environment() {
                let le = env.le(ray.d);
                if le != Vec3A::ZERO {
                    l += beta
                        * le
                        * emission_weight(specular_bounce, params.mis, prev_bsdf_pdf, || {
                            scene.light_pmf(i) * env.pdf_wi(ray.d)
                        });
                }
            }
            break;
        };
        let wo = -ray.d;
        if depth == 0 {
            out.depth = Some(si.t);
        }
        beta *= scene.transmittance(&si, ray.d);
        let le = scene.emitted_at(&si, wo, time);
        if le != Vec3A::ZERO {
            let w = emission_weight(specular_bounce, params.mis, prev_bsdf_pdf, || {
                scene.light_of_prim(si.prim).map_or(0.0, |i| {
                    scene.light_pmf(i) * scene.light_at(i, time).pdf_li(&prev_ctx, si.p, params.light_sampling)
                })
            });
            l += beta * le * w;
        }
        // The next segment would exceed the depth limit.
        if params.max_depth != 0 && depth + 1 >= params.max_depth {
            if depth == 0 {
                let sh = shade(scene, &si, wo, 0.5);
                out.albedo = sh.albedo.to_array();
                out.normal = sh.ns.to_array();
            }
            break;
        }
        let sh = shade(scene, &si, wo, sampler.get_1d());
        if depth == 0 {
            out.albedo = sh.albedo.to_array();
            out.normal = sh.ns.to_array();
        }
        let Some(bsdf) = &sh.bsdf else { break };
        if !bsdf.is_delta() {
            l += beta * sample_ld(scene, si.p, &sh, wo, sampler, params, time);
        }
        let Some((bs, weight)) = sample_scatter(bsdf, sh.ng, wo, sampler) else { break };
        beta *= weight;
        specular_bounce = bs.is_specular();
        prev_bsdf_pdf = bs.pdf;
        prev_ctx = LightSampleContext { p: si.p, n: sh.ng };
        if bs.is_transmission() {
            eta_scale *= bs.eta * bs.eta;
        }
        depth += 1;
        if !(beta.max_element() > 0.0) || !beta.is_finite() {
            break;
        }
        if depth >= params.rr_depth {
            let u_rr = sampler.get_1d();
            let q = (beta.max_element() * eta_scale).min(RR_MAX_SURVIVAL);
            if u_rr >= q {
                break;
            }
            beta /= q;
        }
        ray = Ray::new(offset_ray_origin(si.p, sh.ng, bs.wi), bs.wi);
    }
    out.radiance = l.to_array();
    out
}
