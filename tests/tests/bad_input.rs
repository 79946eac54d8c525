//! Bad input against a real coordinator process: every refusal has the right status, a JSON
//! error body whose message names the problem, and the server keeps serving afterwards.
//!
//! Needs the release binaries: `cargo build --release -p pathfarm-coordinator -p pathfarm-worker`
//! then `cargo test --release -p pathfarm-tests --test bad_input`.

use glam::Vec3;
use pathfarm_common::film::TileAccum;
use pathfarm_common::protocol::{LeaseGrant, Registered, UnitResultFrame};
use pathfarm_common::scene::LoadOptions;
use pathfarm_common::scene::bundle::tar_bundle;
use pathfarm_common::scene::demo::{GltfBuilder, cornell_demo_glb, lambert};
use pathfarm_common::scene::load_scene_from_slice;
use pathfarm_tests::procs::{Coordinator, assert_exr_identical, error_code, expect_error, render_local};
use pathfarm_worker::render::Renderer;
use reqwest::StatusCode;
use serde_json::json;
use std::time::Duration;

fn start(extra: &[&str]) -> Coordinator {
    Coordinator::start(extra).expect("start the coordinator")
}

// ------------------------------------------------------------------------------- uploads

/// Sends a request head declaring `len` body bytes and no body (the server answers before it
/// reads a body over the limit; a client still writing it could see its connection reset before
/// reading the answer): the status code and the body of the answer.
fn declare_only(c: &Coordinator, method: &str, path: &str, len: usize) -> (u16, String) {
    use std::io::{Read, Write};
    let addr = c.url.trim_start_matches("http://");
    let mut s = std::net::TcpStream::connect(addr).expect("connect");
    let head = format!("{method} /api/v1{path} HTTP/1.1\r\nHost: x\r\nContent-Length: {len}\r\n\r\n");
    s.write_all(head.as_bytes()).expect("head");
    s.set_read_timeout(Some(Duration::from_secs(5))).expect("timeout");
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let text = String::from_utf8_lossy(&out).to_string();
    let status = text.get(9..12).and_then(|c| c.parse().ok()).unwrap_or(0);
    (status, text)
}

#[test]
fn upload_over_the_size_limit_is_413() {
    let mut c = start(&["--max-upload-mb", "1"]);
    let (status, text) = declare_only(&c, "POST", "/scenes", 2 << 20);
    assert_eq!(status, 413, "{text}");
    assert!(text.contains("limit") && text.contains("1048576") && text.contains("bytes"), "{text}");
    // Results have the same limit.
    let (status, text) = declare_only(&c, "PUT", "/leases/1/result", 2 << 20);
    assert_eq!(status, 413, "{text}");
    assert!(text.contains("limit"), "{text}");
    c.assert_serving();
    // A scene under the limit is still accepted.
    c.upload_ok(cornell_demo_glb());
}

#[test]
fn invalid_gltf_is_422_with_the_loaders_message() {
    let mut c = start(&[]);
    let cases: [(&[u8], &[&str]); 5] = [
        (b"hello, I am not a scene", &["not a scene bundle"]),
        (b"{\"asset\": {\"version\": ", &["scene.gltf", "invalid json"]),
        (b"{\"asset\": {\"version\": \"2.0\"}, \"meshes\": 7}", &["scene.gltf", "invalid gltf"]),
        (b"glTF\x02\0\0\0\xff\xff\0\0garbage", &["scene.glb", "glb"]),
        (
            b"{\"asset\": {\"version\": \"2.0\"}, \"buffers\": [{\"byteLength\": 64, \"uri\": \"data:application/octet-stream;base64,AAAA\"}]}",
            &["scene.gltf", "buffer 0", "bytelength"],
        ),
    ];
    for (bytes, needles) in cases {
        let r = c.upload(bytes.to_vec());
        expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, needles);
    }
    let r = c.upload(Vec::new());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["empty"]);
    c.assert_serving();
}

