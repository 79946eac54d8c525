//! The scene as the renderer sees it: world-space triangles in a BVH, the surface data to shade
//! a hit, the lights and the light-selection distribution.

use super::accel::{Accel, Hit, RayQuery, lerp_triangle};
use super::geometry::{offset_ray_origin, shadow_segment};
use super::lambert::LambertLanes;
use super::light::{EnvironmentLight, Light, LightLanes, LightLeSample, LightLiSample, LightSampleContext};
use super::math;
use super::sampler::hash_u64;
use super::sampling::Distribution1D;
use super::wide::SimdLevel;
use glam::{Vec2, Vec3, Vec3A, Vec4};
use pathfarm_common::job::LightSampling;
use pathfarm_common::scene::{AlphaMode, Material, Mesh, PunctualKind, Scene, Texture, TextureRef};
use std::borrow::Cow;

/// Marks a triangle that is not a light.
const NO_LIGHT: u32 = u32::MAX;
/// Most alpha-absent surfaces one ray passes through before the next counts as present.
const MAX_ALPHA_LAYERS: usize = 256;

/// Geometry of a ray hit.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceInteraction {
    pub p: Vec3A,
    pub t: f32,
    /// Geometric normal from the triangle's winding (counter-clockwise front), not flipped.
    pub ng: Vec3A,
    /// Interpolated shading normal (`ng` when the mesh has none), not flipped.
    pub ns: Vec3A,
    pub uv: [Vec2; 2],
    /// Interpolated vertex colour (COLOR_0), white when the mesh has none.
    pub color: glam::Vec4,
    /// Interpolated tangent (xyz) and handedness (w) where `has_tangent` (the mesh has
    /// tangents; read with [`SurfaceInteraction::tangent`]). Not an `Option`: the flag gives
    /// `Option<SurfaceInteraction>` its niche, so a wavefront's surfaces take 128 bytes each
    /// (two cache lines), not 144.
    tangent_xyzw: Vec4,
    has_tangent: bool,
    pub prim: u32,
    pub material: u32,
    /// Barycentrics of vertices 1 and 2.
    pub b1: f32,
    pub b2: f32,
}

impl SurfaceInteraction {
    /// The interpolated tangent (xyz) and handedness (w), when the mesh has tangents.
    #[inline]
    pub fn tangent(&self) -> Option<Vec4> {
        self.has_tangent.then_some(self.tangent_xyzw)
    }
}

/// The tangent's flag keeps an absent surface within a surface's own size: two cache lines
/// (less where glam's vectors are not 16-byte SIMD types).
#[cfg(test)]
#[test]
fn a_surface_takes_two_cache_lines() {
    assert!(std::mem::size_of::<Option<SurfaceInteraction>>() <= 128);
}

/// Per-triangle lookup: which mesh and which triangle of it.
#[derive(Clone, Copy, Debug)]
struct TriRef {
    mesh: u32,
    tri: u32,
}

/// The light samples of a batch of points ([`RenderScene::sample_light_at_many`]): 8 to a
/// lane group, or one at a time.
#[derive(Default)]
pub struct LightBatch {
    lanes: Vec<super::light::LightLaneSamples>,
    /// Per point: the light picked (index, selection pmf), `None` where none was.
    picks: Vec<Option<(u32, f32)>>,
    single: Vec<Option<(usize, LightLiSample, f32)>>,
}

impl LightBatch {
    /// Room for the light samples of `points` points taken in lanes (made once, as the
    /// wavefront's other buffers).
    pub fn with_capacity(points: usize) -> Self {
        Self { lanes: Vec::with_capacity(points.div_ceil(8)), picks: Vec::with_capacity(points), single: Vec::new() }
    }

    /// The `n`-th point's light sample, as [`RenderScene::sample_light_at`] gives it.
    #[inline]
    pub fn get(&self, scene: &RenderScene, n: usize) -> Option<(usize, LightLiSample, f32)> {
        if !self.single.is_empty() {
            return self.single.get(n).copied().flatten();
        }
        let (index, pmf) = (*self.picks.get(n)?)?;
        let light = scene.lights.get(index as usize)?;
        let Light::Triangle { n: normal, le, .. } = *light else { return None };
        let s = self.lanes.get(n / 8)?.get(n % 8, le, normal)?;
        Some((index as usize, scene.on_emitter(light, s)?, pmf))
    }

    /// The `n`-th point's light sample written into lane `lane` of `out` (the values
    /// [`LightBatch::get`] gives, read from the lanes they were made in): whether there is one.
    /// Lanes without one keep old values.
    #[inline(always)]
    pub fn write_lane(&self, scene: &RenderScene, n: usize, out: &mut LambertLanes, lane: usize) -> bool {
        let lane = lane & 7;
        if scene.has_alpha || scene.has_emission_texture || !self.single.is_empty() {
            // Alpha and emission textures act on each sample (`on_emitter`).
            let Some((_, ls, pmf)) = self.get(scene, n) else { return false };
            out.ls_l.set(lane, ls.l);
            out.ls_wi.set(lane, ls.wi);
            out.ls_pdf[lane] = ls.pdf;
            out.pmf[lane] = pmf;
            out.p_light.set(lane, ls.p_light);
            // Triangle lights' samples all have their normal.
            out.n_light.set(lane, ls.n_light.unwrap_or(Vec3A::ZERO));
            return true;
        }
        let Some(Some((index, pmf))) = self.picks.get(n).copied() else { return false };
        let Some(&Light::Triangle { n: normal, le, .. }) = scene.lights.get(index as usize) else { return false };
        let Some(s) = self.lanes.get(n / 8) else { return false };
        let k = n % 8;
        if s.ok & (1 << k) == 0 {
            return false;
        }
        out.ls_l.set(lane, le);
        out.ls_wi.set(lane, s.wi.get(k));
        out.p_light.set(lane, s.p.get(k));
        out.ls_pdf[lane] = s.pdf[k];
        out.pmf[lane] = pmf;
        out.n_light.set(lane, normal);
        true
    }
}

/// The render-side scene.
pub struct RenderScene {
    accel: Accel,
    tris: Vec<TriRef>,
    /// Each triangle's geometric normal in a static scene ([`RenderScene::geometric_normal`], as
    /// a hit would compute it): read, not recomputed, by every hit. Empty where things move.
    tri_ng: Vec<Vec3A>,
    pub meshes: Vec<Mesh>,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub lights: Vec<Light>,
    light_distr: Distribution1D,
    /// Light index of each triangle, or [`NO_LIGHT`].
    tri_light: Vec<u32>,
    /// Light index of the environment, if the job has one.
    environment: Option<usize>,
    /// Whether some mesh has a MASK or BLEND material (rays then test alpha at hits).
    has_alpha: bool,
    /// Whether some material has an emission texture (else every area light's factor is 1).
    has_emission_texture: bool,
    /// Whether some material attenuates light inside it (else every transmittance is 1).
    has_attenuation: bool,
    /// Whether every light is a triangle and nothing moves (lights can be sampled in lanes).
    triangle_lights_only: bool,
    /// Per material: whether it shades as a bare Lambertian ([`super::lambert::is_plain_lambert`]).
    plain_lambert: Vec<bool>,
    pub center: Vec3A,
    pub radius: f32,
    /// Motion blur: where things are at shutter close (`None`: nothing moves).
    motion: Option<Motion>,
}

