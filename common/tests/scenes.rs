//! Loads every third-party scene of the corpus (`PATHFARM_CORPUS`, i.e. `../shared/scenes`) and
//! checks what its SOURCES.md says about it, plus our own Cornell box (`reference/`), the
//! loader's error cases, node hierarchy baking, and a no-panic fuzz test.
//!
//! The corpus tests are `#[ignore]`d unless asked for: `PATHFARM_CORPUS=../shared/scenes cargo
//! test --release -- --include-ignored` (what `scripts/test` does when the variable is set).

use base64::Engine as _;
use glam::Vec3;
use pathfarm_common::scene::demo;
use pathfarm_common::scene::{
    LoadOptions, MaterialModel, Projection, PunctualKind, Scene, SceneError, default_camera, load_scene,
    load_scene_from_slice,
};
use proptest::prelude::*;
use std::path::{Path, PathBuf};

/// The third-party scene folder named by `PATHFARM_CORPUS` (only the ignored corpus tests call it).
fn corpus() -> PathBuf {
    let dir = std::env::var_os("PATHFARM_CORPUS").map(PathBuf::from).expect(
        "PATHFARM_CORPUS is not set: point it at the third-party scene folder (../shared/scenes) to run the corpus suite",
    );
    assert!(dir.is_dir(), "PATHFARM_CORPUS={} is not a folder", dir.display());
    dir
}

/// Our own files (`reference/` at the repository root).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn load(rel: &str) -> Scene {
    load_path(&corpus().join(rel))
}

fn load_path(path: &Path) -> Scene {
    let rel = path.display();
    match load_scene(path, &LoadOptions::default()) {
        Ok(s) => s,
        Err(e) => panic!("{rel}: {e}"),
    }
}

fn close(a: Vec3, b: Vec3, eps: f32) -> bool {
    (a - b).abs().max_element() <= eps
}

