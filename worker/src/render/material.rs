//! Materials: glTF material + textures at a hit -> a BSDF in the shading frame.
//!
//! One-sided materials (glTF `doubleSided: false`) are black from behind, as in Mitsuba; the
//! surface still blocks light. Double-sided materials flip their normals toward the viewer.
//! Glass (transmission) keeps its true orientation so that entering and leaving differ. glTF
//! transmission without a volume (or thicknessFactor 0) is a thin-walled sheet: no refraction.

use super::bsdf::{Bsdf, Bxdf, Layers};
use super::geometry::Frame;
use super::microfacet::{Fresnel, MicrofacetDistribution, SMOOTH_ALPHA, Sheen};
use super::scene::{RenderScene, SurfaceInteraction, sample_texture};
use glam::{Vec3A, Vec4Swizzles};
use pathfarm_common::scene::MaterialModel;

/// What the integrators need to scatter at a hit.
#[derive(Clone, Debug)]
pub struct Shading {
    /// `None`: the surface reflects nothing toward this side (back of a one-sided material,
    /// unlit material).
    pub bsdf: Option<Bsdf>,
    /// Geometric normal, flipped toward `wo` unless the material transmits.
    pub ng: Vec3A,
    /// Reflectance for the albedo AOV.
    pub albedo: Vec3A,
    /// Shading normal for the normal AOV (world space, toward `wo` for opaque materials).
    pub ns: Vec3A,
}

