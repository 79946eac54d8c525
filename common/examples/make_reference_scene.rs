//! Writes the scenes of the Mitsuba references that `scripts/make-reference.py` renders, as our
//! exporter writes them: `reference/cornell_mitsuba.glb` (Mitsuba 3's Cornell box) and
//! `reference/cornell_spheres.glb` (its walls with a mirror and a glass sphere).
//!
//! `cargo run -p pathfarm-common --example make_reference_scene [-- OUT_DIR]`

use std::path::PathBuf;

fn main() -> std::io::Result<()> {
    let dir = std::env::args_os()
        .nth(1)
        .map_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../reference"), PathBuf::from);
    std::fs::create_dir_all(&dir)?;
    for (name, bytes) in [
        ("cornell_mitsuba.glb", pathfarm_common::scene::demo::cornell_mitsuba_glb()),
        ("cornell_spheres.glb", pathfarm_common::scene::demo::cornell_spheres_glb()),
    ] {
        let out = dir.join(name);
        std::fs::write(&out, bytes)?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}
