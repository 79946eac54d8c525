//! glTF 2.0 -> [`Scene`]. (The loader is being written; see the scene issue.)

use super::{Scene, SceneError};
use std::path::Path;

/// Loader options.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {}

/// Loads a `.glb` or `.gltf` file (external files resolved next to it).
pub fn load_scene(path: &Path, _opts: &LoadOptions) -> Result<Scene, SceneError> {
    Err(SceneError::Invalid { file: path.display().to_string(), message: "loader not written yet".into() })
}

/// Loads a scene from bytes; `base_dir` resolves external URIs (none: only data URIs allowed).
pub fn load_scene_from_slice(
    _bytes: &[u8],
    name: &str,
    _base_dir: Option<&Path>,
    _opts: &LoadOptions,
) -> Result<Scene, SceneError> {
    Err(SceneError::Invalid { file: name.into(), message: "loader not written yet".into() })
}