/// Every glTF file in `shared/scenes` with its triangle count (after instancing) where
/// SOURCES.md gives it; where SOURCES.md rounds ("14.4k"), the exact count found agrees.
const SCENES: &[(&str, Option<usize>)] = &[
    ("01_vertex_count_32bit/01_vertex_count_32bit.gltf", Some(130_380)),
    ("02_node_hierarchy/02_node_hierarchy.gltf", None),
    ("14_emission_strength/14_emission_strength.gltf", Some(17_280)),
    ("15_transmission/15_transmission.gltf", Some(4_800)),
    ("17_ior/17_ior.gltf", None),
    ("23_multi_prim_vertex_attribute/23_multi_prim_vertex_attribute.gltf", Some(6)),
    ("24_animation_pointer/24_animation_pointer.gltf", Some(14_436)),
    ("Box/Box.glb", Some(12)),
    ("Box/Box.gltf", Some(12)),
    ("Cameras/Cameras.gltf", Some(2)),
    ("CornellBox_bevy/CornellBox.glb", Some(36)),
    ("Cubes_bevy/Cubes.glb", Some(36)),
    ("Fox_bevy/Fox.glb", None),
    ("GlassHurricaneCandleHolder/GlassHurricaneCandleHolder.gltf", Some(4_126)),
    ("MixedLightingExample_bevy/MixedLightingExample.gltf", Some(40_898)),
    ("SimpleSparseAccessor/SimpleSparseAccessor.gltf", Some(12)),
    ("TextureTransformTest/TextureTransformTest.gltf", None),
    ("TriangleWithoutIndices/TriangleWithoutIndices.gltf", Some(1)),
    ("barycentric_bevy/barycentric.gltf", Some(2)),
    ("box_sparse/box_sparse.glb", Some(12)),
    ("box_sparse/box_sparse.gltf", Some(12)),
    ("cornellBox_nvpro/cornellBox.gltf", Some(16_732)),
    ("emissive_triangle_kajiya/triangle.glb", Some(1)),
];

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn every_scene_loads() {
    // The list above must stay complete: compare it with the folder.
    let mut found = Vec::new();
    for dir in std::fs::read_dir(corpus()).expect("read the corpus folder").flatten() {
        if !dir.path().is_dir() {
            continue;
        }
        for f in std::fs::read_dir(dir.path()).expect("read scene folder").flatten() {
            let p = f.path();
            if p.extension().is_some_and(|e| e == "gltf" || e == "glb") {
                let rel = p.strip_prefix(corpus()).expect("prefix");
                found.push(rel.to_string_lossy().replace('\\', "/"));
            }
        }
    }
    found.sort();
    let mut listed: Vec<String> = SCENES.iter().map(|(s, _)| s.to_string()).collect();
    listed.sort();
    assert_eq!(found, listed, "SCENES must list every .gltf/.glb in the corpus");

    for &(rel, tris) in SCENES {
        let s = load(rel);
        assert!(s.triangle_count() > 0, "{rel}: no triangles");
        if let Some(t) = tris {
            assert_eq!(s.triangle_count(), t, "{rel}");
        }
        for m in &s.meshes {
            assert!(m.material < s.materials.len(), "{rel}: {}", m.name);
            let n = m.positions.len();
            assert!(m.indices.iter().flatten().all(|&i| (i as usize) < n), "{rel}: {}", m.name);
            assert!(m.positions.iter().all(|p| p.is_finite()), "{rel}: {}", m.name);
            for len in [m.normals.as_ref().map(Vec::len), m.tangents.as_ref().map(Vec::len)].into_iter().flatten() {
                assert_eq!(len, n, "{rel}: {}", m.name);
            }
            if let Some(normals) = &m.normals {
                assert!(normals.iter().all(|v| (v.length() - 1.0).abs() < 1e-3), "{rel}: {}", m.name);
            }
        }
        for mat in &s.materials {
            for t in [mat.base_color_texture, mat.emissive_texture, mat.normal_texture].into_iter().flatten() {
                assert!(t.texture < s.textures.len(), "{rel}: {}", mat.name);
            }
        }
        for t in &s.textures {
            assert_eq!(t.texels.len() as u64, u64::from(t.width) * u64::from(t.height), "{rel}: {}", t.name);
        }
    }
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn big_mesh_uses_u32_indices() {
    let s = load("01_vertex_count_32bit/01_vertex_count_32bit.gltf");
    assert_eq!(s.triangle_count(), 130_380);
    assert!(s.meshes.iter().any(|m| m.positions.len() > 65_535));
    assert!(s.cameras.is_empty() && s.lights.is_empty(), "the Lamp/Camera nodes carry nothing");
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn triangle_without_indices_has_no_normals() {
    let s = load("TriangleWithoutIndices/TriangleWithoutIndices.gltf");
    assert_eq!(s.meshes.len(), 1);
    let m = &s.meshes[0];
    assert_eq!(m.indices, vec![[0, 1, 2]]);
    assert!(m.normals.is_none());
    assert_eq!(s.materials.len(), 1, "the default material is appended");
    assert_eq!(s.materials[0].name, "default");
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn sparse_accessor_replaces_vertices() {
    let s = load("SimpleSparseAccessor/SimpleSparseAccessor.gltf");
    let p = &s.meshes[0].positions;
    assert_eq!(p.len(), 14);
    assert_eq!(p[8], Vec3::new(1.0, 2.0, 0.0));
    assert_eq!(p[10], Vec3::new(3.0, 3.0, 0.0));
    assert_eq!(p[12], Vec3::new(5.0, 4.0, 0.0));
    assert_eq!(p[9], Vec3::new(2.0, 1.0, 0.0), "vertices between replacements stay");
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn box_sparse_gltf_and_glb_agree() {
    let a = load("box_sparse/box_sparse.gltf");
    let b = load("box_sparse/box_sparse.glb");
    assert_eq!(a.meshes.len(), b.meshes.len());
    for (x, y) in a.meshes.iter().zip(&b.meshes) {
        assert_eq!(x.positions, y.positions);
        assert_eq!(x.indices, y.indices);
        assert!(x.normals.is_none());
    }
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn cameras_perspective_and_orthographic() {
    let s = load("Cameras/Cameras.gltf");
    let persp = s.cameras.iter().filter(|c| matches!(c.projection, Projection::Perspective { .. })).count();
    let ortho = s.cameras.iter().filter(|c| matches!(c.projection, Projection::Orthographic { .. })).count();
    assert_eq!((persp, ortho), (1, 1));
    for c in &s.cameras {
        // Scale removed: the rotation part is orthonormal and right-handed.
        let m = glam::Mat3::from_mat4(c.world_from_camera);
        assert!((m.determinant() - 1.0).abs() < 1e-4, "{}", c.name);
        assert!(m.x_axis.dot(m.y_axis).abs() < 1e-4);
    }
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn cubes_point_light() {
    let s = load("Cubes_bevy/Cubes.glb");
    assert_eq!(s.lights.len(), 1);
    let l = &s.lights[0];
    assert_eq!(l.kind, PunctualKind::Point);
    assert!(l.intensity.max_element() > 0.0);
    assert!((l.direction.length() - 1.0).abs() < 1e-5);
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn mixed_lighting_sun_and_texture_transforms() {
    let s = load("MixedLightingExample_bevy/MixedLightingExample.gltf");
    assert!(s.lights.iter().any(|l| l.kind == PunctualKind::Directional));
    let transformed = s
        .materials
        .iter()
        .flat_map(|m| [m.base_color_texture, m.normal_texture, m.metallic_roughness_texture, m.emissive_texture])
        .flatten()
        .any(|t| t.transform != Default::default());
    assert!(transformed, "some texture has a KHR_texture_transform");
    // The normal map's transform sits in normalTexture's extensions.
    let velvet = s.materials.iter().find(|m| m.name == "fabric Mystere Peacock Velvet").expect("velvet");
    let n = velvet.normal_texture.expect("normal texture");
    assert_eq!(n.transform.scale, glam::Vec2::splat(2.0));
    assert_eq!(n.transform.offset, glam::Vec2::new(-0.5, 0.5));
    assert!((velvet.normal_scale - 0.6).abs() < 1e-6);
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn animation_pointer_lights_and_cameras() {
    let s = load("24_animation_pointer/24_animation_pointer.gltf");
    let spots = s.lights.iter().filter(|l| matches!(l.kind, PunctualKind::Spot { .. })).count();
    let dirs = s.lights.iter().filter(|l| l.kind == PunctualKind::Directional).count();
    assert_eq!((spots, dirs), (3, 1));
    assert_eq!(s.cameras.len(), 4);
    let ortho = s.cameras.iter().filter(|c| matches!(c.projection, Projection::Orthographic { .. })).count();
    assert_eq!(ortho, 1);
    for l in &s.lights {
        if let PunctualKind::Spot { inner_cone, outer_cone } = l.kind {
            assert!(inner_cone <= outer_cone && outer_cone > 0.0, "{}", l.name);
        }
    }
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn texture_transform_test_reads_transforms() {
    let s = load("TextureTransformTest/TextureTransformTest.gltf");
    let refs: Vec<_> = s.materials.iter().filter_map(|m| m.base_color_texture).collect();
    assert!(refs.iter().any(|t| t.transform.rotation != 0.0));
    assert!(refs.iter().any(|t| t.transform.offset != glam::Vec2::ZERO));
    assert!(refs.iter().any(|t| t.transform.scale != glam::Vec2::ONE));
}

fn check_cornell_mitsuba(s: &Scene) {
    assert!(s.triangle_count() >= 6 * 2 + 24, "5 walls + light quad + 2 boxes");
    let lights: Vec<_> = s.materials.iter().filter(|m| m.emissive != Vec3::ZERO).collect();
    assert_eq!(lights.len(), 1);
    assert!(close(lights[0].emissive, Vec3::new(18.387, 13.9873, 6.75357), 1e-3), "{:?}", lights[0].emissive);
    for m in &s.materials {
        assert_eq!(m.specular_factor, 0.0, "{}", m.name);
        assert!(!m.double_sided, "{}", m.name);
    }
    assert_eq!(s.cameras.len(), 1);
    let c = &s.cameras[0];
    assert!(close(c.world_from_camera.w_axis.truncate(), Vec3::new(0.0, 0.0, 3.9), 1e-5));
    match c.projection {
        Projection::Perspective { yfov, .. } => assert!((yfov - 0.686_048_8).abs() < 1e-5),
        p => panic!("{p:?}"),
    }
    // The light quad faces down: its geometric normal (CCW front) is -Y.
    let mat = s.materials.iter().position(|m| m.emissive != Vec3::ZERO);
    let quad = s.meshes.iter().find(|m| Some(m.material) == mat).expect("light mesh");
    for t in &quad.indices {
        let [a, b, c] = t.map(|i| quad.positions[i as usize]);
        let n = (b - a).cross(c - a).normalize();
        assert!(close(n, Vec3::NEG_Y, 1e-4), "{n:?}");
    }
}

#[test]
fn cornell_mitsuba_reference() {
    check_cornell_mitsuba(&load_path(&repo().join("reference/cornell_mitsuba.glb")));
    let built =
        load_scene_from_slice(&demo::cornell_mitsuba_glb(), "cornell_mitsuba.glb", None, &LoadOptions::default());
    check_cornell_mitsuba(&built.expect("cornell_mitsuba_glb loads"));
}

/// The committed `reference/*.glb` files are what our exporter writes today (regenerate with
/// `cargo run -p pathfarm-common --example make_reference_scene`).
#[test]
fn committed_reference_scenes_are_current() {
    for (name, built) in
        [("cornell_mitsuba.glb", demo::cornell_mitsuba_glb()), ("cornell_spheres.glb", demo::cornell_spheres_glb())]
    {
        let committed = std::fs::read(repo().join("reference").join(name)).expect("committed reference scene");
        assert!(
            committed == built,
            "reference/{name} differs from what demo.rs writes: run `cargo run -p pathfarm-common --example make_reference_scene`"
        );
    }
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn emission_strength_materials() {
    let s = load("14_emission_strength/14_emission_strength.gltf");
    let emissive = s.materials.iter().filter(|m| m.emissive.max_element() > 0.0).count();
    assert!(emissive >= 8, "{emissive} emissive materials");
    assert!(s.materials.iter().any(|m| m.emissive.max_element() > 1.0), "strength > 1 applied");
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn cornell_bevy_emissive_strength() {
    let s = load("CornellBox_bevy/CornellBox.glb");
    let light = s.materials.iter().find(|m| m.emissive != Vec3::ZERO).expect("emissive material");
    assert!(close(light.emissive, Vec3::splat(100.0), 1e-3), "{:?}", light.emissive);
    assert!(s.cameras.is_empty());
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn cornell_nvpro_loads_with_warning_on_dangling_texture() {
    let s = load("cornellBox_nvpro/cornellBox.gltf");
    assert!(
        s.warnings.iter().any(|w| w.contains("texture 0 \"tex\"") && w.contains("image 0 does not exist")),
        "{:?}",
        s.warnings
    );
    assert!(s.textures.is_empty());
    assert_eq!(s.cameras.len(), 1);
    assert!(s.materials.iter().any(|m| m.emissive == Vec3::splat(3.0)));
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn transmission_and_ior() {
    let s = load("17_ior/17_ior.gltf");
    assert!(s.materials.iter().any(|m| m.transmission > 0.0));
    assert!(s.materials.iter().any(|m| m.ior != 1.5));
    let s = load("15_transmission/15_transmission.gltf");
    assert!(s.materials.iter().any(|m| m.transmission_texture.is_some()));
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn default_camera_frames_bounds() {
    let s = load("Box/Box.gltf");
    let c = default_camera(&s, 1.5);
    let (lo, hi) = s.bounds().expect("bounds");
    let eye = c.world_from_camera.w_axis.truncate();
    assert!(eye.z > hi.z);
    assert!(close(eye.truncate().extend(0.0), ((lo + hi) * 0.5).truncate().extend(0.0), 1e-5));
}

// ---- Building glTF files in tests ----

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// One triangle (positions only, indexed u16) in buffer 0 with the given uri; `nodes` and
/// `extra` are spliced into the JSON.
fn triangle_gltf(buffer_uri: &str, nodes: &str, extra: &str) -> String {
    format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "buffers": [{{"byteLength": 44, "uri": "{buffer_uri}"}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 36}},
    {{"buffer": 0, "byteOffset": 36, "byteLength": 6}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
      "min": [0, 0, 0], "max": [1, 1, 0]}},
    {{"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}}
  ],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}],
  {nodes}
  {extra}
  "scene": 0
}}"#
    )
}

fn triangle_data_uri() -> String {
    let mut data = f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    data.extend([0u16, 1, 2].iter().flat_map(|i| i.to_le_bytes()));
    data.extend([0, 0]);
    format!("data:application/octet-stream;base64,{}", b64(&data))
}

const ONE_NODE: &str = r#""nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}],"#;

fn load_str(json: &str, base: Option<&Path>, opts: &LoadOptions) -> Result<Scene, SceneError> {
    load_scene_from_slice(json.as_bytes(), "scene.gltf", base, opts)
}

/// A GLB holding the triangle of [`triangle_gltf`] with a material and a camera.
fn triangle_glb() -> Vec<u8> {
    let json = triangle_gltf("", ONE_NODE, r#""materials": [{"emissiveFactor": [1, 1, 1]}],"#)
        .replace(r#", "uri": """#, "")
        .replace(
            r#""attributes": {"POSITION": 0}, "indices": 1"#,
            r#""attributes": {"POSITION": 0}, "indices": 1, "material": 0"#,
        );
    let mut bin = f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    bin.extend([0u16, 1, 2].iter().flat_map(|i| i.to_le_bytes()));
    bin.extend([0, 0]);
    let mut j = json.into_bytes();
    j.resize(j.len().next_multiple_of(4), b' ');
    let total = 12 + 8 + j.len() + 8 + bin.len();
    let mut out = b"glTF".to_vec();
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(j);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin);
    out
}

#[test]
fn glb_built_in_test_loads() {
    let s = load_scene_from_slice(&triangle_glb(), "t.glb", None, &LoadOptions::default()).expect("load");
    assert_eq!(s.triangle_count(), 1);
    assert_eq!(s.materials.len(), 1);
    assert_eq!(s.materials[0].emissive, Vec3::ONE);
}

#[test]
fn truncated_glb_is_an_error() {
    let glb = triangle_glb();
    for cut in [3, 11, 12, 30, glb.len() - 1] {
        let e = load_scene_from_slice(&glb[..cut], "t.glb", None, &LoadOptions::default())
            .expect_err("truncated glb must fail");
        assert!(e.to_string().starts_with("t.glb: "), "{e}");
    }
}

#[test]
fn garbage_is_an_error() {
    for bytes in [&b""[..], b"\0\x01\x02garbage", b"{\"asset\": 3}", b"glTF\x02\0\0\0\xff\xff\xff\xff"] {
        let e = load_scene_from_slice(bytes, "g.gltf", None, &LoadOptions::default()).expect_err("garbage");
        assert!(e.to_string().starts_with("g.gltf: "), "{e}");
    }
}

#[test]
fn forbidden_uris_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    for uri in ["../secret.bin", "/etc/passwd", "http://x/y.bin", "file:///etc/passwd", "sub/../../x.bin"] {
        let json = triangle_gltf(uri, ONE_NODE, "");
        for base in [Some(dir.path()), None] {
            let e = load_str(&json, base, &LoadOptions::default()).expect_err(uri);
            assert!(matches!(e, SceneError::ForbiddenUri { .. }), "{uri}: {e:?}");
            let msg = e.to_string();
            assert!(msg.starts_with("scene.gltf: buffer 0 uri ") && msg.contains(&format!("{uri:?}")), "{msg}");
        }
    }
    let e = load_str(&triangle_gltf("tri.bin", ONE_NODE, ""), None, &LoadOptions::default()).expect_err("no base");
    assert!(matches!(e, SceneError::ForbiddenUri { .. }), "{e:?}");
}

#[test]
fn external_buffer_inside_bundle_loads() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = triangle_data_uri();
    let bytes =
        base64::engine::general_purpose::STANDARD.decode(data.split_once(',').expect("data uri").1).expect("base64");
    std::fs::create_dir(dir.path().join("bin dir")).expect("mkdir");
    std::fs::write(dir.path().join("bin dir/tri.bin"), bytes).expect("write");
    let json = triangle_gltf("bin%20dir/tri.bin", ONE_NODE, "");
    std::fs::write(dir.path().join("scene.gltf"), &json).expect("write");
    let s = load_scene(&dir.path().join("scene.gltf"), &LoadOptions::default()).expect("load");
    assert_eq!(s.triangle_count(), 1);
}

#[test]
fn accessor_out_of_range_names_mesh_primitive_accessor() {
    // The index accessor claims 300 elements in a 6-byte view.
    let json = triangle_gltf(&triangle_data_uri(), ONE_NODE, "")
        .replace(r#""componentType": 5123, "count": 3"#, r#""componentType": 5123, "count": 300"#);
    let e = load_str(&json, None, &LoadOptions::default()).expect_err("out of range");
    assert!(e.to_string().starts_with("scene.gltf: mesh 0 primitive 0: accessor 1: "), "{e}");
    // A POSITION accessor that does not exist.
    let json = triangle_gltf(&triangle_data_uri(), ONE_NODE, "").replace(r#""POSITION": 0"#, r#""POSITION": 7"#);
    let e = load_str(&json, None, &LoadOptions::default()).expect_err("missing accessor");
    assert!(e.to_string().starts_with("scene.gltf: mesh 0 primitive 0: accessor 7"), "{e}");
}

#[test]
fn out_of_range_indices_are_dropped_with_a_warning() {
    let mut data = f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    data.extend([0u16, 1, 9].iter().flat_map(|i| i.to_le_bytes()));
    data.extend([0, 0]);
    let uri = format!("data:application/octet-stream;base64,{}", b64(&data));
    let s = load_str(&triangle_gltf(&uri, ONE_NODE, ""), None, &LoadOptions::default()).expect("load");
    assert_eq!(s.triangle_count(), 0);
    assert!(s.warnings.iter().any(|w| w.contains("mesh 0 primitive 0") && w.contains("out-of-range")));
}

#[test]
fn triangle_limit_names_the_limit() {
    let opts = LoadOptions { max_triangles: Some(1), ..Default::default() };
    let nodes = r#""nodes": [{"mesh": 0}, {"mesh": 0}], "scenes": [{"nodes": [0, 1]}],"#;
    let json = triangle_gltf(&triangle_data_uri(), nodes, "");
    let e = load_str(&json, None, &opts).expect_err("limit");
    assert!(matches!(e, SceneError::LimitExceeded { limit: "max_triangles", .. }), "{e:?}");
    assert!(e.to_string().contains("max_triangles = 1"), "{e}");
    assert!(load_str(&json, None, &LoadOptions { max_triangles: Some(2), ..Default::default() }).is_ok());
}

#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn texture_limit_names_the_limit() {
    let opts = LoadOptions { max_texture_pixels: Some(16), ..Default::default() };
    let e = load_scene(&corpus().join("TextureTransformTest/TextureTransformTest.gltf"), &opts).expect_err("limit");
    assert!(matches!(e, SceneError::LimitExceeded { limit: "max_texture_pixels", .. }), "{e:?}");
    assert!(e.to_string().contains("image "), "{e}");
}

#[test]
fn node_hierarchy_is_baked_to_world_space() {
    // Node 0: translate (10, 0, 0), children 1 and 2.
    // Node 1: matrix = uniform scale 2, mesh 0.
    // Node 2: rotate 90 degrees about +Z, translate (0, 5, 0), mesh 0; child 3.
    // Node 3: scale (-1, 1, 1) (mirror), mesh 0.
    let s2 = std::f32::consts::FRAC_1_SQRT_2;
    let nodes = format!(
        r#""nodes": [
    {{"translation": [10, 0, 0], "children": [1, 2]}},
    {{"matrix": [2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1], "mesh": 0}},
    {{"rotation": [0, 0, {s2}, {s2}], "translation": [0, 5, 0], "mesh": 0, "children": [3]}},
    {{"scale": [-1, 1, 1], "mesh": 0, "name": "mirror"}}
  ],
  "scenes": [{{"nodes": [0]}}],"#
    );
    let s = load_str(&triangle_gltf(&triangle_data_uri(), &nodes, ""), None, &LoadOptions::default()).expect("load");
    assert_eq!(s.meshes.len(), 3, "mesh 0 instanced three times");
    let p = |i: usize| s.meshes[i].positions.clone();
    let eps = 1e-5;
    let expect = |got: Vec<Vec3>, want: [Vec3; 3]| {
        for (g, w) in got.iter().zip(want) {
            assert!(close(*g, w, eps), "{got:?} vs {want:?}");
        }
    };
    expect(p(0), [Vec3::new(10.0, 0.0, 0.0), Vec3::new(12.0, 0.0, 0.0), Vec3::new(10.0, 2.0, 0.0)]);
    // Rotation maps x -> y and y -> -x.
    expect(p(1), [Vec3::new(10.0, 5.0, 0.0), Vec3::new(10.0, 6.0, 0.0), Vec3::new(9.0, 5.0, 0.0)]);
    // Mirror first (x -> -x), then the parent's rotation and translation.
    expect(p(2), [Vec3::new(10.0, 5.0, 0.0), Vec3::new(10.0, 4.0, 0.0), Vec3::new(9.0, 5.0, 0.0)]);
    assert!(s.meshes[2].name.contains("\"mirror\""), "{}", s.meshes[2].name);
    // Winding: the mirrored instance is flipped so its geometric normal stays +Z.
    for m in &s.meshes {
        let [a, b, c] = m.indices[0].map(|i| m.positions[i as usize]);
        assert!(close((b - a).cross(c - a).normalize(), Vec3::Z, eps), "{}", m.name);
    }
    assert_eq!(s.meshes[2].indices[0], [0, 2, 1]);
}

#[test]
fn node_cycle_is_an_error() {
    let nodes = r#""nodes": [{"children": [1]}, {"children": [0], "mesh": 0}], "scenes": [{"nodes": [0]}],"#;
    let e =
        load_str(&triangle_gltf(&triangle_data_uri(), nodes, ""), None, &LoadOptions::default()).expect_err("cycle");
    assert!(e.to_string().contains("cycle"), "{e}");
}

#[test]
fn extras_choose_the_material_model() {
    let materials = r#""materials": [
    {"extras": {"pathfarm": {"model": "lambert"}}},
    {"extras": {"pathfarm": {"model": "blinn", "exponent": 50}}},
    {"extras": {"pathfarm": {"model": "ashikhmin_shirley", "exponent_x": 200, "exponent_y": 10}}},
    {"extras": {"pathfarm": {"model": "mirror"}}},
    {"extras": {"other": 1}}
  ],"#;
    let s = load_str(&triangle_gltf(&triangle_data_uri(), ONE_NODE, materials), None, &LoadOptions::default())
        .expect("load");
    let models: Vec<_> = s.materials.iter().map(|m| m.model).collect();
    assert_eq!(
        &models[..5],
        &[
            MaterialModel::Lambert,
            MaterialModel::Blinn { exponent: 50.0 },
            MaterialModel::AshikhminShirley { exponent_x: 200.0, exponent_y: 10.0 },
            MaterialModel::Mirror,
            MaterialModel::Gltf,
        ]
    );
    let bad = r#""materials": [{"name": "Bad", "extras": {"pathfarm": {"model": "phong"}}}],"#;
    let e = load_str(&triangle_gltf(&triangle_data_uri(), ONE_NODE, bad), None, &LoadOptions::default())
        .expect_err("bad model");
    assert!(e.to_string().starts_with("scene.gltf: material 0 \"Bad\": extras.pathfarm"), "{e}");
}

/// A quad with normals and UVs, a material whose normal texture and base colour texture share
/// one 1x1 PNG, and no tangents.
fn normal_mapped_quad() -> String {
    let png = {
        let mut out = Vec::new();
        image::RgbaImage::from_pixel(1, 1, image::Rgba([128, 128, 255, 255]))
            .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
            .expect("png");
        out
    };
    let mut data = f32_bytes(&[0., 0., 0., 1., 0., 0., 1., 1., 0., 0., 1., 0.]);
    data.extend(f32_bytes(&[0., 0., 1., 0., 0., 1., 0., 0., 1., 0., 0., 1.]));
    data.extend(f32_bytes(&[0., 1., 1., 1., 1., 0., 0., 0.]));
    data.extend([0u16, 1, 2, 0, 2, 3].iter().flat_map(|i| i.to_le_bytes()));
    format!(
        r#"{{"asset": {{"version": "2.0"}},
  "buffers": [{{"byteLength": {}, "uri": "data:application/octet-stream;base64,{}"}}],
  "bufferViews": [{{"buffer": 0, "byteLength": 48}}, {{"buffer": 0, "byteOffset": 48, "byteLength": 48}},
    {{"buffer": 0, "byteOffset": 96, "byteLength": 32}}, {{"buffer": 0, "byteOffset": 128, "byteLength": 12}}],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0,0,0], "max": [1,1,0]}},
    {{"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"}},
    {{"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"}},
    {{"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}}],
  "images": [{{"uri": "data:image/png;base64,{}"}}],
  "textures": [{{"source": 0}}],
  "materials": [{{"normalTexture": {{"index": 0}}, "pbrMetallicRoughness": {{"baseColorTexture": {{"index": 0}}}}}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}}, "indices": 3, "material": 0}}]}}],
  "nodes": [{{"mesh": 0}}]}}"#,
        data.len(),
        b64(&data),
        b64(&png)
    )
}