#[test]
fn gltf_uris_leaving_the_bundle_are_422() {
    let mut c = start(&[]);
    let uris = [
        ("/etc/passwd", "absolute"),
        ("../../secret.bin", "outside the bundle"),
        ("textures/../../x.bin", "outside the bundle"),
        ("%2e%2e/x.bin", "outside the bundle"),
        ("file:///etc/passwd", "only data: uris"),
        ("http://example.com/scene.bin", "only data: uris"),
        ("C:\\Windows\\win.ini", "only data: uris"),
    ];
    for (uri, reason) in uris {
        let doc = json!({"asset": {"version": "2.0"}, "buffers": [{"byteLength": 4, "uri": uri}]});
        let r = c.upload(serde_json::to_vec(&doc).expect("json"));
        let msg = expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["buffer 0", reason]);
        assert!(msg.contains(&format!("{uri:?}")), "{msg} does not name {uri}");
        // Images too.
        let doc = json!({"asset": {"version": "2.0"}, "images": [{"uri": uri}],
            "textures": [{"source": 0}], "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]});
        let r = c.upload(serde_json::to_vec(&doc).expect("json"));
        let r_code = error_code(r, StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(r_code, "forbidden_uri", "image uri {uri}");
    }
    // A tar entry that would leave the unpack directory.
    let mut tar = tar_bundle(&[("scene.gltf", b"{}".as_slice())]).expect("tar");
    let name = b"../evil.gltf";
    tar[..100].fill(0);
    tar[..name.len()].copy_from_slice(name);
    fix_tar_checksum(&mut tar[..512]);
    let r = c.upload(tar);
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["evil.gltf", "inside the bundle"]);
    c.assert_serving();
}

fn fix_tar_checksum(header: &mut [u8]) {
    header[148..156].fill(b' ');
    let sum: u32 = header.iter().map(|&b| u32::from(b)).sum();
    let s = format!("{sum:06o}\0 ");
    header[148..156].copy_from_slice(s.as_bytes());
}

// ------------------------------------------------------------------------------- limits

#[test]
fn triangle_limit_is_422_naming_the_limit() {
    let mut c = start(&["--max-triangles", "10"]);
    let r = c.upload(cornell_demo_glb());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["max_triangles", "10"]);
    c.assert_serving();
}

/// Concurrent uploads of the same bundle each unpack into their own scratch folder (they shared
/// one: 6 parallel uploads got 422 in 4 of 5 rounds). Five rounds of six; a missing file's error
/// names the file, never a server path.
#[test]
fn concurrent_uploads_of_one_scene_all_succeed() {
    let c = start(&[]);
    for round in 0..5u8 {
        let mut files = pathfarm_common::scene::demo::cornell_separate_files();
        files.push(("round.txt".to_string(), vec![round; 16]));
        let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
        let bundle = tar_bundle(&refs).expect("tar");
        let statuses: Vec<StatusCode> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..6).map(|_| s.spawn(|| c.upload(bundle.clone()).status())).collect();
            handles.into_iter().map(|h| h.join().expect("upload thread")).collect()
        });
        assert!(statuses.iter().all(|s| *s == StatusCode::CREATED), "round {round}: {statuses:?}");
    }
    let files = pathfarm_common::scene::demo::cornell_separate_files();
    let refs: Vec<(&str, &[u8])> =
        files.iter().filter(|(n, _)| n != "cornell.bin").map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let msg =
        expect_error(c.upload(tar_bundle(&refs).expect("tar")), StatusCode::UNPROCESSABLE_ENTITY, &["cornell.bin"]);
    let data_dir = c.dir.path().to_string_lossy().into_owned();
    assert!(!msg.contains(&data_dir) && !msg.contains("/tmp/"), "the message reveals a server path: {msg}");
}

/// A vertex at 1e25 used to pass the upload and then crash every worker in the BVH build.
#[test]
fn huge_coordinates_are_422_naming_the_mesh() {
    let mut c = start(&[]);
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("white", Vec3::ONE));
    let p = [Vec3::ZERO, Vec3::new(1e25, 0.0, 0.0), Vec3::Y];
    b.mesh("far-away", &p, &[Vec3::Z; 3], &[0, 1, 2], m);
    let r = c.upload(b.to_glb());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["mesh 0", "far-away", "finite and within", "1e7"]);
    c.assert_serving();
}

