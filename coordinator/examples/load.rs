//! Load test of the coordinator: N simulated workers register, long-poll leases and upload
//! synthetic results for one large job; prints units merged per second, lease latency p50/p99,
//! the coordinator's CPU time and peak memory.
//!
//! ```text
//! cargo build --release -p pathfarm-coordinator --bins --example load
//! target/release/examples/load --workers 500 --width 1024 --height 1024 --tile 64 --spp 100
//! target/release/examples/load --workers 50 --width 1920 --height 1080 --spp 1 --frames 1-1000 --stop-after-frames 40
//! target/release/examples/load --workers 500 --width 1024 --height 1024 --tile 64 --spp 40 --jobs 2
//! ```
//!
//! `--frames` makes the job a sequence (frame order) and prints the coordinator's RSS as frames
//! are written: it stays flat, bounded by the frames in progress, not by the frames in the job.
//!
//! By default the coordinator is the `pathfarm-coordinator` binary next to this example
//! (`target/release/`), run as its own process so that its CPU time (`/proc/PID/stat`) and peak
//! memory (`VmHWM`) are its own; `--in-process` starts `Server` inside this process instead (the
//! figures then include the simulated workers). `--url` uses a coordinator that is already
//! running (no CPU or memory figures).
//!
//! A result is a real `PFR2` frame (header, the section of the tile's 64-byte pixel sums, CRC),
//! built per lease from a section encoded once per tile size and shared by every body (no copy;
//! the CRC of the header is combined with the section's), so the workers cost little.
//! `--payload noise` (default) puts 3 random low bytes in every sum and random AOV means,
//! `--payload zeros` sends all-zero sums; `--codec raw|lz4|packed` stores the section as it is,
//! lz4-compressed, or packed (each field cut to the bytes it needs: the default,
//! `RESULT_CODEC`).
//!
//! With `--render-ms 0` (default) every worker asks for its next unit as soon as the last one is
//! delivered: the coordinator is saturated and lease latency is mostly queueing behind 499
//! other workers. `--render-ms N` makes each worker "render" N ms per unit, an offered load of
//! about `workers * 1000 / N` units/s, to measure latency below saturation.

#![allow(clippy::print_stdout)]

use anyhow::{Context, bail};
use axum::body::Bytes;
use pathfarm_common::film::{PIXEL_BYTES, PixelSums};
use pathfarm_common::job::TileRect;
use pathfarm_common::protocol::{
    API, Codec, JobInfo, LeaseGrant, RESULT_CODEC, RESULT_MAGIC, Registered, WORKER_SECRET_HEADER, push_pixels,
};
use pathfarm_common::routes;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::Mutex;

#[derive(Clone, Debug)]
struct Args {
    workers: usize,
    width: u32,
    height: u32,
    tile: u32,
    spp: u32,
    payload: String,
    codec: Codec,
    in_process: bool,
    url: Option<String>,
    threads: usize,
    wait_ms: u64,
    render_ms: u64,
    /// A sequence: the job's `frames`.
    frames: Option<String>,
    /// Cancel the job once this many frames are written (a long sequence's memory is flat
    /// long before its end).
    stop_after_frames: Option<u32>,
    /// Identical jobs submitted at once (their units interleave by fair share).
    jobs: usize,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut a = Args {
        workers: 500,
        width: 1024,
        height: 1024,
        tile: 64,
        spp: 100,
        payload: "noise".into(),
        codec: RESULT_CODEC,
        in_process: false,
        url: None,
        threads: 2,
        wait_ms: 5000,
        render_ms: 0,
        frames: None,
        stop_after_frames: None,
        jobs: 1,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut val = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--workers" => a.workers = val()?.parse()?,
            "--width" => a.width = val()?.parse()?,
            "--height" => a.height = val()?.parse()?,
            "--tile" => a.tile = val()?.parse()?,
            "--spp" | "--passes" => a.spp = val()?.parse()?,
            "--units" => {
                // As many passes as needed for about this many units.
                let units: u64 = val()?.parse()?;
                let tiles = u64::from(a.width.div_ceil(a.tile)) * u64::from(a.height.div_ceil(a.tile));
                a.spp = units.div_ceil(tiles).max(1) as u32;
            }
            "--payload" => a.payload = val()?,
            "--codec" => {
                a.codec = match val()?.as_str() {
                    "raw" => Codec::Raw,
                    "lz4" => Codec::Lz4,
                    "packed" => Codec::Packed,
                    other => bail!("--codec raw|lz4|packed, not {other}"),
                }
            }
            "--in-process" => a.in_process = true,
            "--url" => a.url = Some(val()?),
            "--client-threads" => a.threads = val()?.parse()?,
            "--wait-ms" => a.wait_ms = val()?.parse()?,
            "--render-ms" => a.render_ms = val()?.parse()?,
            "--frames" => a.frames = Some(val()?),
            "--jobs" => a.jobs = val()?.parse::<usize>()?.max(1),
            "--stop-after-frames" => a.stop_after_frames = Some(val()?.parse()?),
            "-h" | "--help" => {
                eprintln!(
                    "load [--workers 500] [--width 1024] [--height 1024] [--tile 64] [--spp 100 | --units N] \
                     [--payload noise|zeros] [--codec raw|lz4|packed] [--in-process | --url URL] [--client-threads 2] [--wait-ms 5000] [--render-ms 0] [--frames 1-1000 [--stop-after-frames N]] [--jobs 1]"
                );
                std::process::exit(0);
            }
            other => bail!("unknown flag {other}"),
        }
    }
    Ok(a)
}