#[test]
fn generated_tangents_for_normal_maps() {
    let s = load_str(&normal_mapped_quad(), None, &LoadOptions::default()).expect("load");
    let t = s.meshes[0].tangents.as_ref().expect("tangents generated");
    for v in t {
        assert!((v.truncate() - Vec3::X).length() < 1e-4 && v.w.abs() == 1.0, "{v:?}");
    }
    // One image used as sRGB (base colour) and as linear (normal map): two textures.
    assert_eq!(s.textures.len(), 2);
    let n = s.materials[0].normal_texture.expect("normal texture").texture;
    let b = s.materials[0].base_color_texture.expect("base texture").texture;
    assert!((s.textures[n].texels[0].x - 128.0 / 255.0).abs() < 1e-6);
    assert!((s.textures[b].texels[0].x - 0.2158605).abs() < 1e-4, "sRGB decoded");
    assert_eq!(s.textures[b].texels[0].w, 1.0);
}

#[test]
fn non_triangle_modes_are_skipped_with_a_warning() {
    let json =
        triangle_gltf(&triangle_data_uri(), ONE_NODE, "").replace(r#""indices": 1}"#, r#""indices": 1, "mode": 1}"#);
    let s = load_str(&json, None, &LoadOptions::default()).expect("load");
    assert_eq!(s.triangle_count(), 0);
    assert!(s.warnings.iter().any(|w| w.contains("mesh 0 primitive 0")), "{:?}", s.warnings);
    // A fan of 3 vertices is one triangle.
    let json =
        triangle_gltf(&triangle_data_uri(), ONE_NODE, "").replace(r#""indices": 1}"#, r#""indices": 1, "mode": 6}"#);
    assert_eq!(load_str(&json, None, &LoadOptions::default()).expect("load").triangle_count(), 1);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, failure_persistence: None, ..ProptestConfig::default() })]

    /// Mutated bytes of a valid GLB never panic the loader.
    #[test]
    fn mutated_glb_never_panics(edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8)) {
        let mut glb = triangle_glb();
        for (at, byte) in edits {
            let i = at.index(glb.len());
            glb[i] = byte;
        }
        let _ = load_scene_from_slice(&glb, "fuzz.glb", None, &LoadOptions::default());
    }

    /// Mutated glTF JSON (digits changed, so indices and counts go wild) never panics.
    #[test]
    fn mutated_json_never_panics(
        quad in any::<bool>(),
        edits in prop::collection::vec((any::<prop::sample::Index>(), 0u8..10), 1..6),
    ) {
        let mut json = if quad {
            normal_mapped_quad()
        } else {
            triangle_gltf(&triangle_data_uri(), ONE_NODE, r#""materials": [{}],"#)
        }
        .into_bytes();
        let digits: Vec<usize> = json.iter().enumerate().filter(|(_, c)| c.is_ascii_digit()).map(|(i, _)| i).collect();
        for (at, d) in edits {
            json[digits[at.index(digits.len())]] = b'0' + d;
        }
        let _ = load_scene_from_slice(&json, "fuzz.gltf", None, &LoadOptions::default());
    }

    /// Random bytes and random JSON-ish text never panic.
    #[test]
    fn random_input_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..256), text in "\\{[\"a-z0-9:,\\[\\]{} ]{0,80}\\}") {
        let _ = load_scene_from_slice(&bytes, "r.glb", None, &LoadOptions::default());
        let _ = load_scene_from_slice(text.as_bytes(), "r.gltf", None, &LoadOptions::default());
    }
}