/// The scene at shutter close; geometry moves linearly from `meshes` to `close` over the shutter
/// interval, whose times are in [0, 1].
struct Motion {
    /// Same meshes, triangles and vertex counts as `RenderScene::meshes`.
    close: Vec<Mesh>,
    /// Each light's triangle at shutter close (area lights; `None` for the others).
    light_close: Vec<Option<[Vec3A; 3]>>,
}

/// Looks up a texture reference at a hit.
pub fn sample_texture(textures: &[Texture], r: &TextureRef, uv: &[Vec2; 2]) -> Vec4 {
    let uv = uv[(r.tex_coord as usize).min(1)];
    textures.get(r.texture).map_or(Vec4::ONE, |t| t.sample(r.transform.apply(uv)))
}

/// The environment of a job, before the scene's bounds are known.
#[derive(Clone, Debug)]
pub struct EnvironmentSpec {
    pub image: Option<pathfarm_common::scene::EnvironmentImage>,
    /// Radiance factor: the colour (or white for an image) x the intensity.
    pub scale: Vec3A,
    pub rotation_deg: f32,
}

impl RenderScene {
    pub fn new(scene: &Scene) -> Self {
        Self::build(scene, None, None)
    }

    /// The render-side scene lit also by `environment`.
    pub fn with_environment(scene: &Scene, environment: Option<EnvironmentSpec>) -> Self {
        Self::build(scene, None, environment)
    }

    /// A scene whose geometry moves from `open` (shutter open, time 0) to `close` (time 1): both
    /// must come from posing one file (same meshes, triangles and vertex counts). Lights,
    /// materials and textures are those of `open`. When nothing moves this is [`Self::new`].
    pub fn new_moving(open: &Scene, close: &Scene, environment: Option<EnvironmentSpec>) -> Result<Self, String> {
        if open.meshes.len() != close.meshes.len() {
            return Err(format!(
                "the scene has {} meshes at shutter open and {} at shutter close",
                open.meshes.len(),
                close.meshes.len()
            ));
        }
        for (a, b) in open.meshes.iter().zip(&close.meshes) {
            if a.indices != b.indices || a.positions.len() != b.positions.len() {
                return Err(format!("mesh {:?} changes its triangles during the shutter", a.name));
            }
        }
        let moves = open
            .meshes
            .iter()
            .zip(&close.meshes)
            .any(|(a, b)| a.positions != b.positions || a.normals != b.normals || a.tangents != b.tangents);
        Ok(Self::build(open, moves.then_some(close), environment))
    }

    fn build(scene: &Scene, close: Option<&Scene>, environment: Option<EnvironmentSpec>) -> Self {
        let mut world_tris = Vec::with_capacity(scene.triangle_count());
        let mut tris = Vec::with_capacity(scene.triangle_count());
        for (mi, mesh) in scene.meshes.iter().enumerate() {
            for (ti, idx) in mesh.indices.iter().enumerate() {
                let v = idx.map(|i| Vec3A::from(mesh.positions.get(i as usize).copied().unwrap_or_default()));
                world_tris.push(v);
                tris.push(TriRef { mesh: mi as u32, tri: ti as u32 });
            }
        }
        let close_tris: Option<Vec<[Vec3A; 3]>> = close.map(|c| {
            tris.iter()
                .zip(&world_tris)
                .map(|(tr, open)| {
                    let mesh = &c.meshes[tr.mesh as usize];
                    let idx = mesh.indices.get(tr.tri as usize).copied().unwrap_or_default();
                    let at = |k: usize| mesh.positions.get(idx[k] as usize).copied().map(Vec3A::from);
                    match (at(0), at(1), at(2)) {
                        (Some(a), Some(b), Some(c)) => [a, b, c],
                        _ => *open,
                    }
                })
                .collect()
        });
        let (lo, hi) = scene.bounds().unwrap_or_default();
        let center = Vec3A::from((lo + hi) * 0.5);
        let radius = (Vec3A::from(hi - lo).length() * 0.5).max(1e-3);

        let mut lights = Vec::new();
        let mut tri_light = vec![NO_LIGHT; world_tris.len()];
        for (prim, (v, tr)) in world_tris.iter().zip(&tris).enumerate() {
            let mesh = &scene.meshes[tr.mesh as usize];
            let Some(material) = scene.materials.get(mesh.material) else { continue };
            let le = if material.unlit {
                Vec3A::from(material.base_color.truncate())
            } else {
                Vec3A::from(material.emissive)
            };
            if le.max_element() <= 0.0 {
                continue;
            }
            let cross = (v[1] - v[0]).cross(v[2] - v[0]);
            let area = 0.5 * cross.length();
            if !(area > 0.0) {
                continue;
            }
            tri_light[prim] = lights.len() as u32;
            lights.push(Light::Triangle {
                prim: prim as u32,
                v: *v,
                n: cross.normalize(),
                area,
                le,
                two_sided: material.double_sided || material.unlit,
            });
        }
        for pl in &scene.lights {
            let i = Vec3A::from(pl.intensity);
            let p = Vec3A::from(pl.position);
            let dir = Vec3A::from(pl.direction).normalize_or(-Vec3A::Z);
            lights.push(match pl.kind {
                PunctualKind::Point => Light::Point { p, i },
                PunctualKind::Spot { inner_cone, outer_cone } => {
                    Light::Spot { p, i, axis: dir, cos_inner: math::cos(inner_cone), cos_outer: math::cos(outer_cone) }
                }
                PunctualKind::Directional => Light::Directional { w: dir, e: i, radius },
            });
        }
        let environment = environment.map(|e| {
            lights.push(Light::Environment(std::sync::Arc::new(EnvironmentLight::new(
                e.image,
                e.scale,
                e.rotation_deg,
                center,
                radius,
            ))));
            lights.len() - 1
        });
        let weights: Vec<f32> = lights.iter().map(|l| luminance(l.power())).collect();
        let has_alpha = scene
            .meshes
            .iter()
            .any(|m| scene.materials.get(m.material).is_some_and(|mat| mat.alpha_mode != AlphaMode::Opaque));
        let has_emission_texture = scene
            .materials
            .iter()
            .any(|m| if m.unlit { m.base_color_texture.is_some() } else { m.emissive_texture.is_some() });
        let triangle_lights_only =
            close.is_none() && !lights.is_empty() && lights.iter().all(|l| matches!(l, Light::Triangle { .. }));
        let motion = close.zip(close_tris.as_ref()).map(|(c, ct)| Motion {
            close: c.meshes.clone(),
            light_close: lights
                .iter()
                .map(|l| match l {
                    Light::Triangle { prim, .. } => ct.get(*prim as usize).copied(),
                    _ => None,
                })
                .collect(),
        });
        let accel = match &close_tris {
            Some(ct) => Accel::new_moving(&world_tris, ct),
            None => Accel::new(&world_tris),
        };
        // Only static scenes read them (a moving mesh's normal is made at the ray's time).
        let tri_ng = match close {
            None => world_tris.iter().map(|&p| Self::geometric_normal(p)).collect(),
            Some(_) => Vec::new(),
        };
        Self {
            accel,
            tris,
            tri_ng,
            meshes: scene.meshes.clone(),
            materials: scene.materials.clone(),
            textures: scene.textures.clone(),
            lights,
            light_distr: Distribution1D::new(&weights),
            tri_light,
            environment,
            has_alpha,
            has_emission_texture,
            has_attenuation: scene.materials.iter().any(|m| m.attenuation != glam::Vec3::ZERO),
            triangle_lights_only,
            plain_lambert: scene.materials.iter().map(super::lambert::is_plain_lambert).collect(),
            center,
            radius,
            motion,
        }
    }

