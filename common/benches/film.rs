//! Film benchmark: what the coordinator spends per result and per progressive write.
//! - merge: folding 64 x 64 px tile results (4 samples per pixel, random radiance, albedo,
//!   normals and depths) into a film, as for every result: nanoseconds per pixel; once into a
//!   64 x 64 film (in cache) and once spread over two 1024 x 1024 films (out of cache, as the
//!   coordinator's films are);
//! - decode: a 64 x 64 result body (CRC, header, sums) decoded, per codec: nanoseconds per
//!   pixel and bytes per pixel on the wire;
//! - outputs: resolving a 1024 x 1024 film, encoding its EXR (ZIP, as written) and its PNG:
//!   CPU seconds of this process (the EXR encoder uses threads), and sizes.
//!
//! Best of several rounds (the machine may be busy). `cargo bench -p pathfarm-common --bench film`

#![allow(clippy::print_stdout)]

use pathfarm_common::film::{Film, SampleValue, TileAccum, add_sample};
use pathfarm_common::job::{TileRect, UnitKey};
use pathfarm_common::protocol::{Codec, UnitResultFrame, push_pixels, read_packed_pixels, read_pixels};
use std::time::Duration;
use std::time::Instant;

fn main() {
    let rect = TileRect { x0: 0, y0: 0, x1: 64, y1: 64 };
    let mut state = 0x5eed_u64;
    let mut rnd = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 11) as f64 / (1u64 << 53) as f64) as f32
    };
    let tiles: Vec<TileAccum> = (0..8)
        .map(|_| {
            let mut t = TileAccum::new(rect);
            for y in 0..64 {
                for x in 0..64 {
                    for _ in 0..4 {
                        let v = SampleValue {
                            radiance: [rnd(), rnd(), rnd()],
                            albedo: [rnd(), rnd(), rnd()],
                            normal: [rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0],
                            depth: Some(rnd() * 10.0),
                        };
                        add_sample(t.pixel_mut(x, y), &v);
                    }
                }
            }
            t
        })
        .collect();
    let rounds = 1000;
    let mut best = f64::INFINITY;
    let mut check = 0u64;
    for _ in 0..5 {
        let mut film = Film::new(64, 64);
        film.add_tile(&tiles[0]);
        let t0 = Instant::now();
        for i in 0..rounds {
            film.add_tile(&tiles[1 + i % 7]);
        }
        best = best.min(t0.elapsed().as_secs_f64());
        check = film.sums.iter().fold(0, |h, p| {
            h.wrapping_mul(31)
                .wrapping_add(p.rgb[0] ^ u64::from(p.albedo[1]) ^ u64::from(p.normal[2] as u16) ^ u64::from(p.depth))
        });
    }
    let px = (rounds * 64 * 64) as f64;
    println!(
        "film merge: {:.2} ns per pixel, {:.1} us per 64x64 tile (film checksum {check:016x})",
        best * 1e9 / px,
        best * 1e6 / rounds as f64
    );
    merge_cold(&tiles);
    decode(&tiles[1]);
    outputs(&tiles);
}

