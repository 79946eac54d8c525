//! Posing animated scenes (`Scene::posed`): skins and morph targets against references computed
//! here, KHR_animation_pointer on materials, lights and cameras, which animations play, the
//! errors for broken channels, and (corpus) the 24_animation_pointer scene.

use glam::{Mat3, Mat4, Quat, Vec3, Vec4};
use pathfarm_common::scene::demo::{GltfBuilder, emitter, lambert, turned_box};
use pathfarm_common::scene::{LoadOptions, Projection, Scene, SceneError, load_scene, load_scene_from_slice};
use serde_json::json;
use std::path::PathBuf;

fn load(bytes: &[u8]) -> Result<Scene, SceneError> {
    load_scene_from_slice(bytes, "anim.glb", None, &LoadOptions::default())
}

fn close(a: Vec3, b: Vec3, eps: f32) -> bool {
    (a - b).abs().max_element() <= eps
}

/// A strip along +X (x = 0..2, y = +-0.1, tangents +X with handedness -1) skinned to two joints: j0 at the origin, j1 its child
/// at x = 1; vertex weights blend linearly from j0 (x <= 0.5) to j1 (x >= 1.5). j0 moves
/// along +Z and j1 bends about Z by up to 90 degrees. The mesh node's own transform must be
/// ignored (glTF: skinned meshes are placed by their joints).
#[test]
fn linear_blend_skinning_matches_a_reference() {
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("grey", Vec3::splat(0.5)));
    let xs = [0.0f32, 0.5, 1.0, 1.5, 2.0];
    let pos: Vec<Vec3> = xs.iter().flat_map(|&x| [Vec3::new(x, -0.1, 0.0), Vec3::new(x, 0.1, 0.0)]).collect();
    let nrm = vec![Vec3::Z; pos.len()];
    let idx: Vec<u32> = (0..4u32).flat_map(|i| [2 * i, 2 * i + 2, 2 * i + 3, 2 * i, 2 * i + 3, 2 * i + 1]).collect();
    let strip = b.mesh("strip", &pos, &nrm, &idx, m);
    b.tangents(strip, &vec![Vec4::new(1.0, 0.0, 0.0, -1.0); pos.len()]);
    b.node_mut(strip)["translation"] = json!([5.0, 5.0, 5.0]);
    let j1 = b.node(json!({"name": "j1", "translation": [1.0, 0.0, 0.0]}));
    let j0 = b.node(json!({"name": "j0", "children": [j1]}));
    let w1 = |x: f32| (x - 0.5).clamp(0.0, 1.0);
    let weights: Vec<[f32; 4]> = pos.iter().map(|p| [1.0 - w1(p.x), w1(p.x), 0.0, 0.0]).collect();
    let ibm = [Mat4::IDENTITY, Mat4::from_translation(Vec3::new(-1.0, 0.0, 0.0))];
    b.skin(strip, &[j0, j1], &ibm, &vec![[0, 1, 0, 0]; pos.len()], &weights);
    b.animate(
        "bend",
        json!({"node": j0, "path": "translation"}),
        "LINEAR",
        &[0.0, 1.0],
        &[0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        "VEC3",
    );
    let q: Vec<f32> = [Quat::IDENTITY, Quat::from_rotation_z(std::f32::consts::FRAC_PI_2)]
        .iter()
        .flat_map(|q| q.to_array())
        .collect();
    b.animate("bend", json!({"node": j1, "path": "rotation"}), "LINEAR", &[0.0, 1.0], &q, "VEC4");
    let scene = load(&b.to_glb()).expect("loads");
    for t in [0.0f32, 0.5, 1.0, 3.0] {
        let posed = scene.posed(t, None).expect("poses");
        let mesh = posed.meshes.iter().find(|m| m.name.contains("strip")).expect("strip");
        // The reference: joint worlds from the analytic pose, skin matrix per vertex.
        let u = t.clamp(0.0, 1.0);
        let world0 = Mat4::from_translation(Vec3::new(0.0, 0.0, u));
        let world1 =
            world0 * Mat4::from_rotation_translation(Quat::from_rotation_z(u * std::f32::consts::FRAC_PI_2), Vec3::X);
        for (i, p) in pos.iter().enumerate() {
            let m = world0 * ibm[0] * weights[i][0] + world1 * ibm[1] * weights[i][1];
            let expected = m.transform_point3(*p);
            assert!(close(mesh.positions[i], expected, 1e-5), "t {t} vertex {i}: {} vs {expected}", mesh.positions[i]);
            let n = (Mat3::from_mat4(m).inverse().transpose() * Vec3::Z).normalize();
            let got = mesh.normals.as_ref().expect("normals")[i];
            assert!(close(got, n, 1e-5), "t {t} vertex {i}: normal {got} vs {n}");
            let tangent = (Mat3::from_mat4(m) * Vec3::X).normalize();
            let got = mesh.tangents.as_ref().expect("tangents")[i];
            assert!(
                close(got.truncate(), tangent, 1e-5) && got.w == -1.0,
                "t {t} vertex {i}: tangent {got} vs {tangent}"
            );
        }
    }
    // Halfway, the tip (x = 2, weight 1 on j1) is at j1 rotated by 45 degrees: (1 + cos 45 ...).
    let posed = scene.posed(0.5, None).expect("poses");
    let tip = posed.meshes[0].positions[8];
    let a = std::f32::consts::FRAC_PI_4;
    assert!(close(tip, Vec3::new(1.0 + a.cos() + 0.1 * a.sin(), a.sin() - 0.1 * a.cos(), 0.5), 1e-5), "{tip}");
}