// ---- Hostile geometry and images ----

/// A vertex at 1e25 (here through a node translation, as an attack would) made every worker
/// panic in the BVH build; the loader refuses it, naming the mesh and the bound.
#[test]
fn huge_or_non_finite_coordinates_are_refused() {
    for node in [
        r#""nodes": [{"mesh": 0, "translation": [1e25, 0, 0]}], "scenes": [{"nodes": [0]}],"#,
        r#""nodes": [{"mesh": 0, "scale": [1e30, 1e30, 1e30]}], "scenes": [{"nodes": [0]}],"#,
    ] {
        let json = triangle_gltf(&triangle_data_uri(), node, "");
        let e = load_str(&json, None, &LoadOptions::default()).expect_err("refused");
        let msg = e.to_string();
        assert!(matches!(e, SceneError::Invalid { .. }), "{e:?}");
        assert!(msg.contains("mesh 0") && msg.contains("finite and within") && msg.contains("1e7"), "{msg}");
    }
    // A NaN coordinate in the buffer itself.
    let mut data = f32_bytes(&[0.0, 0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0, 1.0, 0.0]);
    data.extend([0u16, 1, 2].iter().flat_map(|i| i.to_le_bytes()));
    data.extend([0, 0]);
    let uri = format!("data:application/octet-stream;base64,{}", b64(&data));
    let e = load_str(&triangle_gltf(&uri, ONE_NODE, ""), None, &LoadOptions::default()).expect_err("NaN refused");
    assert!(e.to_string().contains("POSITION has non-finite values"), "{e}");
    // 1e6 is a large but sane scene (a city in metres).
    let json = triangle_gltf(
        &triangle_data_uri(),
        r#""nodes": [{"mesh": 0, "scale": [1e6, 1e6, 1e6]}], "scenes": [{"nodes": [0]}],"#,
        "",
    );
    assert!(load_str(&json, None, &LoadOptions::default()).is_ok());
}

