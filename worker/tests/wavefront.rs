//! The wavefront path integrator gives the scalar `li_path`'s unit results bit for bit, at every
//! SIMD level, over scenes that use every feature the path integrator has; and a sample's value
//! does not depend on the batch it was traced in (split invariance); and path, direct, igi and
//! bdpt units are those of the renderer before the wavefront (golden digests).

mod common;

use common::{file_scene, glb_scene, reference};
use glam::{Vec2, Vec3, Vec4};
use pathfarm_common::adaptive::BlockMask;
use pathfarm_common::film::PIXEL_BYTES;
use pathfarm_common::job::{
    EnvironmentSettings, IntegratorSettings, LightSampling, MisHeuristic, Pass, RenderSettings, SamplerKind, TileRect,
};
use pathfarm_common::scene::demo;
use pathfarm_common::scene::{
    AlphaMode, EnvironmentImage, MaterialModel, PunctualKind, PunctualLight, Scene, Texture, TextureRef,
    TextureTransform, WrapMode,
};
use pathfarm_worker::render::sampling::{ONE_MINUS_EPSILON, cosine_hemisphere_many, sample_cosine_hemisphere};
use pathfarm_worker::render::scene::RenderScene;
use pathfarm_worker::render::wavefront::{BATCH, PathKernel, batch_len};
use pathfarm_worker::render::wide::SimdLevel;
use pathfarm_worker::render::{Renderer, UnitResult};
use std::sync::Arc;

fn path(max_depth: u32, rr_depth: u32, mis: MisHeuristic, light_sampling: LightSampling) -> IntegratorSettings {
    IntegratorSettings::Path { max_depth, rr_depth, mis, light_sampling }
}

fn default_path() -> IntegratorSettings {
    path(8, 3, MisHeuristic::Power, LightSampling::SolidAngle)
}

fn settings(size: u32, spp: u32, integrator: IntegratorSettings) -> RenderSettings {
    let mut s = RenderSettings::new(size, size, spp);
    s.integrator = integrator;
    s
}

/// A 16 x 16 checker of two colours with an alpha checker of its own.
fn checker() -> Texture {
    let n = 16u32;
    let texels = (0..n * n)
        .map(|i| {
            let (x, y) = (i % n, i / n);
            if (x / 4 + y / 4) % 2 == 0 { Vec4::new(0.9, 0.6, 0.2, 1.0) } else { Vec4::new(0.2, 0.5, 0.9, 0.3) }
        })
        .collect();
    Texture {
        name: "checker".into(),
        width: n,
        height: n,
        texels: Arc::new(texels),
        wrap_s: WrapMode::Repeat,
        wrap_t: WrapMode::Repeat,
    }
}

fn texture_ref() -> Option<TextureRef> {
    Some(TextureRef { texture: 0, tex_coord: 0, transform: TextureTransform::default() })
}

/// The Cornell box with spheres, its materials turned into textured glTF microfacet layers
/// (metal, clearcoat, sheen, rough glass), UVs from positions, and one alpha-blended wall.
fn textured_microfacet_scene() -> Scene {
    let mut scene = glb_scene(&demo::cornell_spheres_glb());
    scene.textures = vec![checker()];
    for m in &mut scene.meshes {
        m.uv0 = Some(m.positions.iter().map(|p| Vec2::new(p.x + p.z, p.y * 2.0)).collect());
    }
    let count = scene.materials.len();
    for (k, m) in scene.materials.iter_mut().enumerate() {
        if m.emissive.max_element() > 0.0 {
            continue;
        }
        m.model = MaterialModel::Gltf;
        m.base_color_texture = texture_ref();
        m.metallic = [0.0, 0.5, 1.0][k % 3];
        m.roughness = [0.2, 0.5, 0.05][k % 3];
        m.metallic_roughness_texture = texture_ref();
        match k % 4 {
            0 => {
                m.clearcoat = 0.8;
                m.clearcoat_roughness = 0.02;
            }
            1 => {
                m.sheen_color = Vec3::new(0.5, 0.3, 0.2);
                m.sheen_roughness = 0.4;
            }
            2 if k + 1 < count => {
                m.transmission = 0.7;
                m.roughness = 0.3;
                m.ior = 1.5;
            }
            _ => {}
        }
        if k == 1 {
            m.alpha_mode = AlphaMode::Blend;
            m.double_sided = true;
        }
    }
    scene
}

