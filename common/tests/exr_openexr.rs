//! Our EXR files open in an independent reader (the `openexr` Python package) with the same
//! channel names and bit-identical float32 values.

use pathfarm_common::film::{Film, SampleValue, TileAccum, add_sample};
use pathfarm_common::job::TileRect;
use std::path::Path;
use std::process::Command;

#[test]
fn openexr_python_reads_our_layers_bit_for_bit() {
    let (w, h) = (7u32, 5u32);
    let mut film = Film::new(w, h);
    let mut tile = TileAccum::new(TileRect { x0: 0, y0: 0, x1: w, y1: h });
    for y in 0..h {
        for x in 0..w {
            for s in 0..3 {
                let v = (x as f32 + 0.1) * (y as f32 + 0.3) / (s as f32 + 1.0);
                add_sample(
                    tile.pixel_mut(x, y),
                    &SampleValue {
                        radiance: [v, 0.5 * v, 0.25 * v],
                        albedo: [0.1 * x as f32, 0.2, 0.3],
                        normal: [0.0, 1.0, 0.0],
                        depth: if x == 0 { None } else { Some(1.5 + y as f32) },
                    },
                );
            }
        }
    }
    film.add_tile(&tile);
    let image = film.resolve();
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("layers.exr");
    image.write_exr(&path).expect("write exr");

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/exr_dump.py");
    let out = Command::new("python3").arg(&script).arg(&path).output().expect("run python3");
    assert!(
        out.status.success(),
        "the OpenEXR Python package could not read our file (install it: pip install OpenEXR numpy): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let dump: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json from exr_dump.py");
    assert_eq!(dump["width"], w);
    assert_eq!(dump["height"], h);
    let channels = dump["channels"].as_object().expect("channels");
    let ours = image.exr_channels();
    assert_eq!(channels.len(), ours.len(), "channel list: {:?}", channels.keys().collect::<Vec<_>>());
    for (name, values) in ours {
        let theirs = &channels.get(name).unwrap_or_else(|| panic!("channel {name} missing"))["values"];
        let theirs = theirs.as_array().expect("values");
        assert_eq!(theirs.len(), values.len(), "{name}");
        for (i, (a, b)) in values.iter().zip(theirs).enumerate() {
            match b.as_f64() {
                Some(b) => assert_eq!(a.to_bits(), (b as f32).to_bits(), "{name}[{i}]: ours {a}, OpenEXR {b}"),
                None => assert!(!a.is_finite() && b.as_str() == Some(&a.to_string()), "{name}[{i}]: {a} vs {b}"),
            }
        }
    }
}
