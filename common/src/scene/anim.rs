//! glTF animation: keyframe samplers evaluated at a time, written into the document.
//!
//! Every channel is kept as a JSON pointer into the glTF document: a core channel on node `n`'s
//! `translation` becomes `/nodes/n/translation`, and `KHR_animation_pointer` channels already are
//! pointers (camera, light and material properties). Posing a scene at time `t` evaluates every
//! playing channel, writes the values into a copy of the document (without `animations`) and
//! loads that copy again from the buffers and decoded textures kept here; the loader then applies
//! morph targets and skins. One mechanism thus covers every property the still loader reads.
//!
//! Times before a sampler's first key take the first key's value, times after its last key the
//! last key's value. When several playing animations drive the same property, the later one in
//! the file wins.

use glam::Vec4;
use serde_json::Value;
use std::collections::HashMap;
use std::sync::Arc;

/// How a sampler interpolates between keys (glTF `interpolation`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    Step,
    /// Linear; spherical linear (shortest arc, normalized) for rotations.
    Linear,
    /// Cubic Hermite spline with in and out tangents per key; rotations are normalized.
    CubicSpline,
}

/// Keyframes of one channel: `times` ascending, `values` with `key_len` floats per key (times
/// three for cubic splines: in-tangent, value, out-tangent).
#[derive(Clone, Debug)]
pub struct KeySampler {
    pub interpolation: Interpolation,
    /// Shared by every channel whose sampler reads the same accessors.
    pub times: Arc<[f32]>,
    pub values: Arc<[f32]>,
    pub key_len: usize,
    /// Unit quaternions (x, y, z, w): slerp and normalize.
    pub rotation: bool,
}

impl KeySampler {
    /// The value at time `t` (`key_len` floats).
    pub fn sample(&self, t: f32) -> Vec<f32> {
        let n = self.times.len();
        let k = self.key_len;
        let stride = if self.interpolation == Interpolation::CubicSpline { 3 * k } else { k };
        // The value of key i (the middle element for cubic splines).
        let value = |i: usize| -> &[f32] {
            let at = i * stride + if self.interpolation == Interpolation::CubicSpline { k } else { 0 };
            self.values.get(at..at + k).unwrap_or(&[])
        };
        let (Some(&first), Some(&last)) = (self.times.first(), self.times.last()) else { return vec![0.0; k] };
        let mut out = if !(t > first) {
            value(0).to_vec()
        } else if t >= last {
            value(n - 1).to_vec()
        } else {
            // times[i] <= t < times[i + 1]
            let i = self.times.partition_point(|&x| x <= t).saturating_sub(1).min(n - 2);
            let (t0, t1) = (self.times[i], self.times[i + 1]);
            let dt = t1 - t0;
            let u = if dt > 0.0 { ((t - t0) / dt).clamp(0.0, 1.0) } else { 1.0 };
            match self.interpolation {
                Interpolation::Step => value(i).to_vec(),
                Interpolation::Linear if self.rotation && k == 4 => slerp(value(i), value(i + 1), u).to_vec(),
                Interpolation::Linear => value(i).iter().zip(value(i + 1)).map(|(a, b)| a + (b - a) * u).collect(),
                Interpolation::CubicSpline => {
                    let out_tangent = |j: usize| self.values.get(j * stride + 2 * k..j * stride + 3 * k).unwrap_or(&[]);
                    let in_tangent = |j: usize| self.values.get(j * stride..j * stride + k).unwrap_or(&[]);
                    let (u2, u3) = (u * u, u * u * u);
                    let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
                    let h10 = u3 - 2.0 * u2 + u;
                    let h01 = -2.0 * u3 + 3.0 * u2;
                    let h11 = u3 - u2;
                    (0..k)
                        .map(|c| {
                            let g = |s: &[f32]| s.get(c).copied().unwrap_or(0.0);
                            h00 * g(value(i))
                                + h10 * dt * g(out_tangent(i))
                                + h01 * g(value(i + 1))
                                + h11 * dt * g(in_tangent(i + 1))
                        })
                        .collect()
                }
            }
        };
        if self.rotation && k == 4 {
            let q = Vec4::from_slice(&out).normalize_or(Vec4::W);
            out = q.to_array().to_vec();
        }
        out
    }
}