/// The Cornell box's diffuse materials as plain Lambertian BSDFs in every form the wavefront
/// bounces in lanes (glTF with factors 0, the Lambert model, double-sided, vertex colours),
/// beside a mirror and a rough metal that it bounces one at a time. Every other mesh has its
/// winding reversed and is double-sided: its faces are seen from their backs (the normals
/// turned to the viewer, the shading normal then on the wrong side and replaced).
fn lambert_scene() -> Scene {
    let mut scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    for (k, m) in scene.materials.iter_mut().enumerate() {
        if m.emissive.max_element() > 0.0 {
            continue;
        }
        match k % 4 {
            0 => m.model = MaterialModel::Lambert,
            1 => m.double_sided = true,
            2 => {
                m.metallic = 1.0;
                m.roughness = 0.4;
                m.specular_factor = 1.0;
            }
            _ => m.model = MaterialModel::Mirror,
        }
    }
    let lights: Vec<bool> = scene.materials.iter().map(|m| m.emissive.max_element() > 0.0).collect();
    for (i, mesh) in scene.meshes.iter_mut().enumerate() {
        if i % 2 == 0 {
            mesh.colors =
                Some(mesh.positions.iter().map(|p| Vec4::new(0.5 + 0.4 * p.x, 0.8, 0.6 + 0.3 * p.y, 1.0)).collect());
        } else if !lights[mesh.material] {
            for t in &mut mesh.indices {
                t.swap(1, 2);
            }
        }
    }
    // The reversed meshes' materials (and so some others') are double-sided.
    let reversed: Vec<usize> =
        scene.meshes.iter().enumerate().filter(|(i, _)| i % 2 == 1).map(|(_, m)| m.material).collect();
    for k in reversed {
        if !lights[k] {
            scene.materials[k].double_sided = true;
        }
    }
    scene
}

/// The Cornell box with a point, a spot and a directional light besides its area light.
fn punctual_lights_scene() -> Scene {
    let mut scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let light = |kind, position: Vec3, direction: Vec3, intensity: f32| PunctualLight {
        name: "test".into(),
        kind,
        intensity: Vec3::splat(intensity),
        position,
        direction: direction.normalize(),
        range: None,
    };
    scene.lights.push(light(PunctualKind::Point, Vec3::new(0.3, 0.5, 0.2), Vec3::NEG_Y, 0.8));
    scene.lights.push(light(
        PunctualKind::Spot { inner_cone: 0.3, outer_cone: 0.5 },
        Vec3::new(-0.4, 0.8, 0.5),
        Vec3::new(0.2, -1.0, -0.3),
        3.0,
    ));
    scene.lights.push(light(PunctualKind::Directional, Vec3::ZERO, Vec3::new(0.1, -1.0, -0.4), 0.5));
    scene
}

/// A sky image: a bright band near the horizon on a blue gradient.
fn sky() -> EnvironmentImage {
    let (w, h) = (32u32, 16u32);
    let texels = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let sun = if y == 5 && (8..11).contains(&x) { 40.0 } else { 0.0 };
            Vec3::new(0.3 + sun, 0.4 + y as f32 * 0.02 + sun, 0.8 + sun)
        })
        .collect();
    EnvironmentImage::new(w, h, texels).expect("sky")
}

struct Case {
    name: &'static str,
    scene: Scene,
    settings: RenderSettings,
    environment: Option<EnvironmentImage>,
}

