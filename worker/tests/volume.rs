//! KHR_materials_volume: light crossing a transmissive object is attenuated by Beer-Lambert,
//! `exp(-sigma d)` with `sigma = -ln(attenuationColor) / attenuationDistance`.

use glam::Vec3;
use pathfarm_common::job::{EnvironmentSettings, IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::{GltfBuilder, turned_box};
use pathfarm_common::scene::{LoadOptions, Scene, load_scene_from_slice};
use pathfarm_worker::render::{Renderer, render_local};

/// A slab of clear glass (ior 1: no refraction, no Fresnel loss) `thickness` deep across the
/// view of a narrow camera, with the volume extension.
fn slab(thickness: f32, volume: serde_json::Value) -> Scene {
    let mut b = GltfBuilder::new();
    let m = b.material(serde_json::json!({"name": "tinted glass",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.0},
            "KHR_materials_volume": volume}}));
    turned_box(&mut b, "slab", Vec3::new(0.0, 0.0, -3.0), Vec3::new(4.0, 4.0, thickness), 0.0, m);
    b.camera(Vec3::ZERO, -Vec3::Z, Vec3::Y, 0.05, 1.0);
    load_scene_from_slice(&b.to_glb(), "slab.glb", None, &LoadOptions::default()).expect("loads")
}

fn mean_rgb(scene: &Scene, integrator: IntegratorSettings) -> [f64; 3] {
    let mut s = RenderSettings::new(8, 8, 4);
    s.integrator = integrator;
    s.environment = Some(EnvironmentSettings { file: None, color: Some([1.0; 3]), intensity: 1.0, rotation_deg: 0.0 });
    let img = render_local(&Renderer::new(scene, &s).expect("renderer"), |_, _| {}).resolve();
    let mut m = [0.0; 3];
    for p in &img.rgb {
        for c in 0..3 {
            m[c] += f64::from(p[c]) / img.rgb.len() as f64;
        }
    }
    m
}

#[test]
fn a_slab_transmits_exp_minus_sigma_d() {
    // attenuationColor (0.1, 0.5, 0.9) at distance 2: through d the slab keeps color^(d / 2).
    // The camera's rays are within 1.5 degrees of the normal (path length d / cos: 0.03% more);
    // tolerance 0.5%.
    let color = [0.1f64, 0.5, 0.9];
    let volume = |d: f32| serde_json::json!({"thicknessFactor": d, "attenuationColor": [0.1, 0.5, 0.9], "attenuationDistance": 2.0});
    let path = IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 8,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    let bdpt = IntegratorSettings::Bdpt { max_depth: 8, mis: MisHeuristic::Power, rr_depth: 8, strategy: None };
    for d in [0.5f32, 1.0, 2.0] {
        for (name, integrator) in [("path", path.clone()), ("bdpt", bdpt.clone())] {
            let m = mean_rgb(&slab(d, volume(d)), integrator);
            for c in 0..3 {
                let expected = color[c].powf(f64::from(d) / 2.0);
                assert!(
                    (m[c] / expected - 1.0).abs() < 0.005,
                    "{name}, d {d}, channel {c}: {:.4} vs {expected:.4}",
                    m[c]
                );
            }
        }
    }
    // Without attenuation (the default distance is infinite) the slab is clear.
    let m = mean_rgb(&slab(1.0, serde_json::json!({"thicknessFactor": 1.0})), path);
    assert!(m.iter().all(|&v| (v - 1.0).abs() < 0.005), "{m:?}");
}

#[test]
fn volume_settings_are_read_and_checked() {
    let s = slab(
        1.0,
        serde_json::json!({"thicknessFactor": 1.0, "attenuationColor": [0.5, 1.0, 0.25], "attenuationDistance": 4.0}),
    );
    let a = s.materials[0].attenuation;
    let expected = Vec3::new(0.5f32.ln(), 0.0, 0.25f32.ln()) / -4.0;
    assert!((a - expected).abs().max_element() < 1e-6, "{a} vs {expected}");
    assert!(!s.materials[0].thin_walled, "a volume with a thickness is solid");
    // Thin-walled (thickness 0) keeps no attenuation.
    let thin = slab(
        1.0,
        serde_json::json!({"thicknessFactor": 0.0, "attenuationColor": [0.5, 0.5, 0.5], "attenuationDistance": 1.0}),
    );
    assert_eq!(thin.materials[0].attenuation, Vec3::ZERO);
    assert!(thin.materials[0].thin_walled);
    assert!(!thin.warnings.iter().any(|w| w.contains("thin")), "{:?}", thin.warnings);
}