/// Spherical linear interpolation of unit quaternions along the shorter arc (in f64; falls back
/// to normalized linear interpolation for nearly equal rotations).
pub fn slerp(a: &[f32], b: &[f32], u: f32) -> [f32; 4] {
    let q = |s: &[f32]| [0, 1, 2, 3].map(|i| f64::from(s.get(i).copied().unwrap_or(0.0)));
    let (a, mut b) = (q(a), q(b));
    let u = f64::from(u);
    let mut dot: f64 = (0..4).map(|i| a[i] * b[i]).sum();
    if dot < 0.0 {
        b = b.map(|x| -x);
        dot = -dot;
    }
    let (wa, wb) = if dot > 0.9995 {
        (1.0 - u, u)
    } else {
        let theta = dot.min(1.0).acos();
        let s = theta.sin();
        (((1.0 - u) * theta).sin() / s, (u * theta).sin() / s)
    };
    let r = [0, 1, 2, 3].map(|i| wa * a[i] + wb * b[i]);
    let len = r.iter().map(|x| x * x).sum::<f64>().sqrt();
    if len > 0.0 { r.map(|x| (x / len) as f32) } else { [0.0, 0.0, 0.0, 1.0] }
}

/// One animated property: a JSON pointer into the document and its sampler.
#[derive(Clone, Debug)]
pub struct Channel {
    pub pointer: String,
    /// Written as a JSON array (vectors, morph weights) rather than a number.
    pub array: bool,
    pub sampler: KeySampler,
}

/// A glTF animation.
#[derive(Clone, Debug)]
pub struct Clip {
    /// The file's name, or `animation N` when it has none.
    pub name: String,
    pub channels: Vec<Channel>,
    /// Last key time over the channels, in seconds.
    pub duration: f32,
}

/// Decoded textures by (image, sRGB): width, height, linear texels.
pub(super) type TexelCache = HashMap<(usize, bool), (u32, u32, Arc<Vec<Vec4>>)>;

/// What posing needs, kept beside a loaded scene that has animations.
#[derive(Debug)]
pub struct Animation {
    pub(super) file: String,
    /// The glTF document without `animations`.
    pub(super) document: Value,
    pub(super) buffers: Arc<Vec<Vec<u8>>>,
    /// Decoded textures by (image, sRGB): width, height, texels.
    pub(super) texels: TexelCache,
    pub(super) clips: Vec<Clip>,
    pub(super) max_triangles: Option<usize>,
}

impl Animation {
    pub fn clips(&self) -> &[Clip] {
        &self.clips
    }

    /// The clips named by `names` (all for `None`), or an error naming the unknown name and the
    /// available ones.
    pub fn select(&self, names: Option<&[String]>) -> Result<Vec<&Clip>, String> {
        let Some(names) = names else { return Ok(self.clips.iter().collect()) };
        let mut out = Vec::new();
        for n in names {
            match self.clips.iter().find(|c| &c.name == n) {
                Some(c) => out.push(c),
                None => return Err(unknown_animation(n, &self.clips)),
            }
        }
        // File order, so "later in the file wins" holds whatever order the names come in.
        out.sort_by_key(|c| self.clips.iter().position(|x| std::ptr::eq(x, *c)));
        out.dedup_by(|a, b| std::ptr::eq(*a, *b));
        Ok(out)
    }

    /// The document with the selected clips' values at time `t` written in.
    pub(super) fn posed_document(&self, t: f32, names: Option<&[String]>) -> Result<Value, String> {
        let clips = self.select(names)?;
        let mut doc = self.document.clone();
        for clip in clips {
            for ch in &clip.channels {
                let v = ch.sampler.sample(t);
                let num = |x: f32| {
                    serde_json::Number::from_f64(f64::from(x))
                        .map(Value::Number)
                        .ok_or_else(|| format!("animation {:?}: {} is not finite at t = {t}", clip.name, ch.pointer))
                };
                let value = if ch.array {
                    Value::Array(v.iter().map(|&x| num(x)).collect::<Result<_, _>>()?)
                } else {
                    num(v.first().copied().unwrap_or(0.0))?
                };
                set_pointer(&mut doc, &ch.pointer, value)?;
            }
        }
        Ok(doc)
    }
}

/// The error for an animation name the scene does not have.
pub fn unknown_animation(name: &str, clips: &[Clip]) -> String {
    let available: Vec<String> = clips.iter().map(|c| format!("{:?}", c.name)).collect();
    if available.is_empty() {
        format!("animation {name:?} does not exist: the scene has no animations")
    } else {
        format!("animation {name:?} does not exist; the scene has {}", available.join(", "))
    }
}