fn cases() -> Vec<Case> {
    let cornell = file_scene(&reference().join("cornell_mitsuba.glb"));
    let spheres = file_scene(&reference().join("cornell_spheres.glb"));
    let mut cases = Vec::new();
    let mut add = |name, scene: &Scene, settings, environment| {
        cases.push(Case { name, scene: scene.clone(), settings, environment });
    };
    add("cornell area", &cornell, settings(24, 6, path(8, 5, MisHeuristic::Power, LightSampling::Area)), None);
    add("cornell solid angle", &cornell, settings(24, 6, default_path()), None);
    add(
        "cornell no depth limit",
        &cornell,
        settings(16, 4, path(0, 2, MisHeuristic::Power, LightSampling::Area)),
        None,
    );
    add("cornell depth 1", &cornell, settings(16, 4, path(1, 5, MisHeuristic::Power, LightSampling::Area)), None);
    add(
        "cornell direct balance",
        &cornell,
        settings(16, 4, IntegratorSettings::Direct { mis: MisHeuristic::Balance, light_sampling: LightSampling::Area }),
        None,
    );
    for mis in [MisHeuristic::Light, MisHeuristic::Bsdf] {
        add("cornell one strategy", &cornell, settings(16, 4, path(6, 3, mis, LightSampling::SolidAngle)), None);
    }
    let mut independent = settings(16, 5, default_path());
    independent.sampler = SamplerKind::Independent;
    add("cornell independent sampler", &cornell, independent, None);
    add("spheres (mirror, glass)", &spheres, settings(24, 6, default_path()), None);
    add("caustics", &glb_scene(&demo::caustics_glb()), settings(16, 4, default_path()), None);
    add("gltf mirror", &glb_scene(&demo::gltf_mirror_glb()), settings(16, 4, default_path()), None);
    add("mis plates", &glb_scene(&demo::mis_glb()), settings(16, 4, default_path()), None);
    add("textured microfacet layers alpha", &textured_microfacet_scene(), settings(24, 6, default_path()), None);
    // Area sampling: where every light is a triangle, the lights are sampled in lanes, here
    // with alpha-cut and textured surfaces.
    let area = path(8, 5, MisHeuristic::Power, LightSampling::Area);
    add("textured microfacet layers alpha, area", &textured_microfacet_scene(), settings(24, 6, area.clone()), None);
    add("plain lambert, area", &lambert_scene(), settings(24, 6, area.clone()), None);
    add(
        "plain lambert, balance, roulette from 1",
        &lambert_scene(),
        settings(24, 6, path(0, 1, MisHeuristic::Balance, LightSampling::Area)),
        None,
    );
    add("plain lambert, solid angle", &lambert_scene(), settings(24, 6, default_path()), None);
    add("spheres (mirror, glass), area", &spheres, settings(24, 6, area), None);
    add("point spot directional", &punctual_lights_scene(), settings(24, 6, default_path()), None);
    let mut env = settings(16, 4, default_path());
    env.environment =
        Some(EnvironmentSettings { file: Some("sky.exr".into()), color: None, intensity: 1.5, rotation_deg: 30.0 });
    add("environment image", &glb_scene(&demo::caustics_glb()), env, Some(sky()));
    let mut constant = settings(16, 4, default_path());
    constant.environment =
        Some(EnvironmentSettings { file: None, color: Some([0.5, 0.6, 0.7]), intensity: 1.0, rotation_deg: 0.0 });
    add("environment constant", &spheres, constant, None);
    let mut blur = settings(16, 4, default_path());
    blur.shutter = 0.5;
    blur.fps = 1.0;
    add("motion blur", &glb_scene(&demo::cornell_animated_glb()), blur, None);
    let mut lens = settings(16, 4, default_path());
    lens.aperture_radius = 0.05;
    lens.focus_distance = Some(3.0);
    add("thin lens", &cornell, lens, None);
    cases
}