/// One 64 x 64 PNG used by five textures that differ only in their samplers (the texture bomb:
/// each texture/sampler pair used to copy the image).
fn one_image_five_samplers() -> String {
    let png = {
        let mut out = Vec::new();
        image::RgbaImage::from_fn(64, 64, |x, y| image::Rgba([(x * 4) as u8, (y * 4) as u8, 128, 255]))
            .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
            .expect("png");
        out
    };
    let materials: Vec<String> =
        (0..5).map(|i| format!(r#"{{"pbrMetallicRoughness": {{"baseColorTexture": {{"index": {i}}}}}}}"#)).collect();
    let textures: Vec<String> = (0..5).map(|i| format!(r#"{{"source": 0, "sampler": {i}}}"#)).collect();
    let extra = format!(
        r#""images": [{{"uri": "data:image/png;base64,{}"}}],
  "samplers": [{{"wrapS": 10497, "wrapT": 10497}}, {{"wrapS": 33071, "wrapT": 33071}}, {{"wrapS": 33648, "wrapT": 33648}},
               {{"wrapS": 10497, "wrapT": 33071}}, {{"wrapS": 33071, "wrapT": 10497}}],
  "textures": [{}],
  "materials": [{}],"#,
        b64(&png),
        textures.join(", "),
        materials.join(", ")
    );
    triangle_gltf(&triangle_data_uri(), ONE_NODE, &extra)
}

#[test]
fn textures_of_one_image_share_texels_within_the_memory_budget() {
    let json = one_image_five_samplers();
    // Decode buffer (64 x 64 x 4) + RGBA copy (x 4) + linear texels once (x 16) = 98,304 bytes.
    let need = 64 * 64 * (4 + 4 + 16);
    let s = load_str(&json, None, &LoadOptions { max_texture_bytes: Some(need), ..Default::default() })
        .expect("five textures of one image fit the budget of one");
    assert_eq!(s.textures.len(), 5);
    for t in &s.textures[1..] {
        assert!(std::sync::Arc::ptr_eq(&t.texels, &s.textures[0].texels), "{} copies the image", t.name);
    }
    let wraps: std::collections::HashSet<_> = s.textures.iter().map(|t| (t.wrap_s, t.wrap_t)).collect();
    assert_eq!(wraps.len(), 5, "each texture keeps its own sampler");
    let e = load_str(&json, None, &LoadOptions { max_texture_bytes: Some(need - 1), ..Default::default() })
        .expect_err("one byte short");
    assert!(matches!(e, SceneError::LimitExceeded { limit: "max_texture_bytes", .. }), "{e:?}");
    assert!(e.to_string().contains("image memory"), "{e}");
}

/// COLOR_0 is read as linear RGBA: float VEC3 (alpha 1) here, interpolable per vertex.
#[test]
fn vertex_colors_are_read() {
    let mut b = demo::GltfBuilder::new();
    let m = b.material(demo::lambert("white", Vec3::ONE));
    let p = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let node = b.mesh("tri", &p, &[Vec3::Z; 3], &[0, 1, 2], m);
    b.vertex_colors(node, &[Vec3::X, Vec3::Y, Vec3::Z]);
    let s = load_scene_from_slice(&b.to_glb(), "c.glb", None, &LoadOptions::default()).expect("loads");
    let colors = s.meshes[0].colors.as_ref().expect("COLOR_0 read");
    assert_eq!(
        colors,
        &vec![
            glam::Vec4::new(1.0, 0.0, 0.0, 1.0),
            glam::Vec4::new(0.0, 1.0, 0.0, 1.0),
            glam::Vec4::new(0.0, 0.0, 1.0, 1.0)
        ]
    );
}
