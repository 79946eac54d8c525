//! glTF 2.0 -> [`Scene`].
//!
//! The loader parses the JSON with `gltf-json` but reads everything else itself: the GLB
//! container, buffers, URIs, accessors (including sparse ones) and images. That keeps three
//! promises the `gltf` crate's wrapper and importer cannot:
//!
//! * **Nothing panics on a bad file.** The wrapper API unwraps indices (it assumes a validated
//!   document), its validator indexes accessors unchecked, and its accessor reader subtracts 1
//!   from `count` and hits `unreachable!` on unexpected component types. Here every index is
//!   bounds-checked and every size computed with checked arithmetic.
//! * **External files never escape the bundle.** See [`resolve_external`].
//! * **Errors name the file and the element**, e.g.
//!   `scene.gltf: mesh 3 primitive 1: accessor 7: ...`.
//!
//! Since we validate as we go instead of up front, a document that the `gltf` crate would reject
//! for a dangling reference nobody follows still loads. This is deliberate for
//! `cornellBox_nvpro`, whose `textures[0].source` names an image that does not exist while no
//! material uses that texture: it loads with a warning naming the texture. A material that does
//! use a dangling texture loses that texture, also with a warning (a visible fallback, not a
//! failed job).
//!
//! Order of things in the [`Scene`]: `materials[i]` is glTF material `i` (the default material is
//! appended after them when some primitive has none); meshes, cameras and lights appear in node
//! traversal order (depth first, children in file order, root nodes in the scene's order), so
//! `cameras[0]` is the first camera met in that traversal.

use super::anim::{self, Animation};
use super::{
    AlphaMode, Camera, Material, MaterialModel, Mesh, Projection, PunctualKind, PunctualLight, Scene, SceneError,
    Texture, TextureRef, TextureTransform, WrapMode,
};
use glam::{Mat3, Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::json;
use gltf::json::validation::Checked;
use std::collections::HashMap;
use std::fmt::Display;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Loader options. The defaults have no limits; a server should set them.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Refuse scenes with more triangles than this (after instancing).
    pub max_triangles: Option<usize>,
    /// Refuse any image with more pixels (width x height) than this; checked before decoding.
    pub max_texture_pixels: Option<u64>,
    /// Memory budget for one scene's images, in bytes: decode buffers plus the linear texels
    /// kept for rendering (16 bytes a texel, shared by every texture of an image in one colour
    /// space). Checked before each allocation, so a small file naming one huge image many
    /// times is refused before it costs memory.
    pub max_texture_bytes: Option<u64>,
}

/// Largest accepted magnitude of a world-space vertex coordinate. Beyond it single-precision
/// geometry loses all detail and bounding-box areas overflow (1e25 crashed the BVH build).
pub const MAX_COORDINATE: f32 = 1e7;

/// Extensions we implement, so a file may require them.
const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_pbrSpecularGlossiness",
    "KHR_materials_unlit",
    "KHR_texture_transform",
    "KHR_materials_transmission",
    "KHR_materials_ior",
    "KHR_materials_emissive_strength",
    "KHR_materials_specular",
    "KHR_materials_volume",
    "KHR_materials_clearcoat",
    "KHR_materials_sheen",
    // The accessor reader converts every component type, which is all this extension asks.
    "KHR_mesh_quantization",
    // Camera, light and material properties (see `anim`); unknown pointers are skipped with a
    // warning.
    "KHR_animation_pointer",
];

/// Extensions we ignore with a warning even when required: the still image stays meaningful
/// without them (material refinements, variants).
const IGNORABLE_EXTENSIONS: &[&str] =
    &["KHR_materials_iridescence", "KHR_materials_anisotropy", "KHR_materials_dispersion", "KHR_materials_variants"];

/// Deepest node hierarchy we follow; deeper means a cycle or a hostile file.
const MAX_NODE_DEPTH: usize = 512;
/// Most node visits in one traversal; nodes shared by several parents multiply visits.
const MAX_NODE_VISITS: usize = 1 << 20;
/// An accessor without a bufferView is all zeros (plus sparse values); its count is only bounded
/// by this, so a tiny file cannot ask for gigabytes.
const MAX_ZERO_ACCESSOR_ELEMENTS: usize = 1 << 22;

/// Loads a `.glb` or `.gltf` file; external files are resolved next to it and may not leave its
/// directory.
pub fn load_scene(path: &Path, opts: &LoadOptions) -> Result<Scene, SceneError> {
    let name = path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned());
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        file: name.clone(),
        element: format!("reading {name}"),
        source,
    })?;
    let base = path.parent().map(|p| if p.as_os_str().is_empty() { Path::new(".") } else { p });
    load_scene_from_slice(&bytes, &name, base, opts)
}

/// Loads a scene from bytes (`.glb` or `.gltf` JSON); `name` is used in messages.
///
/// `base_dir` resolves external URIs, which must be relative paths inside it; with `None` only
/// `data:` URIs and the GLB binary chunk are allowed. Whatever `base_dir` is, a URI that is
/// absolute, contains a `..` segment or has a scheme other than `data:` is refused with
/// [`SceneError::ForbiddenUri`].
pub fn load_scene_from_slice(
    bytes: &[u8],
    name: &str,
    base_dir: Option<&Path>,
    opts: &LoadOptions,
) -> Result<Scene, SceneError> {
    let file = name.to_string();
    let invalid = |message: String| SceneError::Invalid { file: file.clone(), message };
    let (json_bytes, bin) = if bytes.starts_with(b"glTF") {
        let (j, b) = split_glb(bytes).map_err(|m| invalid(format!("GLB container: {m}")))?;
        (j, b)
    } else {
        (bytes, None)
    };
    // Animations are parsed by `anim` (gltf-json cannot parse KHR_animation_pointer channels:
    // they have no `node`), the rest of the document by gltf-json.
    let mut value: serde_json::Value =
        serde_json::from_slice(json_bytes).map_err(|e| invalid(format!("invalid JSON: {e}")))?;
    let animations = value.as_object_mut().and_then(|obj| obj.remove("animations"));
    let root: json::Root = serde_json::from_value(value.clone()).map_err(|e| invalid(format!("invalid glTF: {e}")))?;
    let mut loader = Loader::new(file.clone(), &root, base_dir, opts);
    loader.check_extensions()?;
    loader.load_buffers(bin)?;
    loader.check_textures();
    loader.load_materials()?;
    loader.traverse()?;
    let Some(animations) = animations.filter(|a| a.as_array().is_some_and(|a| !a.is_empty())) else {
        if !loader.scene.has_emitters() {
            loader.warn(super::NO_LIGHT_WARNING.to_string());
        }
        return Ok(loader.scene);
    };
    let mut warnings = Vec::new();
    // Key data is budgeted from the accessors' declared sizes, before reading them.
    let mut floats = 0usize;
    let clips = anim::parse_clips(
        &animations,
        &value,
        |a| {
            floats = floats.saturating_add(loader.accessor_floats(a));
            if floats > MAX_ANIMATION_FLOATS {
                return Err(format!(
                    "accessor {a}: animation keys hold more than {MAX_ANIMATION_FLOATS} numbers in all"
                ));
            }
            loader.read_accessor(a, false).map(|e| (e.comps, e.values))
        },
        |w| warnings.push(w),
    )
    .map_err(invalid)?;
    for w in warnings {
        loader.warn(w);
    }
    let animation = Arc::new(Animation {
        file,
        document: value,
        buffers: loader.buffers.clone(),
        texels: std::mem::take(&mut loader.texels),
        clips,
        max_triangles: opts.max_triangles,
    });
    let mut scene = loader.scene;
    scene.animation = Some(animation);
    // A still render of an animated scene shows time 0 (frame 0), with every animation playing.
    let mut posed = scene.posed(0.0, None)?;
    if !posed.has_emitters() && !posed.warnings.iter().any(|w| w == super::NO_LIGHT_WARNING) {
        tracing::warn!(file = %name, "{}", super::NO_LIGHT_WARNING);
        posed.warnings.push(super::NO_LIGHT_WARNING.to_string());
    }
    Ok(posed)
}

/// Most numbers (key times and values) that one file's animations may hold: 64 MiB of f32.
const MAX_ANIMATION_FLOATS: usize = 1 << 24;

/// Loads the animated scene's document posed at time `t` (see [`Scene::posed`]).
pub(super) fn load_posed(anim: &Arc<Animation>, t: f32, names: Option<&[String]>) -> Result<Scene, SceneError> {
    let invalid = |message: String| SceneError::Invalid { file: anim.file.clone(), message };
    let doc = anim.posed_document(t, names).map_err(invalid)?;
    let root: json::Root =
        serde_json::from_value(doc).map_err(|e| invalid(format!("posed at t = {t}: invalid glTF: {e}")))?;
    let opts = LoadOptions { max_triangles: anim.max_triangles, ..LoadOptions::default() };
    let mut loader = Loader::new(anim.file.clone(), &root, None, &opts);
    loader.buffers = anim.buffers.clone();
    loader.texels = anim.texels.clone();
    loader.load_materials()?;
    loader.traverse()?;
    loader.scene.animation = Some(anim.clone());
    Ok(loader.scene)
}

