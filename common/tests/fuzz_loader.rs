//! Bounded fuzzing of the glTF loader: `load_scene_from_slice` must return `Ok` or `Err` for
//! any bytes, never panic (a panic in the coordinator's upload handler is a 500, in a worker a
//! failed unit).
//!
//! Seeds: our own demo scenes plus, when `PATHFARM_CORPUS` names the third-party scene folder,
//! its small glTF files, with their
//! external buffers and images inlined as `data:` URIs. Three mutators: raw bytes (flips, sets,
//! truncation, insertions), JSON values (numbers, strings and arrays of the glTF document
//! replaced by hostile values, GLB re-packed), and the GLB binary chunk (indices, offsets).
//!
//! Fixed RNG seed, so a run is reproducible; `PROPTEST_CASES` overrides the case counts.
//! `cargo test --release -p pathfarm-common --test fuzz_loader`.

use base64::Engine;
use pathfarm_common::scene::demo;
use pathfarm_common::scene::{LoadOptions, load_scene_from_slice};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};
use serde_json::Value;
use std::path::Path;
use std::sync::OnceLock;

/// Cases per target (three targets).
const CASES: u32 = 6000;

fn config() -> Config {
    Config {
        cases: std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(CASES),
        rng_seed: RngSeed::Fixed(0x5eed_f00d),
        failure_persistence: None,
        // The loader is deterministic; shrinking a failure is worth its time.
        max_shrink_iters: 2000,
        ..Config::default()
    }
}

/// The server's limits, smaller: mutated counts must not turn into huge allocations here.
fn opts() -> LoadOptions {
    LoadOptions { max_triangles: Some(1 << 20), max_texture_pixels: Some(1 << 22), max_texture_bytes: Some(256 << 20) }
}

/// The third-party corpus (`PATHFARM_CORPUS`), when the run names one: more seeds.
fn shared_scenes() -> Option<&'static Path> {
    let dir = std::path::PathBuf::from(std::env::var_os("PATHFARM_CORPUS")?);
    dir.is_dir().then(|| &*Box::leak(dir.into_boxed_path()))
}

/// A `.gltf` document with every relative buffer/image URI replaced by a `data:` URI.
fn inline_gltf(path: &Path) -> Option<Vec<u8>> {
    let mut doc: Value = serde_json::from_slice(&std::fs::read(path).ok()?).ok()?;
    let dir = path.parent()?;
    for key in ["buffers", "images"] {
        let Some(items) = doc.get_mut(key).and_then(Value::as_array_mut) else { continue };
        for item in items {
            let Some(uri) = item.get("uri").and_then(Value::as_str) else { continue };
            if uri.starts_with("data:") {
                continue;
            }
            let bytes = std::fs::read(dir.join(uri)).ok()?;
            if bytes.len() > 256 << 10 {
                return None;
            }
            let mime = if key == "images" {
                if uri.ends_with(".png") { "image/png" } else { "image/jpeg" }
            } else {
                "application/octet-stream"
            };
            let b64 = base64::engine::general_purpose::STANDARD.encode(&bytes);
            item["uri"] = Value::String(format!("data:{mime};base64,{b64}"));
        }
    }
    serde_json::to_vec(&doc).ok()
}

/// Seed inputs: (name, bytes); each loads without error.
fn corpus() -> &'static [(String, Vec<u8>)] {
    static CORPUS: OnceLock<Vec<(String, Vec<u8>)>> = OnceLock::new();
    CORPUS.get_or_init(|| {
        let mut c = vec![
            ("cornell.glb".to_string(), demo::cornell_demo_glb()),
            ("furnace.glb".to_string(), demo::furnace_glb(1.0, 0.5)),
            ("caustics.glb".to_string(), demo::caustics_glb()),
            ("mis.glb".to_string(), demo::mis_glb()),
            ("cornell_mitsuba.glb".to_string(), demo::cornell_mitsuba_glb()),
        ];
        if let Some(dir) = shared_scenes() {
            let mut files: Vec<_> = walk(dir);
            files.sort();
            for p in files {
                let ext = p.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
                let size = std::fs::metadata(&p).map_or(u64::MAX, |m| m.len());
                let bytes = match ext.as_str() {
                    "glb" if size <= 256 << 10 => std::fs::read(&p).ok(),
                    "gltf" if size <= 64 << 10 => inline_gltf(&p),
                    _ => None,
                };
                let Some(bytes) = bytes else { continue };
                let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                if load_scene_from_slice(&bytes, &name, None, &opts()).is_ok() {
                    c.push((name, bytes));
                }
            }
        }
        c
    })
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let Ok(rd) = std::fs::read_dir(dir) else { return out };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

