//! Scene bundles: what `POST /scenes` takes and what workers download.
//!
//! A bundle is one of
//! - a binary glTF (`.glb`, starts with `glTF`),
//! - a glTF JSON document whose buffers and images are all `data:` URIs,
//! - an uncompressed tar archive holding exactly one `.gltf` or `.glb` file plus the files it
//!   names (`tar -cf scene.tar scene.gltf scene.bin textures/`).
//!
//! Bundles are content-addressed by the SHA-256 of their bytes. Unpacking refuses entries that
//! would leave the target directory (absolute paths, `..`, links), so a bundle can only ever name
//! files inside itself; the loader refuses such URIs a second time.

use super::{LoadOptions, Scene, SceneError, load_scene};
use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Component, Path, PathBuf};

/// Most files in a tar bundle.
const MAX_ENTRIES: usize = 10_000;

/// The content address of a bundle: lower-case hex SHA-256.
pub fn scene_id(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// True if `id` looks like a scene id (64 lower-case hex digits), so it is safe in a path.
pub fn is_scene_id(id: &str) -> bool {
    id.len() == 64 && id.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

fn invalid(message: impl Into<String>) -> SceneError {
    SceneError::Invalid { file: "bundle".into(), message: message.into() }
}

fn io(element: &str, source: std::io::Error) -> SceneError {
    SceneError::Io { file: "bundle".into(), element: element.into(), source }
}

fn is_tar(bytes: &[u8]) -> bool {
    bytes.len() >= 512 && &bytes[257..262] == b"ustar"
}

/// Writes the bundle's files under `dir` (created) and returns the path of its scene file.
pub fn unpack_bundle(bytes: &[u8], dir: &Path) -> Result<PathBuf, SceneError> {
    std::fs::create_dir_all(dir).map_err(|e| io("creating the scene directory", e))?;
    if bytes.starts_with(b"glTF") {
        let path = dir.join("scene.glb");
        std::fs::write(&path, bytes).map_err(|e| io("writing scene.glb", e))?;
        return Ok(path);
    }
    if is_tar(bytes) {
        return unpack_tar(bytes, dir);
    }
    if bytes.iter().find(|b| !b.is_ascii_whitespace()) == Some(&b'{') {
        let path = dir.join("scene.gltf");
        std::fs::write(&path, bytes).map_err(|e| io("writing scene.gltf", e))?;
        return Ok(path);
    }
    Err(invalid(
        "not a scene bundle: expected a .glb, a .gltf JSON document, or a tar archive of a .gltf and its files",
    ))
}

fn unpack_tar(bytes: &[u8], dir: &Path) -> Result<PathBuf, SceneError> {
    let mut archive = tar::Archive::new(bytes);
    let mut scenes = Vec::new();
    let entries = archive.entries().map_err(|e| invalid(format!("tar: {e}")))?;
    for (i, entry) in entries.enumerate() {
        if i >= MAX_ENTRIES {
            return Err(invalid(format!("tar: more than {MAX_ENTRIES} entries")));
        }
        let mut entry = entry.map_err(|e| invalid(format!("tar entry {i}: {e}")))?;
        let kind = entry.header().entry_type();
        let path = entry.path().map_err(|e| invalid(format!("tar entry {i}: path: {e}")))?.into_owned();
        if kind.is_dir() {
            continue;
        }
        if !kind.is_file() {
            return Err(invalid(format!("tar entry {:?}: only regular files are allowed (no links)", path)));
        }
        let mut rel = PathBuf::new();
        for c in path.components() {
            match c {
                Component::Normal(part) => rel.push(part),
                Component::CurDir => {}
                _ => return Err(invalid(format!("tar entry {:?}: path must stay inside the bundle", path))),
            }
        }
        if rel.as_os_str().is_empty() {
            continue;
        }
        let target = dir.join(&rel);
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).map_err(|e| io("creating a bundle directory", e))?;
        }
        let mut data = Vec::new();
        entry.read_to_end(&mut data).map_err(|e| invalid(format!("tar entry {:?}: {e}", path)))?;
        std::fs::write(&target, &data).map_err(|e| io("writing a bundle file", e))?;
        let ext = rel.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("gltf" | "glb")) {
            scenes.push(target);
        }
    }
    match scenes.len() {
        1 => Ok(scenes.remove(0)),
        0 => Err(invalid("tar archive holds no .gltf or .glb file")),
        n => Err(invalid(format!("tar archive holds {n} .gltf/.glb files; a bundle has exactly one"))),
    }
}

