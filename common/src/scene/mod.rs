//! The scene model: what the renderer needs from a glTF file, flattened to world space.
//!
//! `load` turns a glTF 2.0 file (`.glb`, `.gltf` with files beside it, or data URIs) into a
//! [`Scene`]. Every mesh instance is baked to world space (one [`Mesh`] per primitive per node
//! instance, morph targets and skins applied); materials, textures, cameras and punctual lights
//! keep glTF's meaning, with units documented in README.md ("Units"). A file with animations is
//! loaded posed at t = 0 and keeps what [`Scene::posed`] needs to pose it at any other time
//! (`anim`; README.md "Animation").

pub mod anim;
pub mod bundle;
pub mod demo;
mod environment;
mod error;
mod load;
mod texture;

pub use environment::{EnvironmentImage, MAX_ENVIRONMENT_PIXELS, load_environment, load_job_environment};
pub use error::SceneError;
pub use load::{LoadOptions, MAX_COORDINATE, load_scene, load_scene_from_slice};
pub use texture::{Texture, TextureTransform, WrapMode};

use glam::{Mat4, Vec2, Vec3, Vec4};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// A loaded scene, flattened to world space.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    pub meshes: Vec<Mesh>,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    /// In node traversal order (depth first, children in file order), so `cameras[0]` is the
    /// first camera met; empty when the file has none (see [`default_camera`]).
    pub cameras: Vec<Camera>,
    /// In node traversal order, like `cameras`.
    pub lights: Vec<PunctualLight>,
    /// Non-fatal problems (skipped primitives, dangling textures...), each naming the element.
    pub warnings: Vec<String>,
    /// The file's animations and what posing needs (`None` for a still scene); see
    /// [`Scene::posed`].
    pub animation: Option<Arc<anim::Animation>>,
}

/// One triangle mesh in world space (one glTF primitive of one node instance).
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// `mesh 3 primitive 1 (node 7 "Chair")`, for messages.
    pub name: String,
    pub positions: Vec<Vec3>,
    /// World-space shading normals (normalized); `None` -> geometric normals are used.
    pub normals: Option<Vec<Vec3>>,
    /// World-space tangents, `w` = handedness (MikkTSpace convention); present when the material
    /// has a normal map (read from the file or generated).
    pub tangents: Option<Vec<Vec4>>,
    /// TEXCOORD_0 and TEXCOORD_1 when present.
    pub uv0: Option<Vec<Vec2>>,
    pub uv1: Option<Vec<Vec2>>,
    /// COLOR_0 (linear RGBA; RGB files get alpha 1): multiplies the base colour.
    pub colors: Option<Vec<Vec4>>,
    /// Triangles as vertex indices (non-indexed primitives get 0, 1, 2, ...).
    pub indices: Vec<[u32; 3]>,
    /// Index into `Scene::materials` (a default material is appended when a primitive has none).
    pub material: usize,
}

/// Which reflection model a material uses. glTF's metallic-roughness model is the default;
/// the lecture's models are chosen with material `extras`: `{"pathfarm": {"model": ...}}`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum MaterialModel {
    /// glTF 2.0 metallic-roughness (GGX), with transmission and ior when present.
    #[default]
    Gltf,
    /// Pure Lambertian with the base colour.
    Lambert,
    /// Torrance-Sparrow with the normalized Blinn distribution, `D = (e+2)/(2 pi) cos^e`.
    Blinn { exponent: f32 },
    /// Torrance-Sparrow with the Ashikhmin-Shirley anisotropic distribution.
    AshikhminShirley { exponent_x: f32, exponent_y: f32 },
    /// Perfect mirror tinted by the base colour.
    Mirror,
}

/// A texture reference of a material: texture index, UV set and optional transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureRef {
    /// Index into `Scene::textures`.
    pub texture: usize,
    /// 0 or 1.
    pub tex_coord: u32,
    pub transform: TextureTransform,
}