/// Sums sections, one per tile size (`push_pixels` with `codec`): every pixel one sample
/// (weight 1; the job's passes are 1 spp and the coordinator checks weights against the pass),
/// so the image resolves to finite values either way.
fn section(w: u32, h: u32, noise: bool, codec: Codec) -> Vec<u8> {
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15 ^ u64::from(w * 131 + h);
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let pixels: Vec<PixelSums> = (0..w * h)
        .map(|_| {
            let mut p = PixelSums { weight: 1, ..Default::default() };
            if noise {
                // One sample's sums: 3 random low bytes (a value of order 1 at 2^-24), random
                // AOV means.
                let mut v = || (next() >> 40) & 0xFF_FFFF;
                p.rgb = [v(), v(), v()];
                p.lum = v();
                p.lum_sq = v();
                p.hits = 1;
                p.depth = 1.5f32.to_bits();
                let mut f = || (next() >> 49) as u16;
                p.albedo = [f(), f(), f()];
                p.normal = [f() as i16, f() as i16, f() as i16];
            }
            p
        })
        .collect();
    let mut out = Vec::new();
    push_pixels(&mut out, &pixels, codec);
    out
}

/// A tile size's encoded section, shared by every result of that size, with its CRC state.
struct Section {
    bytes: Bytes,
    crc: crc32fast::Hasher,
}

impl Section {
    fn new(bytes: Vec<u8>) -> Self {
        let mut crc = crc32fast::Hasher::new();
        crc.update(&bytes);
        Section { bytes: Bytes::from(bytes), crc }
    }
}

/// A result body for a grant, in the `PFR2` layout of `UnitResultFrame::encode`: the header is
/// built per lease, the section is shared (not copied) and its CRC combined with the header's,
/// so a simulated worker costs little besides sending the bytes. Returns the body and its length.
fn frame(g: &LeaseGrant, section: &Section) -> (reqwest::Body, u64) {
    let header = serde_json::json!({
        "lease_id": g.lease_id,
        "job_id": g.job_id,
        "unit": g.unit,
        "tile": g.tile,
        "pixel_bytes": PIXEL_BYTES,
        "splats": null,
    });
    let header = serde_json::to_vec(&header).unwrap_or_default();
    let mut head = Vec::with_capacity(8 + header.len());
    head.extend_from_slice(RESULT_MAGIC);
    head.extend_from_slice(&(header.len() as u32).to_le_bytes());
    head.extend_from_slice(&header);
    let mut crc = crc32fast::Hasher::new();
    crc.update(&head);
    crc.combine(&section.crc);
    let tail = crc.finalize().to_le_bytes().to_vec();
    let len = (head.len() + section.bytes.len() + tail.len()) as u64;
    let parts: [std::io::Result<Bytes>; 3] = [Ok(Bytes::from(head)), Ok(section.bytes.clone()), Ok(Bytes::from(tail))];
    (reqwest::Body::wrap_stream(futures_util::stream::iter(parts)), len)
}

/// `VmRSS` of a process in MiB.
fn proc_rss(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kb: f64 = status.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// `/proc/PID/stat` utime + stime in seconds, and `VmHWM` in MiB.
fn proc_figures(pid: u32) -> Option<(f64, f64)> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let hwm_kb: f64 = status.lines().find(|l| l.starts_with("VmHWM:"))?.split_whitespace().nth(1)?.parse().ok()?;
    // USER_HZ is 100 on Linux.
    Some((ticks / 100.0, hwm_kb / 1024.0))
}