/// Splits a GLB container into its JSON chunk and optional BIN chunk (unknown chunks skipped).
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let u32_at = |at: usize| -> Option<u32> {
        let b = bytes.get(at..at.checked_add(4)?)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    let version = u32_at(4).ok_or("truncated header")?;
    if version != 2 {
        return Err(format!("unsupported GLB version {version}"));
    }
    let length = u32_at(8).ok_or("truncated header")? as usize;
    if length > bytes.len() {
        return Err(format!("truncated: header says {length} bytes, file has {}", bytes.len()));
    }
    let mut at = 12usize;
    let (mut json, mut bin) = (None, None);
    while at < length {
        let chunk_len = u32_at(at).ok_or("truncated chunk header")? as usize;
        let kind = bytes.get(at + 4..at + 8).ok_or("truncated chunk header")?;
        let start = at + 8;
        let end = start
            .checked_add(chunk_len)
            .filter(|&e| e <= length)
            .ok_or_else(|| format!("truncated: chunk at byte {at} claims {chunk_len} bytes past the end"))?;
        let data = bytes.get(start..end).ok_or("truncated chunk")?;
        match kind {
            b"JSON" if json.is_none() => json = Some(data),
            b"BIN\0" if json.is_some() && bin.is_none() => bin = Some(data),
            b"JSON" | b"BIN\0" => return Err(format!("unexpected chunk at byte {at}")),
            _ => {}
        }
        at = end;
    }
    Ok((json.ok_or("no JSON chunk")?, bin))
}

/// Why a URI may not be read, or the relative path it names.
pub(crate) fn check_uri(uri: &str) -> Result<PathBuf, String> {
    if uri.contains(':') {
        return Err("only data: URIs and relative paths are allowed".into());
    }
    let decoded = percent_decode(uri).ok_or("bad percent-encoding")?;
    if decoded.is_empty() || decoded.contains('\0') {
        return Err("empty or invalid path".into());
    }
    if decoded.starts_with('/') || decoded.starts_with('\\') || decoded.contains(':') {
        return Err("absolute paths are not allowed".into());
    }
    if decoded.split(['/', '\\']).any(|seg| seg == "..") {
        return Err("outside the bundle".into());
    }
    Ok(decoded.split(['/', '\\']).filter(|s| !s.is_empty() && *s != ".").collect())
}

fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while let Some(&c) = b.get(i) {
        if c == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(c);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// Decodes a `data:` URI (base64 or percent-encoded payload).
fn decode_data_uri(uri: &str) -> Result<Vec<u8>, String> {
    use base64::Engine as _;
    let rest = uri.strip_prefix("data:").ok_or("not a data URI")?;
    let (meta, payload) = rest.split_once(',').ok_or("data URI without ','")?;
    if meta.ends_with(";base64") {
        let engine = base64::engine::GeneralPurpose::new(
            &base64::alphabet::STANDARD,
            base64::engine::GeneralPurposeConfig::new()
                .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent),
        );
        engine.decode(payload.trim()).map_err(|e| format!("bad base64: {e}"))
    } else {
        percent_decode(payload).map(String::into_bytes).ok_or_else(|| "bad percent-encoding".into())
    }
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

fn wrap_mode(w: Checked<json::texture::WrappingMode>) -> WrapMode {
    match w {
        Checked::Valid(json::texture::WrappingMode::ClampToEdge) => WrapMode::ClampToEdge,
        Checked::Valid(json::texture::WrappingMode::MirroredRepeat) => WrapMode::MirroredRepeat,
        _ => WrapMode::Repeat,
    }
}

fn quoted(name: Option<&str>) -> String {
    name.map(|n| format!(" {n:?}")).unwrap_or_default()
}

/// A decoded image (before colour-space conversion).
struct Decoded {
    width: u32,
    height: u32,
    /// 8-bit images keep bytes (sRGB decode by table); others are converted to f32.
    rgba8: Option<Vec<u8>>,
    rgba32f: Option<Vec<f32>>,
}

struct Loader<'a> {
    file: String,
    root: &'a json::Root,
    base_dir: Option<&'a Path>,
    opts: &'a LoadOptions,
    /// Buffer data, each cut to its `byteLength` (shared with [`Animation`] for posing).
    buffers: Arc<Vec<Vec<u8>>>,
    images: HashMap<usize, Decoded>,
    /// (image, sRGB, wrap_s, wrap_t) -> index into `scene.textures`.
    textures: HashMap<(usize, bool, WrapMode, WrapMode), usize>,
    /// (image, sRGB) -> width, height and linear texels, shared by textures that differ only in
    /// wrap modes (and by every pose of an animated scene).
    texels: anim::TexelCache,
    /// Bytes of image memory charged against `max_texture_bytes` so far.
    texture_bytes: u64,
    scene: Scene,
    triangles: usize,
    default_material: Option<usize>,
    /// World matrix of every node (through its first parent), for skins' joints.
    node_world: Vec<Option<Mat4>>,
}

/// Raw f32 components of an accessor, `comps` per element.
struct Elements {
    comps: usize,
    values: Vec<f32>,
}

impl<'a> Loader<'a> {
    fn new(file: String, root: &'a json::Root, base_dir: Option<&'a Path>, opts: &'a LoadOptions) -> Self {
        Loader {
            file,
            root,
            base_dir,
            opts,
            buffers: Arc::default(),
            images: HashMap::new(),
            textures: HashMap::new(),
            texels: HashMap::new(),
            texture_bytes: 0,
            scene: Scene::default(),
            triangles: 0,
            default_material: None,
            node_world: Vec::new(),
        }
    }

    fn invalid(&self, element: impl Display, message: impl Display) -> SceneError {
        SceneError::Invalid { file: self.file.clone(), message: format!("{element}: {message}") }
    }

    fn warn(&mut self, message: String) {
        tracing::warn!(file = %self.file, "{message}");
        self.scene.warnings.push(message);
    }

    fn check_extensions(&mut self) -> Result<(), SceneError> {
        for ext in &self.root.extensions_required {
            if SUPPORTED_EXTENSIONS.contains(&ext.as_str()) {
                continue;
            }
            if IGNORABLE_EXTENSIONS.contains(&ext.as_str()) {
                self.warn(format!("extensionsRequired: {ext} is not supported; ignored"));
            } else {
                return Err(self.invalid("extensionsRequired", format!("{ext} is not supported")));
            }
        }
        Ok(())
    }

    /// Reads an external file named by `uri` for `element`, under the URI rules.
    fn resolve_external(&self, element: &str, uri: &str) -> Result<Vec<u8>, SceneError> {
        let forbidden = |reason: String| SceneError::ForbiddenUri {
            file: self.file.clone(),
            element: element.to_string(),
            uri: uri.to_string(),
            reason,
        };
        let rel = check_uri(uri).map_err(forbidden)?;
        let base =
            self.base_dir.ok_or_else(|| forbidden("external files are not allowed without a base directory".into()))?;
        let io = |source| SceneError::Io { file: self.file.clone(), element: format!("{element} uri {uri:?}"), source };
        // Symbolic links could still lead out of the bundle: compare canonical paths.
        let base = base.canonicalize().map_err(io)?;
        let path = base.join(rel).canonicalize().map_err(io)?;
        if !path.starts_with(&base) {
            return Err(forbidden("outside the bundle".into()));
        }
        std::fs::read(&path).map_err(io)
    }

    fn load_buffers(&mut self, bin: Option<&[u8]>) -> Result<(), SceneError> {
        let mut buffers = Vec::with_capacity(self.root.buffers.len());
        for (i, b) in self.root.buffers.iter().enumerate() {
            let element = format!("buffer {i}");
            let mut data = match b.uri.as_deref() {
                None if i == 0 => bin.ok_or_else(|| self.invalid(&element, "no uri and no GLB binary chunk"))?.to_vec(),
                None => return Err(self.invalid(&element, "no uri")),
                Some(uri) if uri.starts_with("data:") => {
                    decode_data_uri(uri).map_err(|m| self.invalid(format!("{element} data uri"), m))?
                }
                Some(uri) => self.resolve_external(&element, uri)?,
            };
            let len = usize::try_from(b.byte_length.0).unwrap_or(usize::MAX);
            if data.len() < len {
                return Err(
                    self.invalid(&element, format!("byteLength is {len} but only {} bytes were found", data.len()))
                );
            }
            data.truncate(len);
            buffers.push(data);
        }
        self.buffers = Arc::new(buffers);
        Ok(())
    }

    /// The bytes of a buffer view.
    fn view_bytes(&self, index: usize) -> Result<(&[u8], Option<usize>), String> {
        let view = self.root.buffer_views.get(index).ok_or(format!("bufferView {index} does not exist"))?;
        let buffer = view.buffer.value();
        let data = self.buffers.get(buffer).ok_or(format!("bufferView {index}: buffer {buffer} does not exist"))?;
        let offset = view.byte_offset.map_or(0, |o| o.0);
        let range = usize::try_from(offset)
            .ok()
            .and_then(|o| Some(o..o.checked_add(usize::try_from(view.byte_length.0).ok()?)?));
        let bytes = range.and_then(|r| data.get(r)).ok_or(format!(
            "bufferView {index} (offset {offset}, length {}) exceeds buffer {buffer} ({} bytes)",
            view.byte_length.0,
            data.len()
        ))?;
        Ok((bytes, view.byte_stride.map(|s| s.0).filter(|&s| s > 0)))
    }

    /// The number of f32 components accessor `index` declares (0 when it does not exist).
    fn accessor_floats(&self, index: usize) -> usize {
        use json::accessor::Type;
        let Some(acc) = self.root.accessors.get(index) else { return 0 };
        let comps = match acc.type_ {
            Checked::Valid(Type::Vec2) => 2,
            Checked::Valid(Type::Vec3) => 3,
            Checked::Valid(Type::Vec4) => 4,
            Checked::Valid(Type::Mat4) => 16,
            _ => 1,
        };
        usize::try_from(acc.count.0).unwrap_or(usize::MAX).saturating_mul(comps)
    }