/// Image memory per scene is budgeted before decoding (--max-texture-mb): a 256 x 256 image
/// needs 1.5 MiB (decode buffer, RGBA copy, linear texels), over a 1 MiB budget.
#[test]
fn image_memory_budget_is_422_naming_the_limit() {
    let mut files = pathfarm_common::scene::demo::cornell_separate_files();
    let mut png = Vec::new();
    image::RgbaImage::from_pixel(256, 256, image::Rgba([200, 200, 200, 255]))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("png");
    for (name, bytes) in &mut files {
        if name == "checker.png" {
            *bytes = png.clone();
        }
    }
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let bundle = tar_bundle(&refs).expect("tar");
    let mut c = start(&["--max-texture-mb", "1"]);
    let r = c.upload(bundle.clone());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["max_texture_bytes", "1048576", "image memory"]);
    c.assert_serving();
    start(&["--max-texture-mb", "2"]).upload_ok(bundle);
}

#[test]
fn texture_size_limit_is_422_naming_the_limit() {
    let mut c = start(&["--max-texture-pixels", "64"]);
    // A .gltf + .bin + 16 x 16 PNG bundle (256 texels > 64).
    let files = pathfarm_common::scene::demo::cornell_separate_files();
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    let bundle = tar_bundle(&refs).expect("tar");
    let r = c.upload(bundle.clone());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["max_texture_pixels", "64", "image"]);
    c.assert_serving();
    // The same bundle under a default server is fine (the limit, not the file, refused it).
    let c2 = start(&[]);
    c2.upload_ok(bundle);
}

#[test]
fn job_settings_over_the_limits_are_422_naming_the_limit() {
    let mut c = start(&[]);
    let scene = c.upload_ok(cornell_demo_glb());
    let base = json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1});
    let with = |k: &str, v: serde_json::Value| {
        let mut b = base.clone();
        b[k] = v;
        b
    };
    let cases = [
        (
            with("width", json!(16384)).as_object().cloned().map(|mut o| {
                o.insert("height".into(), json!(16384));
                serde_json::Value::Object(o)
            }),
            "width x height",
        ),
        (Some(with("width", json!(20000))), "width"),
        (Some(with("height", json!(0))), "height"),
        (Some(with("spp", json!(2_000_000))), "spp"),
        (Some(with("spp", json!(0))), "spp"),
        (Some(with("integrator", json!({"type": "path", "max_depth": 5000}))), "max_depth"),
        (Some(with("integrator", json!({"type": "bdpt", "max_depth": 5000}))), "max_depth"),
        (Some(with("tile_size", json!(2))), "tile_size"),
        (Some(with("tile_size", json!(100_000))), "tile_size"),
        (Some(with("passes", json!({"type": "fixed", "spp": 0}))), "passes.spp"),
        (Some(with("camera", json!(99))), "camera 99"),
        (Some(with("integrator", json!({"type": "igi", "vpls": 10_000_000}))), "vpls"),
    ];
    for (body, needle) in cases {
        let body = body.expect("body");
        let r = c.submit(&body);
        expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &[needle]);
    }
    // Negative and fractional numbers, wrong types: refused by the parser, naming the field's value.
    let r = c.submit(&with("width", json!(-5)));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["-5"]);
    let r = c.submit(&with("spp", json!("many")));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["many"]);
    // A scene that was never uploaded.
    let r = c.submit(&with("scene_id", json!("0".repeat(64))));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["scene_id", "not been uploaded"]);
    c.assert_serving();
    // Nothing was created.
    let jobs: serde_json::Value = c.client(c.http.get(c.api("/jobs"))).send().expect("jobs").json().expect("json");
    assert_eq!(jobs.as_array().map(Vec::len), Some(0), "{jobs}");
}