/// Properties we animate: pointer pattern (`*` = an index) and floats per key (`None`: morph
/// weights, any count). Anything else is skipped with a warning.
const ANIMATABLE: &[(&str, Option<usize>)] = &[
    ("/nodes/*/translation", Some(3)),
    ("/nodes/*/rotation", Some(4)),
    ("/nodes/*/scale", Some(3)),
    ("/nodes/*/weights", None),
    ("/meshes/*/weights", None),
    ("/cameras/*/perspective/yfov", Some(1)),
    ("/cameras/*/perspective/aspectRatio", Some(1)),
    ("/cameras/*/perspective/znear", Some(1)),
    ("/cameras/*/perspective/zfar", Some(1)),
    ("/cameras/*/orthographic/xmag", Some(1)),
    ("/cameras/*/orthographic/ymag", Some(1)),
    ("/cameras/*/orthographic/znear", Some(1)),
    ("/cameras/*/orthographic/zfar", Some(1)),
    ("/extensions/KHR_lights_punctual/lights/*/color", Some(3)),
    ("/extensions/KHR_lights_punctual/lights/*/intensity", Some(1)),
    ("/extensions/KHR_lights_punctual/lights/*/range", Some(1)),
    ("/extensions/KHR_lights_punctual/lights/*/spot/innerConeAngle", Some(1)),
    ("/extensions/KHR_lights_punctual/lights/*/spot/outerConeAngle", Some(1)),
    ("/materials/*/pbrMetallicRoughness/baseColorFactor", Some(4)),
    ("/materials/*/pbrMetallicRoughness/metallicFactor", Some(1)),
    ("/materials/*/pbrMetallicRoughness/roughnessFactor", Some(1)),
    ("/materials/*/emissiveFactor", Some(3)),
    ("/materials/*/normalTexture/scale", Some(1)),
    ("/materials/*/extensions/KHR_materials_emissive_strength/emissiveStrength", Some(1)),
    ("/materials/*/extensions/KHR_materials_ior/ior", Some(1)),
    ("/materials/*/extensions/KHR_materials_transmission/transmissionFactor", Some(1)),
    ("/materials/*/extensions/KHR_materials_specular/specularFactor", Some(1)),
    ("/materials/*/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/offset", Some(2)),
    ("/materials/*/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/scale", Some(2)),
    ("/materials/*/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/rotation", Some(1)),
    ("/materials/*/emissiveTexture/extensions/KHR_texture_transform/offset", Some(2)),
    ("/materials/*/emissiveTexture/extensions/KHR_texture_transform/scale", Some(2)),
    ("/materials/*/emissiveTexture/extensions/KHR_texture_transform/rotation", Some(1)),
    ("/materials/*/normalTexture/extensions/KHR_texture_transform/offset", Some(2)),
    ("/materials/*/normalTexture/extensions/KHR_texture_transform/scale", Some(2)),
    ("/materials/*/normalTexture/extensions/KHR_texture_transform/rotation", Some(1)),
];

/// The floats per key of an animatable pointer: `Some(Some(n))`, `Some(None)` for weights, or
/// `None` when we do not animate it.
pub fn animatable(pointer: &str) -> Option<Option<usize>> {
    let segs: Vec<&str> = pointer.split('/').collect();
    ANIMATABLE.iter().find_map(|(pat, n)| {
        let p: Vec<&str> = pat.split('/').collect();
        let matches = p.len() == segs.len()
            && p.iter().zip(&segs).all(|(a, b)| if *a == "*" { b.parse::<usize>().is_ok() } else { a == b });
        matches.then_some(*n)
    })
}

/// Whether an object key may be created when a pointer reaches a missing one: extension
/// objects and `pbrMetallicRoughness`, whose properties all have defaults.
fn creatable(key: &str) -> bool {
    key == "extensions" || key == "pbrMetallicRoughness" || key.starts_with("KHR_")
}

/// Checks that `pointer` can be written into `doc`: arrays are indexed within bounds, objects
/// exist (or are creatable extension objects). The last segment may be missing (glTF defaults).
pub fn check_pointer(doc: &Value, pointer: &str) -> Result<(), String> {
    let segs: Vec<&str> = pointer.strip_prefix('/').ok_or("must start with '/'")?.split('/').collect();
    let mut cur = Some(doc);
    for (i, s) in segs.iter().enumerate() {
        let last = i + 1 == segs.len();
        match cur {
            Some(Value::Array(a)) => {
                let idx: usize = s.parse().map_err(|_| format!("{s:?} is not an index"))?;
                cur = Some(a.get(idx).ok_or_else(|| format!("index {idx} does not exist ({} elements)", a.len()))?);
            }
            Some(Value::Object(o)) => match o.get(*s) {
                Some(v) => cur = Some(v),
                None if last || creatable(s) => cur = None,
                None => return Err(format!("{s:?} does not exist")),
            },
            None if last || creatable(s) => {}
            _ => return Err(format!("{s:?}: the parent is not an object or array")),
        }
    }
    Ok(())
}