/// Merges as the coordinator does under load: two 1024 x 1024 films (two jobs, 128 MiB: larger
/// than the caches), each result landing on the next tile of one of them, so a merge reads and
/// writes film memory that is not in cache.
fn merge_cold(tiles: &[TileAccum]) {
    let (w, h) = (1024u32, 1024u32);
    let mut films = [Film::new(w, h), Film::new(w, h)];
    let places: Vec<(u32, u32)> = (0..h).step_by(64).flat_map(|y| (0..w).step_by(64).map(move |x| (x, y))).collect();
    let mut moved: Vec<TileAccum> = tiles.to_vec();
    let rounds = 4 * places.len();
    let mut best = f64::INFINITY;
    for _ in 0..3 {
        let t0 = Instant::now();
        for i in 0..rounds {
            let (x, y) = places[(i / 2) % places.len()];
            let n = moved.len();
            let t = &mut moved[i % n];
            t.rect = TileRect { x0: x, y0: y, x1: x + 64, y1: y + 64 };
            films[i % 2].add_tile(t);
        }
        best = best.min(t0.elapsed().as_secs_f64());
    }
    let px = (rounds * 64 * 64) as f64;
    // The same merges from packed result sections: decoded to a tile first, or read in place.
    let sections: Vec<Vec<u8>> = tiles
        .iter()
        .map(|t| {
            let mut s = Vec::new();
            push_pixels(&mut s, &t.sums, Codec::Packed);
            s
        })
        .collect();
    let (mut decoded, mut fused) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..3 {
        for in_place in [false, true] {
            let t0 = Instant::now();
            for i in 0..rounds {
                let (x, y) = places[(i / 2) % places.len()];
                let rect = TileRect { x0: x, y0: y, x1: x + 64, y1: y + 64 };
                let mut rest = &sections[i % sections.len()][..];
                if in_place {
                    if let Some(Ok(p)) = read_packed_pixels(&mut rest, 4096, "sums") {
                        films[i % 2].add_tile_with(rect, |k| p.get(k));
                    }
                } else if let Ok(sums) = read_pixels(&mut rest, 4096, "sums") {
                    films[i % 2].add_tile(&TileAccum { rect, sums });
                }
            }
            let t = t0.elapsed().as_secs_f64();
            if in_place { fused = fused.min(t) } else { decoded = decoded.min(t) }
        }
    }
    println!(
        "film merge of packed results (cold): decoded then merged {:.2} ns per pixel, merged as read {:.2}",
        decoded * 1e9 / px,
        fused * 1e9 / px
    );
    println!(
        "film merge, two 1024x1024 films (cold): {:.2} ns per pixel, {:.1} us per 64x64 tile",
        best * 1e9 / px,
        best * 1e6 / rounds as f64
    );
}

/// User + system CPU time of this process (Linux, 100 ticks per second).
fn cpu() -> Duration {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or_default();
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    Duration::from_secs_f64((ticks(11) + ticks(12)) / 100.0)
}

/// A 1024 x 1024 film of the tiles, resolved and encoded as the output loop does.
fn outputs(tiles: &[TileAccum]) {
    let (w, h) = (1024u32, 1024u32);
    let mut film = Film::new(w, h);
    for (i, (ty, tx)) in (0..h).step_by(64).flat_map(|y| (0..w).step_by(64).map(move |x| (y, x))).enumerate() {
        let mut t = tiles[i % tiles.len()].clone();
        t.rect = TileRect { x0: tx, y0: ty, x1: tx + 64, y1: ty + 64 };
        film.add_tile(&t);
    }
    let mut best = [Duration::MAX; 3];
    let mut sizes = (0, 0);
    for _ in 0..3 {
        let c0 = cpu();
        let layers = film.resolve();
        let c1 = cpu();
        let exr = layers.encode_exr().map(|b| b.len()).unwrap_or(0);
        let c2 = cpu();
        let png = layers.encode_png(0.0).map(|b| b.len()).unwrap_or(0);
        let c3 = cpu();
        for (b, d) in best.iter_mut().zip([c1 - c0, c2 - c1, c3 - c2]) {
            *b = (*b).min(d);
        }
        sizes = (exr, png);
    }
    println!(
        "outputs 1024x1024: resolve {:.2} s CPU, EXR {:.2} s CPU ({} KiB), PNG {:.2} s CPU ({} KiB)",
        best[0].as_secs_f64(),
        best[1].as_secs_f64(),
        sizes.0 / 1024,
        best[2].as_secs_f64(),
        sizes.1 / 1024
    );
}

/// Decoding one result of the tile `accum` with each codec, as the coordinator does per result.
fn decode(accum: &TileAccum) {
    let frame = UnitResultFrame {
        lease_id: 1,
        job_id: 1,
        unit: UnitKey { frame: 0, pass: 0, tile: 0 },
        accum: accum.clone(),
        splats: None,
    };
    let px = accum.sums.len() as f64;
    for (name, codec) in [("raw", Codec::Raw), ("packed", Codec::Packed), ("lz4", Codec::Lz4)] {
        let body = frame.encode_with(codec);
        let rounds = 2000;
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t0 = Instant::now();
            for _ in 0..rounds {
                let f = UnitResultFrame::decode(std::hint::black_box(&body));
                std::hint::black_box(f.is_ok());
            }
            best = best.min(t0.elapsed().as_secs_f64());
        }
        println!(
            "result decode, 64x64 {name}: {:.2} ns per pixel, {:.1} bytes per pixel",
            best * 1e9 / (px * rounds as f64),
            body.len() as f64 / px
        );
    }
}