#[test]
fn job_limits_set_by_flags_are_422_naming_the_limit() {
    let mut c = start(&["--max-pixels", "10000", "--max-spp", "64", "--max-depth", "16"]);
    let scene = c.upload_ok(cornell_demo_glb());
    let job = |w: u32, h: u32, spp: u32, depth: u32| {
        json!({"scene_id": scene, "width": w, "height": h, "spp": spp,
            "integrator": {"type": "path", "max_depth": depth}})
    };
    let r = c.submit(&job(200, 100, 1, 8));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["width x height", "20000", "10000"]);
    let r = c.submit(&job(16, 16, 65, 8));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["spp", "65", "64"]);
    let r = c.submit(&job(16, 16, 1, 17));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["max_depth", "17", "16"]);
    // At the limits: accepted.
    c.submit_ok(&job(100, 100, 64, 16));
    c.assert_serving();
}

#[test]
fn unknown_json_fields_are_422() {
    let mut c = start(&[]);
    let scene = c.upload_ok(cornell_demo_glb());
    let r = c.submit(&json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1, "wdth": 3}));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["wdth"]);
    let r = c.submit(&json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1,
        "integrator": {"type": "path", "maxdepth": 3}}));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["maxdepth"]);
    let r = c.submit(&json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1,
        "integrator": {"type": "whitted"}}));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["whitted"]);
    let r = c.worker(c.http.post(c.api("/workers/register"))).json(&json!({"name": "w", "threads": 1, "gpu": true}));
    expect_error(r.send().expect("register"), StatusCode::UNPROCESSABLE_ENTITY, &["gpu"]);
    let id = c.submit_ok(&json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1}));
    let r = c.client(c.http.put(c.api(&format!("/jobs/{id}/priority")))).json(&json!({"priority": 1, "urgent": true}));
    expect_error(r.send().expect("priority"), StatusCode::UNPROCESSABLE_ENTITY, &["urgent"]);
    c.assert_serving();
}

/// Memory is bounded by configuration, not by what clients submit: the request that aborted the
/// coordinator (a 16 TiB unit table) is 422 naming the units, and a film beyond
/// --film-memory-mb is refused with the numbers; jobs whose film fits are queued (a queued job
/// holds no film); the server keeps serving.
#[test]
fn jobs_beyond_the_memory_budget_are_422() {
    let mut c = start(&["--film-memory-mb", "64"]);
    let scene = c.upload_ok(cornell_demo_glb());
    let r = c.submit(&json!({"scene_id": scene, "width": 8192, "height": 8192, "spp": 1_048_576,
        "tile_size": 8, "passes": {"type": "fixed", "spp": 1}}));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["units (tiles x passes)", "4194304"]);
    // 512 x 512 is 16 MiB of film (64 bytes per pixel): any number of them queue; 2048 x 1024
    // (128 MiB) never fits.
    for _ in 0..5 {
        c.submit_ok(&json!({"scene_id": scene, "width": 512, "height": 512, "spp": 1}));
    }
    let r = c.submit(&json!({"scene_id": scene, "width": 2048, "height": 1024, "spp": 1}));
    let msg = expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["128 MiB", "64 MiB", "--film-memory-mb"]);
    assert!(msg.contains("lower the resolution"), "{msg}");
    c.assert_serving();
}

#[test]
fn malformed_json_is_400() {
    let mut c = start(&[]);
    for body in [&b"{\"scene_id\": "[..], b"not json", b"", b"{\"a\":1}{"] {
        let r = c
            .client(c.http.post(c.api("/jobs")))
            .header("content-type", "application/json")
            .body(body.to_vec())
            .send()
            .expect("POST /jobs");
        expect_error(r, StatusCode::BAD_REQUEST, &["json"]);
    }
    // A JSON value that is not an object is well-formed but unprocessable.
    let r = c.submit(&json!([1, 2, 3]));
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["object"]);
    // Bad ids and query strings are 400 with a JSON body too.
    let r = c.client(c.http.get(c.api("/jobs/abc"))).send().expect("GET");
    expect_error(r, StatusCode::BAD_REQUEST, &["abc"]);
    let r = c.worker(c.http.post(c.api("/workers/1/lease?wait_ms=soon"))).send().expect("lease");
    expect_error(r, StatusCode::BAD_REQUEST, &["wait_ms"]);
    let r = c.client(c.http.delete(c.api("/scenes"))).send().expect("DELETE");
    expect_error(r, StatusCode::METHOD_NOT_ALLOWED, &["method"]);
    c.assert_serving();
}