/// Writes `value` at `pointer`, creating missing objects along the way (see [`check_pointer`]).
fn set_pointer(doc: &mut Value, pointer: &str, value: Value) -> Result<(), String> {
    let segs: Vec<&str> = pointer.strip_prefix('/').unwrap_or(pointer).split('/').collect();
    let mut cur = doc;
    for (i, s) in segs.iter().enumerate() {
        let last = i + 1 == segs.len();
        cur = match cur {
            Value::Array(a) => {
                let idx: usize = s.parse().map_err(|_| format!("{pointer}: {s:?} is not an index"))?;
                a.get_mut(idx).ok_or_else(|| format!("{pointer}: index {idx} does not exist"))?
            }
            Value::Object(o) => {
                if last {
                    o.insert((*s).to_string(), value);
                    return Ok(());
                }
                o.entry((*s).to_string()).or_insert_with(|| Value::Object(Default::default()))
            }
            _ => return Err(format!("{pointer}: {s:?}: the parent is not an object or array")),
        };
    }
    *cur = value;
    Ok(())
}

/// An animation's samplers by index: times, interpolation, values, elements per key (3 for
/// cubic splines, else 1).
type SamplerCache = HashMap<usize, (Arc<[f32]>, Interpolation, Arc<[f32]>, usize)>;