fn renderer(case: &Case, kernel: PathKernel, level: SimdLevel) -> Option<Renderer> {
    let mut r = Renderer::with_environment(&case.scene, &case.settings, case.environment.clone())
        .unwrap_or_else(|e| panic!("{}: {e}", case.name));
    r.set_path_kernel(kernel);
    (r.set_simd_level(level) == level).then_some(r)
}

fn full_tile(s: &RenderSettings) -> TileRect {
    TileRect { x0: 0, y0: 0, x1: s.width, y1: s.height }
}

/// Every case: the wavefront's unit results (a whole-image tile, an off-origin tile, a later
/// sample range) equal the scalar integrator's bit for bit, at the baseline and at AVX2 where
/// the CPU has it.
#[test]
fn wavefront_matches_scalar_bit_for_bit() {
    let mut compared = 0;
    for case in cases() {
        let s = &case.settings;
        let units = [
            (full_tile(s), Pass { index: 0, s0: 0, s1: s.spp }),
            (TileRect { x0: 3, y0: 5, x1: s.width - 2, y1: s.height - 1 }, Pass { index: 1, s0: 7, s1: 7 + s.spp }),
        ];
        let scalar = renderer(&case, PathKernel::Scalar, SimdLevel::Baseline).expect("the baseline always runs");
        for (tile, pass) in units {
            let want = scalar.render_unit(tile, pass);
            let nonzero = want.accum.sums.iter().filter(|p| p.rgb.iter().any(|&v| v > 0)).count();
            // Emitters seen directly light a few pixels of the whole image (none of the
            // off-origin tile), one strategy alone at 4 spp a few more; every other case most.
            let lit_enough = if case.name.ends_with("depth 1") {
                nonzero > 0 || tile != full_tile(s)
            } else if case.name.ends_with("one strategy") {
                nonzero > 0
            } else {
                nonzero * 4 > want.accum.sums.len()
            };
            assert!(lit_enough, "{}: {nonzero} lit pixels, a dark image", case.name);
            for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
                let Some(wavefront) = renderer(&case, PathKernel::Wavefront, level) else { continue };
                let got = wavefront.render_unit(tile, pass);
                assert!(got == want, "{} at {level:?}, tile {tile:?} pass {pass:?}: differs from li_path", case.name);
                compared += 1;
            }
        }
    }
    assert!(compared >= 2 * cases().len(), "{compared} comparisons");
}

/// The wavefront's lane-wise cosine-hemisphere directions (8 lanes, at the baseline and in
/// AVX2 code) are `sample_cosine_hemisphere`'s bits, for a dense grid of numbers, the disk's
/// centre and edges, and lengths that leave short chunks.
#[test]
fn lane_wise_diffuse_directions_are_the_scalar_bits() {
    let mut us: Vec<Vec2> = Vec::new();
    let edges = [0.0, 0.25, 0.5, 0.5 + f32::EPSILON, 0.75, ONE_MINUS_EPSILON, 1e-30, 0.499_999_97];
    for &x in &edges {
        for &y in &edges {
            us.push(Vec2::new(x, y));
        }
    }
    let n = 701;
    us.extend((0..n * n).map(|i| Vec2::new((i % n) as f32 / n as f32, (i / n) as f32 / n as f32)));
    let bits = |v: glam::Vec3A| v.to_array().map(f32::to_bits);
    let mut compared = 0;
    for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
        for len in [us.len(), us.len() - 3] {
            let mut out = Vec::new();
            cosine_hemisphere_many(&us[..len], level, &mut out);
            assert_eq!(out.len(), len);
            for (got, &u) in out.iter().zip(&us) {
                assert_eq!(got.u, u);
                assert_eq!(bits(got.w), bits(sample_cosine_hemisphere(u)), "{level:?} at {u}");
                compared += 1;
            }
        }
    }
    assert!(compared > 4 * n * n);
}