// ------------------------------------------------------------------------------- worker side

/// A job small enough to render in a blink: 32 x 32, 2 spp, 16 px tiles, 1 spp per pass
/// (4 tiles x 2 passes = 8 units).
const JOB_ARGS: [&str; 8] = ["--width", "32", "--height", "32", "--spp", "2", "--tile-size", "16"];

struct Farm {
    c: Coordinator,
    job: u64,
    reg: Registered,
    renderer: Renderer,
    scene_file: std::path::PathBuf,
}

impl Farm {
    fn new(extra: &[&str]) -> Self {
        let c = start(extra);
        let glb = cornell_demo_glb();
        let scene_file = c.dir.path().join("cornell.glb");
        std::fs::write(&scene_file, &glb).expect("write scene");
        let scene_id = c.upload_ok(glb.clone());
        let body = json!({"scene_id": scene_id, "width": 32, "height": 32, "spp": 2, "tile_size": 16,
            "passes": {"type": "fixed", "spp": 1}});
        let job = c.submit_ok(&body);
        let reg = c.register("fake");
        let scene = load_scene_from_slice(&glb, "cornell.glb", None, &LoadOptions::default()).expect("scene");
        let settings = c.job(job).settings;
        let renderer = Renderer::new(&scene, &settings).expect("renderer");
        Self { c, job, reg, renderer, scene_file }
    }

    fn lease(&self) -> LeaseGrant {
        let url = self.c.api(&format!("/workers/{}/lease?wait_ms=2000", self.reg.worker_id));
        let r = self.c.as_worker(self.c.http.post(url), &self.reg).send().expect("lease");
        assert_eq!(r.status(), StatusCode::OK);
        r.json().expect("grant")
    }

    fn frame(&self, g: &LeaseGrant) -> UnitResultFrame {
        let out = self.renderer.render_unit(g.tile, g.pass);
        UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum: out.accum, splats: out.splats }
    }

    fn put(&self, lease: u64, body: Vec<u8>) -> reqwest::blocking::Response {
        self.c
            .as_worker(self.c.http.put(self.c.api(&format!("/leases/{lease}/result"))), &self.reg)
            .header("content-type", "application/octet-stream")
            .body(body)
            .send()
            .expect("PUT result")
    }

    fn units_merged(&self) -> u64 {
        self.c.job(self.job).units_merged
    }

    /// Lets a real worker finish the job, then compares the farm's EXR with a local render.
    fn finish_and_compare(mut self) {
        let _w = self.c.start_worker().expect("worker");
        let farm_exr = self.c.dir.path().join("farm.exr");
        self.c.wait_completed_exr(self.job, Duration::from_secs(60), &farm_exr);
        let info = self.c.job(self.job);
        assert_eq!(info.units_merged, info.units_total);
        let local_exr = self.c.dir.path().join("local.exr");
        let mut args = JOB_ARGS.to_vec();
        args.extend(["--pass-spp", "1"]);
        render_local(&self.scene_file, &local_exr, &args).expect("local render");
        assert_exr_identical(&farm_exr, &local_exr);
        self.c.assert_serving();
    }
}