    /// Whether batches of rays go through the BVH in sorted packets now (small scenes, and
    /// larger ones while it pays: [`Accel::sorts_rays`]).
    pub fn sorts_rays(&self) -> bool {
        self.accel.sorts_rays()
    }

    /// Whether some material shades as a bare Lambertian BSDF ([`RenderScene::plain_lambert_at`]).
    pub fn has_plain_lambert(&self) -> bool {
        self.plain_lambert.iter().any(|&p| p)
    }

    /// The reflectance of a hit whose material shades as a bare Lambertian BSDF
    /// ([`super::lambert`]) seen from `wo`: `shade`'s base colour (factor, no texture, times the
    /// hit's colour). `None` for other materials, hits with tangents (their frame is not the
    /// normal's alone), and the back of one-sided materials (no BSDF there).
    ///
    /// Tried on an Intel Xeon with AVX-512 and dropped: each plain material's base colour factor
    /// and sidedness cached in one per-material entry (one lookup, not two): `tiny` 412,450,036
    /// -> 413,275,516 instructions, `tiny long` 1.003x the time (median of 11 interleaved pairs,
    /// quartiles 0.992-1.016): no gain.
    #[inline]
    pub fn plain_lambert_at(&self, si: &SurfaceInteraction, wo: Vec3A) -> Option<Vec3A> {
        let m = self.materials.get(si.material as usize)?;
        let plain = self.plain_lambert.get(si.material as usize).copied().unwrap_or(false);
        if !plain || si.has_tangent || !(m.double_sided || si.ng.dot(wo) > 0.0) {
            return None;
        }
        use glam::Vec4Swizzles;
        Some(Vec3A::from((m.base_color * glam::Vec4::ONE * si.color).xyz()))
    }

    /// Whether geometry moves during the shutter.
    pub fn has_motion(&self) -> bool {
        self.motion.is_some()
    }