/// The wavefront's lane-wise camera rays (8 lanes in AVX2, where the CPU has it) are
/// `Camera::generate_ray`'s bits, over every pixel of images of several shapes and offsets at
/// the pixel's edges; a thin-lens camera has no lane-wise rays.
#[test]
fn lane_wise_camera_rays_are_the_scalar_bits() {
    use pathfarm_worker::render::camera::{Camera, Lens};
    use pathfarm_worker::render::wide::Avx2;
    let Some(avx2) = Avx2::new() else { return };
    let bounds = Some((Vec3::new(-1.0, -0.5, -2.0), Vec3::new(1.5, 1.0, 0.5)));
    let offsets = [0.0, 0.5, 0.999_999_94, 0.25, 1e-7, 0.75, 0.123_456_7, 0.9];
    let mut compared = 0;
    for (w, h) in [(64, 48), (17, 33), (1, 1), (1920, 1080)] {
        let camera = Camera::framing(bounds, w, h);
        let pixels: Vec<glam::UVec2> = (0..h)
            .step_by((h / 40).max(1) as usize)
            .flat_map(|y| (0..w).map(move |x| glam::UVec2::new(x, y)))
            .collect();
        for chunk in pixels.chunks(8).filter(|c| c.len() == 8) {
            for (k, &o) in offsets.iter().enumerate() {
                let us: [Vec2; 8] = std::array::from_fn(|i| Vec2::new(o, offsets[(k + i) % 8]));
                let lanes = |f: &dyn Fn(usize) -> f32| -> [f32; 8] { std::array::from_fn(f) };
                let (px, py) = (lanes(&|i| chunk[i].x as f32), lanes(&|i| chunk[i].y as f32));
                let (ux, uy) = (lanes(&|i| us[i].x), lanes(&|i| us[i].y));
                let [x, y, z] =
                    avx2.run(|| avx2.pinhole_directions(&camera, [&px, &py], [&ux, &uy])).expect("a pinhole camera");
                for i in 0..8 {
                    let want = camera.generate_ray(chunk[i], us[i]);
                    assert_eq!(want.o, camera.position());
                    assert_eq!(
                        [x[i], y[i], z[i]].map(f32::to_bits),
                        want.d.to_array().map(f32::to_bits),
                        "{w}x{h} {}",
                        chunk[i]
                    );
                    compared += 1;
                }
            }
        }
        let lens = camera.clone().with_lens(Lens { radius: 0.1, focus_distance: 2.0 }).expect("a lens");
        let zeros = [0.0f32; 8];
        assert!(avx2.pinhole_directions(&lens, [&zeros, &zeros], [&zeros, &zeros]).is_none());
    }
    assert!(compared > 50_000, "{compared}");
}

/// Adaptive sampling's block masks: converged blocks stay empty in both kernels, the others
/// equal.
#[test]
fn wavefront_matches_scalar_under_a_block_mask() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let s = settings(32, 4, default_path());
    let tile = full_tile(&s);
    let mut mask = BlockMask::none_converged(tile);
    let (bw, bh) = mask.blocks();
    assert!(bw * bh >= 2, "the tile has {bw} x {bh} blocks");
    mask.set_converged(0, 0);
    let pass = Pass { index: 1, s0: 4, s1: 8 };
    let render = |kernel| {
        let mut r = Renderer::new(&scene, &s).expect("renderer");
        r.set_path_kernel(kernel);
        r.render_unit_masked(tile, pass, Some(&mask)).expect("masked unit")
    };
    let (scalar, wavefront) = (render(PathKernel::Scalar), render(PathKernel::Wavefront));
    assert!(scalar.accum.sums[0] == Default::default(), "a converged block got samples");
    assert!(scalar.accum.sums.iter().any(|p| p.weight > 0));
    assert!(scalar == wavefront);
}