struct Stats {
    lease_us: Mutex<Vec<u32>>,
    /// Each worker's first grant: all workers poll before the job exists, so these include the
    /// wait for the job and the herd of 500 grants at once.
    first_us: Mutex<Vec<u32>>,
    merged: AtomicU64,
    refused: AtomicU64,
    errors: AtomicU64,
    done: AtomicBool,
}

#[allow(clippy::too_many_arguments)]
async fn worker(
    http: reqwest::Client,
    base: String,
    i: usize,
    sections: Arc<HashMap<(u32, u32), Section>>,
    stats: Arc<Stats>,
    wait_ms: u64,
    render_ms: u64,
    start: Arc<tokio::sync::Barrier>,
) -> anyhow::Result<()> {
    let reg: Registered = http
        .post(format!("{base}{API}{}", routes::WORKER_REGISTER))
        .json(&serde_json::json!({"name": format!("sim-{i}"), "threads": 1}))
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    start.wait().await;
    let lease_url = format!("{base}{API}{}?wait_ms={wait_ms}", routes::fill(routes::WORKER_LEASE, &[&reg.worker_id]));
    let mut lats = Vec::new();
    let mut first = None;
    while !stats.done.load(Ordering::Relaxed) {
        let t0 = Instant::now();
        let r = match http.post(&lease_url).header(WORKER_SECRET_HEADER, &reg.worker_secret).send().await {
            Ok(r) => r,
            Err(_) => {
                stats.errors.fetch_add(1, Ordering::Relaxed);
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        if r.status() == reqwest::StatusCode::NO_CONTENT {
            continue;
        }
        if !r.status().is_success() {
            stats.errors.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        let g: LeaseGrant = r.json().await?;
        let us = t0.elapsed().as_micros().min(u128::from(u32::MAX)) as u32;
        if first.is_none() {
            first = Some(us);
        } else {
            lats.push(us);
        }
        if render_ms > 0 {
            tokio::time::sleep(Duration::from_millis(render_ms)).await;
        }
        let TileRect { x0, y0, x1, y1 } = g.tile;
        let sec = sections.get(&(x1 - x0, y1 - y0)).context("tile size")?;
        let (body, len) = frame(&g, sec);
        let r = http
            .put(format!("{base}{API}{}", routes::fill(routes::LEASE_RESULT, &[&g.lease_id])))
            .header(WORKER_SECRET_HEADER, &reg.worker_secret)
            .header("content-type", "application/octet-stream")
            .header("content-length", len)
            .body(body)
            .send()
            .await;
        match r {
            Ok(r) if r.status().is_success() => {
                stats.merged.fetch_add(1, Ordering::Relaxed);
            }
            Ok(r) => {
                stats.refused.fetch_add(1, Ordering::Relaxed);
                if stats.refused.load(Ordering::Relaxed) < 5 {
                    eprintln!("result refused: {} {}", r.status(), r.text().await.unwrap_or_default());
                }
            }
            Err(_) => {
                stats.errors.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    stats.lease_us.lock().await.extend(lats);
    stats.first_us.lock().await.extend(first);
    Ok(())
}

fn pct(sorted: &[u32], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    f64::from(sorted[i]) / 1000.0
}

fn main() -> anyhow::Result<()> {
    let a = parse_args()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(a.threads).enable_all().build()?;
    rt.block_on(run(a))
}

async fn run(a: Args) -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let mut child = None;
    let mut server = None;
    let (base, pid) = if let Some(url) = &a.url {
        (url.trim_end_matches('/').to_string(), None)
    } else if a.in_process {
        let mut cfg = pathfarm_coordinator::server::ServerConfig::new("127.0.0.1:0".parse()?, dir.path().into());
        // Simulated workers do not heartbeat; they deliver well within the default timeout.
        cfg.farm.lease_timeout_ms = 60_000;
        let s = pathfarm_coordinator::server::Server::start(cfg).await?;
        let url = s.url();
        server = Some(s);
        (url, Some(std::process::id()))
    } else {
        let exe = std::env::current_exe()?;
        let bin: PathBuf = exe
            .parent()
            .and_then(|p| p.parent())
            .map(|p| p.join("pathfarm-coordinator"))
            .context("locating pathfarm-coordinator")?;
        if !bin.exists() {
            bail!("{} is missing: cargo build --release -p pathfarm-coordinator", bin.display());
        }
        let c = tokio::process::Command::new(&bin)
            .arg("--listen")
            .arg("127.0.0.1:0")
            .arg("--no-auth")
            // Every simulated worker registers from 127.0.0.1: no per-address rate limit.
            .args(["--register-per-minute", "0"])
            .arg("--data-dir")
            .arg(dir.path())
            .arg("--lease-timeout-ms")
            .arg("60000")
            .env("RUST_LOG", "warn")
            .kill_on_drop(true)
            .spawn()?;
        let pid = c.id();
        child = Some(c);
        let addr_file = dir.path().join("coordinator.addr");
        let t0 = Instant::now();
        let addr = loop {
            if let Ok(s) = std::fs::read_to_string(&addr_file)
                && !s.trim().is_empty()
            {
                break s.trim().to_string();
            }
            if t0.elapsed() > Duration::from_secs(20) {
                bail!("the coordinator did not start");
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        (format!("http://{addr}"), pid)
    };
    let http =
        reqwest::Client::builder().pool_max_idle_per_host(a.workers + 16).timeout(Duration::from_secs(120)).build()?;
    // Scene and job.
    let scene: serde_json::Value = http
        .post(format!("{base}{API}{}", routes::SCENES))
        .body(pathfarm_common::scene::demo::cornell_demo_glb())
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    let scene_id = scene["scene_id"].as_str().context("scene_id")?.to_string();
    let tiles = u64::from(a.width.div_ceil(a.tile)) * u64::from(a.height.div_ceil(a.tile));
    let units = tiles * u64::from(a.spp);
    let film_mb = pathfarm_common::film::Film::bytes_for(a.width, a.height) as f64 / (1 << 20) as f64;
    eprintln!(
        "job: {}x{} tile {} spp {} (1 spp per pass) = {tiles} tiles x {} passes = {units} units; film {film_mb:.0} MiB; {} workers, render {} ms",
        a.width, a.height, a.tile, a.spp, a.spp, a.workers, a.render_ms
    );
    // Sections for every tile size of the plan.
    let noise = a.payload != "zeros";
    let mut sections = HashMap::new();
    for w in [a.tile, a.width % a.tile] {
        for h in [a.tile, a.height % a.tile] {
            if w > 0 && h > 0 {
                sections.insert((w, h), Section::new(section(w, h, noise, a.codec)));
            }
        }
    }
    let full = sections.get(&(a.tile, a.tile)).map_or(0, |s| s.bytes.len());
    eprintln!(
        "result body: {} bytes ({} KiB raw, {:?}); film {PIXEL_BYTES} bytes per pixel",
        full,
        (a.tile * a.tile) as usize * PIXEL_BYTES / 1024,
        a.codec
    );
    let sections = Arc::new(sections);
    let stats = Arc::new(Stats {
        lease_us: Mutex::new(Vec::new()),
        first_us: Mutex::new(Vec::new()),
        merged: AtomicU64::new(0),
        refused: AtomicU64::new(0),
        errors: AtomicU64::new(0),
        done: AtomicBool::new(false),
    });
    // Workers register and wait; the job is submitted once all are polling.
    let barrier = Arc::new(tokio::sync::Barrier::new(a.workers + 1));
    let mut tasks = Vec::new();
    for i in 0..a.workers {
        tasks.push(tokio::spawn(worker(
            http.clone(),
            base.clone(),
            i,
            sections.clone(),
            stats.clone(),
            a.wait_ms,
            a.render_ms,
            barrier.clone(),
        )));
    }
    barrier.wait().await;
    let before = pid.and_then(proc_figures);
    let mut body = serde_json::json!({
        "scene_id": scene_id, "name": "load", "width": a.width, "height": a.height, "spp": a.spp,
        "tile_size": a.tile, "passes": {"type": "fixed", "spp": 1},
    });
    if let Some(f) = &a.frames {
        body["frames"] = f.clone().into();
    }
    let rss_before = pid.and_then(proc_rss);
    if let Some(r) = rss_before {
        eprintln!("coordinator RSS before the job: {r:.0} MiB");
    }
    let t0 = Instant::now();
    let mut job_ids = Vec::new();
    for _ in 0..a.jobs {
        let job: serde_json::Value = http
            .post(format!("{base}{API}{}", routes::JOBS))
            .json(&body)
            .send()
            .await?
            .error_for_status()?
            .json()
            .await?;
        job_ids.push(job["id"].as_u64().context("job id")?);
    }
    let job_id = job_ids[0];
    if let Some(r) = pid.and_then(proc_rss) {
        eprintln!("coordinator RSS after submitting: {r:.0} MiB");
    }
    let mut rss_max_after_first_frame: f64 = 0.0;
    let mut last = (Instant::now(), 0u64);
    let info: JobInfo = loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let mut info: JobInfo =
            http.get(format!("{base}{API}{}", routes::fill(routes::JOB, &[&job_id]))).send().await?.json().await?;
        // More jobs: their units add up, and the run ends when every job has.
        for id in &job_ids[1..] {
            let other: JobInfo =
                http.get(format!("{base}{API}{}", routes::fill(routes::JOB, &[id]))).send().await?.json().await?;
            info.units_merged += other.units_merged;
            info.units_total += other.units_total;
            if !other.state.is_finished() {
                info.state = other.state;
            }
        }
        let now = Instant::now();
        let rate = (info.units_merged - last.1) as f64 / (now - last.0).as_secs_f64();
        last = (now, info.units_merged);
        let rss = pid.and_then(proc_rss).unwrap_or(f64::NAN);
        if info.frames.done >= 1 {
            rss_max_after_first_frame = rss_max_after_first_frame.max(rss);
        }
        eprintln!(
            "{:6.1} s  merged {:>8}/{}  {:>8.0} units/s  frames written {}/{} (in progress {})  RSS {rss:.0} MiB  state {:?}",
            t0.elapsed().as_secs_f64(),
            info.units_merged,
            info.units_total,
            rate,
            info.frames.done,
            info.frames.total,
            info.frames.in_progress,
            info.state
        );
        if info.state.is_finished() {
            break info;
        }
        if a.stop_after_frames.is_some_and(|n| info.frames.done >= n) {
            http.post(format!("{base}{API}{}", routes::fill(routes::JOB_CANCEL, &[&job_id])))
                .send()
                .await?
                .error_for_status()?;
            eprintln!("cancelled after {} frames", info.frames.done);
            break http
                .get(format!("{base}{API}{}", routes::fill(routes::JOB, &[&job_id])))
                .send()
                .await?
                .json()
                .await?;
        }
    };
    let elapsed = t0.elapsed().as_secs_f64();
    let after = pid.and_then(proc_figures);
    stats.done.store(true, Ordering::Relaxed);
    // Workers blocked in a long poll return after wait_ms at most.
    for t in tasks {
        let _ = tokio::time::timeout(Duration::from_millis(a.wait_ms + 2000), t).await;
    }
    let mut lats = stats.lease_us.lock().await.clone();
    lats.sort_unstable();
    let mut firsts = stats.first_us.lock().await.clone();
    firsts.sort_unstable();
    println!("state                 {:?}", info.state);
    println!("units merged          {} of {}", info.units_merged, info.units_total);
    println!("elapsed               {elapsed:.2} s");
    println!("units merged / s      {:.0}", info.units_merged as f64 / elapsed);
    println!(
        "lease latency         p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms  ({} grants)",
        pct(&lats, 0.5),
        pct(&lats, 0.99),
        pct(&lats, 1.0),
        lats.len()
    );
    println!(
        "first lease (herd)    p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms  ({} workers; from before the job existed)",
        pct(&firsts, 0.5),
        pct(&firsts, 0.99),
        pct(&firsts, 1.0),
        firsts.len()
    );
    println!(
        "results refused       {}  request errors {}",
        stats.refused.load(Ordering::Relaxed),
        stats.errors.load(Ordering::Relaxed)
    );
    if let (Some((c0, _)), Some((c1, hwm))) = (before, after) {
        let who = if a.in_process { "process (coordinator + simulated workers)" } else { "coordinator" };
        println!(
            "{who} CPU  {:.2} s ({:.0}% of one core; {:.1} us per unit)",
            c1 - c0,
            100.0 * (c1 - c0) / elapsed,
            1e6 * (c1 - c0) / info.units_merged.max(1) as f64
        );
        println!("{who} peak memory (VmHWM)  {hwm:.0} MiB");
        if a.frames.is_some() {
            println!(
                "{who} RSS: before the job {:.0} MiB, highest sampled after the first frame was written {rss_max_after_first_frame:.0} MiB; frames written {}/{}",
                rss_before.unwrap_or(f64::NAN),
                info.frames.done,
                info.frames.total
            );
        }
    }
    drop(server);
    if let Some(mut c) = child {
        let _ = c.kill().await;
    }
    Ok(())
}
