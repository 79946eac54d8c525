//! The user-facing commands as processes: the README's demo, and the `pathfarm` client.

mod support;

use pathfarm_common::job::{IntegratorSettings, PassSchedule, RenderSettings};
use pathfarm_common::scene::demo::cornell_demo_glb;
use std::process::Command;
use support::*;

#[test]
fn the_demo_command_leaves_an_exr_and_a_png() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("demo");
    let status = Command::new(bin("pathfarm-coordinator"))
        .args(["demo", "--width", "48", "--height", "32", "--spp", "8", "--local-workers", "2", "--out"])
        .arg(&out)
        .env("RUST_LOG", "warn")
        .output()
        .expect("run demo");
    let stderr = String::from_utf8_lossy(&status.stderr);
    assert!(status.status.success(), "{stderr}");
    // Two local workers share one scene cache; neither may fail a unit on the other's files.
    assert!(!stderr.contains("ERROR"), "the demo logged errors:\n{stderr}");
    let exr = pathfarm_common::film::read_exr(&out.join("demo.exr")).expect("demo.exr reads back");
    let r = exr.get("R").expect("R channel");
    assert_eq!(r.len(), 48 * 32);
    assert!(r.iter().any(|&v| v > 0.0), "the demo image is black");
    assert_eq!(exr.get("samples.Y").expect("samples").iter().copied().fold(0.0f32, f32::max), 8.0);
    let png = image::open(out.join("demo.png")).expect("demo.png decodes");
    assert_eq!((png.width(), png.height()), (48, 32));
}

#[test]
fn the_client_submits_waits_and_fetches_the_same_bits_as_a_local_render() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _w = start_worker(&coord.url, "w", &dir.path().join("cache"), &[]);
    let scene_path = dir.path().join("scene.glb");
    let scene = cornell_demo_glb();
    std::fs::write(&scene_path, &scene).expect("write scene");
    let out = dir.path().join("out.exr");
    let output = Command::new(bin("pathfarm"))
        .args(["--server", &coord.url, "submit"])
        .arg(&scene_path)
        .args(["--width", "40", "--height", "24", "--spp", "6", "--integrator", "direct", "--seed", "5"])
        .args(["--tile-size", "16", "--pass-spp", "2", "--name", "cli", "--wait", "--out"])
        .arg(&out)
        .output()
        .expect("run client");
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let id: u64 = String::from_utf8_lossy(&output.stdout).trim().parse().expect("job id on stdout");
    let mut s = RenderSettings::new(40, 24, 6);
    s.seed = 5;
    s.tile_size = 16;
    s.passes = PassSchedule::Fixed { spp: 2 };
    s.integrator = IntegratorSettings::Direct { mis: Default::default(), light_sampling: Default::default() };
    assert!(std::fs::read(&out).expect("out.exr") == local_exr(&scene, &s), "client's EXR differs from a local render");
    let status = Command::new(bin("pathfarm")).args(["--server", &coord.url, "status"]).output().expect("status");
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(text.contains("completed") && text.contains(&id.to_string()), "{text}");
    let bad = Command::new(bin("pathfarm")).args(["--server", &coord.url, "cancel", "999"]).output().expect("cancel");
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("job 999 does not exist"));
}

/// `pathfarm submit scene.gltf` of a "glTF Separate" export (.gltf + .bin + .png) packs the
/// files itself; the farm's image equals a local render of the same files as a tar bundle. A
/// missing buffer is refused before anything is uploaded, naming the file.
#[test]
fn the_client_packs_a_separate_gltf_with_its_files() {
    let dir = tempfile::tempdir().expect("tempdir");
    let coord = start_coordinator(&dir.path().join("data"), &[]);
    let _w = start_worker(&coord.url, "w", &dir.path().join("cache"), &[]);
    let export = dir.path().join("export");
    let files = pathfarm_common::scene::demo::cornell_separate_files();
    for (name, bytes) in &files {
        std::fs::create_dir_all(export.join(name).parent().expect("parent")).expect("mkdir");
        std::fs::write(export.join(name), bytes).expect("write");
    }
    let out = dir.path().join("out.exr");
    let output = Command::new(bin("pathfarm"))
        .args(["--server", &coord.url, "submit"])
        .arg(export.join("cornell.gltf"))
        .args(["--width", "32", "--height", "24", "--spp", "4", "--integrator", "direct", "--tile-size", "16"])
        .args(["--wait", "--out"])
        .arg(&out)
        .output()
        .expect("run client");
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let bundle = pathfarm_common::scene::bundle::tar_bundle(&refs).expect("tar");
    let mut s = RenderSettings::new(32, 24, 4);
    s.tile_size = 16;
    s.integrator = IntegratorSettings::Direct { mis: Default::default(), light_sampling: Default::default() };
    assert!(std::fs::read(&out).expect("out.exr") == local_exr(&bundle, &s), "packed .gltf renders differently");

    std::fs::remove_file(export.join("cornell.bin")).expect("rm");
    let output = Command::new(bin("pathfarm"))
        .args(["--server", &coord.url, "submit"])
        .arg(export.join("cornell.gltf"))
        .args(["--width", "32", "--height", "24", "--spp", "4"])
        .output()
        .expect("run client");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("cornell.bin"), "{stderr}");
}