    /// Reads accessor `index` as f32 components (integers normalized when the accessor says so).
    /// `integer` asks for unsigned integer components only (indices).
    fn read_accessor(&self, index: usize, integer: bool) -> Result<Elements, String> {
        use json::accessor::{ComponentType as C, Type};
        let here = |m: String| format!("accessor {index}: {m}");
        let acc = self.root.accessors.get(index).ok_or(format!("accessor {index} does not exist"))?;
        let Checked::Valid(json::accessor::GenericComponentType(ctype)) = acc.component_type else {
            return Err(here("invalid componentType".into()));
        };
        let comps = match acc.type_ {
            Checked::Valid(Type::Scalar) => 1,
            Checked::Valid(Type::Vec2) => 2,
            Checked::Valid(Type::Vec3) => 3,
            Checked::Valid(Type::Vec4) => 4,
            // Float matrices only: byte and short matrices have column padding.
            Checked::Valid(Type::Mat4) if ctype == C::F32 => 16,
            _ => return Err(here("unsupported or invalid type (expected SCALAR, VECn or float MAT4)".into())),
        };
        if integer && !matches!(ctype, C::U8 | C::U16 | C::U32) {
            return Err(here("indices must be unsigned integers".into()));
        }
        let csize = ctype.size();
        let elem = csize * comps;
        let normalized = acc.normalized;
        let decode = move |b: &[u8]| -> f32 {
            let v = match (ctype, b) {
                (C::F32, &[a, b2, c, d]) => return f32::from_le_bytes([a, b2, c, d]),
                (C::U32, &[a, b2, c, d]) => u32::from_le_bytes([a, b2, c, d]) as f64,
                (C::U16, &[a, b2]) => f64::from(u16::from_le_bytes([a, b2])),
                (C::I16, &[a, b2]) => f64::from(i16::from_le_bytes([a, b2])),
                (C::U8, &[a]) => f64::from(a),
                (C::I8, &[a]) => f64::from(a as i8),
                _ => 0.0,
            };
            if !normalized {
                return v as f32;
            }
            let n = match ctype {
                C::U8 => 255.0,
                C::I8 => 127.0,
                C::U16 => 65535.0,
                C::I16 => 32767.0,
                _ => f64::from(u32::MAX),
            };
            (v / n).max(-1.0) as f32
        };
        let count = usize::try_from(acc.count.0).map_err(|_| here("count too large".into()))?;
        let total = count.checked_mul(comps).ok_or_else(|| here("count too large".into()))?;
        let mut values;
        if let Some(view) = acc.buffer_view {
            let (bytes, stride) = self.view_bytes(view.value()).map_err(here)?;
            let stride = stride.unwrap_or(elem);
            if stride < elem {
                return Err(here(format!("byteStride {stride} is smaller than an element ({elem} bytes)")));
            }
            let offset = usize::try_from(acc.byte_offset.map_or(0, |o| o.0)).unwrap_or(usize::MAX);
            if count > 0 {
                let need = count
                    .checked_sub(1)
                    .and_then(|c| c.checked_mul(stride))
                    .and_then(|n| n.checked_add(elem))
                    .and_then(|n| n.checked_add(offset));
                if need.is_none_or(|n| n > bytes.len()) {
                    return Err(here(format!(
                        "{count} elements at offset {offset} do not fit in bufferView {} ({} bytes)",
                        view.value(),
                        bytes.len()
                    )));
                }
            }
            values = Vec::with_capacity(total);
            for i in 0..count {
                let start = offset + i * stride;
                let e = bytes.get(start..start + elem).ok_or_else(|| here("out of range".into()))?;
                values.extend(e.chunks_exact(csize).map(decode));
            }
        } else {
            if count > MAX_ZERO_ACCESSOR_ELEMENTS {
                return Err(here(format!(
                    "{count} elements without a bufferView (at most {MAX_ZERO_ACCESSOR_ELEMENTS})"
                )));
            }
            values = vec![0.0; total];
        }
        if let Some(sparse) = &acc.sparse {
            let n = usize::try_from(sparse.count.0).map_err(|_| here("sparse count too large".into()))?;
            if n > count {
                return Err(here(format!("sparse count {n} exceeds count {count}")));
            }
            let Checked::Valid(json::accessor::IndexComponentType(itype)) = sparse.indices.component_type else {
                return Err(here("sparse: invalid indices componentType".into()));
            };
            let isize_ = itype.size();
            let slice = |view: usize, offset: u64, size: usize| -> Result<&[u8], String> {
                let (bytes, _) = self.view_bytes(view)?;
                let offset = usize::try_from(offset).unwrap_or(usize::MAX);
                let end = n.checked_mul(size).and_then(|l| l.checked_add(offset));
                end.and_then(|e| bytes.get(offset..e)).ok_or(format!("sparse data does not fit in bufferView {view}"))
            };
            let ib = slice(sparse.indices.buffer_view.value(), sparse.indices.byte_offset.0, isize_).map_err(here)?;
            let vb = slice(sparse.values.buffer_view.value(), sparse.values.byte_offset.0, elem).map_err(here)?;
            for (ie, ve) in ib.chunks_exact(isize_).zip(vb.chunks_exact(elem)) {
                let target = match *ie {
                    [a] => usize::from(a),
                    [a, b] => usize::from(u16::from_le_bytes([a, b])),
                    [a, b, c, d] => u32::from_le_bytes([a, b, c, d]) as usize,
                    _ => usize::MAX,
                };
                let dst = target
                    .checked_mul(comps)
                    .and_then(|s| values.get_mut(s..s + comps))
                    .ok_or_else(|| here(format!("sparse index {target} out of range (count {count})")))?;
                for (d, s) in dst.iter_mut().zip(ve.chunks_exact(csize)) {
                    *d = decode(s);
                }
            }
        }
        Ok(Elements { comps, values })
    }

    /// Marks textures whose image does not exist (see the module docs) with a warning.
    fn check_textures(&mut self) {
        for (i, t) in self.root.textures.iter().enumerate() {
            let src = t.source.value();
            if self.root.images.get(src).is_none() {
                let used = self.root.materials.iter().any(|m| material_textures(m).contains(&i));
                let what = if used { "materials using it lose it" } else { "unused, ignored" };
                self.warn(format!(
                    "texture {i}{}: source image {src} does not exist; {what}",
                    quoted(t.name.as_deref())
                ));
            }
        }
    }

    fn image_bytes(&self, index: usize, element: &str) -> Result<Vec<u8>, SceneError> {
        let img = self.root.images.get(index).ok_or_else(|| self.invalid(element, "does not exist"))?;
        match (&img.uri, img.buffer_view) {
            (Some(uri), _) if uri.starts_with("data:") => decode_data_uri(uri).map_err(|m| self.invalid(element, m)),
            (Some(uri), _) => self.resolve_external(element, uri),
            (None, Some(view)) => {
                self.view_bytes(view.value()).map(|(b, _)| b.to_vec()).map_err(|m| self.invalid(element, m))
            }
            (None, None) => Err(self.invalid(element, "neither uri nor bufferView")),
        }
    }

    fn decode_image(&mut self, index: usize) -> Result<(), SceneError> {
        if self.images.contains_key(&index) {
            return Ok(());
        }
        let img = self.root.images.get(index);
        let label = img.and_then(|i| i.name.as_deref().or(i.uri.as_deref().filter(|u| !u.starts_with("data:"))));
        let element = format!("image {index}{}", quoted(label));
        let bytes = self.image_bytes(index, &element)?;
        let reader = || {
            image::ImageReader::new(std::io::Cursor::new(&bytes))
                .with_guessed_format()
                .map_err(|e| self.invalid(&element, e))
        };
        let decoder = reader()?.into_decoder().map_err(|e| self.invalid(&element, e))?;
        let (w, h) = image::ImageDecoder::dimensions(&decoder);
        let pixels = u64::from(w) * u64::from(h);
        if let Some(max) = self.opts.max_texture_pixels.filter(|&m| pixels > m) {
            return Err(SceneError::LimitExceeded {
                file: self.file.clone(),
                element: format!("{element}: {w}x{h} pixels"),
                limit: "max_texture_pixels",
                actual: pixels,
                max,
            });
        }
        let color = image::ImageDecoder::color_type(&decoder);
        let eight_bit = matches!(
            color,
            image::ColorType::L8 | image::ColorType::La8 | image::ColorType::Rgb8 | image::ColorType::Rgba8
        );
        // The decoder's buffer and the RGBA copy we keep, both before either is allocated.
        let kept = pixels.saturating_mul(if eight_bit { 4 } else { 16 });
        self.charge_texture_bytes(image::ImageDecoder::total_bytes(&decoder).saturating_add(kept), &element)?;
        let decoded = image::DynamicImage::from_decoder(decoder).map_err(|e| self.invalid(&element, e))?;
        let d = Decoded {
            width: w,
            height: h,
            rgba8: eight_bit.then(|| decoded.to_rgba8().into_raw()),
            rgba32f: (!eight_bit).then(|| decoded.to_rgba32f().into_raw()),
        };
        self.images.insert(index, d);
        Ok(())
    }