/// Morph targets: position = base + sum of weight x displacement, normals likewise
/// (normalized); animated node weights (LINEAR) override the mesh's default weights, which
/// apply when no animation plays.
#[test]
fn morph_targets_follow_animated_weights() {
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("grey", Vec3::splat(0.5)));
    let pos = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y];
    let quad = b.mesh("quad", &pos, &[Vec3::Z; 4], &[0, 1, 2, 0, 2, 3], m);
    let dp = [Vec3::new(0.0, 0.0, 2.0), Vec3::ZERO, Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0)];
    let dn = [Vec3::new(1.0, 0.0, 0.0), Vec3::ZERO, Vec3::ZERO, Vec3::ZERO];
    b.morph_target(quad, &dp, &dn, 0.5);
    b.animate("grow", json!({"node": quad, "path": "weights"}), "LINEAR", &[0.0, 2.0], &[0.0, 1.0], "SCALAR");
    let scene = load(&b.to_glb()).expect("loads");
    for (t, w) in [(0.0f32, 0.0f32), (0.5, 0.25), (2.0, 1.0)] {
        let posed = scene.posed(t, None).expect("poses");
        let mesh = &posed.meshes[0];
        for i in 0..4 {
            assert!(close(mesh.positions[i], pos[i] + dp[i] * w, 1e-6), "t {t} vertex {i}: {}", mesh.positions[i]);
        }
        let n0 = mesh.normals.as_ref().expect("normals")[0];
        assert!(close(n0, (Vec3::Z + Vec3::X * w).normalize(), 1e-6), "t {t}: normal {n0}");
    }
    let rest = scene.posed(1.0, Some(&[])).expect("poses");
    assert!(close(rest.meshes[0].positions[0], Vec3::new(0.0, 0.0, 1.0), 1e-6), "default weight 0.5");
}