fn load(bytes: &[u8], name: &str) {
    // Ok or Err are both fine; a panic fails the case.
    let _ = load_scene_from_slice(bytes, name, None, &opts());
}

// ------------------------------------------------------------------------ GLB (un)packing

fn split_glb(bytes: &[u8]) -> Option<(Value, Vec<u8>)> {
    if !bytes.starts_with(b"glTF") || bytes.len() < 20 {
        return None;
    }
    let jlen = u32::from_le_bytes(bytes[12..16].try_into().ok()?) as usize;
    let json = bytes.get(20..20 + jlen)?;
    let rest = &bytes[20 + jlen..];
    let bin = if rest.len() >= 8 { rest[8..].to_vec() } else { Vec::new() };
    Some((serde_json::from_slice(json).ok()?, bin))
}

fn pack_glb(json: &Value, bin: &[u8]) -> Vec<u8> {
    let mut j = serde_json::to_vec(json).unwrap_or_default();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + if b.is_empty() { 0 } else { 8 + b.len() };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(j.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&j);
    if !b.is_empty() {
        out.extend_from_slice(&(b.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&b);
    }
    out
}

/// The document and binary chunk of a corpus entry (`.gltf`: no chunk).
fn parts(bytes: &[u8]) -> Option<(Value, Vec<u8>, bool)> {
    if let Some((j, b)) = split_glb(bytes) {
        return Some((j, b, true));
    }
    serde_json::from_slice(bytes).ok().map(|j| (j, Vec::new(), false))
}

// ------------------------------------------------------------------------ JSON mutation

/// Hostile replacements for a JSON value.
fn hostile(k: u8) -> Value {
    use serde_json::json;
    match k % 24 {
        0 => json!(0),
        1 => json!(-1),
        2 => json!(1),
        3 => json!(u32::MAX),
        4 => json!(u64::MAX),
        5 => json!(i64::MIN),
        6 => json!(1e300),
        7 => json!(-1e-300),
        8 => json!(0.5),
        9 => json!(4_294_967_296u64),
        10 => json!(65_536),
        11 => json!(null),
        12 => json!(""),
        13 => json!("data:application/octet-stream;base64,AAAA"),
        14 => json!([]),
        15 => json!({}),
        16 => json!([0, 0, 0]),
        17 => json!([1e30, -1e30, 0, 1]),
        18 => json!(true),
        19 => json!(3),
        20 => json!(2_147_483_647),
        21 => json!(5126),
        22 => json!("VEC3"),
        _ => json!(7),
    }
}

/// Visits the values of a document in a fixed order (depth first) and returns how many.
fn count(v: &Value) -> usize {
    1 + match v {
        Value::Array(a) => a.iter().map(count).sum(),
        Value::Object(o) => o.values().map(count).sum(),
        _ => 0,
    }
}

/// Replaces the `target`-th value (depth first) with `with`; returns true once done.
fn replace_nth(v: &mut Value, target: &mut usize, with: &Value) -> bool {
    if *target == 0 {
        *v = with.clone();
        return true;
    }
    *target -= 1;
    match v {
        Value::Array(a) => a.iter_mut().any(|x| replace_nth(x, target, with)),
        Value::Object(o) => o.values_mut().any(|x| replace_nth(x, target, with)),
        _ => false,
    }
}

/// Removes a key or element: the `target`-th container's `which`-th child.
fn remove_nth(v: &mut Value, target: &mut usize, which: usize) -> bool {
    let here = *target == 0;
    *target = target.saturating_sub(1);
    match v {
        Value::Array(a) if here && !a.is_empty() => {
            a.remove(which % a.len());
            true
        }
        Value::Object(o) if here && !o.is_empty() => {
            let k = o.keys().nth(which % o.len()).cloned().unwrap_or_default();
            o.remove(&k);
            true
        }
        Value::Array(a) => a.iter_mut().any(|x| remove_nth(x, target, which)),
        Value::Object(o) => o.values_mut().any(|x| remove_nth(x, target, which)),
        _ => false,
    }
}

// ------------------------------------------------------------------------ targets

#[derive(Clone, Debug)]
enum ByteOp {
    Flip {
        at: usize,
        bit: u8,
    },
    Set {
        at: usize,
        value: u8,
    },
    Truncate {
        at: usize,
    },
    Insert {
        at: usize,
        bytes: Vec<u8>,
    },
    /// Overwrite 4 bytes with a little-endian u32 (lengths, counts, offsets).
    Word {
        at: usize,
        value: u32,
    },
}

fn byte_op() -> impl Strategy<Value = ByteOp> {
    let word = prop_oneof![Just(0u32), Just(u32::MAX), Just(0x7fff_ffff), Just(0x8000_0000), any::<u32>()];
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(at, bit)| ByteOp::Flip { at, bit }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, value)| ByteOp::Set { at, value }),
        any::<usize>().prop_map(|at| ByteOp::Truncate { at }),
        (any::<usize>(), proptest::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(at, bytes)| ByteOp::Insert { at, bytes }),
        (any::<usize>(), word).prop_map(|(at, value)| ByteOp::Word { at, value }),
    ]
}