    /// The scene texture for glTF texture `index` in the given colour space, built on first use.
    fn texture(&mut self, index: usize, srgb: bool, owner: &str) -> Result<Option<usize>, SceneError> {
        let Some(t) = self.root.textures.get(index) else {
            self.warn(format!("{owner}: texture {index} does not exist; ignored"));
            return Ok(None);
        };
        let image = t.source.value();
        if self.root.images.get(image).is_none() {
            self.warn(format!("{owner}: texture {index} has no image (image {image} does not exist); ignored"));
            return Ok(None);
        }
        let (wrap_s, wrap_t) = match t.sampler.map(|s| self.root.samplers.get(s.value())) {
            Some(None) => return Err(self.invalid(format!("texture {index}"), "sampler does not exist")),
            Some(Some(s)) => (wrap_mode(s.wrap_s), wrap_mode(s.wrap_t)),
            None => (WrapMode::Repeat, WrapMode::Repeat),
        };
        let key = (image, srgb, wrap_s, wrap_t);
        if let Some(&i) = self.textures.get(&key) {
            return Ok(Some(i));
        }
        if let Some((width, height, texels)) = self.texels.get(&(image, srgb)) {
            let (width, height) = (*width, *height);
            let name = self.texture_name(image, srgb);
            let texels = texels.clone();
            self.scene.textures.push(Texture { name, width, height, texels, wrap_s, wrap_t });
            let i = self.scene.textures.len() - 1;
            self.textures.insert(key, i);
            return Ok(Some(i));
        }
        self.decode_image(image)?;
        let pixels = self.images.get(&image).map_or(0, |d| u64::from(d.width) * u64::from(d.height));
        self.charge_texture_bytes(pixels.saturating_mul(16), &format!("texture {index}"))?;
        let Some(d) = self.images.get(&image) else { return Ok(None) };
        let texels: Vec<Vec4> = if let Some(px) = &d.rgba8 {
            let lut: Vec<f32> = (0..256u16)
                .map(|v| {
                    let c = f32::from(v) / 255.0;
                    if srgb { srgb_to_linear(c) } else { c }
                })
                .collect();
            let l = |v: u8| lut.get(usize::from(v)).copied().unwrap_or(0.0);
            px.chunks_exact(4)
                .map(|p| match *p {
                    [r, g, b, a] => Vec4::new(l(r), l(g), l(b), f32::from(a) / 255.0),
                    _ => Vec4::ONE,
                })
                .collect()
        } else {
            let px = d.rgba32f.as_deref().unwrap_or_default();
            let cs = |c: f32| if srgb { srgb_to_linear(c) } else { c };
            px.chunks_exact(4)
                .map(|p| match *p {
                    [r, g, b, a] => Vec4::new(cs(r), cs(g), cs(b), a),
                    _ => Vec4::ONE,
                })
                .collect()
        };
        let (width, height) = (d.width, d.height);
        let texels = Arc::new(texels);
        self.texels.insert((image, srgb), (width, height, texels.clone()));
        let name = self.texture_name(image, srgb);
        self.scene.textures.push(Texture { name, width, height, texels, wrap_s, wrap_t });
        let i = self.scene.textures.len() - 1;
        self.textures.insert(key, i);
        Ok(Some(i))
    }

    fn texture_name(&self, image: usize, srgb: bool) -> String {
        let img = self.root.images.get(image);
        let base = img
            .and_then(|i| i.name.clone().or(i.uri.clone().filter(|u| !u.starts_with("data:"))))
            .unwrap_or_else(|| format!("image {image}"));
        format!("{base} ({})", if srgb { "sRGB" } else { "linear" })
    }

    /// Charges `bytes` of image memory against `max_texture_bytes` before they are allocated.
    fn charge_texture_bytes(&mut self, bytes: u64, element: &str) -> Result<(), SceneError> {
        let total = self.texture_bytes.saturating_add(bytes);
        if let Some(max) = self.opts.max_texture_bytes.filter(|&m| total > m) {
            return Err(SceneError::LimitExceeded {
                file: self.file.clone(),
                element: format!("{element}: image memory"),
                limit: "max_texture_bytes",
                actual: total,
                max,
            });
        }
        self.texture_bytes = total;
        Ok(())
    }

    fn texture_ref(
        &mut self,
        info: Option<&json::texture::Info>,
        srgb: bool,
        owner: &str,
    ) -> Result<Option<TextureRef>, SceneError> {
        let Some(info) = info else { return Ok(None) };
        let transform = info.extensions.as_ref().and_then(|e| e.texture_transform.as_ref());
        self.texture_ref_parts(info.index.value(), info.tex_coord, transform, srgb, owner)
    }

    fn texture_ref_parts(
        &mut self,
        index: usize,
        tex_coord: u32,
        transform: Option<&json::extensions::texture::TextureTransform>,
        srgb: bool,
        owner: &str,
    ) -> Result<Option<TextureRef>, SceneError> {
        let Some(texture) = self.texture(index, srgb, owner)? else { return Ok(None) };
        let mut r = TextureRef { texture, tex_coord, transform: TextureTransform::default() };
        if let Some(t) = transform {
            r.transform = TextureTransform {
                offset: Vec2::from(t.offset.0),
                rotation: t.rotation.0,
                scale: Vec2::from(t.scale.0),
            };
            if let Some(tc) = t.tex_coord {
                r.tex_coord = tc;
            }
        }
        if r.tex_coord > 1 {
            self.warn(format!(
                "{owner}: texture {index} uses TEXCOORD_{}; only 0 and 1 are read, using 0",
                r.tex_coord
            ));
            r.tex_coord = 0;
        }
        Ok(Some(r))
    }

    fn load_materials(&mut self) -> Result<(), SceneError> {
        for (i, m) in self.root.materials.iter().enumerate() {
            let material = self.material(i, m)?;
            self.scene.materials.push(material);
        }
        Ok(())
    }

    /// Converts one material.
    fn material(&mut self, i: usize, m: &json::Material) -> Result<Material, SceneError> {
        let owner = format!("material {i}{}", quoted(m.name.as_deref()));
        let pbr = &m.pbr_metallic_roughness;
        let ext = m.extensions.as_ref();
        let mut mat = Material {
            name: m.name.clone().unwrap_or_else(|| format!("material {i}")),
            model: self.material_model(m, &owner)?,
            base_color: Vec4::from(pbr.base_color_factor.0),
            base_color_texture: self.texture_ref(pbr.base_color_texture.as_ref(), true, &owner)?,
            metallic: pbr.metallic_factor.0,
            roughness: pbr.roughness_factor.0,
            metallic_roughness_texture: self.texture_ref(pbr.metallic_roughness_texture.as_ref(), false, &owner)?,
            emissive: Vec3::from(m.emissive_factor.0),
            emissive_texture: self.texture_ref(m.emissive_texture.as_ref(), true, &owner)?,
            normal_texture: None,
            normal_scale: 1.0,
            double_sided: m.double_sided,
            alpha_mode: match m.alpha_mode {
                Checked::Valid(json::material::AlphaMode::Mask) => {
                    AlphaMode::Mask { cutoff: m.alpha_cutoff.map_or(0.5, |c| c.0) }
                }
                Checked::Valid(json::material::AlphaMode::Blend) => AlphaMode::Blend,
                _ => AlphaMode::Opaque,
            },
            ..Material::default()
        };
        if let Some(n) = &m.normal_texture {
            // gltf-json has no typed KHR_texture_transform on normal textures; read it ourselves.
            let transform = n
                .extensions
                .as_ref()
                .and_then(|e| e.others.get("KHR_texture_transform"))
                .map(|v| serde_json::from_value(v.clone()))
                .transpose()
                .map_err(|e| self.invalid(&owner, format!("normalTexture KHR_texture_transform: {e}")))?;
            mat.normal_texture =
                self.texture_ref_parts(n.index.value(), n.tex_coord, transform.as_ref(), false, &owner)?;
            mat.normal_scale = n.scale;
        }
        if let Some(ext) = ext {
            if let Some(sg) = &ext.pbr_specular_glossiness {
                // Approximation: diffuse -> base colour, a dielectric whose roughness is 1 - gloss.
                mat.base_color = Vec4::from(sg.diffuse_factor.0);
                mat.base_color_texture = self.texture_ref(sg.diffuse_texture.as_ref(), true, &owner)?;
                mat.metallic = 0.0;
                mat.roughness = 1.0 - sg.glossiness_factor.0;
                mat.metallic_roughness_texture = None;
            }
            if let Some(s) = &ext.emissive_strength {
                mat.emissive *= s.emissive_strength.0;
            }
            if let Some(t) = &ext.transmission {
                mat.transmission = t.transmission_factor.0;
                mat.transmission_texture = self.texture_ref(t.transmission_texture.as_ref(), false, &owner)?;
            }
            if let Some(ior) = &ext.ior {
                mat.ior = ior.ior.0;
            }
            if let Some(s) = &ext.specular {
                mat.specular_factor = s.specular_factor.0;
            }
            if let Some(v) = &ext.volume {
                let (color, distance) = (Vec3::from(v.attenuation_color.0), v.attenuation_distance.0);
                if !(color.is_finite() && color.min_element() >= 0.0 && distance > 0.0) {
                    return Err(self.invalid(
                        &owner,
                        "KHR_materials_volume: attenuationColor must be in [0, 1] and attenuationDistance > 0",
                    ));
                }
                if v.thickness_factor.0 > 0.0 {
                    mat.thin_walled = false;
                    if distance.is_finite() {
                        // A colour of 0 absorbs everything: a large finite coefficient.
                        let c = color.max(Vec3::splat(1e-6)).min(Vec3::ONE);
                        mat.attenuation = -Vec3::new(c.x.ln(), c.y.ln(), c.z.ln()) / distance;
                    }
                }
            }
            mat.unlit = ext.unlit.is_some();
            if let Some(v) = ext.others.get("KHR_materials_clearcoat") {
                let c: ClearcoatJson = serde_json::from_value(v.clone())
                    .map_err(|e| self.invalid(&owner, format!("KHR_materials_clearcoat: {e}")))?;
                mat.clearcoat = c.clearcoat_factor;
                mat.clearcoat_texture = self.texture_ref(c.clearcoat_texture.as_ref(), false, &owner)?;
                mat.clearcoat_roughness = c.clearcoat_roughness_factor;
                mat.clearcoat_roughness_texture =
                    self.texture_ref(c.clearcoat_roughness_texture.as_ref(), false, &owner)?;
                if c.clearcoat_normal_texture.is_some() {
                    self.warn(format!(
                        "{owner}: KHR_materials_clearcoat clearcoatNormalTexture is not read (the coat uses the base's normal)"
                    ));
                }
                if !(0.0..=1.0).contains(&mat.clearcoat) || !(0.0..=1.0).contains(&mat.clearcoat_roughness) {
                    return Err(self.invalid(&owner, "KHR_materials_clearcoat: factors must be in [0, 1]"));
                }
            }
            if let Some(v) = ext.others.get("KHR_materials_sheen") {
                let sh: SheenJson = serde_json::from_value(v.clone())
                    .map_err(|e| self.invalid(&owner, format!("KHR_materials_sheen: {e}")))?;
                mat.sheen_color = Vec3::from(sh.sheen_color_factor);
                mat.sheen_color_texture = self.texture_ref(sh.sheen_color_texture.as_ref(), true, &owner)?;
                mat.sheen_roughness = sh.sheen_roughness_factor;
                mat.sheen_roughness_texture = self.texture_ref(sh.sheen_roughness_texture.as_ref(), false, &owner)?;
                let in_range = |v: f32| (0.0..=1.0).contains(&v);
                if !(in_range(mat.sheen_color.min_element())
                    && in_range(mat.sheen_color.max_element())
                    && in_range(mat.sheen_roughness))
                {
                    return Err(self.invalid(&owner, "KHR_materials_sheen: factors must be in [0, 1]"));
                }
            }
        }
        let cutoff = match mat.alpha_mode {
            AlphaMode::Mask { cutoff } => cutoff,
            _ => 0.0,
        };
        let finite = mat.base_color.is_finite()
            && mat.emissive.is_finite()
            && mat.attenuation.is_finite()
            && cutoff.is_finite()
            && [mat.metallic, mat.roughness, mat.transmission, mat.ior, mat.specular_factor, mat.normal_scale]
                .iter()
                .all(|v| v.is_finite());
        if !finite {
            return Err(self.invalid(owner, "non-finite factor"));
        }
        Ok(mat)
    }