#[test]
fn duplicate_result_is_409_and_not_merged() {
    let f = Farm::new(&[]);
    let g = f.lease();
    let body = f.frame(&g).encode();
    let r = f.put(g.lease_id, body.clone());
    assert_eq!(r.status(), StatusCode::OK, "{}", r.text().unwrap_or_default());
    let merged = f.units_merged();
    let r = f.put(g.lease_id, body);
    let msg = expect_error(r, StatusCode::CONFLICT, &[&format!("lease {}", g.lease_id), "not held"]);
    assert!(msg.contains("already delivered"), "{msg}");
    assert_eq!(f.units_merged(), merged, "the duplicate was merged");
    // The lease is checked before the body is decoded: garbage for it is also a 409.
    let r = f.put(g.lease_id, b"garbage".to_vec());
    expect_error(r, StatusCode::CONFLICT, &["not held"]);
    f.finish_and_compare();
}

#[test]
fn late_result_after_lease_expiry_is_409() {
    let f = Farm::new(&["--lease-timeout-ms", "400", "--heartbeat-ms", "100"]);
    let g = f.lease();
    let body = f.frame(&g).encode();
    // Expiry runs every 250 ms.
    std::thread::sleep(Duration::from_millis(1200));
    let r = f.put(g.lease_id, body);
    expect_error(r, StatusCode::CONFLICT, &[&format!("lease {}", g.lease_id), "expired"]);
    assert_eq!(f.units_merged(), 0);
    // The unit is handed out again, first.
    let again = f.lease();
    assert_eq!((again.unit, again.tile), (g.unit, g.tile));
    let r = f.put(again.lease_id, f.frame(&again).encode());
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(f.units_merged(), 1);
    f.finish_and_compare();
}

#[test]
fn corrupt_results_are_422_and_the_unit_requeued() {
    let f = Farm::new(&[]);
    let mut g = f.lease();
    let good = f.frame(&g);
    let bytes = good.encode();
    let mut variants: Vec<(&str, Vec<u8>, &[&str])> = Vec::new();
    variants.push(("truncated to 10 bytes", bytes[..10].to_vec(), &["truncated"]));
    variants.push(("truncated by half", bytes[..bytes.len() / 2].to_vec(), &["checksum"]));
    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x40;
    variants.push(("one bit flipped", flipped, &["checksum"]));
    let mut short = good.clone();
    short.accum.sums.pop();
    variants.push(("sums one value short", short.encode(), &["sums", "expected"]));
    let mut magic = bytes.clone();
    magic[..4].copy_from_slice(b"PNG\0");
    variants.push(("bad magic", magic, &["magic"]));
    variants.push(("empty", Vec::new(), &["truncated"]));
    for (what, body, needles) in variants {
        let r = f.put(g.lease_id, body);
        let code = {
            let m = expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, needles);
            format!("{what}: {m}")
        };
        assert_eq!(f.units_merged(), 0, "{code}");
        // The unit is pending again at once (no waiting for the lease to expire).
        let again = f.lease();
        assert_eq!((again.unit, again.tile), (g.unit, g.tile), "{code}");
        assert_ne!(again.lease_id, g.lease_id);
        g = again;
    }
    // Well-formed, but for another tile: refused as a mismatch, also requeued.
    let mut wrong = f.frame(&g);
    let other = pathfarm_common::job::TileRect { x0: 0, y0: 0, x1: 8, y1: 8 };
    wrong.accum = TileAccum::new(other);
    let r = f.put(g.lease_id, wrong.encode());
    expect_error(r, StatusCode::UNPROCESSABLE_ENTITY, &["tile"]);
    let again = f.lease();
    assert_eq!(again.unit, g.unit);
    // The old lease is gone: a good body for it is now 409.
    let r = f.put(g.lease_id, f.frame(&g).encode());
    assert_eq!(r.status(), StatusCode::CONFLICT);
    let r = f.put(again.lease_id, f.frame(&again).encode());
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(f.units_merged(), 1);
    f.finish_and_compare();
}

// ------------------------------------------------------------------------------- auth