fn apply(bytes: &mut Vec<u8>, op: &ByteOp) {
    if bytes.is_empty() {
        return;
    }
    let n = bytes.len();
    match op {
        ByteOp::Flip { at, bit } => bytes[at % n] ^= 1 << bit,
        ByteOp::Set { at, value } => bytes[at % n] = *value,
        ByteOp::Truncate { at } => bytes.truncate(at % n),
        ByteOp::Insert { at, bytes: ins } => {
            let at = at % n;
            bytes.splice(at..at, ins.iter().copied());
        }
        ByteOp::Word { at, value } => {
            let at = (at % n) & !3;
            for (i, b) in value.to_le_bytes().into_iter().enumerate() {
                if let Some(x) = bytes.get_mut(at + i) {
                    *x = b;
                }
            }
        }
    }
}

proptest! {
    #![proptest_config(config())]

    /// Raw byte mutations of whole files (GLB headers, chunk lengths, JSON syntax).
    #[test]
    fn byte_mutations_never_panic(seed in any::<usize>(), ops in proptest::collection::vec(byte_op(), 1..6)) {
        let c = corpus();
        let (name, bytes) = &c[seed % c.len()];
        let mut b = bytes.clone();
        for op in &ops {
            apply(&mut b, op);
        }
        load(&b, name);
    }

    /// Structured mutations of the glTF document: values replaced or removed, then re-packed,
    /// so the input gets past the JSON parser and into the loader's checks.
    #[test]
    fn json_mutations_never_panic(
        seed in any::<usize>(),
        edits in proptest::collection::vec((any::<usize>(), any::<u8>(), any::<bool>()), 1..5),
    ) {
        let c = corpus();
        let (name, bytes) = &c[seed % c.len()];
        let Some((mut doc, bin, glb)) = parts(bytes) else { return Ok(()) };
        for (at, k, remove) in &edits {
            let n = count(&doc);
            let mut t = at % n;
            if *remove {
                remove_nth(&mut doc, &mut t, *k as usize);
            } else {
                replace_nth(&mut doc, &mut t, &hostile(*k));
            }
        }
        let b = if glb { pack_glb(&doc, &bin) } else { serde_json::to_vec(&doc).unwrap_or_default() };
        load(&b, name);
    }

    /// Mutations of the GLB binary chunk only: indices out of range, NaN positions, etc.
    #[test]
    fn bin_chunk_mutations_never_panic(
        seed in any::<usize>(),
        ops in proptest::collection::vec(byte_op(), 1..8),
    ) {
        let c = corpus();
        let glbs: Vec<_> = c.iter().filter(|(_, b)| b.starts_with(b"glTF")).collect();
        let (name, bytes) = glbs[seed % glbs.len()];
        let Some((doc, mut bin)) = split_glb(bytes) else { return Ok(()) };
        let len = bin.len();
        for op in &ops {
            // Keep the length: buffer byteLength checks would refuse everything else early.
            if !matches!(op, ByteOp::Truncate { .. } | ByteOp::Insert { .. }) {
                apply(&mut bin, op);
            }
        }
        bin.resize(len, 0);
        load(&pack_glb(&doc, &bin), name);
    }
}

#[test]
fn corpus_is_not_trivial() {
    let c = corpus();
    for (name, bytes) in c {
        assert!(load_scene_from_slice(bytes, name, None, &opts()).is_ok(), "{name}");
    }
    let names: Vec<&str> = c.iter().map(|(n, _)| n.as_str()).collect();
    eprintln!("fuzz corpus: {} files: {names:?}", c.len());
    assert!(c.len() >= 4);
}