fn exact_sums(r: &UnitResult) -> Vec<([u64; 3], u64, u64, u32, u32)> {
    r.accum.sums.iter().map(|p| (p.rgb, p.lum, p.lum_sq, p.weight, p.hits)).collect()
}

/// A sample's value does not depend on its batch: a one-column tile (batches of one pixel's
/// samples) gives the pixels of a whole tile (batches spanning pixels), and a sample range
/// split in two adds up to the whole range's exact sums.
#[test]
fn wavefront_samples_do_not_depend_on_their_batch() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    // 300 samples a pixel: batches split pixels' samples, and the whole tile's batches mix
    // pixels.
    let s = settings(6, 300, path(8, 3, MisHeuristic::Power, LightSampling::Area));
    let r = Renderer::new(&scene, &s).expect("renderer");
    assert_eq!(r.path_kernel(), PathKernel::Wavefront, "the wavefront is the default");
    let whole = r.render_unit(full_tile(&s), Pass { index: 0, s0: 0, s1: 300 });
    let column = r.render_unit(TileRect { x0: 2, y0: 0, x1: 3, y1: s.height }, Pass { index: 0, s0: 0, s1: 300 });
    for y in 0..s.height as usize {
        assert!(column.accum.sums[y] == whole.accum.sums[y * s.width as usize + 2], "pixel (2, {y})");
    }
    let first = r.render_unit(full_tile(&s), Pass { index: 0, s0: 0, s1: 117 });
    let rest = r.render_unit(full_tile(&s), Pass { index: 1, s0: 117, s1: 300 });
    let added: Vec<_> = exact_sums(&first)
        .iter()
        .zip(exact_sums(&rest))
        .map(|(a, b)| ([a.0[0] + b.0[0], a.0[1] + b.0[1], a.0[2] + b.0[2]], a.1 + b.1, a.2 + b.2, a.3 + b.3, a.4 + b.4))
        .collect();
    assert_eq!(added, exact_sums(&whole));
}

/// The batch size: larger than [`BATCH`] for the Cornell box (its rays go in sorted packets, and
/// it has no textures: fuller packets), [`BATCH`] for the same box textured (measured slower in
/// the larger batches) and for a scene too large to sort its rays.
#[test]
fn batches_are_large_where_rays_are_sorted_and_nothing_is_textured() {
    let cornell = RenderScene::new(&file_scene(&reference().join("cornell_mitsuba.glb")));
    assert!(cornell.sorts_rays(), "the Cornell box's rays go in sorted packets");
    assert!(batch_len(&cornell) > BATCH, "{}", batch_len(&cornell));
    let textured = RenderScene::new(&textured_microfacet_scene());
    assert!(textured.sorts_rays(), "on trial at first");
    assert_eq!(batch_len(&textured), BATCH);
    // 70,000 small triangles in a grid: above the sorted packets' limit.
    let mut large = file_scene(&reference().join("cornell_mitsuba.glb"));
    let mesh = &mut large.meshes[0];
    mesh.normals = None;
    mesh.positions = (0..70_000u32)
        .flat_map(|i| {
            let o = Vec3::new((i % 300) as f32, (i / 300) as f32, 0.0) * 0.01;
            [o, o + Vec3::new(0.008, 0.0, 0.0), o + Vec3::new(0.0, 0.008, 0.0)]
        })
        .collect();
    mesh.indices = (0..70_000u32).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    let large = RenderScene::new(&large);
    assert!(!large.sorts_rays());
    assert_eq!(batch_len(&large), BATCH);
}