    /// The reflection model chosen by `extras.pathfarm` (glTF's own model without it).
    fn material_model(&self, m: &json::Material, owner: &str) -> Result<MaterialModel, SceneError> {
        let Some(raw) = m.extras.as_ref() else { return Ok(MaterialModel::Gltf) };
        let Ok(serde_json::Value::Object(extras)) = serde_json::from_str(raw.get()) else {
            return Ok(MaterialModel::Gltf);
        };
        let Some(v) = extras.get("pathfarm") else { return Ok(MaterialModel::Gltf) };
        let model: MaterialModel =
            serde_json::from_value(v.clone()).map_err(|e| self.invalid(owner, format!("extras.pathfarm: {e}")))?;
        let ok = |e: f32| e.is_finite() && e >= 0.0;
        let valid = match model {
            MaterialModel::Blinn { exponent } => ok(exponent),
            MaterialModel::AshikhminShirley { exponent_x, exponent_y } => ok(exponent_x) && ok(exponent_y),
            _ => true,
        };
        if !valid {
            return Err(self.invalid(owner, "extras.pathfarm: exponents must be finite and >= 0"));
        }
        Ok(model)
    }

    fn default_material(&mut self) -> usize {
        *self.default_material.get_or_insert_with(|| {
            self.scene.materials.push(Material::default());
            self.scene.materials.len() - 1
        })
    }

    /// Root nodes: the default scene's, else scene 0's, else every node that is nobody's child.
    fn traverse(&mut self) -> Result<(), SceneError> {
        let root = self.root;
        let scene = root.scene.map(|s| s.value()).unwrap_or(0);
        let roots: Vec<usize> = match root.scenes.get(scene) {
            Some(s) => s.nodes.iter().map(|n| n.value()).collect(),
            None if root.scene.is_some() => return Err(self.invalid("scene", format!("scene {scene} does not exist"))),
            None => {
                let mut child = vec![false; root.nodes.len()];
                for n in &root.nodes {
                    for c in n.children.iter().flatten() {
                        if let Some(f) = child.get_mut(c.value()) {
                            *f = true;
                        }
                    }
                }
                (0..root.nodes.len()).filter(|&i| !child.get(i).copied().unwrap_or(true)).collect()
            }
        };
        if !root.skins.is_empty() {
            self.node_world = self.node_worlds()?;
        }
        let mut path = Vec::new();
        let mut visits = 0usize;
        for n in roots {
            self.visit(n, Mat4::IDENTITY, &mut path, &mut visits)?;
        }
        Ok(())
    }

    /// World matrices of all nodes through their first parent (joints need not be in the scene's
    /// tree); each node's chain is walked once, at most [`MAX_NODE_DEPTH`] deep.
    fn node_worlds(&self) -> Result<Vec<Option<Mat4>>, SceneError> {
        let nodes = &self.root.nodes;
        let mut parent: Vec<Option<usize>> = vec![None; nodes.len()];
        for (i, n) in nodes.iter().enumerate() {
            for c in n.children.iter().flatten() {
                if let Some(p @ None) = parent.get_mut(c.value()) {
                    *p = Some(i);
                }
            }
        }
        let mut world: Vec<Option<Mat4>> = vec![None; nodes.len()];
        let mut chain = Vec::new();
        for i in 0..nodes.len() {
            chain.clear();
            let mut cur = Some(i);
            while let Some(c) = cur.filter(|&c| world.get(c).is_some_and(Option::is_none)) {
                chain.push(c);
                if chain.len() > MAX_NODE_DEPTH {
                    return Err(self.invalid(
                        format!("node {i}"),
                        format!("node hierarchy deeper than {MAX_NODE_DEPTH} or cyclic"),
                    ));
                }
                cur = parent.get(c).copied().flatten();
            }
            let mut m = cur.and_then(|c| world.get(c).copied().flatten()).unwrap_or(Mat4::IDENTITY);
            for &c in chain.iter().rev() {
                m *= nodes.get(c).map_or(Mat4::IDENTITY, local_matrix);
                if let Some(w) = world.get_mut(c) {
                    *w = Some(m);
                }
            }
        }
        Ok(world)
    }

    fn visit(
        &mut self,
        index: usize,
        parent: Mat4,
        path: &mut Vec<usize>,
        visits: &mut usize,
    ) -> Result<(), SceneError> {
        let root = self.root;
        let node = root.nodes.get(index).ok_or_else(|| self.invalid(format!("node {index}"), "does not exist"))?;
        let element = format!("node {index}{}", quoted(node.name.as_deref()));
        if path.contains(&index) {
            return Err(self.invalid(element, "the node hierarchy has a cycle"));
        }
        if path.len() >= MAX_NODE_DEPTH {
            return Err(self.invalid(element, format!("node hierarchy deeper than {MAX_NODE_DEPTH}")));
        }
        *visits += 1;
        if *visits > MAX_NODE_VISITS {
            return Err(self.invalid(element, format!("more than {MAX_NODE_VISITS} node instances")));
        }
        let world = parent * local_matrix(node);
        if !world.is_finite() {
            return Err(self.invalid(element, "non-finite transform"));
        }
        if let Some(m) = node.mesh {
            let mi = m.value();
            let mesh =
                root.meshes.get(mi).ok_or_else(|| self.invalid(&element, format!("mesh {mi} does not exist")))?;
            let skin = node.skin.map(|s| s.value());
            let weights = node.weights.as_deref().or(mesh.weights.as_deref());
            for (pi, prim) in mesh.primitives.iter().enumerate() {
                self.primitive(mi, pi, prim, &element, world, Deform { skin, weights })?;
            }
        }
        if let Some(c) = node.camera {
            self.camera(c.value(), &element, world)?;
        }
        if let Some(l) = node.extensions.as_ref().and_then(|e| e.khr_lights_punctual.as_ref()) {
            self.light(l.light.value(), &element, world)?;
        }
        path.push(index);
        for c in node.children.iter().flatten() {
            self.visit(c.value(), world, path, visits)?;
        }
        path.pop();
        Ok(())
    }

