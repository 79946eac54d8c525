//! `pathfarm-worker render` as a real process: its EXR equals the in-process render bit for
//! bit, and bad input gives a usage error or a message naming the problem, never a panic.

mod common;

use common::glb_scene;
use pathfarm_common::film::read_exr;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_worker::render::{Renderer, render_local};
use std::process::Command;

fn worker() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pathfarm-worker"))
}

#[test]
fn render_cli_matches_in_process_render_bit_for_bit() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene_path = dir.path().join("demo.glb");
    std::fs::write(&scene_path, cornell_demo_glb()).expect("write scene");
    let out = dir.path().join("out.exr");
    let png = dir.path().join("out.png");
    let status = worker()
        .args(["render"])
        .arg(&scene_path)
        .args(["--width", "40", "--height", "24", "--spp", "6", "--integrator", "path", "--seed", "3"])
        .args(["--max-depth", "5", "--tile-size", "16", "--threads", "2", "--quiet", "--out"])
        .arg(&out)
        .arg("--png")
        .arg(&png)
        .status()
        .expect("run pathfarm-worker");
    assert!(status.success());
    assert!(png.exists());

    let mut s = RenderSettings::new(40, 24, 6);
    s.seed = 3;
    s.tile_size = 16;
    s.integrator = IntegratorSettings::Path {
        max_depth: 5,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    let scene = glb_scene(&cornell_demo_glb());
    let local = render_local(&Renderer::new(&scene, &s).expect("renderer"), |_, _| {}).resolve();
    let file = read_exr(&out).expect("read exr");
    for (name, values) in local.exr_channels() {
        let theirs = file.get(name).unwrap_or_else(|| panic!("{name} missing"));
        assert!(
            values.iter().zip(theirs).all(|(a, b)| a.to_bits() == b.to_bits()),
            "channel {name} differs between the CLI and the in-process render"
        );
    }
}

#[test]
fn bad_flags_and_files_fail_cleanly() {
    let bad_flag = worker().args(["render", "x.glb", "--width", "many"]).output().expect("run");
    assert_eq!(bad_flag.status.code(), Some(2), "usage errors exit with 2");
    assert!(String::from_utf8_lossy(&bad_flag.stderr).contains("--width"));

    let unknown = worker().args(["render", "x.glb", "--integrator", "magic"]).output().expect("run");
    assert_eq!(unknown.status.code(), Some(2));

    let missing = worker().args(["render", "/nonexistent/scene.glb", "--quiet"]).output().expect("run");
    assert!(!missing.status.success());
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(err.contains("scene.glb") && !err.contains("panicked"), "{err}");

    let dir = tempfile::tempdir().expect("tempdir");
    let garbage = dir.path().join("garbage.glb");
    std::fs::write(&garbage, b"glTF not really").expect("write");
    let bad = worker().arg("render").arg(&garbage).arg("--quiet").output().expect("run");
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("garbage.glb") && !err.contains("panicked"), "{err}");

    let zero = worker().args(["render", "x.glb", "--spp", "0", "--quiet"]).output().expect("run");
    assert!(!zero.status.success());
    assert!(String::from_utf8_lossy(&zero.stderr).contains("spp"), "the error names the setting");
}

/// A binary built without the `denoise` feature refuses `--denoise` before rendering, saying
/// how to get one that can.
#[cfg(not(feature = "denoise"))]
#[test]
fn denoise_without_the_feature_is_a_clear_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = worker()
        .args(["render", "no-such-scene.glb", "--denoise", "--out"])
        .arg(dir.path().join("x.exr"))
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot denoise") && err.contains("pyoidn"), "{err}");
}

/// `--frames 1-3 --fps 4 --out 'seq/shot.####.exr'` writes one EXR per frame (the `#` run
/// zero-padded), each bit-identical to the in-process render of that frame; the keyframed cube
/// moves, so the frames differ.
#[test]
fn render_cli_writes_a_sequence_of_frames() {
    use glam::Vec3;
    use pathfarm_common::scene::demo::{GltfBuilder, lambert, turned_box};
    let mut b = GltfBuilder::new();
    let red = b.material(lambert("red", Vec3::new(1.0, 0.0, 0.0)));
    let cube = turned_box(&mut b, "cube", Vec3::ZERO, Vec3::splat(0.5), 0.0, red);
    b.ortho_camera(Vec3::new(0.0, 0.0, 5.0), 2.0, 2.0);
    b.point_light(Vec3::new(0.0, 0.0, 5.0), Vec3::ONE, 10.0);
    let target = serde_json::json!({"node": cube, "path": "translation"});
    b.animate("move", target, "LINEAR", &[0.0, 1.0], &[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0], "VEC3");
    let glb = b.to_glb();
    let dir = tempfile::tempdir().expect("tempdir");
    let scene_path = dir.path().join("anim.glb");
    std::fs::write(&scene_path, &glb).expect("write scene");
    let status = worker()
        .args(["render"])
        .arg(&scene_path)
        .args(["--width", "24", "--height", "24", "--spp", "2", "--frames", "1-3", "--fps", "4", "--quiet", "--out"])
        .arg(dir.path().join("seq/shot.####.exr"))
        .status()
        .expect("run pathfarm-worker");
    assert!(status.success());
    let scene = glb_scene(&glb);
    let mut previous: Option<Vec<f32>> = None;
    for frame in 1..=3 {
        let file = read_exr(&dir.path().join(format!("seq/shot.000{frame}.exr"))).expect("frame written");
        let mut s = RenderSettings::new(24, 24, 2);
        s.frame = frame;
        s.fps = 4.0;
        let local = render_local(&Renderer::new(&scene, &s).expect("renderer"), |_, _| {}).resolve();
        for (name, values) in local.exr_channels() {
            let theirs = file.get(name).unwrap_or_else(|| panic!("{name} missing"));
            assert!(values.iter().zip(theirs).all(|(a, b)| a.to_bits() == b.to_bits()), "frame {frame} {name}");
        }
        let albedo = file.get("albedo.R").expect("albedo").to_vec();
        assert!(previous.as_ref() != Some(&albedo), "frame {frame} equals the previous one");
        previous = Some(albedo);
    }
}
