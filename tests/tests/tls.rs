//! HTTPS end to end: a coordinator serving TLS with a self-signed certificate (made here with
//! rcgen), a worker that trusts it through `--ca-cert`, the `pathfarm` client through
//! `PATHFARM_CA_CERT`, a job rendered through it bit-identically to a local render; plain HTTP
//! and clients that do not trust the issuer are refused.

mod support;

use pathfarm_common::job::RenderSettings;
use pathfarm_common::scene::demo::cornell_demo_glb;
use std::time::Duration;
use support::*;

#[test]
fn a_job_renders_over_https_with_a_private_ca() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rcgen::CertifiedKey { cert, key_pair } =
        rcgen::generate_simple_self_signed(vec!["localhost".to_string(), "127.0.0.1".to_string()]).expect("cert");
    let (cert_path, key_path) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).expect("write cert");
    std::fs::write(&key_path, key_pair.serialize_pem()).expect("write key");
    let coord = start_coordinator(
        &dir.path().join("data"),
        &["--tls-cert", &cert_path.to_string_lossy(), "--tls-key", &key_path.to_string_lossy()],
    );
    let url = coord.url.replacen("http://", "https://", 1);

    let ca = reqwest::Certificate::from_pem(cert.pem().as_bytes()).expect("ca");
    let https = reqwest::blocking::Client::builder()
        .add_root_certificate(ca)
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client");
    let healthy = wait_for("the coordinator to answer over HTTPS", Duration::from_secs(30), || {
        https.get(format!("{url}/healthz")).send().ok().filter(|r| r.status().is_success())
    });
    assert!(healthy.status().is_success());
    // Plain HTTP on the TLS port and HTTPS without trusting the issuer both fail.
    let plain = reqwest::blocking::Client::new().get(format!("{}/healthz", coord.url)).send();
    assert!(plain.map_or(true, |r| !r.status().is_success()), "plain HTTP was served on the TLS port");
    let untrusted = reqwest::blocking::Client::new().get(format!("{url}/healthz")).send();
    assert!(untrusted.is_err(), "a client that does not trust the issuer connected");

    let scene = cornell_demo_glb();
    let created: serde_json::Value = https
        .post(format!("{url}/api/v1/scenes"))
        .body(scene.clone())
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.json())
        .expect("upload over HTTPS");
    let mut settings = RenderSettings::new(48, 48, 8);
    settings.tile_size = 16;
    settings.seed = 4;
    let job: serde_json::Value = https
        .post(format!("{url}/api/v1/jobs"))
        .json(&serde_json::json!({"scene_id": created["scene_id"], "width": 48, "height": 48, "spp": 8,
            "tile_size": 16, "seed": 4}))
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.json())
        .expect("submit over HTTPS");
    let id = job["id"].as_u64().expect("job id");

    let worker = std::process::Command::new(bin("pathfarm-worker"))
        .args(["run", "--coordinator", &url, "--threads", "1", "--name", "tls-worker", "--cache-dir"])
        .arg(dir.path().join("cache"))
        .arg("--ca-cert")
        .arg(&cert_path)
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn worker");
    let _worker = Proc { child: worker };
    wait_for("the job to complete over HTTPS", Duration::from_secs(120), || {
        let info: serde_json::Value = https.get(format!("{url}/api/v1/jobs/{id}")).send().ok()?.json().ok()?;
        (info["state"] == "completed").then_some(())
    });
    let exr = https
        .get(format!("{url}/api/v1/jobs/{id}/image.exr"))
        .send()
        .and_then(|r| r.error_for_status())
        .and_then(|r| r.bytes())
        .expect("fetch the EXR");
    assert!(
        exr.as_ref() == local_exr(&scene, &settings).as_slice(),
        "the farm's image over HTTPS differs from a local render"
    );
}