    fn camera(&mut self, index: usize, node: &str, world: Mat4) -> Result<(), SceneError> {
        let c =
            self.root.cameras.get(index).ok_or_else(|| self.invalid(node, format!("camera {index} does not exist")))?;
        let element = format!("camera {index}{} ({node})", quoted(c.name.as_deref()));
        let projection = match (c.type_, &c.perspective, &c.orthographic) {
            (Checked::Valid(json::camera::Type::Perspective), Some(p), _) => {
                Projection::Perspective { yfov: p.yfov, aspect: p.aspect_ratio }
            }
            (Checked::Valid(json::camera::Type::Orthographic), _, Some(o)) => {
                Projection::Orthographic { xmag: o.xmag, ymag: o.ymag }
            }
            _ => {
                self.warn(format!("{element}: invalid type or missing projection; skipped"));
                return Ok(());
            }
        };
        // Remove scale (and shear): Gram-Schmidt on the axes, keeping -Z (the view direction)
        // and then +Y (up) as given.
        let z = world.z_axis.truncate().normalize_or(Vec3::Z);
        let y = (world.y_axis.truncate() - z * world.y_axis.truncate().dot(z)).normalize_or(z.any_orthonormal_vector());
        let x = y.cross(z);
        let world_from_camera =
            Mat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), world.w_axis.truncate().extend(1.0));
        let name = c.name.clone().unwrap_or_else(|| format!("camera {index}"));
        self.scene.cameras.push(Camera { name, world_from_camera, projection });
        Ok(())
    }

    fn light(&mut self, index: usize, node: &str, world: Mat4) -> Result<(), SceneError> {
        use json::extensions::scene::khr_lights_punctual::Type;
        let lights = self.root.extensions.as_ref().and_then(|e| e.khr_lights_punctual.as_ref());
        let l = lights
            .and_then(|ls| ls.lights.get(index))
            .ok_or_else(|| self.invalid(node, format!("light {index} does not exist")))?;
        let kind = match l.type_ {
            Checked::Valid(Type::Point) => PunctualKind::Point,
            Checked::Valid(Type::Directional) => PunctualKind::Directional,
            Checked::Valid(Type::Spot) => {
                let (inner, outer) = l
                    .spot
                    .as_ref()
                    .map_or((0.0, std::f32::consts::FRAC_PI_4), |s| (s.inner_cone_angle, s.outer_cone_angle));
                PunctualKind::Spot { inner_cone: inner, outer_cone: outer }
            }
            Checked::Invalid => {
                self.warn(format!("light {index} ({node}): invalid type; skipped"));
                return Ok(());
            }
        };
        // cd or lux -> W/sr or W/m^2 (see LUMENS_PER_WATT).
        let intensity = Vec3::from(l.color) * (l.intensity / super::LUMENS_PER_WATT);
        if !intensity.is_finite() {
            return Err(self.invalid(format!("light {index} ({node})"), "non-finite intensity"));
        }
        self.scene.lights.push(PunctualLight {
            name: l.name.clone().unwrap_or_else(|| format!("light {index}")),
            kind,
            intensity,
            position: world.transform_point3(Vec3::ZERO),
            direction: world.transform_vector3(Vec3::NEG_Z).normalize_or(Vec3::NEG_Z),
            range: l.range,
        });
        Ok(())
    }

    /// Adds the weighted morph-target displacements of `prim` (positions, normals, tangents'
    /// xyz). Weights missing for a target are 0; targets with weight 0 are not read.
    #[allow(clippy::too_many_arguments)]
    fn morph(
        &self,
        prim: &json::mesh::Primitive,
        weights: Option<&[f32]>,
        n: usize,
        element: &str,
        pos: &mut [f32],
        normals: Option<&mut Vec<f32>>,
        tangents: Option<&mut Vec<f32>>,
    ) -> Result<(), SceneError> {
        let (Some(targets), Some(weights)) = (prim.targets.as_ref(), weights) else { return Ok(()) };
        let (mut normals, mut tangents) = (normals, tangents);
        for (k, target) in targets.iter().enumerate() {
            let w = weights.get(k).copied().unwrap_or(0.0);
            if w == 0.0 || !w.is_finite() {
                continue;
            }
            let read = |acc: Option<json::Index<json::Accessor>>, what: &str| -> Result<Option<Vec<f32>>, SceneError> {
                let Some(acc) = acc else { return Ok(None) };
                let here = format!("{element} target {k} {what}");
                let e = self.read_accessor(acc.value(), false).map_err(|m| self.invalid(&here, m))?;
                if e.comps != 3 || e.values.len() != n * 3 {
                    return Err(self.invalid(here, format!("accessor {}: must be VEC3 with {n} elements", acc.value())));
                }
                if !e.values.iter().all(|v| v.is_finite()) {
                    return Err(self.invalid(here, format!("accessor {}: non-finite values", acc.value())));
                }
                Ok(Some(e.values))
            };
            if let Some(d) = read(target.positions, "POSITION")? {
                pos.iter_mut().zip(&d).for_each(|(p, d)| *p += w * d);
            }
            if let (Some(nrm), Some(d)) = (normals.as_deref_mut(), read(target.normals, "NORMAL")?) {
                nrm.iter_mut().zip(&d).for_each(|(p, d)| *p += w * d);
            }
            if let (Some(tan), Some(d)) = (tangents.as_deref_mut(), read(target.tangents, "TANGENT")?) {
                for (t, d) in tan.chunks_exact_mut(4).zip(d.chunks_exact(3)) {
                    t.iter_mut().zip(d).for_each(|(p, d)| *p += w * d);
                }
            }
        }
        Ok(())
    }

    /// Per-vertex skinning matrices of `prim` under skin `si`: sum over JOINTS_n / WEIGHTS_n of
    /// weight x joint world x inverse bind matrix. `None` when the primitive has no JOINTS_0
    /// (it is then placed by its node). A vertex whose weights are all 0 gets the identity.
    fn skin_matrices(
        &self,
        prim: &json::mesh::Primitive,
        si: usize,
        n: usize,
        element: &str,
    ) -> Result<Option<Vec<Mat4>>, SceneError> {
        use json::mesh::Semantic;
        if !prim.attributes.contains_key(&Checked::Valid(Semantic::Joints(0))) {
            return Ok(None);
        }
        let here = format!("{element} skin {si}");
        let skin = self.root.skins.get(si).ok_or_else(|| self.invalid(&here, "does not exist"))?;
        let ibm = match skin.inverse_bind_matrices {
            Some(a) => {
                let e = self.read_accessor(a.value(), false).map_err(|m| self.invalid(&here, m))?;
                if e.comps != 16 || e.values.len() < skin.joints.len() * 16 || !e.values.iter().all(|v| v.is_finite()) {
                    return Err(self.invalid(
                        &here,
                        format!(
                            "inverseBindMatrices accessor {} must hold {} finite MAT4",
                            a.value(),
                            skin.joints.len()
                        ),
                    ));
                }
                e.values.chunks_exact(16).map(Mat4::from_cols_slice).collect()
            }
            None => vec![Mat4::IDENTITY; skin.joints.len()],
        };
        let joints: Vec<Mat4> = skin
            .joints
            .iter()
            .zip(&ibm)
            .map(|(j, ibm)| {
                let w = self.node_world.get(j.value()).copied().flatten();
                w.map(|w| w * *ibm)
                    .ok_or_else(|| self.invalid(&here, format!("joint node {} does not exist", j.value())))
            })
            .collect::<Result<_, _>>()?;
        let mut mats = vec![Mat4::ZERO; n];
        let mut set = 0u32;
        while let (Some(ja), Some(wa)) = (
            prim.attributes.get(&Checked::Valid(Semantic::Joints(set))),
            prim.attributes.get(&Checked::Valid(Semantic::Weights(set))),
        ) {
            let read = |a: usize| self.read_accessor(a, false).map_err(|m| self.invalid(&here, m));
            let (j, w) = (read(ja.value())?, read(wa.value())?);
            if j.comps != 4 || w.comps != 4 || j.values.len() != n * 4 || w.values.len() != n * 4 {
                return Err(
                    self.invalid(&here, format!("JOINTS_{set} and WEIGHTS_{set} must be VEC4 with {n} elements"))
                );
            }
            for (m, (jv, wv)) in mats.iter_mut().zip(j.values.chunks_exact(4).zip(w.values.chunks_exact(4))) {
                for (&ji, &wi) in jv.iter().zip(wv) {
                    if wi == 0.0 {
                        continue;
                    }
                    let joint = joints.get(ji as usize).filter(|_| wi.is_finite()).ok_or_else(|| {
                        self.invalid(
                            &here,
                            format!("JOINTS_{set}: joint {ji} does not exist ({} joints)", joints.len()),
                        )
                    })?;
                    *m += *joint * wi;
                }
            }
            set += 1;
        }
        for m in &mut mats {
            if *m == Mat4::ZERO {
                *m = Mat4::IDENTITY;
            }
        }
        Ok(Some(mats))
    }

    /// Reads a vertex attribute with `comps` components per vertex, `n` vertices (when known).
    fn attribute(
        &self,
        prim: &json::mesh::Primitive,
        semantic: json::mesh::Semantic,
        comps: usize,
        n: Option<usize>,
        element: &str,
    ) -> Result<Option<Vec<f32>>, SceneError> {
        let name = semantic.to_string();
        let Some(acc) = prim.attributes.get(&Checked::Valid(semantic)) else { return Ok(None) };
        let e = self.read_accessor(acc.value(), false).map_err(|m| self.invalid(element, m))?;
        if e.comps != comps {
            return Err(self.invalid(element, format!("accessor {}: {name} must have {comps} components", acc.value())));
        }
        if let Some(n) = n.filter(|&n| e.values.len() != n * comps) {
            return Err(self.invalid(
                element,
                format!("accessor {}: {name} has {} elements, POSITION has {n}", acc.value(), e.values.len() / comps),
            ));
        }
        if !e.values.iter().all(|v| v.is_finite()) {
            return Err(self.invalid(element, format!("accessor {}: {name} has non-finite values", acc.value())));
        }
        Ok(Some(e.values))
    }

    /// COLOR_0 as linear RGBA (VEC3 or VEC4; float or normalized unsigned integers).
    fn vertex_colors(
        &self,
        prim: &json::mesh::Primitive,
        n: usize,
        element: &str,
    ) -> Result<Option<Vec<Vec4>>, SceneError> {
        let Some(acc) = prim.attributes.get(&Checked::Valid(json::mesh::Semantic::Colors(0))) else { return Ok(None) };
        let e = self.read_accessor(acc.value(), false).map_err(|m| self.invalid(element, m))?;
        if !(e.comps == 3 || e.comps == 4) {
            return Err(self.invalid(element, format!("accessor {}: COLOR_0 must be VEC3 or VEC4", acc.value())));
        }
        if e.values.len() != n * e.comps {
            return Err(self.invalid(
                element,
                format!(
                    "accessor {}: COLOR_0 has {} elements, POSITION has {n}",
                    acc.value(),
                    e.values.len() / e.comps
                ),
            ));
        }
        if !e.values.iter().all(|v| v.is_finite()) {
            return Err(self.invalid(element, format!("accessor {}: COLOR_0 has non-finite values", acc.value())));
        }
        let alpha = |c: &[f32]| c.get(3).copied().unwrap_or(1.0);
        Ok(Some(e.values.chunks_exact(e.comps).map(|c| Vec4::new(c[0], c[1], c[2], alpha(c))).collect()))
    }

    fn primitive(
        &mut self,
        mi: usize,
        pi: usize,
        prim: &json::mesh::Primitive,
        node: &str,
        world: Mat4,
        deform: Deform<'_>,
    ) -> Result<(), SceneError> {
        use json::mesh::{Mode, Semantic};
        let element = format!("mesh {mi} primitive {pi}");
        let mode = match prim.mode {
            Checked::Valid(m @ (Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan)) => m,
            Checked::Valid(m) => {
                self.warn(format!("{element}: mode {m:?} is not triangles; skipped"));
                return Ok(());
            }
            Checked::Invalid => {
                self.warn(format!("{element}: invalid mode; skipped"));
                return Ok(());
            }
        };
        let Some(mut pos) = self.attribute(prim, Semantic::Positions, 3, None, &element)? else {
            self.warn(format!("{element}: no POSITION; skipped"));
            return Ok(());
        };
        let n = pos.len() / 3;
        let mut normals = self.attribute(prim, Semantic::Normals, 3, Some(n), &element)?;
        let mut tangents = self.attribute(prim, Semantic::Tangents, 4, Some(n), &element)?;
        self.morph(prim, deform.weights, n, &element, &mut pos, normals.as_mut(), tangents.as_mut())?;
        let skin = match deform.skin {
            Some(s) => self.skin_matrices(prim, s, n, &element)?,
            None => None,
        };
        let uv0 = self.attribute(prim, Semantic::TexCoords(0), 2, Some(n), &element)?;
        let uv1 = self.attribute(prim, Semantic::TexCoords(1), 2, Some(n), &element)?;
        let colors = self.vertex_colors(prim, n, &element)?;
        let indices: Vec<u32> = match prim.indices {
            Some(a) => {
                let e = self.read_accessor(a.value(), true).map_err(|m| self.invalid(&element, m))?;
                if e.comps != 1 {
                    return Err(self.invalid(&element, format!("accessor {}: indices must be SCALAR", a.value())));
                }
                e.values.iter().map(|&v| v as u32).collect()
            }
            None => (0..u32::try_from(n).unwrap_or(u32::MAX)).collect(),
        };
        let idx = |i: usize| indices.get(i).copied().unwrap_or(u32::MAX);
        let mut tris: Vec<[u32; 3]> = match mode {
            Mode::TriangleStrip => (0..indices.len().saturating_sub(2))
                .map(|i| if i % 2 == 0 { [idx(i), idx(i + 1), idx(i + 2)] } else { [idx(i + 1), idx(i), idx(i + 2)] })
                .collect(),
            Mode::TriangleFan => (1..indices.len().saturating_sub(1)).map(|i| [idx(i), idx(i + 1), idx(0)]).collect(),
            _ => indices.chunks_exact(3).map(|t| [idx_of(t, 0), idx_of(t, 1), idx_of(t, 2)]).collect(),
        };
        let before = tris.len();
        tris.retain(|t| t.iter().all(|&v| (v as usize) < n));
        if tris.len() < before {
            self.warn(format!("{element}: {} triangles with out-of-range indices dropped", before - tris.len()));
        }
        self.triangles = self.triangles.saturating_add(tris.len());
        let total = self.triangles;
        if let Some(max) = self.opts.max_triangles.filter(|&m| total > m) {
            return Err(SceneError::LimitExceeded {
                file: self.file.clone(),
                element: format!("{element} ({node}): triangle count"),
                limit: "max_triangles",
                actual: self.triangles as u64,
                max: max as u64,
            });
        }
        let material = match prim.material {
            Some(m) if m.value() < self.root.materials.len() => m.value(),
            Some(m) => return Err(self.invalid(&element, format!("material {} does not exist", m.value()))),
            None => self.default_material(),
        };

        // Bake to world space: the node's transform, or per vertex the skin's blend of joints
        // (the node's own transform is then ignored, as glTF says).
        let normal_matrix = Mat3::from_mat4(world).inverse().transpose();
        let linear = Mat3::from_mat4(world);
        let flip = skin.is_none() && linear.determinant() < 0.0;
        let positions: Vec<Vec3> = match &skin {
            None => pos.chunks_exact(3).map(|p| world.transform_point3(Vec3::from_slice(p))).collect(),
            Some(m) => pos.chunks_exact(3).zip(m).map(|(p, m)| m.transform_point3(Vec3::from_slice(p))).collect(),
        };
        let sane = |p: &Vec3| p.is_finite() && p.abs().max_element() <= MAX_COORDINATE;
        if let Some(&v) = tris.iter().flatten().find(|&&v| !positions.get(v as usize).is_some_and(sane)) {
            let p = positions.get(v as usize).copied().unwrap_or(Vec3::NAN);
            return Err(self.invalid(
                format!("{element} ({node})"),
                format!(
                    "vertex {v} is at {p} in world space: coordinates must be finite and within \
                     +-{MAX_COORDINATE:e} (scale the scene down)"
                ),
            ));
        }
        let normals = normals.map(|v| match &skin {
            None => v
                .chunks_exact(3)
                .map(|p| (normal_matrix * Vec3::from_slice(p)).normalize_or(Vec3::Z))
                .collect::<Vec<_>>(),
            Some(m) => v.chunks_exact(3).zip(m).map(|(p, m)| skin_normal(m, Vec3::from_slice(p))).collect(),
        });
        let mut tangents = tangents.map(|v| {
            v.chunks_exact(4)
                .enumerate()
                .map(|(i, p)| {
                    let t = Vec4::from_slice(p);
                    let w = if flip { -t.w } else { t.w };
                    let l = skin.as_ref().and_then(|m| m.get(i)).map_or(linear, |m| Mat3::from_mat4(*m));
                    (l * t.truncate()).normalize_or(Vec3::X).extend(if w < 0.0 { -1.0 } else { 1.0 })
                })
                .collect::<Vec<_>>()
        });
        let uv = |v: Option<Vec<f32>>| v.map(|v| v.chunks_exact(2).map(Vec2::from_slice).collect::<Vec<_>>());
        let (uv0, uv1) = (uv(uv0), uv(uv1));
        if flip {
            for t in &mut tris {
                t.swap(1, 2);
            }
        }
        let normal_map = self.scene.materials.get(material).and_then(|m| m.normal_texture);
        if let Some(nt) = normal_map.filter(|_| tangents.is_none()) {
            let uvs = if nt.tex_coord == 1 { uv1.as_ref() } else { uv0.as_ref() };
            if let (Some(nrm), Some(uvs)) = (normals.as_ref(), uvs) {
                if mikktspace_safe(&positions, &tris) {
                    let mut g = MikkGeometry {
                        positions: &positions,
                        normals: nrm,
                        uvs,
                        tris: &tris,
                        tangents: vec![Vec4::new(1.0, 0.0, 0.0, 1.0); n],
                    };
                    if mikktspace::generate_tangents(&mut g) {
                        tangents = Some(g.tangents);
                    } else {
                        self.warn(format!("{element}: tangent generation failed; normal map ignored"));
                    }
                } else if !tris.is_empty() {
                    self.warn(format!("{element}: degenerate geometry, no tangents; normal map ignored"));
                }
            }
        }
        let name = format!("{element} ({node})");
        self.scene.meshes.push(Mesh { name, positions, normals, tangents, uv0, uv1, colors, indices: tris, material });
        Ok(())
    }
}