/// Builds the BSDF at `si` seen from direction `wo` (pointing away from the surface).
/// `u_lobe` picks between glTF's transmission and reflection layers (stochastic mixing).
pub fn shade(scene: &RenderScene, si: &SurfaceInteraction, wo: Vec3A, u_lobe: f32) -> Shading {
    let Some(m) = scene.materials.get(si.material as usize) else {
        return Shading { bsdf: None, ng: si.ng, albedo: Vec3A::ZERO, ns: si.ns };
    };
    let tex = |r: &Option<pathfarm_common::scene::TextureRef>| {
        r.as_ref().map_or(glam::Vec4::ONE, |r| sample_texture(&scene.textures, r, &si.uv))
    };
    // glTF: COLOR_0 multiplies the base colour factor and texture.
    let base = Vec3A::from((m.base_color * tex(&m.base_color_texture) * si.color).xyz());
    let front = si.ng.dot(wo) > 0.0;
    let transmission = m.transmission * tex(&m.transmission_texture).x;
    let is_glass = matches!(m.model, MaterialModel::Gltf) && transmission > 0.0 && u_lobe < transmission;

    if m.unlit || (!front && !m.double_sided && !is_glass) {
        return Shading { bsdf: None, ng: si.ng, albedo: base, ns: si.ns };
    }
    // Orient normals: toward the viewer for opaque surfaces, as modelled for glass.
    let flip = !front && !is_glass;
    let ng = if flip { -si.ng } else { si.ng };
    let mut ns = if flip { -si.ns } else { si.ns };
    if ns.dot(ng) < 0.0 {
        ns = ng;
    }
    // Normal map: perturb the shading normal in the tangent frame.
    if let (Some(nt), Some(t)) = (&m.normal_texture, si.tangent()) {
        let c = sample_texture(&scene.textures, nt, &si.uv);
        let tn = Vec3A::new((2.0 * c.x - 1.0) * m.normal_scale, (2.0 * c.y - 1.0) * m.normal_scale, 2.0 * c.z - 1.0);
        let tangent = Vec3A::from(t.xyz());
        let bitangent = ns.cross(tangent) * t.w;
        let n = (tangent * tn.x + bitangent * tn.y + ns * tn.z).normalize_or_zero();
        if n != Vec3A::ZERO && n.dot(ng) > 0.0 {
            ns = n;
        }
    }
    let frame = match si.tangent() {
        Some(t) => Frame::from_xz(Vec3A::from(t.xyz()), ns),
        None => Frame::from_z(ns),
    };
    // The albedo AOV of the whole material, whichever lobe a smooth glTF surface picked.
    let mut albedo = None;
    let mut layers = None;
    let bxdf = match m.model {
        MaterialModel::Lambert => Bxdf::Lambertian { r: base },
        MaterialModel::Mirror => Bxdf::Mirror { r: base },
        // The lecture's Torrance-Sparrow: the base colour is the normal-incidence reflectance
        // (Schlick), the distribution sets the gloss.
        MaterialModel::Blinn { exponent } => Bxdf::TorranceSparrow {
            r: Vec3A::ONE,
            distribution: MicrofacetDistribution::Blinn { exponent: exponent.max(0.0) },
            fresnel: Fresnel::Schlick { f0: base },
        },
        MaterialModel::AshikhminShirley { exponent_x, exponent_y } => Bxdf::TorranceSparrow {
            r: Vec3A::ONE,
            distribution: MicrofacetDistribution::AshikhminShirley {
                exponent_x: exponent_x.max(0.0),
                exponent_y: exponent_y.max(0.0),
            },
            fresnel: Fresnel::Schlick { f0: base },
        },
        MaterialModel::Gltf if is_glass => {
            // KHR_materials_transmission uses the material's roughness for its microfacets.
            let roughness = (m.roughness * tex(&m.metallic_roughness_texture).y).clamp(0.0, 1.0);
            let alpha = roughness * roughness;
            let eta = m.ior.max(1.0001);
            match (m.thin_walled, alpha >= SMOOTH_ALPHA) {
                (true, true) => Bxdf::RoughThinDielectric { eta, tint: base, alpha },
                (true, false) => Bxdf::ThinDielectric { eta, tint: base },
                (false, true) => Bxdf::RoughDielectric { eta, tint: base, alpha },
                (false, false) => Bxdf::Dielectric { eta, tint: base },
            }
        }
        MaterialModel::Gltf => {
            let mr = tex(&m.metallic_roughness_texture);
            let metallic = (m.metallic * mr.z).clamp(0.0, 1.0);
            let roughness = (m.roughness * mr.y).clamp(0.0, 1.0);
            let specular_factor = m.specular_factor.clamp(0.0, 1.0);
            let cos_o = frame.z.dot(wo);
            // What is left of `u_lobe` after the transmission choice picks a smooth coat's
            // mirror, then a smooth surface's (roughness^2 below SMOOTH_ALPHA) mirror or diffuse
            // lobe.
            let mut u = if transmission > 0.0 { (u_lobe - transmission) / (1.0 - transmission) } else { u_lobe };
            u = u.clamp(0.0, 1.0);
            layers = gltf_layers(m, &tex);
            if let Some(l) = &mut layers
                && l.clearcoat > 0.0
                && l.coat_alpha < SMOOTH_ALPHA
            {
                let p = Layers::coat_mirror_probability(l.clearcoat, cos_o);
                if u < p {
                    let r = Vec3A::splat(l.coat_albedo(cos_o) / p);
                    let b = Bxdf::gltf(base, metallic, roughness, specular_factor);
                    let s = Shading { bsdf: Some(Bsdf::new(frame, Bxdf::Mirror { r })), ng, albedo: b.albedo(), ns };
                    return s;
                }
                u = ((u - p) / (1.0 - p)).clamp(0.0, 1.0);
                l.under_weight = 1.0 / (1.0 - p);
            }
            if metallic == 0.0 && specular_factor == 0.0 {
                // KHR_materials_specular factor 0: no dielectric specular layer.
                Bxdf::Lambertian { r: base }
            } else {
                albedo = Some(Bxdf::gltf(base, metallic, roughness, specular_factor).albedo());
                Bxdf::gltf_lobe(base, metallic, roughness, specular_factor, cos_o, u)
            }
        }
    };
    let albedo = albedo.unwrap_or_else(|| bxdf.albedo());
    Shading { bsdf: Some(Bsdf::new(frame, bxdf).with_layers(layers)), ng, albedo, ns }
}

/// The clearcoat and sheen of an opaque glTF material at a hit, `None` without either.
fn gltf_layers(
    m: &pathfarm_common::scene::Material,
    tex: &dyn Fn(&Option<pathfarm_common::scene::TextureRef>) -> glam::Vec4,
) -> Option<Layers> {
    let clearcoat = if m.clearcoat > 0.0 { (m.clearcoat * tex(&m.clearcoat_texture).x).clamp(0.0, 1.0) } else { 0.0 };
    let sheen_color = if m.sheen_color.max_element() > 0.0 {
        (Vec3A::from(m.sheen_color) * Vec3A::from(tex(&m.sheen_color_texture).xyz())).clamp(Vec3A::ZERO, Vec3A::ONE)
    } else {
        Vec3A::ZERO
    };
    if !(clearcoat > 0.0) && !(sheen_color.max_element() > 0.0) {
        return None;
    }
    let coat_roughness = (m.clearcoat_roughness * tex(&m.clearcoat_roughness_texture).y).clamp(0.0, 1.0);
    let sheen_roughness = (m.sheen_roughness * tex(&m.sheen_roughness_texture).w).clamp(0.0, 1.0);
    Some(Layers {
        clearcoat,
        coat_alpha: coat_roughness * coat_roughness,
        sheen_color,
        sheen: Sheen::new(sheen_roughness),
        under_weight: 1.0,
    })
}