/// A mesh with 70,000 copies of one of its triangles (a degenerate scene; a mesh scaled to
/// nothing is alike): the scene builds (the BVH build once chained coincident triangles 70,000
/// deep, then overflowed the stack) and renders the image of the mesh without the copies, bit
/// for bit (a copy is hit where its original is, with the same vertices to shade).
#[test]
fn coincident_triangles_render_as_one() {
    let plain = file_scene(&reference().join("cornell_mitsuba.glb"));
    let mut copies = plain.clone();
    let mesh = copies
        .meshes
        .iter_mut()
        .find(|m| plain.materials[m.material].emissive == Vec3::ZERO)
        .expect("a mesh that emits nothing");
    let first = mesh.indices[0];
    mesh.indices.extend(std::iter::repeat_n(first, 70_000));
    assert_eq!(digest(&copies, default_path(), 24, 4), digest(&plain, default_path(), 24, 4));
}

/// FNV-1a over a whole-image unit's pixel sums in their wire layout.
fn digest(scene: &Scene, integrator: IntegratorSettings, size: u32, spp: u32) -> u64 {
    let s = settings(size, spp, integrator);
    let r = Renderer::new(scene, &s).expect("renderer");
    let unit = r.render_unit(full_tile(&s), Pass { index: 0, s0: 0, s1: spp });
    unit_digest(&unit, false)
}

/// FNV-1a over a unit's pixel sums in their wire layout and, with `splats`, then over its
/// light-tracing splats.
fn unit_digest(unit: &UnitResult, splats: bool) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut fnv = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    let mut buf = [0u8; PIXEL_BYTES];
    for p in &unit.accum.sums {
        p.write_le(&mut buf);
        fnv(&buf);
    }
    if splats {
        for v in unit.splats.iter().flat_map(|s| &s.sums) {
            fnv(&v.to_le_bytes());
        }
    }
    h
}