/// A node's local transform: its matrix, or translation x rotation x scale.
fn local_matrix(node: &json::Node) -> Mat4 {
    match node.matrix {
        Some(m) => Mat4::from_cols_array(&m),
        None => {
            let t = Vec3::from(node.translation.unwrap_or([0.0; 3]));
            let r = node.rotation.map_or(Quat::IDENTITY, |q| Quat::from_array(q.0));
            let r = if r.length_squared() > 0.0 { r.normalize() } else { Quat::IDENTITY };
            let s = Vec3::from(node.scale.unwrap_or([1.0; 3]));
            Mat4::from_scale_rotation_translation(s, r, t)
        }
    }
}

/// How a mesh instance deforms: its node's skin and morph-target weights.
#[derive(Clone, Copy)]
struct Deform<'a> {
    skin: Option<usize>,
    weights: Option<&'a [f32]>,
}

/// A normal under a skinning matrix: the inverse transpose of its linear part (the matrix itself
/// when singular).
fn skin_normal(m: &Mat4, n: Vec3) -> Vec3 {
    let l = Mat3::from_mat4(*m);
    let nm = if l.determinant().abs() > 1e-12 { l.inverse().transpose() } else { l };
    (nm * n).normalize_or(Vec3::Z)
}

fn idx_of(t: &[u32], i: usize) -> u32 {
    t.get(i).copied().unwrap_or(u32::MAX)
}

/// glTF texture indices a material refers to.
fn material_textures(m: &json::Material) -> Vec<usize> {
    let pbr = &m.pbr_metallic_roughness;
    let mut v: Vec<usize> = [&pbr.base_color_texture, &pbr.metallic_roughness_texture, &m.emissive_texture]
        .into_iter()
        .flatten()
        .map(|i| i.index.value())
        .collect();
    v.extend(m.normal_texture.as_ref().map(|n| n.index.value()));
    v.extend(m.occlusion_texture.as_ref().map(|n| n.index.value()));
    if let Some(e) = &m.extensions {
        let infos = [
            e.transmission.as_ref().and_then(|t| t.transmission_texture.as_ref()),
            e.pbr_specular_glossiness.as_ref().and_then(|s| s.diffuse_texture.as_ref()),
            e.pbr_specular_glossiness.as_ref().and_then(|s| s.specular_glossiness_texture.as_ref()),
            e.volume.as_ref().and_then(|s| s.thickness_texture.as_ref()),
        ];
        v.extend(infos.into_iter().flatten().map(|i| i.index.value()));
        for name in ["KHR_materials_clearcoat", "KHR_materials_sheen"] {
            if let Some(x) = e.others.get(name) {
                v.extend(layer_textures(x));
            }
        }
    }
    v
}