/// A glTF material, in linear units.
#[derive(Clone, Debug)]
pub struct Material {
    pub name: String,
    pub model: MaterialModel,
    /// Linear RGBA base colour factor.
    pub base_color: Vec4,
    /// sRGB-decoded to linear when loaded.
    pub base_color_texture: Option<TextureRef>,
    pub metallic: f32,
    pub roughness: f32,
    /// glTF channels: G = roughness, B = metallic (linear).
    pub metallic_roughness_texture: Option<TextureRef>,
    /// Emitted radiance = emissive factor x KHR_materials_emissive_strength (linear).
    pub emissive: Vec3,
    /// sRGB-decoded to linear; multiplies `emissive`.
    pub emissive_texture: Option<TextureRef>,
    pub normal_texture: Option<TextureRef>,
    pub normal_scale: f32,
    /// KHR_materials_transmission factor (0 = opaque).
    pub transmission: f32,
    pub transmission_texture: Option<TextureRef>,
    /// KHR_materials_ior (default 1.5).
    pub ior: f32,
    /// KHR_materials_specular specularFactor (default 1); 0 removes the dielectric specular
    /// layer, leaving a Lambertian material.
    pub specular_factor: f32,
    /// KHR_materials_unlit: emits its base colour, reflects nothing.
    pub unlit: bool,
    /// glTF doubleSided. One-sided materials are black from behind and emit only in front
    /// (Mitsuba's convention); the surface still blocks light.
    pub double_sided: bool,
    /// glTF alphaMode, from the alpha of base colour factor x texture x vertex colour.
    pub alpha_mode: AlphaMode,
    /// KHR_materials_volume: Beer-Lambert attenuation coefficient inside a transmissive object,
    /// per scene unit, `-ln(attenuationColor) / attenuationDistance` (zero: clear).
    pub attenuation: Vec3,
    /// glTF's thin-walled transmission: without KHR_materials_volume, or with thicknessFactor 0,
    /// a transmissive surface is an infinitely thin sheet: light passes straight through it,
    /// tinted by the base colour, and is not refracted. `false` when the volume has a thickness:
    /// the mesh bounds a solid that refracts.
    pub thin_walled: bool,
    /// KHR_materials_clearcoat: a GGX dielectric coat of index 1.5 over the material, of weight
    /// `clearcoat` x texture (R) and roughness `clearcoat_roughness` x texture (G); 0: no coat.
    pub clearcoat: f32,
    pub clearcoat_texture: Option<TextureRef>,
    pub clearcoat_roughness: f32,
    pub clearcoat_roughness_texture: Option<TextureRef>,
    /// KHR_materials_sheen: colour (linear; texture sRGB-decoded, RGB) and roughness (texture A)
    /// of a Charlie sheen over the material; colour 0: no sheen.
    pub sheen_color: Vec3,
    pub sheen_color_texture: Option<TextureRef>,
    pub sheen_roughness: f32,
    pub sheen_roughness_texture: Option<TextureRef>,
}

/// glTF `alphaMode`: how the base colour's alpha makes a surface transparent to every ray.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum AlphaMode {
    /// Alpha is ignored.
    #[default]
    Opaque,
    /// Opaque where alpha >= `cutoff` (glTF's alphaCutoff, default 0.5), absent elsewhere.
    Mask { cutoff: f32 },
    /// Stochastic transparency: each surface point is present with probability alpha.
    Blend,
}

impl Default for Material {
    fn default() -> Self {
        // glTF's default material: white, fully metallic, fully rough.
        Self {
            name: "default".into(),
            model: MaterialModel::Gltf,
            base_color: Vec4::ONE,
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_texture: None,
            emissive: Vec3::ZERO,
            emissive_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            transmission: 0.0,
            transmission_texture: None,
            ior: 1.5,
            specular_factor: 1.0,
            unlit: false,
            double_sided: false,
            alpha_mode: AlphaMode::Opaque,
            attenuation: Vec3::ZERO,
            thin_walled: true,
            clearcoat: 0.0,
            clearcoat_texture: None,
            clearcoat_roughness: 0.0,
            clearcoat_roughness_texture: None,
            sheen_color: Vec3::ZERO,
            sheen_color_texture: None,
            sheen_roughness: 0.0,
            sheen_roughness_texture: None,
        }
    }
}

/// Camera projection, as in glTF.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// Vertical field of view in radians; `aspect` from the file if given.
    Perspective { yfov: f32, aspect: Option<f32> },
    /// Half extents of the view volume.
    Orthographic { xmag: f32, ymag: f32 },
}

/// A camera; it looks down its local -Z with +Y up (glTF convention).
#[derive(Clone, Debug)]
pub struct Camera {
    pub name: String,
    pub world_from_camera: Mat4,
    pub projection: Projection,
}

/// KHR_lights_punctual light types.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PunctualKind {
    Point,
    /// Cone angles in radians from the axis.
    Spot {
        inner_cone: f32,
        outer_cone: f32,
    },
    Directional,
}

/// Luminous efficacy (lm/W) at which glTF's photometric light units become our radiometric
/// scale: `intensity` in cd (point, spot) / 683 = radiant intensity (W/sr), lux (directional) /
/// 683 = irradiance (W/m^2). Blender's glTF exporter writes lights with this factor (its default
/// lighting mode: W / 4 pi x 683 -> cd, W/m^2 x 683 -> lux), so a Blender scene renders as
/// bright as in Cycles (`clients/blender/tests/brightness.py`). Emission is not photometric:
/// `emissiveFactor x emissiveStrength` is radiance as is. See README.md ("Units").
pub const LUMENS_PER_WATT: f32 = 683.0;

/// A KHR_lights_punctual light in world space, in radiometric units ([`LUMENS_PER_WATT`]).
#[derive(Clone, Debug)]
pub struct PunctualLight {
    pub name: String,
    pub kind: PunctualKind,
    /// Linear RGB colour x radiant intensity (W/sr; point, spot) or irradiance (W/m^2;
    /// directional): glTF's `color x intensity / LUMENS_PER_WATT`.
    pub intensity: Vec3,
    pub position: Vec3,
    /// Direction the light points to (spot axis, directional light's travel direction), normalized.
    pub direction: Vec3,
    pub range: Option<f32>,
}