/// The estimators are those of the renderer before the wavefront (main at dfd437a, one path at
/// a time, VPL shadow rays one by one): the same unit results, bit for bit, at the default
/// kernels. The digests were printed by this function's body built against that commit's
/// renderer, and printed anew when the renderer's elementary functions (sin, atan2, exp, pow,
/// ...) became its own (`render::math`) instead of the system's libm, and when the concentric
/// disk map took the sine and cosine of its angle in [-pi/4, pi/4] without range reduction, and
/// when the asin polynomial took Cephes' coefficients verbatim (the only changes of those
/// commits to the renderer's arithmetic; the images still pass the reference, furnace and
/// chi-square tests). A deliberate change of an estimator, of an elementary function or of the
/// film's fixed-point encoding changes them, and they must then be printed anew.
#[test]
fn unit_results_are_those_of_the_renderer_before_the_wavefront() {
    let spheres = file_scene(&reference().join("cornell_spheres.glb"));
    let cornell = file_scene(&reference().join("cornell_mitsuba.glb"));
    let caustics = glb_scene(&demo::caustics_glb());
    let direct = IntegratorSettings::Direct { mis: MisHeuristic::Balance, light_sampling: LightSampling::SolidAngle };
    let igi = IntegratorSettings::Igi { vpls: 16, vpl_sets: 2, g_limit: 2.0, bias_compensation: true, max_depth: 6 };
    let bdpt = IntegratorSettings::Bdpt { max_depth: 6, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
    let got = [
        ("path cornell area", digest(&cornell, path(8, 3, MisHeuristic::Power, LightSampling::Area), 32, 8)),
        ("path spheres solid angle", digest(&spheres, default_path(), 32, 8)),
        ("path caustics", digest(&caustics, default_path(), 24, 8)),
        ("direct cornell", digest(&cornell, direct, 24, 8)),
        ("igi spheres", digest(&spheres, igi, 24, 4)),
        ("bdpt spheres", digest(&spheres, bdpt, 24, 4)),
    ];
    let want = [
        ("path cornell area", 0xe112_283c_2bc9_db91),
        ("path spheres solid angle", 0xd711_0fe7_f39a_f039),
        ("path caustics", 0xe73c_df00_16f0_28b5),
        ("direct cornell", 0xb361_7226_af60_7b4e),
        ("igi spheres", 0x21c0_6cdc_f17e_31c1),
        ("bdpt spheres", 0x73a1_f872_095e_2b81),
    ];
    let differing: Vec<String> = got
        .iter()
        .zip(want)
        .filter(|((_, got), (_, want))| got != want)
        .map(|((name, got), (_, want))| format!("{name}: 0x{got:016x}, not the earlier renderer's 0x{want:016x}"))
        .collect();
    assert!(differing.is_empty(), "{}", differing.join("\n"));
}

/// bdpt traces a row's samples in batches whose visibility rays are answered together
/// (`BdptBatch`, batches spanning pixels): a unit, with its light-tracing splats, is that of
/// one sample at a time, bit for bit. The digest was printed by this body
/// against main at 907cbf5, which answered each connection's ray on its own.
#[test]
fn bdpt_batches_give_the_unit_of_one_sample_at_a_time() {
    let scene = file_scene(&reference().join("cornell_spheres.glb"));
    let bdpt = IntegratorSettings::Bdpt { max_depth: 6, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
    let s = settings(32, 4, bdpt);
    let r = Renderer::new(&scene, &s).expect("renderer");
    let unit = r.render_unit(full_tile(&s), Pass { index: 1, s0: 4, s1: 7 });
    let splats = unit.splats.as_ref().expect("bdpt splats");
    assert!(splats.sums.iter().any(|&v| v != 0), "no light-tracing splat");
    let h = unit_digest(&unit, true);
    assert_eq!(h, 0x931b_0828_95f5_e637, "digest 0x{h:016x}");
}

/// bdpt with lights of every kind: an environment (camera paths that escape end on it; light
/// paths start on it, their first densities set after the walk), point, spot and directional
/// lights (delta), glass and mirrors (specular vertices). Each unit, with its splats, keeps the
/// bits of main at a42558d (the digests were printed by this body against it), so a change to
/// bdpt's walks or batches that moves a bit fails here (checked: leaving out the light path's
/// last step for infinite lights moves all three).
#[test]
fn bdpt_units_with_lights_of_every_kind_keep_their_bits() {
    let spheres = file_scene(&reference().join("cornell_spheres.glb"));
    let bdpt = IntegratorSettings::Bdpt { max_depth: 6, mis: MisHeuristic::Power, rr_depth: 3, strategy: None };
    let mut constant = settings(24, 4, bdpt.clone());
    constant.environment =
        Some(EnvironmentSettings { file: None, color: Some([0.5, 0.6, 0.7]), intensity: 1.0, rotation_deg: 0.0 });
    let mut image = settings(16, 4, bdpt.clone());
    image.environment =
        Some(EnvironmentSettings { file: Some("sky.exr".into()), color: None, intensity: 1.5, rotation_deg: 30.0 });
    let punctual = settings(24, 4, bdpt);
    let cases = [
        ("environment constant", Renderer::with_environment(&spheres, &constant, None), &constant),
        (
            "environment image",
            Renderer::with_environment(&glb_scene(&demo::caustics_glb()), &image, Some(sky())),
            &image,
        ),
        ("punctual lights", Renderer::new(&punctual_lights_scene(), &punctual), &punctual),
    ];
    let mut got = Vec::new();
    for (name, r, s) in cases {
        let r = r.expect("renderer");
        let unit = r.render_unit(full_tile(s), Pass { index: 1, s0: 4, s1: 7 });
        got.push((name, unit_digest(&unit, true)));
    }
    let want = [
        ("environment constant", 0xdb70_b8ca_0958_ab47),
        ("environment image", 0xb8d4_499a_efbd_eb5c),
        ("punctual lights", 0xc49a_7548_de21_3c6c),
    ];
    let differing: Vec<String> = got
        .iter()
        .zip(want)
        .filter(|((_, got), (_, want))| got != want)
        .map(|((name, got), (_, want))| format!("{name}: 0x{got:016x}, not a42558d's 0x{want:016x}"))
        .collect();
    assert!(differing.is_empty(), "{}", differing.join("\n"));
}
