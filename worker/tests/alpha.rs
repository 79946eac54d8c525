//! glTF alphaMode: MASK cuts a surface out where alpha < alphaCutoff, BLEND keeps each point
//! with probability alpha (stochastic transparency), for camera rays, shadow rays and every
//! path segment. Alpha = base colour factor x texture x vertex colour.

mod common;

use glam::{Mat4, Quat, Vec2, Vec3, Vec4};
use pathfarm_common::film::ImageLayers;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::{
    AlphaMode, Camera, Material, MaterialModel, Mesh, Projection, PunctualKind, PunctualLight, Scene, Texture,
    TextureRef, TextureTransform, WrapMode,
};
use pathfarm_worker::render::{Renderer, render_local};
use std::sync::Arc;

/// A quad `half` wide around `center` in the plane z = `center.z`, facing +Z, UVs 0..1.
fn quad_z(name: &str, center: Vec3, half: f32, material: usize) -> Mesh {
    let c = |x: f32, y: f32| center + Vec3::new(x * half, y * half, 0.0);
    Mesh {
        name: name.into(),
        positions: vec![c(-1.0, -1.0), c(1.0, -1.0), c(1.0, 1.0), c(-1.0, 1.0)],
        normals: Some(vec![Vec3::Z; 4]),
        uv0: Some(vec![Vec2::new(0.0, 1.0), Vec2::new(1.0, 1.0), Vec2::new(1.0, 0.0), Vec2::new(0.0, 0.0)]),
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material,
        ..Mesh::default()
    }
}

fn lambert(r: f32) -> Material {
    Material { model: MaterialModel::Lambert, base_color: Vec4::new(r, r, r, 1.0), ..Material::default() }
}

/// A 64 x 64 texture whose alpha is a 2 x 2 checker (top-left and bottom-right opaque).
fn checker() -> Texture {
    let n = 64u32;
    let texels = (0..n * n)
        .map(|i| Vec4::new(1.0, 1.0, 1.0, if ((i % n) < n / 2) == ((i / n) < n / 2) { 1.0 } else { 0.0 }))
        .collect();
    Texture {
        name: "checker".into(),
        width: n,
        height: n,
        texels: Arc::new(texels),
        wrap_s: WrapMode::ClampToEdge,
        wrap_t: WrapMode::ClampToEdge,
    }
}

/// A camera at `eye` looking down -Z, or straight down (-Y) when `down`.
fn camera(eye: Vec3, down: bool, yfov: f32) -> Camera {
    let turn = if down { Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2) } else { Quat::IDENTITY };
    Camera {
        name: "camera".into(),
        world_from_camera: Mat4::from_rotation_translation(turn, eye),
        projection: Projection::Perspective { yfov, aspect: Some(1.0) },
    }
}

/// The camera at the origin looks down -Z through `cover` (z = -1, twice the view's width) at
/// an emitter of radiance 1 (z = -2).
fn window(cover: Material, texture: bool) -> Scene {
    let yfov = 0.6f32;
    let view = (yfov * 0.5).tan();
    let mut emitter = lambert(0.0);
    emitter.emissive = Vec3::ONE;
    let mut cover = cover;
    if texture {
        cover.base_color_texture =
            Some(TextureRef { texture: 0, tex_coord: 0, transform: TextureTransform::default() });
    }
    Scene {
        meshes: vec![
            quad_z("emitter", Vec3::new(0.0, 0.0, -2.0), 10.0, 0),
            quad_z("cover", Vec3::new(0.0, 0.0, -1.0), 2.0 * view, 1),
        ],
        materials: vec![emitter, cover],
        textures: vec![checker()],
        cameras: vec![camera(Vec3::ZERO, false, yfov)],
        ..Scene::default()
    }
}

fn settings(w: u32, spp: u32, integrator: IntegratorSettings) -> RenderSettings {
    let mut s = RenderSettings::new(w, w, spp);
    s.integrator = integrator;
    s.seed = 3;
    s
}

fn path() -> IntegratorSettings {
    IntegratorSettings::Path {
        max_depth: 4,
        rr_depth: 5,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    }
}
fn bdpt() -> IntegratorSettings {
    IntegratorSettings::Bdpt { max_depth: 4, mis: MisHeuristic::Power, rr_depth: 5, strategy: None }
}

fn render(scene: &Scene, s: &RenderSettings) -> ImageLayers {
    render_local(&Renderer::new(scene, s).expect("renderer"), |_, _| {}).resolve()
}

fn mean_red(img: &ImageLayers, x0: usize, x1: usize, y0: usize, y1: usize) -> f64 {
    let w = img.width as usize;
    let mut m = 0.0;
    for y in y0..y1 {
        for x in x0..x1 {
            m += f64::from(img.rgb[y * w + x][0]);
        }
    }
    m / ((x1 - x0) * (y1 - y0)) as f64
}