/// KHR_animation_pointer on a material (baseColorFactor, emissive strength), a light
/// (intensity, colour) and a camera (yfov), sampled at t = 0.5 against hand-computed values.
#[test]
fn animation_pointers_reach_materials_lights_and_cameras() {
    let mut b = GltfBuilder::new();
    let glow = b.material(emitter("glow", Vec3::ONE, Vec3::splat(2.0)));
    turned_box(&mut b, "box", Vec3::ZERO, Vec3::ONE, 0.0, glow);
    b.camera(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y, 0.5, 1.0);
    b.point_light(Vec3::new(0.0, 3.0, 0.0), Vec3::ONE, 10.0);
    let ptr = |p: &str| json!({"path": "pointer", "extensions": {"KHR_animation_pointer": {"pointer": p}}});
    b.animate(
        "p",
        ptr("/materials/0/pbrMetallicRoughness/baseColorFactor"),
        "LINEAR",
        &[0.0, 1.0],
        &[1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0],
        "VEC4",
    );
    b.animate(
        "p",
        ptr("/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength"),
        "STEP",
        &[0.0, 0.4],
        &[1.0, 7.0],
        "SCALAR",
    );
    b.animate(
        "p",
        ptr("/extensions/KHR_lights_punctual/lights/0/intensity"),
        "LINEAR",
        &[0.0, 1.0],
        &[10.0, 20.0],
        "SCALAR",
    );
    b.animate("p", ptr("/extensions/KHR_lights_punctual/lights/0/color"), "STEP", &[0.0], &[1.0, 0.5, 0.25], "VEC3");
    b.animate("p", ptr("/cameras/0/perspective/yfov"), "LINEAR", &[0.0, 1.0], &[0.5, 1.0], "SCALAR");
    b.animate("p", ptr("/materials/0/alphaCutoff"), "LINEAR", &[0.0, 1.0], &[0.0, 1.0], "SCALAR");
    let scene = load(&b.to_glb()).expect("loads");
    assert!(
        scene.warnings.iter().any(|w| w.contains("/materials/0/alphaCutoff") && w.contains("skipped")),
        "{:?}",
        scene.warnings
    );
    let posed = scene.posed(0.5, None).expect("poses");
    let mat = &posed.materials[0];
    assert!((mat.base_color - Vec4::new(0.5, 0.0, 0.5, 1.0)).abs().max_element() < 1e-6, "{}", mat.base_color);
    // emitter(): factor (1, 1, 1) x strength; the strength key at 0.4 (STEP) holds at 0.5.
    assert!(close(mat.emissive, Vec3::splat(7.0), 1e-6), "{}", mat.emissive);
    // The animated intensity is in candela, as the file's: /683 lm/W makes it W/sr.
    let watts = Vec3::new(15.0, 7.5, 3.75) / pathfarm_common::scene::LUMENS_PER_WATT;
    assert!(close(posed.lights[0].intensity, watts, 1e-7), "{}", posed.lights[0].intensity);
    match posed.cameras[0].projection {
        Projection::Perspective { yfov, .. } => assert!((yfov - 0.75).abs() < 1e-6, "{yfov}"),
        p => panic!("{p:?}"),
    }
    // Loading poses at t = 0: the first keys.
    assert!((scene.materials[0].base_color - Vec4::new(1.0, 0.0, 0.0, 1.0)).abs().max_element() < 1e-6);
    assert!(close(
        scene.lights[0].intensity,
        Vec3::new(10.0, 5.0, 2.5) / pathfarm_common::scene::LUMENS_PER_WATT,
        1e-7
    ));
}

/// A scene with animations loads posed at t = 0 (every animation playing), not at its rest
/// pose; with no animation playing it is at the rest pose.
#[test]
fn loading_poses_at_time_zero() {
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("grey", Vec3::splat(0.5)));
    let cube = turned_box(&mut b, "cube", Vec3::ZERO, Vec3::splat(0.5), 0.0, m);
    b.node_mut(cube)["translation"] = json!([3.0, 0.0, 0.0]);
    b.animate(
        "a",
        json!({"node": cube, "path": "translation"}),
        "LINEAR",
        &[0.0, 1.0],
        &[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        "VEC3",
    );
    let scene = load(&b.to_glb()).expect("loads");
    let center = |s: &Scene| s.bounds().map(|(lo, hi)| (lo + hi) * 0.5).expect("bounds");
    assert!(close(center(&scene), Vec3::new(-1.0, 0.0, 0.0), 1e-6), "{}", center(&scene));
    assert!(close(center(&scene.posed(0.25, None).expect("poses")), Vec3::new(-0.5, 0.0, 0.0), 1e-6));
    assert!(close(center(&scene.posed(0.25, Some(&[])).expect("poses")), Vec3::new(3.0, 0.0, 0.0), 1e-6));
    let err = scene.posed(0.0, Some(&["walk".to_string()])).expect_err("unknown").to_string();
    assert!(err.contains("\"walk\" does not exist") && err.contains("\"a\""), "{err}");
    assert_eq!(scene.animation_names(), ["a"]);
}