    /// Light `index` at shutter time `time` in [0, 1]: a moving area light's triangle, normal
    /// and area at that time; every other light as it is.
    pub fn light_at(&self, index: usize, time: f32) -> Cow<'_, Light> {
        let light = &self.lights[index];
        let close = self.motion.as_ref().and_then(|m| m.light_close.get(index).copied().flatten());
        match (light, close) {
            (Light::Triangle { prim, v, le, two_sided, .. }, Some(vc)) => {
                let v = lerp_triangle(v, &vc, time);
                let cross = (v[1] - v[0]).cross(v[2] - v[0]);
                Cow::Owned(Light::Triangle {
                    prim: *prim,
                    v,
                    n: cross.normalize_or(Vec3A::Z),
                    area: (0.5 * cross.length()).max(f32::MIN_POSITIVE),
                    le: *le,
                    two_sided: *two_sided,
                })
            }
            _ => Cow::Borrowed(light),
        }
    }

    /// The environment light: (light index, light).
    pub fn environment(&self) -> Option<(usize, &EnvironmentLight)> {
        let i = self.environment?;
        match self.lights.get(i) {
            Some(Light::Environment(env)) => Some((i, env)),
            _ => None,
        }
    }

    /// Radiance arriving along a ray that leaves the scene in direction `d` (zero without an
    /// environment).
    pub fn environment_le(&self, d: Vec3A) -> Vec3A {
        self.environment().map_or(Vec3A::ZERO, |(_, env)| env.le(d))
    }

    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    /// The SIMD level of the ray queries (see [`super::wide`]).
    pub fn simd_level(&self) -> super::wide::SimdLevel {
        self.accel.simd_level()
    }

    /// The proof of AVX2 (at the scene's level) where the scene runs its AVX2 kernels.
    pub fn avx2(&self) -> Option<super::wide::Avx2> {
        super::wide::Avx2::at(self.simd_level())
    }

    /// Uses the best level up to `level` that the CPU supports for the scene's kernels; returns
    /// the level in use.
    pub fn set_simd_level(&mut self, level: super::wide::SimdLevel) -> super::wide::SimdLevel {
        self.accel.set_simd_level(level)
    }

    /// Closest hit along a ray (at shutter open).
    pub fn intersect(&self, o: Vec3A, d: Vec3A, t_max: f32) -> Option<SurfaceInteraction> {
        self.intersect_at(o, d, t_max, 0.0)
    }

    /// Closest hit along a ray at shutter time `time` in [0, 1]: moving geometry (positions,
    /// normals, tangents) is lerped between shutter open and close; surfaces that alpha makes
    /// absent at the hit point are passed through (glTF MASK and BLEND).
    pub fn intersect_at(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> Option<SurfaceInteraction> {
        let hit = self.accel.intersect_at(o, d, t_max, time)?;
        self.surface_through_alpha(&hit, o, d, t_max, time)
    }

    /// The surface a ray `o + t d` (`t < t_max`, at `time`) meets, given its closest hit `hit`:
    /// that one where it is present, else the first present one behind the cut-out layers
    /// (alpha), each found by a closest-hit query from just beyond the last.
    fn surface_through_alpha(
        &self,
        hit: &Hit,
        o: Vec3A,
        d: Vec3A,
        t_max: f32,
        time: f32,
    ) -> Option<SurfaceInteraction> {
        if !self.has_alpha || self.present(hit.prim, hit.b1, hit.b2) {
            return Some(self.surface(hit, time));
        }
        let (mut o, mut t_max, mut t0) = (o, t_max, 0.0f32);
        let mut si = self.surface(hit, time);
        for _ in 0..MAX_ALPHA_LAYERS {
            // Continue from just beyond the absent surface; t stays measured from the origin.
            let next = offset_ray_origin(si.p, si.ng, d);
            let step = (next - o).dot(d) / d.length_squared();
            (o, t0, t_max) = (next, t0 + step, t_max - step);
            let hit = self.accel.intersect_at(o, d, t_max, time)?;
            si = self.surface(&hit, time);
            si.t += t0;
            if self.present(hit.prim, hit.b1, hit.b2) {
                return Some(si);
            }
        }
        // So many cut-out layers in a row: treat the last as present.
        Some(si)
    }

    /// The closest hits of a batch of rays, in order: each exactly
    /// [`RenderScene::intersect_at`] of its ray (alpha included).
    pub fn intersect_many(
        &self,
        rays: &[RayQuery],
        hits: &mut Vec<Option<Hit>>,
        out: &mut Vec<Option<SurfaceInteraction>>,
    ) {
        self.accel.intersect_many(rays, hits);
        // Each slot is written in place: a mapped `Option` would be built apart and copied
        // whole (about 150 bytes, a `memcpy` call per ray). The last batch's slots are reused
        // as they are (each is written below, a miss's `None` too: made `None` first, every
        // slot was written twice, 1% of the Cornell box's time in perf).
        out.resize(rays.len(), None);
        if self.has_alpha {
            // The batch's closest hits as above; a ray whose hit is cut out goes on alone.
            for ((h, r), slot) in hits.iter().zip(rays).zip(out.iter_mut()) {
                *slot = match h {
                    Some(h) => self.surface_through_alpha(h, r.o, r.d, r.t_max, r.time),
                    None => None,
                };
            }
            return;
        }
        self.surfaces_into(hits, rays, out);
    }

    /// Whether each ray of a batch is blocked by something present (alpha considered), in order:
    /// each exactly [`RenderScene::occluded_at`] of its ray.
    pub fn occluded_many(&self, rays: &[RayQuery], blocked: &mut Vec<bool>) {
        if self.has_alpha {
            // `occluded_at`'s closest hits for the batch at once; cut-out ones go on alone.
            let mut hits = Vec::with_capacity(rays.len());
            self.accel.intersect_many(rays, &mut hits);
            blocked.clear();
            blocked.extend(hits.iter().zip(rays).map(|(h, r)| h.is_some_and(|h| self.blocks(&h, r))));
            return;
        }
        self.accel.occluded_many(rays, blocked);
    }

    /// Whether anything present (alpha considered) lies on the ray before `t_max` at `time`.
    #[inline]
    pub fn occluded_at(&self, o: Vec3A, d: Vec3A, t_max: f32, time: f32) -> bool {
        if !self.has_alpha {
            return self.accel.occluded_at(o, d, t_max, time);
        }
        let r = RayQuery { o, d, t_max, time };
        self.accel.intersect_at(o, d, t_max, time).is_some_and(|h| self.blocks(&h, &r))
    }

    /// Whether the ray `r`, whose closest hit is `hit`, meets something present: `hit` itself,
    /// or a surface behind its cut-out layers (alpha).
    fn blocks(&self, hit: &Hit, r: &RayQuery) -> bool {
        self.present(hit.prim, hit.b1, hit.b2) || self.surface_through_alpha(hit, r.o, r.d, r.t_max, r.time).is_some()
    }

    /// Whether triangle `prim` is present at barycentrics (b1, b2): always for opaque materials;
    /// MASK: alpha >= cutoff; BLEND: with probability alpha, decided by a hash of the point (so
    /// every ray, camera, shadow or light path, sees the same surface).
    pub fn present(&self, prim: u32, b1: f32, b2: f32) -> bool {
        let Some(tr) = self.tris.get(prim as usize) else { return true };
        let mesh = &self.meshes[tr.mesh as usize];
        let Some(m) = self.materials.get(mesh.material) else { return true };
        if m.alpha_mode == AlphaMode::Opaque {
            return true;
        }
        let idx = mesh.indices[tr.tri as usize].map(|i| i as usize);
        let b = [1.0 - b1 - b2, b1, b2];
        let mut alpha = m.base_color.w;
        if let Some(t) = &m.base_color_texture {
            let uv = |set: &Option<Vec<Vec2>>| {
                set.as_ref()
                    .and_then(|uv| Some(*uv.get(idx[0])? * b[0] + *uv.get(idx[1])? * b[1] + *uv.get(idx[2])? * b[2]))
                    .unwrap_or(Vec2::ZERO)
            };
            alpha *= sample_texture(&self.textures, t, &[uv(&mesh.uv0), uv(&mesh.uv1)]).w;
        }
        if let Some(c) = &mesh.colors {
            alpha *= (0..3).map(|k| c.get(idx[k]).map_or(1.0, |c| c.w) * b[k]).sum::<f32>();
        }
        match m.alpha_mode {
            AlphaMode::Mask { cutoff } => alpha >= cutoff,
            AlphaMode::Blend => {
                let h = hash_u64(&[u64::from(prim), u64::from(b1.to_bits()), u64::from(b2.to_bits())]);
                ((h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)) < alpha
            }
            AlphaMode::Opaque => true,
        }
    }

    /// The surface data of a BVH hit at shutter time `time`.
    #[inline(never)]
    fn surface(&self, hit: &Hit, time: f32) -> SurfaceInteraction {
        self.surface_value(hit, time)
    }

    /// [`RenderScene::surface`] of each hit of `hits` (at its ray's time) written into its slot
    /// of `out` in place, `None` into a miss's (a value returned and then pushed is built apart
    /// and copied whole: a `memcpy` call per hit, 3% of the Cornell box's time), in one loop.
    ///
    /// Tried on an AMD EPYC with AVX-512 (Zen 4) and dropped: the hits on meshes with only
    /// positions and normals gathered 8 at a time and their points and normalized shading
    /// normals made in lanes (the same bits; the normal's square root and division are half of
    /// this loop's cycles). The gathering costs more than the lanes save: this function's
    /// instructions went from 37.7M to 42.5M on the bench's `tiny` (50.1M with the vertices
    /// returned by value), `tiny long` 1.018x the time (median of 9 interleaved pairs). Tried on
    /// an AVX2-only AMD EPYC (Zen 3) and dropped: the normalization deferred to a loop of its own
    /// per 64 hits (so that hits' square roots and divisions overlap; perf had a third of this
    /// function's cycles waiting on them): `tiny` 417.9M -> 423.6M instructions, `tiny long`
    /// 0.968x the time (median of 15 interleaved pairs, quartiles 0.912-1.080) but 1.022x by the
    /// fastest of each; this function's share of perf's samples 7.65% -> 7.22%.
    #[inline(never)]
    fn surfaces_into(&self, hits: &[Option<Hit>], rays: &[RayQuery], out: &mut [Option<SurfaceInteraction>]) {
        for ((h, r), slot) in hits.iter().zip(rays).zip(out.iter_mut()) {
            match h {
                Some(h) => *slot = Some(self.surface_value(h, r.time)),
                None => *slot = None,
            }
        }
    }

    #[inline(always)]
    fn surface_value(&self, hit: &Hit, time: f32) -> SurfaceInteraction {
        let tr = self.tris[hit.prim as usize];
        let mesh = &self.meshes[tr.mesh as usize];
        let close = self.motion.as_ref().and_then(|m| m.close.get(tr.mesh as usize));
        let idx = mesh.indices[tr.tri as usize].map(|i| i as usize);
        let (b1, b2) = (hit.b1, hit.b2);
        let b0 = 1.0 - b1 - b2;
        // Where the mesh does not move, its positions and normals as they are (the same values
        // as `at_time` gives them, without its checks).
        let ng = self.tri_ng.get(hit.prim as usize).filter(|_| close.is_none());
        let (p, ng, ns) = match ng.and_then(|&ng| Self::static_geometry(mesh, idx, [b0, b1, b2], ng)) {
            Some(geometry) => geometry,
            None => Self::moving_geometry(mesh, close, idx, [b0, b1, b2], time),
        };
        let interp_uv = |uv: &Option<Vec<Vec2>>| {
            uv.as_ref()
                .and_then(|uv| Some(*uv.get(idx[0])? * b0 + *uv.get(idx[1])? * b1 + *uv.get(idx[2])? * b2))
                .unwrap_or(Vec2::ZERO)
        };
        let tangent = mesh.tangents.as_ref().and_then(|t| {
            let (a, b, c) = (t.get(idx[0])?, t.get(idx[1])?, t.get(idx[2])?);
            let xyz = a.truncate() * b0 + b.truncate() * b1 + c.truncate() * b2;
            let ct = close.and_then(|c| c.tangents.as_ref());
            let xyz = match ct.and_then(|t| Some((t.get(idx[0])?, t.get(idx[1])?, t.get(idx[2])?))) {
                Some((ca, cb, cc)) => xyz.lerp(ca.truncate() * b0 + cb.truncate() * b1 + cc.truncate() * b2, time),
                None => xyz,
            };
            Some(xyz.extend(if a.w < 0.0 { -1.0 } else { 1.0 }))
        });
        SurfaceInteraction {
            p,
            t: hit.t,
            ng,
            ns,
            uv: [interp_uv(&mesh.uv0), interp_uv(&mesh.uv1)],
            color: mesh
                .colors
                .as_ref()
                .and_then(|c| Some(*c.get(idx[0])? * b0 + *c.get(idx[1])? * b1 + *c.get(idx[2])? * b2))
                .unwrap_or(glam::Vec4::ONE),
            tangent_xyzw: tangent.unwrap_or(Vec4::ZERO),
            has_tangent: tangent.is_some(),
            prim: hit.prim,
            material: mesh.material as u32,
            b1,
            b2,
        }
    }

    /// A hit's point, geometric normal and shading normal (`ng` where the mesh has none, or
    /// they interpolate to zero) at barycentrics `b` of triangle `idx` of a mesh that does not
    /// move: `None` where a position index is out of range (then
    /// [`RenderScene::moving_geometry`] decides, as before).
    #[inline(always)]
    fn static_geometry(mesh: &Mesh, idx: [usize; 3], b: [f32; 3], ng: Vec3A) -> Option<(Vec3A, Vec3A, Vec3A)> {
        let pos = &mesh.positions;
        let p = [Vec3A::from(*pos.get(idx[0])?), Vec3A::from(*pos.get(idx[1])?), Vec3A::from(*pos.get(idx[2])?)];
        let n = mesh.normals.as_ref().and_then(|n| {
            Some([Vec3A::from(*n.get(idx[0])?), Vec3A::from(*n.get(idx[1])?), Vec3A::from(*n.get(idx[2])?)])
        });
        Some(Self::geometry(p, n, b, ng))
    }

    /// [`RenderScene::static_geometry`] at shutter time `time` of a mesh whose shutter-close
    /// pose is `close` (missing vertices count as the origin, missing normals as none).
    #[inline(always)]
    fn moving_geometry(
        mesh: &Mesh,
        close: Option<&Mesh>,
        idx: [usize; 3],
        b: [f32; 3],
        time: f32,
    ) -> (Vec3A, Vec3A, Vec3A) {
        // A vertex attribute at the ray's time (the open pose when nothing moves).
        let at_time = |open: Option<Vec3>, close: Option<Vec3>| -> Option<Vec3A> {
            let a = Vec3A::from(open?);
            Some(match close {
                Some(c) => a.lerp(Vec3A::from(c), time),
                None => a,
            })
        };
        let pos = |i: usize| {
            let c = close.and_then(|c| c.positions.get(idx[i]).copied());
            at_time(mesh.positions.get(idx[i]).copied(), c).unwrap_or_default()
        };
        let n = mesh.normals.as_ref().and_then(|n| {
            let cn = close.and_then(|c| c.normals.as_ref());
            let get = |i: usize| at_time(n.get(idx[i]).copied(), cn.and_then(|cn| cn.get(idx[i]).copied()));
            Some([get(0)?, get(1)?, get(2)?])
        });
        let p = [pos(0), pos(1), pos(2)];
        Self::geometry(p, n, b, Self::geometric_normal(p))
    }

    /// The geometric normal of the triangle with vertices `p` (+Z where it has no area).
    #[inline(always)]
    fn geometric_normal(p: [Vec3A; 3]) -> Vec3A {
        (p[1] - p[0]).cross(p[2] - p[0]).normalize_or(Vec3A::Z)
    }

    /// The point and shading normal at barycentrics `b` of the triangle with vertices `p`, vertex
    /// normals `n` and geometric normal `ng` ([`RenderScene::geometric_normal`]), and `ng` (the
    /// shading normal where there are no vertex normals or they interpolate to zero).
    #[inline(always)]
    fn geometry(p: [Vec3A; 3], n: Option<[Vec3A; 3]>, b: [f32; 3], ng: Vec3A) -> (Vec3A, Vec3A, Vec3A) {
        let [b0, b1, b2] = b;
        // Interpolate the hit point from the vertices: more accurate than o + t d.
        let point = p[0] * b0 + p[1] * b1 + p[2] * b2;
        let ns = n
            .map(|n| (n[0] * b0 + n[1] * b1 + n[2] * b2).normalize_or_zero())
            .filter(|n| *n != Vec3A::ZERO)
            .unwrap_or(ng);
        (point, ng, ns)
    }

    /// Beer-Lambert transmittance of the segment a ray in direction `d` travelled to reach
    /// `si`: when it leaves through the back of a surface whose material has
    /// KHR_materials_volume attenuation, the segment ran inside that object (closed meshes,
    /// outward winding, no nesting), and `exp(-sigma t)` of it is left.
    #[inline]
    pub fn transmittance(&self, si: &SurfaceInteraction, d: Vec3A) -> Vec3A {
        if !self.has_attenuation {
            return Vec3A::ONE;
        }
        let Some(m) = self.materials.get(si.material as usize) else { return Vec3A::ONE };
        if m.attenuation == glam::Vec3::ZERO || si.ng.dot(d) <= 0.0 {
            return Vec3A::ONE;
        }
        beer_lambert(Vec3A::from(m.attenuation) * (si.t * d.length()))
    }

    /// Whether the segment between two surface points (or a point and a light) is blocked.
    pub fn unoccluded(&self, p0: Vec3A, n0: Vec3A, s: &LightLiSample) -> bool {
        self.unoccluded_at(p0, n0, s, 0.0)
    }

    /// [`Self::unoccluded`] at shutter time `time`.
    pub fn unoccluded_at(&self, p0: Vec3A, n0: Vec3A, s: &LightLiSample, time: f32) -> bool {
        let (o, d, t_max) = Self::shadow_ray(p0, n0, s);
        !self.occluded_at(o, d, t_max, time)
    }

    /// The shadow ray (origin, direction, max t) of a light sample `s` seen from `p0` (normal
    /// `n0`): unbounded toward a light at infinity, else the offset segment to the light.
    #[inline]
    pub fn shadow_ray(p0: Vec3A, n0: Vec3A, s: &LightLiSample) -> (Vec3A, Vec3A, f32) {
        if s.infinite {
            (offset_ray_origin(p0, n0, s.wi), s.wi, f32::INFINITY)
        } else {
            shadow_segment(p0, n0, s.p_light, s.n_light)
        }
    }

    /// Whether `p1` (normal `n1`) is visible from `p0` (normal `n0`).
    pub fn visible(&self, p0: Vec3A, n0: Vec3A, p1: Vec3A, n1: Option<Vec3A>) -> bool {
        self.visible_at(p0, n0, p1, n1, 0.0)
    }

    /// [`Self::visible`] at shutter time `time`.
    pub fn visible_at(&self, p0: Vec3A, n0: Vec3A, p1: Vec3A, n1: Option<Vec3A>, time: f32) -> bool {
        let (o, d, t_max) = shadow_segment(p0, n0, p1, n1);
        !self.occluded_at(o, d, t_max, time)
    }

    /// Emission-texture factor of an area light's triangle at barycentrics `b`.
    #[inline]
    fn emission_texture(&self, prim: u32, b: [f32; 3]) -> Vec3A {
        if !self.has_emission_texture {
            return Vec3A::ONE;
        }
        self.emission_texture_at(prim, b)
    }

    #[inline(never)]
    fn emission_texture_at(&self, prim: u32, b: [f32; 3]) -> Vec3A {
        let tr = self.tris[prim as usize];
        let mesh = &self.meshes[tr.mesh as usize];
        let Some(m) = self.materials.get(mesh.material) else { return Vec3A::ONE };
        let tex = if m.unlit { m.base_color_texture } else { m.emissive_texture };
        let Some(tex) = tex else { return Vec3A::ONE };
        let idx = mesh.indices[tr.tri as usize].map(|i| i as usize);
        let uv = |set: &Option<Vec<Vec2>>| {
            set.as_ref()
                .and_then(|uv| Some(*uv.get(idx[0])? * b[0] + *uv.get(idx[1])? * b[1] + *uv.get(idx[2])? * b[2]))
                .unwrap_or(Vec2::ZERO)
        };
        Vec3A::from(sample_texture(&self.textures, &tex, &[uv(&mesh.uv0), uv(&mesh.uv1)]).truncate())
    }

    /// Picks a light by power and samples it: (light index, sample, selection pmf).
    pub fn sample_light(
        &self,
        ctx: &LightSampleContext,
        u_select: f32,
        u: Vec2,
        mode: LightSampling,
    ) -> Option<(usize, LightLiSample, f32)> {
        self.sample_light_at(ctx, u_select, u, mode, 0.0)
    }

    /// [`Self::sample_light`] at shutter time `time` (moving area lights where they are then).
    pub fn sample_light_at(
        &self,
        ctx: &LightSampleContext,
        u_select: f32,
        u: Vec2,
        mode: LightSampling,
        time: f32,
    ) -> Option<(usize, LightLiSample, f32)> {
        if self.lights.is_empty() {
            return None;
        }
        let (index, pmf, _) = self.light_distr.sample(u_select);
        if !(pmf > 0.0) {
            return None;
        }
        let light = self.light_at(index, time);
        let s = light.sample_li(ctx, u, mode)?;
        Some((index, self.on_emitter(&light, s)?, pmf))
    }

    /// A light sample of `light` as the emitter gives it: cut out by alpha, times the emission
    /// texture.
    #[inline]
    fn on_emitter(&self, light: &Light, mut s: LightLiSample) -> Option<LightLiSample> {
        if let Light::Triangle { prim, .. } = *light {
            // A point that alpha cuts out of an emitter emits nothing.
            if self.has_alpha && !self.present(prim, s.b[1], s.b[2]) {
                return None;
            }
            s.l *= self.emission_texture(prim, s.b);
        }
        Some(s)
    }

    /// Whether every light is a triangle and nothing moves: every light sample is then a point on
    /// an area light with its normal (no delta, no light at infinity).
    pub fn triangle_lights_only(&self) -> bool {
        self.triangle_lights_only
    }

    /// Whether [`RenderScene::sample_light_at_many`] samples this scene's lights in lanes: every
    /// light a triangle, none moving, and a CPU with AVX2 (by area or by solid angle).
    pub fn samples_lights_in_lanes(&self, mode: LightSampling) -> bool {
        let _ = mode;
        self.triangle_lights_only && self.simd_level() != SimdLevel::Baseline
    }

    /// [`RenderScene::sample_light_at`] of each (point, light selection number, point number,
    /// time), kept in `out` in order (read back with [`LightBatch::get`]; a light sample reads
    /// nothing of the point's surface): the triangle geometry 8 lanes at a time, the same bits
    /// (`TriangleSample` is written once for both). Where
    /// [`RenderScene::samples_lights_in_lanes`] does not hold, one at a time.
    ///
    /// Tried on an Intel Xeon with AVX-512 and dropped: the light picked by a `Distribution1D`
    /// call that skips the remapped number (unused here): `tiny` 412,450,036 -> 412,447,322
    /// instructions, `tiny long` 1.001x the time (median of 11 interleaved pairs, quartiles
    /// 0.997-1.017): no gain.
    pub fn sample_light_at_many(
        &self,
        queries: impl ExactSizeIterator<Item = (Vec3A, f32, Vec2, f32)>,
        mode: LightSampling,
        out: &mut LightBatch,
    ) {
        // `out.lanes` is overwritten in place.
        out.picks.clear();
        out.single.clear();
        let lanes = self.avx2().filter(|_| self.samples_lights_in_lanes(mode));
        let Some(avx2) = lanes else {
            out.single.extend(queries.map(|(p, u_select, u, time)| {
                self.sample_light_at(&LightSampleContext { p, n: Vec3A::ZERO }, u_select, u, mode, time)
            }));
            return;
        };
        let mut queries = queries.peekable();
        let mut chunk = 0;
        // Reused from chunk to chunk (a fresh one zeroed 768 bytes per 8 points, 0.4% of the
        // Cornell box's instructions): lanes a chunk does not set keep old values, whose
        // results are never read (`get` looks up `picks` first).
        let mut lanes = LightLanes::default();
        while queries.peek().is_some() {
            // (Nothing moves here: the query's time changes nothing.)
            for (lane, (p, u_select, u, _)) in queries.by_ref().take(8).enumerate() {
                let (index, pmf, _) = self.light_distr.sample(u_select);
                let light = self.lights.get(index).filter(|_| pmf > 0.0);
                let pick = match light {
                    Some(Light::Triangle { v, n, area, two_sided, .. }) => {
                        lanes.set(lane, v, *n, *area, *two_sided, p, u);
                        Some((index as u32, pmf))
                    }
                    _ => None,
                };
                out.picks.push(pick);
            }
            // Written in place, into the last batch's entries where there are (the entries past
            // this batch's are never read: `get` looks up `picks` first).
            if out.lanes.len() <= chunk {
                out.lanes.push(super::light::LightLaneSamples::default());
            }
            avx2.triangle_samples(&lanes, mode == LightSampling::SolidAngle, &mut out.lanes[chunk]);
            chunk += 1;
        }
    }

    /// Picks a light by power: (light index, selection pmf).
    pub fn pick_light(&self, u: f32) -> Option<(usize, f32)> {
        if self.lights.is_empty() {
            return None;
        }
        let (index, pmf, _) = self.light_distr.sample(u);
        (pmf > 0.0).then_some((index, pmf))
    }

    /// Samples an emitted ray of light `index` (pbrt's `SampleLe`), emission texture applied.
    pub fn sample_le(&self, index: usize, u1: Vec2, u2: Vec2) -> Option<LightLeSample> {
        self.sample_le_at(index, u1, u2, 0.0)
    }

    /// [`Self::sample_le`] at shutter time `time` (a moving area light where it is then).
    pub fn sample_le_at(&self, index: usize, u1: Vec2, u2: Vec2, time: f32) -> Option<LightLeSample> {
        if index >= self.lights.len() {
            return None;
        }
        let light = self.light_at(index, time);
        let mut s = light.sample_le(u1, u2, self.center)?;
        if let Light::Triangle { prim, .. } = *light {
            if self.has_alpha && !self.present(prim, s.b[1], s.b[2]) {
                return None;
            }
            s.l *= self.emission_texture(prim, s.b);
        }
        (s.l.max_element() > 0.0 && s.pdf_pos > 0.0 && s.pdf_dir > 0.0).then_some(s)
    }

    /// Light index of an emissive triangle.
    pub fn light_of_prim(&self, prim: u32) -> Option<usize> {
        self.tri_light.get(prim as usize).copied().filter(|&l| l != NO_LIGHT).map(|l| l as usize)
    }

    /// Selection probability of light `index`.
    pub fn light_pmf(&self, index: usize) -> f32 {
        self.light_distr.pmf(index)
    }

    /// Radiance emitted by the surface at `si` toward `w` (away from the surface).
    pub fn emitted(&self, si: &SurfaceInteraction, w: Vec3A) -> Vec3A {
        self.emitted_at(si, w, 0.0)
    }

    /// [`Self::emitted`] for a hit at shutter time `time`. Inline where the hit is on no light
    /// (most hits: one lookup), out of line where it is.
    #[inline]
    pub fn emitted_at(&self, si: &SurfaceInteraction, w: Vec3A, time: f32) -> Vec3A {
        match self.light_of_prim(si.prim) {
            Some(l) => self.emitted_by(l, si, w, time),
            None => Vec3A::ZERO,
        }
    }

    /// The radiance light `l` emits from the hit `si` toward `w` at `time`.
    #[inline(never)]
    fn emitted_by(&self, l: usize, si: &SurfaceInteraction, w: Vec3A, time: f32) -> Vec3A {
        let le = self.light_at(l, time).l(w);
        if le == Vec3A::ZERO { le } else { le * self.emission_texture(si.prim, [1.0 - si.b1 - si.b2, si.b1, si.b2]) }
    }
}