#[test]
fn a_masked_checker_shows_the_emitter_through_its_cut_out_half() {
    let mut cover = lambert(0.0);
    cover.alpha_mode = AlphaMode::Mask { cutoff: 0.5 };
    let scene = window(cover.clone(), true);
    let w = 32;
    let img = render(&scene, &settings(w as u32, 16, path()));
    // The whole image: half of it sees the emitter (1), half the black cover.
    let all = mean_red(&img, 0, w, 0, w);
    assert!((all - 0.5).abs() < 0.01, "coverage: mean {all:.4}, expected 0.5");
    // Quadrants, one pixel off the seams: top-left and bottom-right opaque (black).
    let h = w / 2;
    let q = [
        mean_red(&img, 0, h - 1, 0, h - 1),
        mean_red(&img, h + 1, w, 0, h - 1),
        mean_red(&img, 0, h - 1, h + 1, w),
        mean_red(&img, h + 1, w, h + 1, w),
    ];
    assert!(q[0] == 0.0 && q[3] == 0.0 && q[1] == 1.0 && q[2] == 1.0, "quadrants {q:?}");
    // MASK is a threshold: cutoff 0 keeps the whole quad, above 1 removes it.
    let mut all_in = cover.clone();
    all_in.alpha_mode = AlphaMode::Mask { cutoff: 0.0 };
    assert_eq!(mean_red(&render(&window(all_in, true), &settings(8, 1, path())), 0, 8, 0, 8), 0.0);
    let mut all_out = cover;
    all_out.alpha_mode = AlphaMode::Mask { cutoff: 1.5 };
    assert_eq!(mean_red(&render(&window(all_out, true), &settings(8, 1, path())), 0, 8, 0, 8), 1.0);
}

#[test]
fn a_blended_cover_lets_one_minus_alpha_through() {
    // Alpha 0.5 (factor) x 0.6 (vertex colour) = 0.3: 70% of camera rays pass. 32 x 32 x 16
    // Bernoulli(0.7) samples: sigma 0.0036; tolerance 0.015 (4 sigma).
    let mut cover = lambert(0.0);
    cover.alpha_mode = AlphaMode::Blend;
    cover.base_color.w = 0.5;
    let mut scene = window(cover, false);
    scene.meshes[1].colors = Some(vec![Vec4::new(1.0, 1.0, 1.0, 0.6); 4]);
    let w = 32;
    let img = render(&scene, &settings(w as u32, 16, path()));
    let all = mean_red(&img, 0, w, 0, w);
    assert!((all - 0.7).abs() < 0.015, "mean {all:.4}, expected 0.7");
    // Deterministic: the same job renders the same bits.
    let again = render(&scene, &settings(w as u32, 16, path()));
    assert_eq!(img.rgb, again.rgb);
}

/// A white floor (z = 0 plane turned to face +Y) under a point light, with `cover` between them
/// and the camera in between looking down.
fn shadow_scene(cover: Option<Material>) -> Scene {
    let turn = |mut m: Mesh| {
        // Rotate about X: (x, y, z) -> (x, z, -y) turns +Z to +Y, so the quad faces up.
        for p in &mut m.positions {
            *p = Vec3::new(p.x, p.z, -p.y);
        }
        m.normals = Some(vec![Vec3::Y; 4]);
        m
    };
    let mut s = Scene {
        meshes: vec![turn(quad_z("floor", Vec3::ZERO, 1.0, 0))],
        materials: vec![lambert(0.8)],
        textures: vec![checker()],
        cameras: vec![camera(Vec3::new(0.0, 1.0, 0.0), true, 0.8)],
        lights: vec![PunctualLight {
            name: "light".into(),
            kind: PunctualKind::Point,
            intensity: Vec3::splat(10.0),
            position: Vec3::new(0.0, 3.0, 0.0),
            direction: -Vec3::Y,
            range: None,
        }],
        ..Scene::default()
    };
    if let Some(cover) = cover {
        // At y = 2, above the camera (which looks down), wide enough to shade the whole floor.
        s.meshes.push(turn(quad_z("cover", Vec3::new(0.0, 0.0, 2.0), 5.0, 1)));
        s.materials.push(cover);
    }
    s
}