/// The loader's warning for a scene in which nothing emits light (see [`Scene::has_emitters`]).
/// A job's warning when its scene has no light ([`NO_LIGHT_WARNING`]) and it sets no environment.
pub const DARK_JOB_WARNING: &str =
    "the scene has no lights or emissive materials and the job sets no environment: every pixel will be black";

pub const NO_LIGHT_WARNING: &str =
    "the scene has no lights or emissive materials: it renders black unless the job sets an environment";

impl Scene {
    /// The scene at animation time `t` seconds with the animations named in `names` playing
    /// (all of them for `None`, none for an empty list): node transforms, morph weights, skins,
    /// and the camera, light and material properties of `KHR_animation_pointer`. A still scene
    /// is returned as it is; naming an animation the scene lacks is an error that lists the
    /// available ones.
    pub fn posed(&self, t: f32, names: Option<&[String]>) -> Result<Scene, SceneError> {
        let Some(anim) = &self.animation else {
            if let Some(name) = names.and_then(|n| n.first()) {
                let message = anim::unknown_animation(name, &[]);
                return Err(SceneError::Invalid { file: "scene".into(), message });
            }
            return Ok(self.clone());
        };
        let mut posed = load::load_posed(anim, t, names)?;
        let mut warnings = self.warnings.clone();
        for w in posed.warnings.drain(..) {
            if !warnings.contains(&w) {
                warnings.push(w);
            }
        }
        posed.warnings = warnings;
        Ok(posed)
    }

    /// Names of the scene's animations, in file order (unnamed ones are `animation N`).
    pub fn animation_names(&self) -> Vec<&str> {
        self.animation.as_ref().map_or_else(Vec::new, |a| a.clips().iter().map(|c| c.name.as_str()).collect())
    }

    /// Whether anything emits light: a punctual light with nonzero intensity, or a mesh whose
    /// material has a nonzero emissive factor or is unlit (it emits its base colour).
    pub fn has_emitters(&self) -> bool {
        self.lights.iter().any(|l| l.intensity.max_element() > 0.0)
            || self.meshes.iter().any(|m| {
                self.materials
                    .get(m.material)
                    .is_some_and(|mat| !m.indices.is_empty() && (mat.emissive.max_element() > 0.0 || mat.unlit))
            })
    }

    /// Axis-aligned bounds of all mesh vertices; `None` for an empty scene.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut it = self.meshes.iter().flat_map(|m| m.positions.iter().copied());
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
    }

    /// Total number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.meshes.iter().map(|m| m.indices.len()).sum()
    }
}

/// A camera that frames the whole scene (used when the file has none): perspective, 40 degrees
/// vertical field of view, looking at the bounds' centre along the bounds' thinnest axis, so
/// the view shows the scene's two widest extents (a wall is seen face on, a terrain from above);
/// ties keep the +Z side looking down -Z. Far enough that the bounding sphere fits in both
/// directions for the given aspect ratio (width / height).
pub fn default_camera(scene: &Scene, aspect: f32) -> Camera {
    default_camera_for_bounds(scene.bounds(), aspect)
}

/// [`default_camera`] for bounds (`None`: the cube [-1, 1]^3).
pub fn default_camera_for_bounds(bounds: Option<(Vec3, Vec3)>, aspect: f32) -> Camera {
    let yfov = 40f32.to_radians();
    let (lo, hi) = bounds.unwrap_or((Vec3::splat(-1.0), Vec3::splat(1.0)));
    let center = (lo + hi) * 0.5;
    let extent = hi - lo;
    let radius = (extent.length() * 0.5).max(1e-3);
    let aspect = if aspect.is_finite() && aspect > 0.0 { aspect } else { 1.0 };
    // The narrower of the two half-angles decides the distance.
    let half = (yfov * 0.5).min((aspect * (yfov * 0.5).tan()).atan());
    let distance = radius / half.sin();
    // Thinnest axis, by a clear margin (1%) over Z; the camera's local +Z points back to it.
    let thinner = |a: f32, b: f32| a < b * 0.99;
    let (back, rotation) = if thinner(extent.x, extent.z) && extent.x <= extent.y {
        (Vec3::X, glam::Quat::from_rotation_y(std::f32::consts::FRAC_PI_2))
    } else if thinner(extent.y, extent.z) && thinner(extent.y, extent.x) {
        // From above, +X to the right, -Z up the image.
        (Vec3::Y, glam::Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2))
    } else {
        (Vec3::Z, glam::Quat::IDENTITY)
    };
    Camera {
        name: "default".into(),
        world_from_camera: Mat4::from_rotation_translation(rotation, center + back * distance),
        projection: Projection::Perspective { yfov, aspect: Some(aspect) },
    }
}