#[test]
fn tokens_missing_401_wrong_kind_403_right_ok() {
    let mut c = start(&["--client-token", "client-secret", "--worker-token", "worker-secret"]);
    let jobs = c.api("/jobs");
    let register = c.api("/workers/register");
    let reg_body = json!({"name": "w", "threads": 1});
    // Missing.
    let r = c.http.get(&jobs).send().expect("GET");
    expect_error(r, StatusCode::UNAUTHORIZED, &["missing", "token"]);
    let r = c.http.post(&register).json(&reg_body).send().expect("POST");
    expect_error(r, StatusCode::UNAUTHORIZED, &["missing", "token"]);
    let r = c.http.get(&jobs).header("authorization", "Basic client-secret").send().expect("GET");
    expect_error(r, StatusCode::UNAUTHORIZED, &["token"]);
    // Unknown.
    let r = c.http.get(&jobs).bearer_auth("client-secreT").send().expect("GET");
    expect_error(r, StatusCode::UNAUTHORIZED, &["invalid token"]);
    // Wrong kind.
    let r = c.http.get(&jobs).bearer_auth("worker-secret").send().expect("GET");
    expect_error(r, StatusCode::FORBIDDEN, &["worker", "may not"]);
    let r = c.http.post(&register).bearer_auth("client-secret").json(&reg_body).send().expect("POST");
    expect_error(r, StatusCode::FORBIDDEN, &["client", "may not"]);
    let r = c.http.post(c.api("/scenes")).bearer_auth("worker-secret").body(cornell_demo_glb()).send().expect("POST");
    expect_error(r, StatusCode::FORBIDDEN, &["worker"]);
    // Right ones.
    let r = c.http.get(&jobs).bearer_auth("client-secret").send().expect("GET");
    assert_eq!(r.status(), StatusCode::OK);
    let r = c.http.post(&register).bearer_auth("worker-secret").json(&reg_body).send().expect("POST");
    assert_eq!(r.status(), StatusCode::OK);
    let scene = c.upload_ok(cornell_demo_glb());
    // Scenes are readable with either token, not without.
    for t in ["client-secret", "worker-secret"] {
        let r = c.http.get(c.api(&format!("/scenes/{scene}"))).bearer_auth(t).send().expect("GET scene");
        assert_eq!(r.status(), StatusCode::OK, "{t}");
    }
    let r = c.http.get(c.api(&format!("/scenes/{scene}"))).send().expect("GET scene");
    expect_error(r, StatusCode::UNAUTHORIZED, &["token"]);
    // Health needs no token.
    c.assert_serving();
    // A job still completes with a worker holding the worker token.
    let id = c.submit_ok(&json!({"scene_id": scene, "width": 16, "height": 16, "spp": 1}));
    let _w = c.start_worker().expect("worker");
    let out = c.dir.path().join("auth.exr");
    c.wait_completed_exr(id, Duration::from_secs(60), &out);
}