#[test]
fn shadow_rays_and_light_paths_see_alpha() {
    // Direct light through a BLEND cover of alpha 0.25 is 0.75 of the unshadowed floor, for path
    // (shadow rays) and bdpt (shadow rays and light subpaths). The floor is lit only directly
    // (max depth 2 would do; the cover is black). 24 x 24 x 64 Bernoulli(0.75) samples: the ratio's
    // sigma is about 0.002; tolerance 0.012.
    let mut blend = lambert(0.0);
    blend.alpha_mode = AlphaMode::Blend;
    blend.base_color.w = 0.25;
    let w = 24;
    for (name, integrator) in [("path", path()), ("bdpt", bdpt())] {
        let open = mean_red(&render(&shadow_scene(None), &settings(w as u32, 64, integrator.clone())), 0, w, 0, w);
        let covered =
            mean_red(&render(&shadow_scene(Some(blend.clone())), &settings(w as u32, 64, integrator)), 0, w, 0, w);
        let ratio = covered / open;
        eprintln!("{name}: open {open:.4}, covered {covered:.4}, ratio {ratio:.4}");
        assert!(open > 0.1, "{name}: the floor is lit ({open})");
        assert!((ratio - 0.75).abs() < 0.012, "{name}: ratio {ratio:.4}, expected 0.75");
    }
    // MASK checker: the floor under the opaque half is dark, under the cut-out half lit.
    let mut mask = lambert(0.0);
    mask.alpha_mode = AlphaMode::Mask { cutoff: 0.5 };
    mask.base_color_texture = Some(TextureRef { texture: 0, tex_coord: 0, transform: TextureTransform::default() });
    let img = render(&shadow_scene(Some(mask)), &settings(w as u32, 4, path()));
    let lit = img.rgb.iter().filter(|p| p[0] > 0.0).count() as f64 / (w * w) as f64;
    assert!((0.3..0.7).contains(&lit), "lit fraction {lit}");
}

#[test]
fn batched_queries_see_alpha_as_single_ones() {
    // The wavefront's batched queries (`intersect_many`, `occluded_many`: the batch's closest
    // hits at once, cut-out ones continued alone) give each ray exactly its single query's
    // answer, through a BLEND cover (stochastic, 0.5) and a MASK checker cover stacked above a
    // floor: rays from above, below and between the layers, some stopping short.
    use pathfarm_worker::render::accel::RayQuery;
    use pathfarm_worker::render::scene::RenderScene;
    let mut blend = lambert(0.3);
    blend.alpha_mode = AlphaMode::Blend;
    blend.base_color.w = 0.5;
    let mut scene = shadow_scene(Some(blend));
    let mut mask = lambert(0.6);
    mask.alpha_mode = AlphaMode::Mask { cutoff: 0.5 };
    mask.base_color_texture = Some(TextureRef { texture: 0, tex_coord: 0, transform: TextureTransform::default() });
    let mut upper = quad_z("mask", Vec3::new(0.0, 0.0, 1.0), 3.0, 2);
    for p in &mut upper.positions {
        *p = Vec3::new(p.x, p.z, -p.y);
    }
    scene.meshes.push(upper);
    scene.materials.push(mask);
    let rs = RenderScene::new(&scene);
    // A fixed hash of (ray, component) to [0, 1).
    let unit = |i: u32, k: u32| {
        let mut x = u64::from(i) << 8 | u64::from(k);
        x = (x ^ (x >> 31)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        x = (x ^ (x >> 29)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        ((x ^ (x >> 32)) >> 40) as f32 / (1u32 << 24) as f32
    };
    let rays: Vec<RayQuery> = (0..3000u32)
        .map(|i| {
            let o = glam::Vec3A::new(
                unit(i, 1) * 6.0 - 3.0,
                [3.0, 1.5, 0.5, -1.0][(i % 4) as usize],
                unit(i, 2) * 6.0 - 3.0,
            );
            let d = glam::Vec3A::new(unit(i, 3) - 0.5, if i % 4 == 3 { 1.0 } else { -1.0 }, unit(i, 4) - 0.5);
            let t_max = if i % 5 == 0 { 1.2 } else { f32::INFINITY };
            RayQuery { o, d, t_max, time: 0.0 }
        })
        .collect();
    let (mut hits, mut surfaces, mut blocked) = (Vec::new(), Vec::new(), Vec::new());
    rs.intersect_many(&rays, &mut hits, &mut surfaces);
    rs.occluded_many(&rays, &mut blocked);
    let (mut through, mut stopped) = (0, 0);
    for (k, r) in rays.iter().enumerate() {
        let one = rs.intersect_at(r.o, r.d, r.t_max, r.time);
        let key = |s: &Option<pathfarm_worker::render::scene::SurfaceInteraction>| {
            s.as_ref().map(|s| (s.prim, s.t.to_bits(), s.p.to_array().map(f32::to_bits)))
        };
        assert_eq!(key(&surfaces[k]), key(&one), "ray {k}: {r:?}");
        assert_eq!(blocked[k], rs.occluded_at(r.o, r.d, r.t_max, r.time), "ray {k}: {r:?}");
        let first = hits[k].map(|h| h.prim);
        through += usize::from(one.is_some() && first != one.as_ref().map(|s| s.prim));
        stopped += usize::from(blocked[k]);
    }
    // Rays that went on through a cut-out surface, and rays blocked: both cases were met.
    assert!(through > 100 && stopped > 300, "{through} through a cut-out, {stopped} blocked");
}