/// Unpacks (into `dir`) and loads a bundle.
pub fn load_bundle(bytes: &[u8], dir: &Path, opts: &LoadOptions) -> Result<Scene, SceneError> {
    let path = unpack_bundle(bytes, dir)?;
    load_scene(&path, opts)
}

/// Writes a tar bundle of `files` (path inside the bundle, bytes); for clients and tests.
pub fn tar_bundle(files: &[(&str, &[u8])]) -> std::io::Result<Vec<u8>> {
    let mut builder = tar::Builder::new(Vec::new());
    for (name, data) in files {
        let mut header = tar::Header::new_ustar();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_entry_type(tar::EntryType::Regular);
        header.set_cksum();
        builder.append_data(&mut header, name, *data)?;
    }
    builder.into_inner()
}

/// Packs a `.gltf` and every file it names (`buffers[].uri`, `images[].uri`; `data:` URIs stay
/// inline) into a tar bundle, so a "glTF Separate" export uploads as one body. The files keep
/// their relative paths; a URI that is absolute, has a scheme, leaves the `.gltf`'s folder
/// (`..`, or a link pointing outside it) or names a missing file is refused by name.
pub fn pack_gltf(gltf: &Path) -> Result<Vec<u8>, SceneError> {
    let file = gltf.display().to_string();
    let failed = |message: String| SceneError::Invalid { file: file.clone(), message };
    let text = std::fs::read(gltf).map_err(|e| failed(format!("cannot read it: {e}")))?;
    let doc: serde_json::Value =
        serde_json::from_slice(&text).map_err(|e| failed(format!("not a glTF JSON document: {e}")))?;
    let base = gltf.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let root = base.canonicalize().map_err(|e| failed(format!("its folder {}: {e}", base.display())))?;
    let name = gltf.file_name().and_then(|n| n.to_str()).unwrap_or("scene.gltf");
    let mut files: Vec<(String, Vec<u8>)> = vec![(name.to_string(), text.clone())];
    for kind in ["buffers", "images"] {
        let Some(list) = doc.get(kind).and_then(|v| v.as_array()) else { continue };
        for (i, item) in list.iter().enumerate() {
            let Some(uri) = item.get("uri").and_then(|u| u.as_str()) else { continue };
            if uri.starts_with("data:") {
                continue;
            }
            let element = format!("{kind}[{i}] \"{uri}\"");
            let rel = super::load::check_uri(uri).map_err(|m| failed(format!("{element}: {m}")))?;
            let entry: Vec<&str> = rel.iter().filter_map(|c| c.to_str()).collect();
            let entry = entry.join("/");
            if entry == name || files.iter().any(|(n, _)| *n == entry) {
                continue;
            }
            let path = root.join(&rel);
            let real = path.canonicalize().map_err(|e| failed(format!("{element}: {}: {e}", path.display())))?;
            if !real.starts_with(&root) {
                return Err(failed(format!("{element}: {} leaves the scene's folder", path.display())));
            }
            let bytes = std::fs::read(&real).map_err(|e| failed(format!("{element}: {}: {e}", path.display())))?;
            files.push((entry, bytes));
        }
    }
    let refs: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    tar_bundle(&refs).map_err(|e| io("packing the tar bundle", e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::demo;

    #[test]
    fn glb_and_tar_bundles_load() {
        let dir = tempfile::tempdir().expect("tempdir");
        let glb = demo::cornell_demo_glb();
        let s = load_bundle(&glb, &dir.path().join("a"), &LoadOptions::default()).expect("glb");
        assert!(s.triangle_count() > 0);
        let tar = tar_bundle(&[("sub/demo.glb", &glb), ("readme.txt", b"hi")]).expect("tar");
        let s2 = load_bundle(&tar, &dir.path().join("b"), &LoadOptions::default()).expect("tar");
        assert_eq!(s.triangle_count(), s2.triangle_count());
        assert_eq!(scene_id(&glb).len(), 64);
        assert!(is_scene_id(&scene_id(&glb)));
        assert!(!is_scene_id("../etc"));
    }

    #[test]
    fn bad_bundles_are_refused_by_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        let e = unpack_bundle(b"hello", dir.path()).expect_err("garbage");
        assert!(e.to_string().contains("not a scene bundle"), "{e}");
        let tar = tar_bundle(&[("a.txt", b"x")]).expect("tar");
        let e = unpack_bundle(&tar, dir.path()).expect_err("no scene");
        assert!(e.to_string().contains("no .gltf"), "{e}");
        let glb = demo::cornell_demo_glb();
        let tar = tar_bundle(&[("a.glb", &glb), ("b.glb", &glb)]).expect("tar");
        let e = unpack_bundle(&tar, dir.path()).expect_err("two scenes");
        assert!(e.to_string().contains("exactly one"), "{e}");
    }

    #[test]
    fn tar_paths_cannot_escape() {
        let dir = tempfile::tempdir().expect("tempdir");
        // tar::Builder refuses `..` itself, so write the header by hand.
        let mut header = tar::Header::new_old();
        let name = b"../escape.gltf";
        header.as_old_mut().name[..name.len()].copy_from_slice(name);
        header.set_size(2);
        header.set_entry_type(tar::EntryType::Regular);
        let mut ustar = tar::Header::new_ustar();
        ustar.as_mut_bytes()[..100].copy_from_slice(&header.as_bytes()[..100]);
        ustar.set_size(2);
        ustar.set_mode(0o644);
        ustar.set_entry_type(tar::EntryType::Regular);
        ustar.set_cksum();
        let mut bytes = ustar.as_bytes().to_vec();
        bytes.extend_from_slice(b"{}");
        bytes.resize(bytes.len() + 510 + 1024, 0);
        let e = unpack_bundle(&bytes, &dir.path().join("x")).expect_err("escape");
        assert!(e.to_string().contains("inside the bundle"), "{e}");
        assert!(!dir.path().join("escape.gltf").exists());
    }

    fn write_files(dir: &Path, files: &[(String, Vec<u8>)]) {
        for (name, bytes) in files {
            let path = dir.join(name);
            std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
            std::fs::write(path, bytes).expect("write");
        }
    }

    #[test]
    fn a_separate_gltf_is_packed_with_its_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let files = demo::cornell_separate_files();
        write_files(&dir.path().join("export"), &files);
        let gltf = dir.path().join("export/cornell.gltf");
        let bundle = pack_gltf(&gltf).expect("pack");
        let packed = load_bundle(&bundle, &dir.path().join("unpacked"), &LoadOptions::default()).expect("loads");
        let direct = load_scene(&gltf, &LoadOptions::default()).expect("direct");
        assert_eq!(packed.triangle_count(), direct.triangle_count());
        assert_eq!(packed.textures.len(), 1, "the checker texture travels with it");
        // Every file of the export is in the tar, under its relative path.
        let mut names: Vec<String> = tar::Archive::new(bundle.as_slice())
            .entries()
            .expect("entries")
            .map(|e| e.expect("entry").path().expect("path").display().to_string())
            .collect();
        names.sort();
        let mut expected: Vec<String> = files.iter().map(|(n, _)| n.clone()).collect();
        expected.sort();
        assert_eq!(names, expected);
    }

    #[test]
    fn packing_refuses_missing_and_escaping_files_by_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        let files = demo::cornell_separate_files();
        let folder = dir.path().join("export");
        write_files(&folder, &files);
        std::fs::remove_file(folder.join("cornell.bin")).expect("rm");
        let e = pack_gltf(&folder.join("cornell.gltf")).expect_err("missing buffer");
        assert!(e.to_string().contains("buffers[0] \"cornell.bin\""), "{e}");

        std::fs::write(dir.path().join("secret.bin"), b"x").expect("write");
        let mut doc: serde_json::Value = serde_json::from_slice(&files[0].1).expect("json");
        doc["buffers"][0]["uri"] = "../secret.bin".into();
        std::fs::write(folder.join("cornell.gltf"), doc.to_string()).expect("write");
        let e = pack_gltf(&folder.join("cornell.gltf")).expect_err("escape");
        assert!(e.to_string().contains("outside the bundle"), "{e}");
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(dir.path().join("secret.bin"), folder.join("link.bin")).expect("symlink");
            doc["buffers"][0]["uri"] = "link.bin".into();
            std::fs::write(folder.join("cornell.gltf"), doc.to_string()).expect("write");
            let e = pack_gltf(&folder.join("cornell.gltf")).expect_err("link out");
            assert!(e.to_string().contains("leaves the scene's folder"), "{e}");
        }
    }
}