/// Relative luminance of linear sRGB.
#[inline]
pub fn luminance(c: Vec3A) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// `exp(-sigma)` per channel; out of line, as few materials have an attenuation.
#[inline(never)]
fn beer_lambert(sigma: Vec3A) -> Vec3A {
    Vec3A::new(math::exp(-sigma.x), math::exp(-sigma.y), math::exp(-sigma.z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::chi2::TestRng;
    use crate::render::sampling::{MAX_SPHERICAL_SAMPLE_AREA, MIN_SPHERICAL_SAMPLE_AREA, triangle_solid_angle};
    use pathfarm_common::job::LightSampling;
    use pathfarm_common::scene::demo::{GltfBuilder, emitter};
    use pathfarm_common::scene::{LoadOptions, load_scene_from_slice};

    /// 4096 small emissive triangles facing down from y = 1 over [-2, 2]^2: 64 meshes of 64
    /// triangles, mesh `k` of radiance `10^(4 k / 63)` (1 to 10^4), triangle `j` of it with edges
    /// `0.0008 (1 + j)` (within its grid cell of 0.0625), so the lights' powers span 7 decades.
    fn many_lights() -> RenderScene {
        lights_scene(false)
    }

    /// [`many_lights`], with the odd meshes' lights two-sided where `two_sided`.
    fn lights_scene(two_sided: bool) -> RenderScene {
        let mut b = GltfBuilder::new();
        for k in 0..64 {
            let le = 10f32.powf(4.0 * k as f32 / 63.0);
            let mut material = emitter(&format!("e{k}"), Vec3::ZERO, Vec3::splat(le));
            if two_sided && k % 2 == 1 {
                material["doubleSided"] = true.into();
            }
            let m = b.material(material);
            let (mut p, mut n, mut idx) = (Vec::new(), Vec::new(), Vec::new());
            for j in 0..64u32 {
                // Scatter the lights over the grid (1031 is odd: a permutation of the 4096
                // cells), so that bright and dim, large and small lights mix everywhere.
                let cell = (j * 64 + k as u32) * 1031 % 4096;
                let (x, z) =
                    (-2.0 + 4.0 * ((cell % 64) as f32 + 0.5) / 64.0, -2.0 + 4.0 * ((cell / 64) as f32 + 0.5) / 64.0);
                let s = 0.0008 * (1.0 + j as f32);
                let base = p.len() as u32;
                // Counter-clockwise seen from below: the normal is -Y.
                p.extend([Vec3::new(x, 1.0, z), Vec3::new(x + s, 1.0, z), Vec3::new(x, 1.0, z + s)]);
                n.extend([Vec3::NEG_Y; 3]);
                idx.extend([base, base + 1, base + 2]);
            }
            b.mesh(&format!("lights {k}"), &p, &n, &idx, m);
        }
        b.camera(Vec3::new(0.0, 0.5, 3.0), Vec3::ZERO, Vec3::Y, 0.7, 1.0);
        let scene = load_scene_from_slice(&b.to_glb(), "lights.glb", None, &LoadOptions::default()).expect("loads");
        RenderScene::new(&scene)
    }

    /// Light samples taken 8 lanes at a time (`sample_light_at_many`) are the one-at-a-time
    /// samples, bit for bit, by area and by solid angle: from points below the lights, beside
    /// them, above them (behind one-sided lights), on their plane and at their vertices (zero
    /// distance), near and far (solid angles in and out of the range sampled by solid angle),
    /// with one-sided and two-sided lights.
    #[test]
    fn light_samples_in_lanes_are_the_single_samples() {
        for two_sided in [false, true] {
            let scene = lights_scene(two_sided);
            let any_two_sided = scene.lights.iter().any(|l| matches!(l, Light::Triangle { two_sided: true, .. }));
            assert_eq!(any_two_sided, two_sided);
            light_samples_in_lanes_match(&scene);
        }
    }

    fn light_samples_in_lanes_match(scene: &RenderScene) {
        for mode in [LightSampling::Area, LightSampling::SolidAngle] {
            light_samples_in_lanes_match_in(scene, mode);
        }
    }

    fn light_samples_in_lanes_match_in(scene: &RenderScene, mode: LightSampling) {
        if !scene.samples_lights_in_lanes(mode) {
            eprintln!("this CPU has no AVX2: no lanes to compare");
            return;
        }
        let Light::Triangle { v: corner, .. } = scene.lights[17] else { panic!("a triangle light") };
        let mut rng = TestRng::new(2200);
        let mut queries = Vec::new();
        for i in 0..8003 {
            let (x, z) = (rng.uniform() * 5.0 - 2.5, rng.uniform() * 5.0 - 2.5);
            let p = match i % 5 {
                0 => Vec3A::new(x, rng.uniform() * 0.9, z),
                1 => Vec3A::new(x, 1.0 + rng.uniform(), z),
                2 => Vec3A::new(x, 1.0, z),
                3 => corner[i % 3],
                _ => Vec3A::new(x * 3.0, rng.uniform() * 4.0 - 2.0, z * 3.0),
            };
            // The point's numbers: random, equal (the warp's two halves meet), and 0 and 1.
            let u = match i % 7 {
                0 => Vec2::splat(rng.uniform()),
                1 => Vec2::new(0.0, rng.uniform()),
                2 => Vec2::new(rng.uniform(), 0.0),
                3 => Vec2::new(1.0 - f32::EPSILON / 2.0, rng.uniform()),
                _ => rng.uniform_2d(),
            };
            queries.push((p, rng.uniform(), u, 0.0));
        }
        let bits = |s: &Option<(usize, LightLiSample, f32)>| {
            s.map(|(i, l, pmf)| {
                let v = |v: Vec3A| v.to_array().map(f32::to_bits);
                (
                    i,
                    v(l.l),
                    v(l.wi),
                    l.pdf.to_bits(),
                    v(l.p_light),
                    l.n_light.map(v),
                    l.b.map(f32::to_bits),
                    pmf.to_bits(),
                )
            })
        };
        let mut got = LightBatch::default();
        scene.sample_light_at_many(queries.iter().copied(), mode, &mut got);
        assert!(got.get(scene, queries.len()).is_none());
        let (mut found, mut by_solid_angle) = (0, 0);
        for (n, &(p, u_select, u, time)) in queries.iter().enumerate() {
            let ctx = LightSampleContext { p, n: Vec3A::ZERO };
            let want = scene.sample_light_at(&ctx, u_select, u, mode, time);
            assert_eq!(bits(&got.get(scene, n)), bits(&want), "{mode:?}: {p} {u_select} {u}");
            found += usize::from(want.is_some());
            if let Some((i, ..)) = want
                && let Light::Triangle { v, .. } = scene.lights[i]
                && (MIN_SPHERICAL_SAMPLE_AREA..MAX_SPHERICAL_SAMPLE_AREA).contains(&triangle_solid_angle(v, p))
            {
                by_solid_angle += 1;
            }
        }
        assert!(found > queries.len() / 4 && found < queries.len() * 3 / 4, "{found} samples of {}", queries.len());
        // Both strategies are met (about 7% of the samples by solid angle: the lights are small,
        // most of them seen from afar).
        assert!(by_solid_angle > found / 20 && by_solid_angle < found * 19 / 20, "{by_solid_angle} of {found}");
    }

    #[test]
    fn light_selection_follows_power_and_beats_uniform() {
        // The pmf of every light is its power's luminance over the total (relative 1e-3, plus
        // 1e-7 for the f32 CDF the smallest shares are differences of), and
        // picking by stratified u hits each light as often as its pmf says (within one of 1e6
        // strata). The next-event estimate of the irradiance at the origin (normal +Y, no
        // occluders) with power selection and with uniform selection agree in mean (4 sigma),
        // and power selection's variance is at least 8x lower (measured: 1.71e5 vs 2.06e6, 12.0x;
        // area sampling of each triangle). 4e5 samples each, seed 2100.
        let scene = many_lights();
        assert_eq!(scene.lights.len(), 4096);
        let powers: Vec<f64> = scene.lights.iter().map(|l| f64::from(luminance(l.power()))).collect();
        let total: f64 = powers.iter().sum();
        let (lo, hi) = powers.iter().fold((f64::MAX, 0.0f64), |(a, b), &p| (a.min(p), b.max(p)));
        assert!(hi / lo > 1e7, "powers span {:.1e}", hi / lo);
        for (i, p) in powers.iter().enumerate() {
            let pmf = f64::from(scene.light_pmf(i));
            assert!(
                (pmf - p / total).abs() <= 1e-3 * p / total + 1e-7,
                "light {i}: pmf {pmf:e}, power share {:e}",
                p / total
            );
        }
        let strata = 1_000_000usize;
        let mut hits = vec![0usize; scene.lights.len()];
        for s in 0..strata {
            let (i, _) = scene.pick_light((s as f32 + 0.5) / strata as f32).expect("a light");
            hits[i] += 1;
        }
        for (i, &h) in hits.iter().enumerate() {
            let expected = f64::from(scene.light_pmf(i)) * strata as f64;
            assert!(
                (h as f64 - expected).abs() <= 2.0 + 1e-3 * expected,
                "light {i}: {h} picks, {expected:.1} expected"
            );
        }

        let ctx = LightSampleContext { p: Vec3A::ZERO, n: Vec3A::Y };
        let estimate = |uniform: bool, rng: &mut TestRng| {
            let n = scene.lights.len();
            let (mut sum, mut sum2) = (0.0f64, 0.0f64);
            let samples = 400_000;
            for _ in 0..samples {
                let u = rng.uniform();
                let (i, pmf) = if uniform {
                    (((u * n as f32) as usize).min(n - 1), 1.0 / n as f32)
                } else {
                    scene.pick_light(u).expect("a light")
                };
                let v = scene.lights[i]
                    .sample_li(&ctx, rng.uniform_2d(), LightSampling::Area)
                    .map_or(0.0, |ls| f64::from(luminance(ls.l) * ls.wi.y.max(0.0) / (ls.pdf * pmf)));
                sum += v;
                sum2 += v * v;
            }
            let mean = sum / samples as f64;
            let var = (sum2 / samples as f64 - mean * mean).max(0.0);
            (mean, var, (var / samples as f64).sqrt())
        };
        let mut rng = TestRng::new(2100);
        let (mp, vp, sp) = estimate(false, &mut rng);
        let (mu, vu, su) = estimate(true, &mut rng);
        eprintln!(
            "irradiance: power {mp:.4} (variance {vp:.4e}), uniform {mu:.4} (variance {vu:.4e}), ratio {:.1}",
            vu / vp
        );
        assert!((mp - mu).abs() <= 4.0 * (sp * sp + su * su).sqrt(), "power {mp} +- {sp}, uniform {mu} +- {su}");
        assert!(vu > 8.0 * vp, "uniform variance {vu:e} vs power {vp:e}");
    }
}