/// Parses the `animations` array. `read(accessor)` returns (components, floats) of an accessor
/// and enforces the loader's budget; each accessor is read once and shared by the channels
/// using it, so key data costs at most what the file's accessors hold. `warn` receives skipped
/// channels.
pub fn parse_clips(
    animations: &Value,
    document: &Value,
    mut read: impl FnMut(usize) -> Result<(usize, Vec<f32>), String>,
    mut warn: impl FnMut(String),
) -> Result<Vec<Clip>, String> {
    let list = animations.as_array().ok_or("animations: not an array")?;
    let mut clips = Vec::with_capacity(list.len().min(1024));
    let mut accessors: HashMap<usize, (usize, Arc<[f32]>)> = HashMap::new();
    let mut read_once = |a: usize| -> Result<(usize, Arc<[f32]>), String> {
        if let Some((c, v)) = accessors.get(&a) {
            return Ok((*c, v.clone()));
        }
        let (c, v) = read(a)?;
        let v: Arc<[f32]> = v.into();
        accessors.insert(a, (c, v.clone()));
        Ok((c, v))
    };
    for (ai, a) in list.iter().enumerate() {
        let name = a.get("name").and_then(Value::as_str).map_or_else(|| format!("animation {ai}"), str::to_string);
        let here = format!("animation {ai} {name:?}");
        let samplers = a.get("samplers").and_then(Value::as_array).map_or(&[][..], Vec::as_slice);
        let channels = a.get("channels").and_then(Value::as_array).map_or(&[][..], Vec::as_slice);
        let mut cache: SamplerCache = HashMap::new();
        let mut clip = Clip { name, channels: Vec::new(), duration: 0.0 };
        for (ci, c) in channels.iter().enumerate() {
            let at = format!("{here} channel {ci}");
            let target = c.get("target").ok_or_else(|| format!("{at}: no target"))?;
            let ext_pointer = target
                .get("extensions")
                .and_then(|e| e.get("KHR_animation_pointer"))
                .and_then(|p| p.get("pointer"))
                .and_then(Value::as_str);
            let path = target.get("path").and_then(Value::as_str).ok_or_else(|| format!("{at}: target has no path"))?;
            let pointer = match (path, ext_pointer, target.get("node").and_then(Value::as_u64)) {
                ("pointer", Some(p), _) => p.to_string(),
                ("pointer", None, _) => return Err(format!("{at}: path \"pointer\" without KHR_animation_pointer")),
                (p @ ("translation" | "rotation" | "scale" | "weights"), _, Some(n)) => format!("/nodes/{n}/{p}"),
                (_, _, None) => {
                    warn(format!("{at}: no target node; skipped"));
                    continue;
                }
                (p, _, _) => {
                    warn(format!("{at}: path {p:?} is not animatable; skipped"));
                    continue;
                }
            };
            let Some(expected) = animatable(&pointer) else {
                warn(format!("{at}: {pointer} is not a property the renderer animates; skipped"));
                continue;
            };
            check_pointer(document, &pointer).map_err(|m| format!("{at}: pointer {pointer}: {m}"))?;
            let si = c.get("sampler").and_then(Value::as_u64).ok_or_else(|| format!("{at}: no sampler"))? as usize;
            let cached = match cache.entry(si) {
                std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                std::collections::hash_map::Entry::Vacant(slot) => {
                    let s = samplers.get(si).ok_or_else(|| format!("{at}: sampler {si} does not exist"))?;
                    let interpolation = match s.get("interpolation").and_then(Value::as_str).unwrap_or("LINEAR") {
                        "STEP" => Interpolation::Step,
                        "LINEAR" => Interpolation::Linear,
                        "CUBICSPLINE" => Interpolation::CubicSpline,
                        other => return Err(format!("{here} sampler {si}: unknown interpolation {other:?}")),
                    };
                    let acc = |k: &str| {
                        s.get(k)
                            .and_then(Value::as_u64)
                            .map(|v| v as usize)
                            .ok_or_else(|| format!("{here} sampler {si}: no {k}"))
                    };
                    let (ic, times) =
                        read_once(acc("input")?).map_err(|m| format!("{here} sampler {si} input: {m}"))?;
                    let (_, values) =
                        read_once(acc("output")?).map_err(|m| format!("{here} sampler {si} output: {m}"))?;
                    if ic != 1 {
                        return Err(format!("{here} sampler {si}: input must be SCALAR"));
                    }
                    if !times.iter().chain(values.iter()).all(|v| v.is_finite()) {
                        return Err(format!("{here} sampler {si}: non-finite keys"));
                    }
                    if times.windows(2).any(|w| w[1] < w[0]) {
                        return Err(format!("{here} sampler {si}: input times must not decrease"));
                    }
                    let m = if interpolation == Interpolation::CubicSpline { 3 } else { 1 };
                    slot.insert((times, interpolation, values, m))
                }
            };
            let (times, interpolation, values, m) = &*cached;
            if times.is_empty() {
                warn(format!("{at}: sampler {si} has no keys; skipped"));
                continue;
            }
            let per_key = values.len() / (times.len() * m);
            let key_len = expected.unwrap_or(per_key);
            if key_len == 0 || values.len() != times.len() * m * key_len {
                return Err(format!(
                    "{at}: sampler {si} has {} output values for {} keys; {pointer} needs {} per key",
                    values.len(),
                    times.len(),
                    expected.map_or_else(|| "the same number".to_string(), |n| (n * m).to_string())
                ));
            }
            clip.duration = clip.duration.max(times.last().copied().unwrap_or(0.0));
            let rotation = pointer.ends_with("/rotation") && key_len == 4;
            let array = key_len > 1 || pointer.ends_with("/weights");
            clip.channels.push(Channel {
                pointer,
                array,
                sampler: KeySampler {
                    interpolation: *interpolation,
                    times: times.clone(),
                    values: values.clone(),
                    key_len,
                    rotation,
                },
            });
        }
        clips.push(clip);
    }
    Ok(clips)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sampler(interpolation: Interpolation, times: &[f32], values: &[f32], key_len: usize) -> KeySampler {
        KeySampler { interpolation, times: times.into(), values: values.into(), key_len, rotation: false }
    }

    fn close(a: &[f32], b: &[f32], tol: f32) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn step_and_linear_with_clamping() {
        let s = sampler(Interpolation::Step, &[1.0, 2.0, 4.0], &[0.0, 10.0, 20.0], 1);
        assert_eq!(s.sample(0.0), vec![0.0]); // before the first key
        assert_eq!(s.sample(1.5), vec![0.0]);
        assert_eq!(s.sample(2.0), vec![10.0]);
        assert_eq!(s.sample(3.9), vec![10.0]);
        assert_eq!(s.sample(9.0), vec![20.0]); // after the last key
        let l = sampler(Interpolation::Linear, &[1.0, 2.0, 4.0], &[0.0, 0.0, 10.0, 20.0, 20.0, 60.0], 2);
        assert!(close(&l.sample(1.25), &[2.5, 5.0], 1e-6));
        assert!(close(&l.sample(3.0), &[15.0, 40.0], 1e-6));
        assert!(close(&l.sample(-5.0), &[0.0, 0.0], 0.0));
        assert!(close(&l.sample(5.0), &[20.0, 60.0], 0.0));
    }

    #[test]
    fn linear_rotation_is_slerp_on_the_short_arc() {
        // 0 and 90 degrees about Z; halfway is 45 degrees: (0, 0, sin 22.5, cos 22.5).
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let mut s = sampler(Interpolation::Linear, &[0.0, 1.0], &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, h, h], 4);
        s.rotation = true;
        let a = 22.5f32.to_radians();
        assert!(close(&s.sample(0.5), &[0.0, 0.0, a.sin(), a.cos()], 1e-6), "{:?}", s.sample(0.5));
        // A quarter of the way: 22.5 degrees, not the normalized lerp (which gives 23.4...).
        let q = 11.25f32.to_radians();
        assert!(close(&s.sample(0.25), &[0.0, 0.0, q.sin(), q.cos()], 1e-6), "{:?}", s.sample(0.25));
        // The second key given as -q: the same rotation, the short arc is still taken.
        s.values = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -h, -h].into();
        assert!(close(&s.sample(0.5), &[0.0, 0.0, a.sin(), a.cos()], 1e-6), "{:?}", s.sample(0.5));
    }

    #[test]
    fn cubic_spline_is_hermite() {
        // Keys at t = 0 and 2; values 1 and 3; out-tangent of key 0 = 4, in-tangent of key 1 = -2.
        // At u = 0.5 (t = 1): h00 = 0.5, h10 = 0.125, h01 = 0.5, h11 = -0.125, dt = 2:
        // 0.5*1 + 0.125*2*4 + 0.5*3 + (-0.125)*2*(-2) = 0.5 + 1 + 1.5 + 0.5 = 3.5.
        let s = sampler(Interpolation::CubicSpline, &[0.0, 2.0], &[9.0, 1.0, 4.0, -2.0, 3.0, 9.0], 1);
        assert!(close(&s.sample(1.0), &[3.5], 1e-6), "{:?}", s.sample(1.0));
        // u = 0.25 (t = 0.5): h00 = 0.84375, h10 = 0.140625, h01 = 0.15625, h11 = -0.046875:
        // 0.84375 + 0.140625*8 + 0.15625*3 + (-0.046875)*(-4) = 0.84375 + 1.125 + 0.46875 + 0.1875.
        assert!(close(&s.sample(0.5), &[2.625], 1e-6), "{:?}", s.sample(0.5));
        // Clamped to the key values (not the tangents) outside.
        assert_eq!(s.sample(-1.0), vec![1.0]);
        assert_eq!(s.sample(3.0), vec![3.0]);
    }

    #[test]
    fn cubic_spline_rotations_are_normalized() {
        let mut s = sampler(
            Interpolation::CubicSpline,
            &[0.0, 1.0],
            &[
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0,
                0.0, 0.0, 0.0, 0.0,
            ],
            4,
        );
        s.rotation = true;
        let q = s.sample(0.5);
        let len = q.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((len - 1.0).abs() < 1e-6, "{q:?}");
        // Zero tangents: halfway is (0, 0, 0.5, 1) before normalizing, (0, 0, 1, 2) / sqrt 5.
        let r5 = 5f32.sqrt();
        assert!(close(&q, &[0.0, 0.0, 1.0 / r5, 2.0 / r5], 1e-6), "{q:?}");
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert!(close(&s.sample(1.0), &[0.0, 0.0, h, h], 1e-6));
    }

    #[test]
    fn pointers() {
        let doc: Value = serde_json::json!({"nodes": [{"name": "a"}], "materials": [{}]});
        assert!(check_pointer(&doc, "/nodes/0/translation").is_ok());
        assert!(check_pointer(&doc, "/nodes/1/translation").expect_err("no node 1").contains("index 1 does not exist"));
        assert!(
            check_pointer(&doc, "/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength").is_ok()
        );
        assert!(check_pointer(&doc, "/materials/0/normalTexture/scale").is_err());
        let mut d = doc.clone();
        set_pointer(&mut d, "/materials/0/pbrMetallicRoughness/baseColorFactor", serde_json::json!([1, 0, 0, 1]))
            .expect("writes");
        assert_eq!(d["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"][0], 1);
        assert_eq!(animatable("/nodes/3/rotation"), Some(Some(4)));
        assert_eq!(animatable("/meshes/0/weights"), Some(None));
        assert_eq!(animatable("/materials/0/alphaCutoff"), None);
        assert_eq!(animatable("/nodes/x/rotation"), None);
    }
}
