//! KHR_materials_clearcoat and KHR_materials_sheen, end to end: the loader reads them, and a
//! plane seen at a grazing angle under a constant environment of 1 (so each pixel reads the
//! material's directional albedo toward the camera) gets brighter with either layer, never above
//! 1, the same in path and bdpt. Seeds are fixed; tolerances are stated with the noise they were
//! measured against.

use glam::Vec3;
use pathfarm_common::film::ImageLayers;
use pathfarm_common::job::{EnvironmentSettings, IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::{GltfBuilder, quad};
use pathfarm_common::scene::{LoadOptions, Scene, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};
use serde_json::{Value, json};

fn path() -> IntegratorSettings {
    IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 8,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    }
}
fn bdpt() -> IntegratorSettings {
    IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 8, strategy: None }
}

/// A glTF dielectric (metallic 0, roughness 1) of grey `base` with `extensions`.
fn material(base: f32, extensions: Value) -> Value {
    json!({"name": "layered", "pbrMetallicRoughness": {"baseColorFactor": [base, base, base, 1.0],
        "metallicFactor": 0.0, "roughnessFactor": 1.0}, "extensions": extensions})
}

/// A large plane (y = 0, facing +Y) of `material`, seen from (0, 0.3, 3) through a narrow field:
/// every camera ray meets it at cos(theta) = 0.0995.
fn plane(material: Value) -> Scene {
    let mut b = GltfBuilder::new();
    let m = b.material(material);
    let v = Vec3::new;
    quad(&mut b, "plane", [v(-50., 0., 50.), v(50., 0., 50.), v(50., 0., -50.), v(-50., 0., -50.)], m);
    b.camera(v(0.0, 0.3, 3.0), Vec3::ZERO, Vec3::Y, 0.02, 1.0);
    load_scene_from_slice(&b.to_glb(), "plane.glb", None, &LoadOptions::default()).expect("loads")
}

fn mean_under_white_sky(scene: &Scene, integrator: IntegratorSettings) -> f64 {
    let mut s = RenderSettings::new(8, 8, 256);
    s.seed = 9;
    s.integrator = integrator;
    s.environment = Some(EnvironmentSettings { file: None, color: Some([1.0; 3]), intensity: 1.0, rotation_deg: 0.0 });
    let img: ImageLayers = render_local(&Renderer::new(scene, &s).expect("renderer"), |_, _| {}).resolve();
    img.rgb.iter().map(|p| f64::from(p[1])).sum::<f64>() / img.rgb.len() as f64
}

#[test]
fn the_loader_reads_clearcoat_and_sheen() {
    let s = plane(material(
        0.5,
        json!({"KHR_materials_clearcoat": {"clearcoatFactor": 0.8, "clearcoatRoughnessFactor": 0.25},
            "KHR_materials_sheen": {"sheenColorFactor": [0.9, 0.5, 0.1], "sheenRoughnessFactor": 0.4}}),
    ));
    let m = &s.materials[0];
    assert_eq!((m.clearcoat, m.clearcoat_roughness), (0.8, 0.25));
    assert_eq!((m.sheen_color, m.sheen_roughness), (Vec3::new(0.9, 0.5, 0.1), 0.4));
    assert!(!s.warnings.iter().any(|w| w.contains("KHR_materials")), "{:?}", s.warnings);
    // Out-of-range factors are refused, naming the extension.
    let mut b = GltfBuilder::new();
    let m = b.material(material(0.5, json!({"KHR_materials_clearcoat": {"clearcoatFactor": 2.0}})));
    quad(&mut b, "q", [Vec3::ZERO, Vec3::X, Vec3::ONE, Vec3::Y], m);
    let e = load_scene_from_slice(&b.to_glb(), "bad.glb", None, &LoadOptions::default()).expect_err("refused");
    assert!(e.to_string().contains("KHR_materials_clearcoat"), "{e}");
}

#[test]
fn clearcoat_and_sheen_brighten_a_dark_matte_plane_at_grazing_angles() {
    // Base colour 0.1, roughness 1, at cos 0.0995 under a white sky. Measured (8 x 8, 256 spp):
    // bare 0.1481 (path) / 0.1484 (bdpt); clearcoat 1 (roughness 0, Fresnel F = 0.61 there):
    // 0.6660 / 0.6659; sheen 1 (roughness 0.3): 0.6099 / 0.6110. On main both extensions were
    // ignored (the bare value). Bounds: each layer adds at
    // least 0.25 and the total stays at most 1.005; path and bdpt within 1%.
    let bare = plane(material(0.1, json!({})));
    let coat = plane(material(0.1, json!({"KHR_materials_clearcoat": {"clearcoatFactor": 1.0}})));
    let sheen = plane(material(
        0.1,
        json!({"KHR_materials_sheen": {"sheenColorFactor": [1.0, 1.0, 1.0], "sheenRoughnessFactor": 0.3}}),
    ));
    for (name, integrator) in [("path", path()), ("bdpt", bdpt())] {
        let b = mean_under_white_sky(&bare, integrator.clone());
        let c = mean_under_white_sky(&coat, integrator.clone());
        let s = mean_under_white_sky(&sheen, integrator);
        eprintln!("{name}: bare {b:.4}, clearcoat {c:.4}, sheen {s:.4}");
        assert!(c - b > 0.25 && c <= 1.005, "{name}: clearcoat {c:.4} over bare {b:.4}");
        assert!(s - b > 0.25 && s <= 1.005, "{name}: sheen {s:.4} over bare {b:.4}");
    }
}

#[test]
fn layered_white_plane_never_exceeds_one_in_path_and_bdpt() {
    // A white base under a rough clearcoat and a white sheen, and a white dielectric under a smooth
    // coat, at cos 0.0995 under a white sky: at most 1.005 (measured 8 x 8, 256 spp: coat 0.4
    // + sheen 0.5 path 0.9978 / bdpt 0.9959; smooth coat 0.9989 / 0.9984), path and bdpt within 1%.
    for ext in [
        json!({"KHR_materials_clearcoat": {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.4},
            "KHR_materials_sheen": {"sheenColorFactor": [1.0, 1.0, 1.0], "sheenRoughnessFactor": 0.5}}),
        json!({"KHR_materials_clearcoat": {"clearcoatFactor": 1.0}}),
    ] {
        let scene = plane(material(1.0, ext.clone()));
        let p = mean_under_white_sky(&scene, path());
        let b = mean_under_white_sky(&scene, bdpt());
        eprintln!("{ext}: path {p:.4}, bdpt {b:.4}");
        assert!(p <= 1.005 && b <= 1.005 && p > 0.8, "{ext}: path {p:.4}, bdpt {b:.4}");
        assert!((p / b - 1.0).abs() < 0.01, "{ext}: path {p:.4}, bdpt {b:.4}");
    }
}