/// KHR_materials_clearcoat's JSON (gltf-json has no type for it).
#[derive(serde::Deserialize)]
#[serde(rename_all = "camelCase")]
struct ClearcoatJson {
    #[serde(default)]
    clearcoat_factor: f32,
    clearcoat_texture: Option<json::texture::Info>,
    #[serde(default)]
    clearcoat_roughness_factor: f32,
    clearcoat_roughness_texture: Option<json::texture::Info>,
    clearcoat_normal_texture: Option<serde_json::Value>,
}

/// KHR_materials_sheen's JSON.
#[derive(serde::Deserialize)]
#[serde(rename_all = "camelCase")]
struct SheenJson {
    #[serde(default)]
    sheen_color_factor: [f32; 3],
    sheen_color_texture: Option<json::texture::Info>,
    #[serde(default)]
    sheen_roughness_factor: f32,
    sheen_roughness_texture: Option<json::texture::Info>,
}

/// Texture indices in a layer extension's JSON (`*Texture.index`), for the image budget.
fn layer_textures(v: &serde_json::Value) -> impl Iterator<Item = usize> + '_ {
    v.as_object()
        .into_iter()
        .flat_map(|o| o.iter())
        .filter(|(k, _)| k.ends_with("Texture"))
        .filter_map(|(_, t)| t.get("index").and_then(serde_json::Value::as_u64))
        .map(|i| usize::try_from(i).unwrap_or(usize::MAX))
}

/// Whether `mikktspace` 0.3 can run without panicking (found by the fuzz tests):
/// * its vertex welding hashes positions into cells along the widest axis and indexes one past
///   its table when that extent is zero (all vertices equal) or not finite;
/// * it computes `triangles - 1` after removing degenerate triangles (two corners welded), which
///   underflows when every triangle is degenerate.
///
/// Meshes that fail this have no meaningful tangents anyway.
fn mikktspace_safe(positions: &[Vec3], tris: &[[u32; 3]]) -> bool {
    let corner = |t: &[u32; 3]| t.map(|i| positions.get(i as usize).copied().unwrap_or(Vec3::NAN));
    let mut used = tris.iter().flat_map(corner);
    let Some(first) = used.next() else { return false };
    let (lo, hi) = used.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p)));
    let extent = hi - lo;
    let proper = tris.iter().map(corner).any(|[a, b, c]| a != b && b != c && a != c);
    extent.is_finite() && extent.max_element() > 0.0 && proper
}

/// World-space triangle data for MikkTSpace; tangents are written per vertex.
struct MikkGeometry<'a> {
    positions: &'a [Vec3],
    normals: &'a [Vec3],
    uvs: &'a [Vec2],
    tris: &'a [[u32; 3]],
    tangents: Vec<Vec4>,
}

impl MikkGeometry<'_> {
    fn vertex(&self, face: usize, vert: usize) -> usize {
        self.tris.get(face).and_then(|t| t.get(vert)).map_or(usize::MAX, |&v| v as usize)
    }
}

impl mikktspace::Geometry for MikkGeometry<'_> {
    fn num_faces(&self) -> usize {
        self.tris.len()
    }
    fn num_vertices_of_face(&self, _face: usize) -> usize {
        3
    }
    fn position(&self, face: usize, vert: usize) -> [f32; 3] {
        self.positions.get(self.vertex(face, vert)).copied().unwrap_or_default().to_array()
    }
    fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
        self.normals.get(self.vertex(face, vert)).copied().unwrap_or(Vec3::Z).to_array()
    }
    fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
        self.uvs.get(self.vertex(face, vert)).copied().unwrap_or_default().to_array()
    }
    fn set_tangent_encoded(&mut self, tangent: [f32; 4], face: usize, vert: usize) {
        let v = self.vertex(face, vert);
        if let Some(t) = self.tangents.get_mut(v) {
            *t = Vec4::from_array(tangent);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uri_rules() {
        assert!(check_uri("tex/a%20b.png").is_ok_and(|p| p == Path::new("tex/a b.png")));
        for bad in
            ["../x.bin", "/etc/passwd", "http://x/y.bin", "file:///etc/passwd", "a/%2e%2e/b", "C:\\x", "a\\..\\b"]
        {
            assert!(check_uri(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn data_uris() {
        assert_eq!(decode_data_uri("data:application/octet-stream;base64,AAEC").ok(), Some(vec![0, 1, 2]));
        assert_eq!(decode_data_uri("data:,a%20b").ok(), Some(b"a b".to_vec()));
        assert!(decode_data_uri("data:;base64,!!").is_err());
    }

    #[test]
    fn glb_header_checks() {
        assert!(split_glb(b"glTF").is_err());
        let mut glb = b"glTF".to_vec();
        glb.extend(2u32.to_le_bytes());
        glb.extend(4u32.to_le_bytes()); // shorter than the header itself
        assert!(split_glb(&glb).is_err());
    }

    #[test]
    fn alpha_modes_are_read() {
        use super::super::AlphaMode;
        use super::super::demo::{GltfBuilder, lambert};
        let mut b = GltfBuilder::new();
        let tri = [glam::Vec3::ZERO, glam::Vec3::X, glam::Vec3::Y];
        for (k, extra) in [
            serde_json::json!({}),
            serde_json::json!({"alphaMode": "MASK"}),
            serde_json::json!({"alphaMode": "MASK", "alphaCutoff": 0.25}),
            serde_json::json!({"alphaMode": "BLEND"}),
            serde_json::json!({"alphaMode": "OPAQUE", "alphaCutoff": 0.9}),
        ]
        .into_iter()
        .enumerate()
        {
            let mut m = lambert(&format!("m{k}"), glam::Vec3::ONE);
            for (key, v) in extra.as_object().expect("object") {
                m[key] = v.clone();
            }
            let mi = b.material(m);
            b.mesh(&format!("t{k}"), &tri, &[glam::Vec3::Z; 3], &[0, 1, 2], mi);
        }
        let s = load_scene_from_slice(&b.to_glb(), "t.glb", None, &LoadOptions::default()).expect("loads");
        let modes: Vec<AlphaMode> = s.materials.iter().map(|m| m.alpha_mode).collect();
        assert_eq!(
            modes,
            [
                AlphaMode::Opaque,
                AlphaMode::Mask { cutoff: 0.5 },
                AlphaMode::Mask { cutoff: 0.25 },
                AlphaMode::Blend,
                AlphaMode::Opaque
            ]
        );
    }

    #[test]
    fn a_scene_without_emitters_warns() {
        // Nothing emits: one warning saying it renders black; an emissive surface or a point
        // light silences it.
        use super::super::demo::{GltfBuilder, emitter, lambert, point_furnace_glb};
        use super::super::{NO_LIGHT_WARNING, load_scene_from_slice};
        let load = |bytes: &[u8]| load_scene_from_slice(bytes, "t.glb", None, &LoadOptions::default()).expect("loads");
        let tri = [glam::Vec3::ZERO, glam::Vec3::X, glam::Vec3::Y];
        let scene_with = |m: serde_json::Value| {
            let mut b = GltfBuilder::new();
            let m = b.material(m);
            b.mesh("tri", &tri, &[glam::Vec3::Z; 3], &[0, 1, 2], m);
            b.to_glb()
        };
        let dark = load(&scene_with(lambert("grey", glam::Vec3::splat(0.5))));
        assert!(!dark.has_emitters());
        assert_eq!(dark.warnings.iter().filter(|w| *w == NO_LIGHT_WARNING).count(), 1, "{:?}", dark.warnings);
        let lit = load(&scene_with(emitter("light", glam::Vec3::ONE, glam::Vec3::splat(2.0))));
        assert!(lit.has_emitters() && !lit.warnings.iter().any(|w| w == NO_LIGHT_WARNING), "{:?}", lit.warnings);
        let point = load(&point_furnace_glb(1.0, 0.5, 1.0));
        assert!(point.has_emitters() && !point.warnings.iter().any(|w| w == NO_LIGHT_WARNING));
    }

    #[test]
    fn photometric_light_units_become_radiometric_at_683_lumens_per_watt() {
        // Blender's exporter writes a 50 W point light as 50 / (4 pi) x 683 cd and a 2 W/m^2 sun
        // as 2 x 683 lux; they must load as Cycles' 50 / (4 pi) W/sr and 2 W/m^2.
        let cd = 50.0 / (4.0 * std::f32::consts::PI) * 683.0;
        let doc = serde_json::json!({
            "asset": {"version": "2.0"},
            "extensionsUsed": ["KHR_lights_punctual"],
            "extensions": {"KHR_lights_punctual": {"lights": [
                {"type": "point", "intensity": cd, "color": [1.0, 0.5, 0.25]},
                {"type": "directional", "intensity": 2.0 * 683.0},
            ]}},
            "nodes": [
                {"extensions": {"KHR_lights_punctual": {"light": 0}}},
                {"extensions": {"KHR_lights_punctual": {"light": 1}}},
            ],
            "scenes": [{"nodes": [0, 1]}],
        });
        let bytes = serde_json::to_vec(&doc).expect("json");
        let s = super::super::load_scene_from_slice(&bytes, "t.gltf", None, &LoadOptions::default()).expect("loads");
        let watts_per_sr = 50.0 / (4.0 * std::f32::consts::PI);
        let point = s.lights[0].intensity;
        assert!((point - Vec3::new(1.0, 0.5, 0.25) * watts_per_sr).abs().max_element() < 1e-4, "{point}");
        let sun = s.lights[1].intensity;
        assert!((sun - Vec3::splat(2.0)).abs().max_element() < 1e-5, "{sun}");
    }

    #[test]
    fn srgb_decode_endpoints() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214).abs() < 1e-3);
    }
}
