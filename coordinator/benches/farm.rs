//! Farm benchmark: the same job rendered locally (one thread) and by N worker processes of one
//! thread each. Prints farm efficiency (local time / (N x farm time)), coordinator CPU time per
//! unit and bytes on the wire per unit, and checks that every farm image equals the local one.
//!
//! `cargo build --release --bins && cargo bench -p pathfarm-coordinator --bench farm -- [--workers 1,2] [--size 128] [--spp 64]`

#![allow(clippy::print_stdout, clippy::unwrap_used)]

use pathfarm_common::job::{PassSchedule, RenderSettings};
use pathfarm_common::protocol::{JobRequest, JobState};
use pathfarm_common::scene::LoadOptions;
use pathfarm_common::scene::bundle::load_bundle;
use pathfarm_common::scene::demo::cornell_demo_glb;
use pathfarm_coordinator::client::Client;
use pathfarm_coordinator::server::{Server, ServerConfig};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// User + system CPU seconds of this process (Linux, 100 ticks per second).
fn cpu_secs() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or_default();
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn arg(name: &str, default: &str) -> String {
    let args: Vec<String> = std::env::args().collect();
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1).cloned()).unwrap_or_else(|| default.to_string())
}

fn main() {
    let workers: Vec<usize> = arg("--workers", "1,2").split(',').filter_map(|v| v.parse().ok()).collect();
    let size: u32 = arg("--size", "128").parse().unwrap();
    let spp: u32 = arg("--spp", "64").parse().unwrap();
    let exe = std::env::current_exe().unwrap();
    let worker_bin = exe.parent().and_then(|d| d.parent()).unwrap().join("pathfarm-worker");
    assert!(worker_bin.exists(), "build the worker first: cargo build --release --bins");

    let scene = cornell_demo_glb();
    let mut settings = RenderSettings::new(size, size, spp);
    settings.tile_size = 32;
    settings.passes = PassSchedule::Doubling { first: 4, max: 16 };
    let units = settings.plan().unit_count();

    let tmp = tempfile::tempdir().unwrap();
    let loaded = load_bundle(&scene, &tmp.path().join("scene"), &LoadOptions::default()).unwrap();
    let renderer = pathfarm_worker::render::Renderer::new(&loaded, &settings).unwrap();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    // The local time is the best of three runs (the machine may be busy; the farm runs get
    // the same chance below by taking the best of `--repeat` runs).
    let mut local = f64::INFINITY;
    let mut film = None;
    for _ in 0..3 {
        let t0 = Instant::now();
        film = Some(pool.install(|| pathfarm_worker::render::render_local(&renderer, |_, _| {})));
        local = local.min(t0.elapsed().as_secs_f64());
    }
    let film = film.unwrap();
    let local_exr = film.resolve().encode_exr().unwrap();
    println!("farm benchmark: {size}x{size}, {spp} spp, path, {units} units (tile 32, passes 4,8,16,16,..)");
    println!("local render, 1 thread: {local:.2} s (best of 3)");
    let repeat: usize = arg("--repeat", "3").parse().unwrap();
    println!(
        "{:>8} {:>10} {:>11} {:>16} {:>15} {:>10}",
        "workers", "farm s", "efficiency", "coord CPU/unit", "bytes/unit", "raw/unit"
    );

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    for &n in &workers {
        let data = tmp.path().join(format!("data{n}"));
        let server = rt.block_on(Server::start(ServerConfig::new("127.0.0.1:0".parse().unwrap(), data))).unwrap();
        let url = server.url();
        let client = Client::new(&url, None).unwrap();
        let procs: Vec<Killed> = (0..n)
            .map(|i| {
                Killed(
                    Command::new(&worker_bin)
                        .args(["run", "--coordinator", &url, "--threads", "1", "--name", &format!("b{i}")])
                        .arg("--cache-dir")
                        .arg(tmp.path().join(format!("cache{n}-{i}")))
                        .env("RUST_LOG", "warn")
                        .stdout(Stdio::null())
                        .stderr(Stdio::null())
                        .spawn()
                        .unwrap(),
                )
            })
            .collect();
        while server.state.farm.lock().workers(0).len() < n {
            std::thread::sleep(Duration::from_millis(10));
        }
        let created = client.upload_scene(scene.clone()).unwrap();
        let (mut farm, mut cpu, mut bytes) = (f64::INFINITY, f64::INFINITY, 0);
        for _ in 0..repeat {
            let bytes0 = server.state.metrics.bytes_received.load(Ordering::Relaxed);
            let cpu0 = cpu_secs();
            let t0 = Instant::now();
            let job = JobRequest {
                frames: None,
                order: Default::default(),
                scene_id: created.scene_id.clone(),
                name: None,
                priority: 0,
                requires: Vec::new(),
                notify: None,
                settings: settings.clone(),
            };
            let id = client.submit(&job).unwrap();
            loop {
                let info = client.job(id).unwrap();
                if info.state == JobState::Completed {
                    break;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            farm = farm.min(t0.elapsed().as_secs_f64());
            cpu = cpu.min(cpu_secs() - cpu0);
            bytes = server.state.metrics.bytes_received.load(Ordering::Relaxed) - bytes0;
            assert!(client.image_exr(id).unwrap() == local_exr, "farm image differs from the local render");
        }
        let raw = settings.tile_size.pow(2) as usize * pathfarm_common::film::PIXEL_BYTES;
        println!(
            "{n:>8} {farm:>10.2} {:>11.3} {:>13.2} ms {:>15} {:>10}",
            local / (n as f64 * farm),
            cpu * 1000.0 / units as f64,
            bytes / units as u64,
            raw
        );
        drop(procs);
    }
    println!("(coordinator CPU includes this process's polling client; images verified bit-identical)");
}