/// Broken channels are refused at load, naming the animation, the channel and the problem.
#[test]
fn broken_channels_are_refused_by_name() {
    let broken = |target: serde_json::Value, values: &[f32], type_: &str| {
        let mut b = GltfBuilder::new();
        let m = b.material(lambert("grey", Vec3::splat(0.5)));
        turned_box(&mut b, "cube", Vec3::ZERO, Vec3::ONE, 0.0, m);
        b.animate("bad", target, "LINEAR", &[0.0, 1.0], values, type_);
        load(&b.to_glb()).expect_err("refused").to_string()
    };
    let e = broken(json!({"node": 9, "path": "translation"}), &[0.0; 6], "VEC3");
    assert!(e.contains("animation 0 \"bad\" channel 0") && e.contains("index 9 does not exist"), "{e}");
    let e = broken(json!({"node": 0, "path": "translation"}), &[0.0; 8], "VEC4");
    assert!(e.contains("channel 0") && e.contains("needs 3 per key"), "{e}");
    let e = broken(json!({"node": 0, "path": "rotation"}), &[f32::NAN; 8], "VEC4");
    assert!(e.contains("non-finite"), "{e}");
}

/// Animation keys are budgeted from the accessors' declared sizes before they are read: a tiny
/// file whose sampler names bufferless accessors of 4M keys (all zeros, 20M numbers) is refused.
#[test]
fn animation_keys_are_budgeted_before_reading() {
    use base64::Engine as _;
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("grey", Vec3::splat(0.5)));
    turned_box(&mut b, "cube", Vec3::ZERO, Vec3::ONE, 0.0, m);
    let uri =
        format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(b.bin()));
    let mut doc = b.document(Some(&uri));
    let accessors = doc["accessors"].as_array_mut().expect("accessors");
    let n = accessors.len();
    accessors.push(json!({"componentType": 5126, "count": 4_000_000, "type": "SCALAR"}));
    accessors.push(json!({"componentType": 5126, "count": 4_000_000, "type": "VEC4"}));
    doc["animations"] = json!([{"name": "huge", "samplers": [{"input": n, "output": n + 1}],
        "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}]}]);
    let bytes = serde_json::to_vec(&doc).expect("json");
    let err = load(&bytes).expect_err("refused").to_string();
    assert!(err.contains("animation keys hold more than"), "{err}");
}

fn corpus() -> PathBuf {
    let dir = std::env::var_os("PATHFARM_CORPUS").map(PathBuf::from).expect(
        "PATHFARM_CORPUS is not set: point it at the third-party scene folder (../shared/scenes) to run the corpus suite",
    );
    assert!(dir.is_dir(), "PATHFARM_CORPUS={} is not a folder", dir.display());
    dir
}

/// The KHR_animation_pointer sample scene poses at several times without error, and what it
/// animates changes: some material, light, camera and vertex differ between t = 0 and t = 1.5.
#[test]
#[ignore = "corpus: needs PATHFARM_CORPUS (the third-party scenes, ../shared/scenes)"]
fn animation_pointer_scene_poses_and_changes() {
    let path = corpus().join("24_animation_pointer/24_animation_pointer.gltf");
    let scene = load_scene(&path, &LoadOptions::default()).expect("loads");
    assert_eq!(scene.animation_names(), ["AllAnimatedProperties"]);
    let a = scene.posed(0.0, None).expect("t = 0");
    let b = scene.posed(1.5, None).expect("t = 1.5");
    for t in [-1.0f32, 0.3, 0.77, 2.9, 100.0] {
        scene.posed(t, None).unwrap_or_else(|e| panic!("t = {t}: {e}"));
    }
    let materials = a
        .materials
        .iter()
        .zip(&b.materials)
        .filter(|(x, y)| x.base_color != y.base_color || x.emissive != y.emissive || x.roughness != y.roughness)
        .count();
    let lights = a.lights.iter().zip(&b.lights).filter(|(x, y)| x.intensity != y.intensity || x.kind != y.kind).count();
    let cameras = a.cameras.iter().zip(&b.cameras).filter(|(x, y)| x.projection != y.projection).count();
    let vertices = a.meshes.iter().zip(&b.meshes).filter(|(x, y)| x.positions != y.positions).count();
    assert!(
        materials > 0 && lights > 0 && cameras > 0 && vertices > 0,
        "changed: {materials} materials, {lights} lights, {cameras} cameras, {vertices} meshes"
    );
}
