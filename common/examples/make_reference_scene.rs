//! Writes `reference/cornell_mitsuba.glb` (Mitsuba 3's Cornell box as our exporter writes it),
//! the scene of the Mitsuba reference that `scripts/make-reference.py` renders.
//!
//! `cargo run -p pathfarm-common --example make_reference_scene [-- OUT.glb]`

use std::path::PathBuf;

fn main() -> std::io::Result<()> {
    let out = std::env::args_os().nth(1).map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../reference/cornell_mitsuba.glb"),
        PathBuf::from,
    );
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&out, pathfarm_common::scene::demo::cornell_mitsuba_glb())?;
    eprintln!("wrote {}", out.display());
    Ok(())
}