/// The denoise routes check before they read or allocate: a render lease has no denoise input
/// (422), a layer of another size is refused (422, counted as a failure of the step, which then
/// waits again), a body larger than the frame's layer can be is a 413, another worker's secret a
/// 403; a good layer is stored, completes the job and is the EXR's `denoised` layer.
#[test]
fn denoise_routes_refuse_bad_bodies_and_other_leases() {
    use pathfarm_common::protocol::{DenoiseInput, LeaseKind, encode_denoised, max_denoised_bytes};
    let mut c = start(&[]);
    let glb = cornell_demo_glb();
    let scene_id = c.upload_ok(glb.clone());
    let job = c.submit_ok(&json!({"scene_id": scene_id, "width": 32, "height": 32, "spp": 2, "tile_size": 16,
        "passes": {"type": "fixed", "spp": 1}, "denoise": true}));
    let r = c
        .worker(c.http.post(c.api("/workers/register")))
        .json(&json!({"name": "fake denoiser", "threads": 1, "tags": ["denoise"]}))
        .send()
        .expect("register");
    let reg: Registered = r.json().expect("registered");
    let other = c.register("other");
    let lease = || -> LeaseGrant {
        let url = c.api(&format!("/workers/{}/lease?wait_ms=2000", reg.worker_id));
        let r = c.as_worker(c.http.post(url), &reg).send().expect("lease");
        assert_eq!(r.status(), StatusCode::OK);
        r.json().expect("grant")
    };
    let put = |lease: u64, body: Vec<u8>, who: &Registered| {
        c.as_worker(c.http.put(c.api(&format!("/leases/{lease}/denoised"))), who)
            .header("content-type", "application/octet-stream")
            .body(body)
            .send()
            .expect("PUT denoised")
    };
    let input = |lease: u64| c.as_worker(c.http.get(c.api(&format!("/leases/{lease}/denoise-input"))), &reg).send();
    let scene = load_scene_from_slice(&glb, "cornell.glb", None, &LoadOptions::default()).expect("scene");
    let renderer = Renderer::new(&scene, &c.job(job).settings).expect("renderer");
    // 4 tiles x 2 passes; the first render lease also shows a render lease has no input.
    for i in 0..8 {
        let g = lease();
        assert_eq!(g.kind, LeaseKind::Render);
        if i == 0 {
            assert_eq!(
                error_code(input(g.lease_id).expect("GET"), StatusCode::UNPROCESSABLE_ENTITY),
                "result_mismatch"
            );
            assert_eq!(
                error_code(put(g.lease_id, vec![0; 64], &reg), StatusCode::UNPROCESSABLE_ENTITY),
                "result_mismatch"
            );
        }
        let out = renderer.render_unit(g.tile, g.pass);
        let frame =
            UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum: out.accum, splats: None };
        let r = c
            .as_worker(c.http.put(c.api(&format!("/leases/{}/result", g.lease_id))), &reg)
            .body(frame.encode())
            .send()
            .expect("PUT result");
        assert_eq!(r.status(), StatusCode::OK);
    }
    assert_eq!(c.job(job).state.as_str(), "running", "the job waits for its denoise step");
    let g = lease();
    assert_eq!((g.kind, g.unit.pass), (LeaseKind::Denoise, 1));
    let body = input(g.lease_id).expect("GET input");
    assert_eq!(body.status(), StatusCode::OK);
    let got = DenoiseInput::decode_expecting(&body.bytes().expect("input"), 32, 32).expect("a 32 x 32 input");
    assert!(got.color.iter().any(|c| c[0] > 0.0), "the input holds the film's colour");
    // Another worker's secret; a body larger than a 32 x 32 layer can be; a 16 x 16 layer.
    assert_eq!(error_code(put(g.lease_id, vec![0; 64], &other), StatusCode::FORBIDDEN), "wrong_worker");
    let huge = vec![0u8; max_denoised_bytes(32, 32) as usize + 1];
    assert_eq!(error_code(put(g.lease_id, huge, &reg), StatusCode::PAYLOAD_TOO_LARGE), "payload_too_large");
    let small = encode_denoised(16, 16, &vec![[1.0; 3]; 256]);
    expect_error(put(g.lease_id, small, &reg), StatusCode::UNPROCESSABLE_ENTITY, &["16 x 16", "32 x 32"]);
    // That counted as a failure: the step waits again, under a new lease; the old one is gone.
    let g2 = lease();
    assert_eq!(g2.kind, LeaseKind::Denoise);
    let good = encode_denoised(32, 32, &vec![[0.25, 0.5, 0.75]; 1024]);
    assert_eq!(error_code(put(g.lease_id, good.clone(), &reg), StatusCode::CONFLICT), "lease_lost");
    assert_eq!(put(g2.lease_id, good, &reg).status(), StatusCode::NO_CONTENT);
    assert_eq!(c.job(job).state.as_str(), "completed");
    let exr = c.dir.path().join("farm.exr");
    let bytes =
        c.client(c.http.get(c.api(&format!("/jobs/{job}/image.exr")))).send().expect("exr").bytes().expect("exr");
    std::fs::write(&exr, &bytes).expect("write");
    let channels = pathfarm_common::film::read_exr(&exr).expect("read");
    assert!(channels.get("denoised.G").expect("denoised layer").iter().all(|&v| v == 0.5));
    c.assert_serving();
}
