//! The thin-lens camera: the plane in focus stays sharp (the same image as the pinhole's), and
//! a point off it spreads over the thin-lens circle of confusion, of radius
//! `aperture_radius x |1 / focus_distance - 1 / depth|` on the image plane at distance 1.

use glam::{Mat4, Vec3, Vec4};
use pathfarm_common::film::ImageLayers;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::{Camera, Material, MaterialModel, Mesh, Projection, Scene};
use pathfarm_worker::render::{Renderer, render_local};

const YFOV: f32 = 0.5;
const W: u32 = 64;

/// A square emitter of radiance 1 and side `side` at depth `depth` in front of a camera at the
/// origin looking down -Z; nothing else.
fn square_scene(side: f32, depth: f32) -> Scene {
    let h = side * 0.5;
    let z = -depth;
    let emitter = Material {
        model: MaterialModel::Lambert,
        base_color: Vec4::new(0.0, 0.0, 0.0, 1.0),
        emissive: Vec3::ONE,
        ..Material::default()
    };
    Scene {
        meshes: vec![Mesh {
            name: "square".into(),
            positions: vec![Vec3::new(-h, -h, z), Vec3::new(h, -h, z), Vec3::new(h, h, z), Vec3::new(-h, h, z)],
            indices: vec![[0, 1, 2], [0, 2, 3]],
            material: 0,
            ..Mesh::default()
        }],
        materials: vec![emitter],
        cameras: vec![Camera {
            name: "camera".into(),
            world_from_camera: Mat4::IDENTITY,
            projection: Projection::Perspective { yfov: YFOV, aspect: Some(1.0) },
        }],
        ..Scene::default()
    }
}

fn settings(spp: u32, lens: Option<(f32, f32)>) -> RenderSettings {
    let mut s = RenderSettings::new(W, W, spp);
    s.integrator = IntegratorSettings::Path {
        max_depth: 1,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::Area,
    };
    s.seed = 7;
    if let Some((r, f)) = lens {
        s.aperture_radius = r;
        s.focus_distance = Some(f);
    }
    s
}

fn render(scene: &Scene, s: &RenderSettings) -> ImageLayers {
    render_local(&Renderer::new(scene, s).expect("renderer"), |_, _| {}).resolve()
}

/// Total, centroid and mean squared distance from the centroid (pixel centres) of the red
/// channel.
fn moments(img: &ImageLayers) -> (f64, (f64, f64), f64) {
    let w = img.width as usize;
    let (mut total, mut cx, mut cy) = (0.0, 0.0, 0.0);
    for (i, p) in img.rgb.iter().enumerate() {
        let v = f64::from(p[0]);
        total += v;
        cx += v * ((i % w) as f64 + 0.5);
        cy += v * ((i / w) as f64 + 0.5);
    }
    let (cx, cy) = (cx / total, cy / total);
    let m2 = img
        .rgb
        .iter()
        .enumerate()
        .map(|(i, p)| f64::from(p[0]) * (((i % w) as f64 + 0.5 - cx).powi(2) + ((i / w) as f64 + 0.5 - cy).powi(2)))
        .sum::<f64>()
        / total;
    (total, (cx, cy), m2)
}

#[test]
fn the_plane_in_focus_is_sharp() {
    // Every ray through a film point meets the pinhole ray's point on the plane of focus, so an
    // emitter lying on it renders as through a pinhole (up to rays grazing its edges).
    let scene = square_scene(0.3, 4.0);
    let pinhole = render(&scene, &settings(16, None));
    let lens = render(&scene, &settings(16, Some((0.2, 4.0))));
    let (a, b) = (moments(&pinhole).0, moments(&lens).0);
    let diff: f64 = pinhole.rgb.iter().zip(&lens.rgb).map(|(p, q)| f64::from((p[0] - q[0]).abs())).sum();
    assert!(
        a > 10.0 && diff / a < 0.01,
        "in focus: |lens - pinhole| / pinhole = {:.4} (totals {a:.2}, {b:.2})",
        diff / a
    );
}

#[test]
fn defocus_blur_matches_the_circle_of_confusion() {
    // Focus at 2, square at depth 4, aperture 0.2: radius 0.2 x |1/2 - 1/4| = 0.05 on the image
    // plane, x W / (2 tan(yfov / 2)) = 6.27 pixels. The image is that disc convolved with the
    // square's image (side a pixels) and the pixel box: its second moment about the centroid is
    // R^2 / 2 + a^2 / 6 + 1 / 6. Tolerance 3% on R (256 spp; measured 0.8% off at 64 spp).
    let (r, focus, depth, side) = (0.2f32, 2.0f32, 4.0f32, 0.1f32);
    let scene = square_scene(side, depth);
    let px_per_unit = f64::from(W) / (2.0 * f64::from((YFOV * 0.5).tan()));
    let expected = f64::from(r * (1.0 / focus - 1.0 / depth)) * px_per_unit;
    let a = f64::from(side / depth) * px_per_unit;
    let img = render(&scene, &settings(256, Some((r, focus))));
    let (total, c, m2) = moments(&img);
    let measured = (2.0 * (m2 - a * a / 6.0 - 1.0 / 6.0)).sqrt();
    eprintln!("circle of confusion: {measured:.3} px, thin-lens {expected:.3} px; centroid {c:?}");
    assert!((measured / expected - 1.0).abs() < 0.03, "radius {measured:.3} px, expected {expected:.3}");
    // Blur moves light, it does not make or lose it: the pinhole image holds the same total
    // (about 2,400 of the lens image's samples hit the square: 2% noise; tolerance 6%).
    let (pin_total, pin_c, pin_m2) = moments(&render(&scene, &settings(256, None)));
    eprintln!("totals: lens {total:.3}, pinhole {pin_total:.3}");
    assert!((total / pin_total - 1.0).abs() < 0.06, "totals {total:.2} vs pinhole {pin_total:.2}");
    assert!((c.0 - pin_c.0).abs() < 0.2 && (c.1 - pin_c.1).abs() < 0.2, "centroid {c:?} vs {pin_c:?}");
    assert!(pin_m2 < m2 / 5.0, "the pinhole image is sharp ({pin_m2:.2} vs {m2:.2})");
}

#[test]
fn a_lens_needs_a_focus_distance_and_bdpt_refuses_it() {
    let scene = square_scene(0.3, 4.0);
    let mut s = settings(1, Some((0.1, 3.0)));
    s.focus_distance = None;
    let e = Renderer::new(&scene, &s).err().expect("refused").to_string();
    assert!(e.contains("focus_distance"), "{e}");
    let mut s = settings(1, Some((0.1, 3.0)));
    s.integrator = IntegratorSettings::Bdpt { max_depth: 4, mis: MisHeuristic::Power, rr_depth: 5, strategy: None };
    let e = Renderer::new(&scene, &s).err().expect("refused").to_string();
    assert!(e.contains("thin lens") && e.contains("aperture_radius"), "{e}");
    // A pinhole job does not serialize the lens fields: its settings (and pixels) are as before.
    let json = serde_json::to_string(&settings(1, None)).expect("json");
    assert!(!json.contains("aperture") && !json.contains("focus"), "{json}");
}
