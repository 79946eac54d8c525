//! Scenes written by our own code, as glTF 2.0 binaries: the demo Cornell box, the analytic
//! furnace enclosures and the caustics scene. [`GltfBuilder`] is a minimal `.glb` writer.

use glam::{Quat, Vec3};
use serde_json::{Value, json};

/// A minimal glTF 2.0 writer: triangle meshes (positions, normals, u32 indices), materials,
/// nodes, cameras, punctual lights, animations (node channels and KHR_animation_pointer), skins
/// and morph targets; one binary buffer.
#[derive(Default)]
pub struct GltfBuilder {
    bin: Vec<u8>,
    buffer_views: Vec<Value>,
    accessors: Vec<Value>,
    meshes: Vec<Value>,
    materials: Vec<Value>,
    nodes: Vec<Value>,
    cameras: Vec<Value>,
    lights: Vec<Value>,
    animations: Vec<Value>,
    skins: Vec<Value>,
}

impl GltfBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    fn push_view(&mut self, bytes: &[u8], target: u32) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.buffer_views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len(), "target": target}));
        self.buffer_views.len() - 1
    }

    fn push_vec3(&mut self, v: &[Vec3], with_bounds: bool) -> usize {
        let bytes: Vec<u8> = v.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect();
        let view = self.push_view(&bytes, 34962);
        let mut acc = json!({"bufferView": view, "componentType": 5126, "count": v.len(), "type": "VEC3"});
        if with_bounds {
            let lo = v.iter().fold(Vec3::splat(f32::INFINITY), |a, &b| a.min(b));
            let hi = v.iter().fold(Vec3::splat(f32::NEG_INFINITY), |a, &b| a.max(b));
            acc["min"] = json!(lo.to_array());
            acc["max"] = json!(hi.to_array());
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }

    /// Adds an accessor of f32 components (`type_`: SCALAR, VEC2..4, MAT4) and returns its index.
    pub fn floats(&mut self, values: &[f32], type_: &str) -> usize {
        let comps = match type_ {
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            "MAT4" => 16,
            _ => 1,
        };
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.push_view(&bytes, 34962);
        let mut acc = json!({"bufferView": view, "componentType": 5126, "count": values.len() / comps, "type": type_});
        if type_ == "SCALAR" && !values.is_empty() {
            // Animation inputs must carry min and max.
            let lo = values.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            acc["min"] = json!([lo]);
            acc["max"] = json!([hi]);
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }

    /// Adds an animation channel to the animation `name` (created on first use). `target` is a
    /// glTF channel target (`{"node": 2, "path": "translation"}`, or `{"path": "pointer",
    /// "extensions": {"KHR_animation_pointer": {"pointer": "/materials/0/emissiveFactor"}}}`);
    /// `values` holds `type_` elements per key (three per key for CUBICSPLINE: in-tangent, value,
    /// out-tangent).
    pub fn animate(
        &mut self,
        name: &str,
        target: Value,
        interpolation: &str,
        times: &[f32],
        values: &[f32],
        type_: &str,
    ) {
        let input = self.floats(times, "SCALAR");
        let output = self.floats(values, type_);
        let at = match self.animations.iter().position(|a| a["name"] == name) {
            Some(i) => i,
            None => {
                self.animations.push(json!({"name": name, "channels": [], "samplers": []}));
                self.animations.len() - 1
            }
        };
        let a = &mut self.animations[at];
        let sampler = a["samplers"].as_array().map_or(0, Vec::len);
        if let Some(s) = a["samplers"].as_array_mut() {
            s.push(json!({"input": input, "output": output, "interpolation": interpolation}));
        }
        if let Some(c) = a["channels"].as_array_mut() {
            c.push(json!({"sampler": sampler, "target": target}));
        }
    }

    /// Adds a node (glTF JSON object) and returns its index; every node is a root of the scene.
    pub fn node(&mut self, n: Value) -> usize {
        self.nodes.push(n);
        self.nodes.len() - 1
    }

    /// The JSON of node `i` (to set a translation, a parent's children...).
    pub fn node_mut(&mut self, i: usize) -> &mut Value {
        &mut self.nodes[i]
    }

    /// Skins the mesh of `node` (from [`GltfBuilder::mesh`]) with `joints` (node indices) and
    /// their inverse bind matrices; per vertex four joint indices (into `joints`) and weights.
    pub fn skin(
        &mut self,
        node: usize,
        joints: &[usize],
        inverse_bind: &[glam::Mat4],
        vertex_joints: &[[u16; 4]],
        vertex_weights: &[[f32; 4]],
    ) {
        let ibm: Vec<f32> = inverse_bind.iter().flat_map(|m| m.to_cols_array()).collect();
        let ibm = self.floats(&ibm, "MAT4");
        let bytes: Vec<u8> = vertex_joints.iter().flatten().flat_map(|j| j.to_le_bytes()).collect();
        let view = self.push_view(&bytes, 34962);
        self.accessors
            .push(json!({"bufferView": view, "componentType": 5123, "count": vertex_joints.len(), "type": "VEC4"}));
        let joints_acc = self.accessors.len() - 1;
        let weights: Vec<f32> = vertex_weights.iter().flatten().copied().collect();
        let weights_acc = self.floats(&weights, "VEC4");
        self.skins.push(json!({"joints": joints, "inverseBindMatrices": ibm}));
        self.nodes[node]["skin"] = json!(self.skins.len() - 1);
        if let Some(mesh) = self.nodes[node]["mesh"].as_u64() {
            let attrs = &mut self.meshes[mesh as usize]["primitives"][0]["attributes"];
            attrs["JOINTS_0"] = json!(joints_acc);
            attrs["WEIGHTS_0"] = json!(weights_acc);
        }
    }

    /// Gives the mesh of `node` TANGENT data (xyz, handedness w), one per position.
    pub fn tangents(&mut self, node: usize, tangents: &[glam::Vec4]) {
        let v: Vec<f32> = tangents.iter().flat_map(|t| t.to_array()).collect();
        let acc = self.floats(&v, "VEC4");
        if let Some(mesh) = self.nodes.get(node).and_then(|n| n["mesh"].as_u64()) {
            self.meshes[mesh as usize]["primitives"][0]["attributes"]["TANGENT"] = json!(acc);
        }
    }

    /// Adds a morph target (position and normal displacements) to the mesh of `node`, with the
    /// mesh's default weight `weight`.
    pub fn morph_target(&mut self, node: usize, positions: &[Vec3], normals: &[Vec3], weight: f32) {
        let p = self.push_vec3(positions, true);
        let n = self.push_vec3(normals, false);
        if let Some(mesh) = self.nodes[node]["mesh"].as_u64() {
            let m = &mut self.meshes[mesh as usize];
            let prim = &mut m["primitives"][0];
            if prim["targets"].is_null() {
                prim["targets"] = json!([]);
            }
            if let Some(t) = prim["targets"].as_array_mut() {
                t.push(json!({"POSITION": p, "NORMAL": n}));
            }
            if m["weights"].is_null() {
                m["weights"] = json!([]);
            }
            if let Some(w) = m["weights"].as_array_mut() {
                w.push(json!(weight));
            }
        }
    }

    /// Adds a material (glTF JSON object) and returns its index.
    pub fn material(&mut self, m: Value) -> usize {
        self.materials.push(m);
        self.materials.len() - 1
    }

    /// Adds a triangle mesh and a node instancing it; returns the node index.
    pub fn mesh(
        &mut self,
        name: &str,
        positions: &[Vec3],
        normals: &[Vec3],
        indices: &[u32],
        material: usize,
    ) -> usize {
        let pos = self.push_vec3(positions, true);
        let nrm = self.push_vec3(normals, false);
        let bytes: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let view = self.push_view(&bytes, 34963);
        self.accessors
            .push(json!({"bufferView": view, "componentType": 5125, "count": indices.len(), "type": "SCALAR"}));
        let idx = self.accessors.len() - 1;
        self.meshes.push(json!({"name": name, "primitives": [{
            "attributes": {"POSITION": pos, "NORMAL": nrm}, "indices": idx, "material": material}]}));
        self.nodes.push(json!({"name": name, "mesh": self.meshes.len() - 1}));
        self.nodes.len() - 1
    }

    /// Gives the mesh of `node` (as returned by [`GltfBuilder::mesh`]) linear RGB vertex colours
    /// (COLOR_0, one per position).
    pub fn vertex_colors(&mut self, node: usize, colors: &[Vec3]) {
        let acc = self.push_vec3(colors, false);
        if let Some(mesh) = self.nodes.get(node).and_then(|n| n["mesh"].as_u64()) {
            self.meshes[mesh as usize]["primitives"][0]["attributes"]["COLOR_0"] = json!(acc);
        }
    }

    /// Adds a perspective camera at `eye` looking at `target` (vertical field of view in radians);
    /// returns its node.
    pub fn camera(&mut self, eye: Vec3, target: Vec3, up: Vec3, yfov: f32, aspect: f32) -> usize {
        self.cameras.push(json!({"type": "perspective", "perspective": {
            "yfov": yfov, "aspectRatio": aspect, "znear": 0.001, "zfar": 1000.0}}));
        let rot = look_rotation(eye, target, up);
        self.nodes.push(json!({"name": "camera", "camera": self.cameras.len() - 1,
            "translation": eye.to_array(), "rotation": rot.to_array()}));
        self.nodes.len() - 1
    }

    /// Adds an orthographic camera at `eye` looking down -Z (half extents `xmag`, `ymag`);
    /// returns its node.
    pub fn ortho_camera(&mut self, eye: Vec3, xmag: f32, ymag: f32) -> usize {
        self.cameras.push(json!({"type": "orthographic", "orthographic": {
            "xmag": xmag, "ymag": ymag, "znear": 0.001, "zfar": 1000.0}}));
        self.nodes.push(json!({"name": "camera", "camera": self.cameras.len() - 1, "translation": eye.to_array()}));
        self.nodes.len() - 1
    }

    /// Adds a KHR_lights_punctual point light of radiant intensity `intensity` (W/sr), written in
    /// cd (x [`super::LUMENS_PER_WATT`], see README "Units").
    pub fn point_light(&mut self, position: Vec3, color: Vec3, intensity: f32) {
        let candela = intensity * super::LUMENS_PER_WATT;
        self.lights.push(json!({"type": "point", "color": color.to_array(), "intensity": candela}));
        self.nodes
            .push(json!({"name": "light", "extensions": {"KHR_lights_punctual": {"light": self.lights.len() - 1}},
            "translation": position.to_array()}));
    }

    /// The glTF document; its one buffer is the GLB's binary chunk (`buffer_uri` None) or an
    /// external file (`Some("scene.bin")`, the bytes of [`GltfBuilder::bin`]).
    pub fn document(&self, buffer_uri: Option<&str>) -> Value {
        let mut extensions_used = vec!["KHR_materials_emissive_strength", "KHR_materials_specular"];
        let mut root = json!({
            "asset": {"version": "2.0", "generator": "pathfarm"},
            "scene": 0,
            "scenes": [{"nodes": (0..self.nodes.len()).collect::<Vec<_>>()}],
            "nodes": self.nodes,
            "meshes": self.meshes,
            "materials": self.materials,
            "accessors": self.accessors,
            "bufferViews": self.buffer_views,
            "buffers": [{"byteLength": self.bin.len()}],
        });
        if let Some(uri) = buffer_uri {
            root["buffers"][0]["uri"] = json!(uri);
        }
        if !self.cameras.is_empty() {
            root["cameras"] = json!(self.cameras);
        }
        if !self.lights.is_empty() {
            root["extensions"] = json!({"KHR_lights_punctual": {"lights": self.lights}});
            extensions_used.push("KHR_lights_punctual");
        }
        if !self.animations.is_empty() {
            root["animations"] = json!(self.animations);
            extensions_used.push("KHR_animation_pointer");
        }
        if !self.skins.is_empty() {
            root["skins"] = json!(self.skins);
        }
        root["extensionsUsed"] = json!(extensions_used);
        root
    }

    /// The binary buffer (vertex and index data).
    pub fn bin(&self) -> &[u8] {
        &self.bin
    }

    /// The `.glb` bytes.
    pub fn to_glb(&self) -> Vec<u8> {
        let root = self.document(None);
        let mut json = serde_json::to_vec(&root).unwrap_or_default();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        let mut bin = self.bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
        out
    }
}

/// Rotation that turns a glTF camera (looking down -Z, +Y up) to look from `eye` at `target`.
fn look_rotation(eye: Vec3, target: Vec3, up: Vec3) -> Quat {
    let f = (target - eye).normalize();
    let r = f.cross(up).normalize();
    let u = r.cross(f);
    Quat::from_mat3(&glam::Mat3::from_cols(r, u, -f))
}

/// A Lambertian material (KHR_materials_specular factor 0 removes the specular layer).
pub fn lambert(name: &str, albedo: Vec3) -> Value {
    json!({"name": name, "pbrMetallicRoughness": {"baseColorFactor": [albedo.x, albedo.y, albedo.z, 1.0],
        "metallicFactor": 0.0, "roughnessFactor": 1.0},
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}},
        "extras": {"pathfarm": {"model": "lambert"}}})
}

/// A Lambertian emitter: `radiance` = emissiveFactor x emissiveStrength.
pub fn emitter(name: &str, albedo: Vec3, radiance: Vec3) -> Value {
    let strength = radiance.max_element().max(1e-6);
    let mut m = lambert(name, albedo);
    m["emissiveFactor"] = json!((radiance / strength).to_array());
    m["extensions"]["KHR_materials_emissive_strength"] = json!({"emissiveStrength": strength});
    m
}

/// Two triangles of the quad `v0 v1 v2 v3` (counter-clockwise seen from the front).
pub fn quad(b: &mut GltfBuilder, name: &str, v: [Vec3; 4], material: usize) {
    let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
    b.mesh(name, &v, &[n; 4], &[0, 1, 2, 0, 2, 3], material);
}

/// An axis-aligned box turned about +Y by `angle` (radians), outward normals; returns its node.
pub fn turned_box(b: &mut GltfBuilder, name: &str, center: Vec3, size: Vec3, angle: f32, material: usize) -> usize {
    let rot = Quat::from_rotation_y(angle);
    let h = size * 0.5;
    let c = |x: f32, y: f32, z: f32| center + rot * Vec3::new(x * h.x, y * h.y, z * h.z);
    let faces: [[Vec3; 4]; 6] = [
        [c(-1., -1., 1.), c(1., -1., 1.), c(1., 1., 1.), c(-1., 1., 1.)],
        [c(1., -1., -1.), c(-1., -1., -1.), c(-1., 1., -1.), c(1., 1., -1.)],
        [c(1., -1., 1.), c(1., -1., -1.), c(1., 1., -1.), c(1., 1., 1.)],
        [c(-1., -1., -1.), c(-1., -1., 1.), c(-1., 1., 1.), c(-1., 1., -1.)],
        [c(-1., 1., 1.), c(1., 1., 1.), c(1., 1., -1.), c(-1., 1., -1.)],
        [c(-1., -1., -1.), c(1., -1., -1.), c(1., -1., 1.), c(-1., -1., 1.)],
    ];
    let mut pos = Vec::new();
    let mut nrm = Vec::new();
    let mut idx = Vec::new();
    for f in faces {
        let n = (f[1] - f[0]).cross(f[2] - f[0]).normalize();
        let base = pos.len() as u32;
        pos.extend_from_slice(&f);
        nrm.extend_from_slice(&[n; 4]);
        idx.extend_from_slice(&[base, base + 1, base + 2, base, base + 2, base + 3]);
    }
    b.mesh(name, &pos, &nrm, &idx, material)
}

/// The materials of Mitsuba's `cornell_box()`, added in this order: white, red, green (Lambertian
/// reflectances) and the light (white-reflecting, radiance 18.387, 13.9873, 6.75357).
fn mitsuba_cornell_materials(b: &mut GltfBuilder) -> [usize; 4] {
    let white_rgb = Vec3::new(0.885_809, 0.698_859, 0.666_422);
    [
        b.material(lambert("white", white_rgb)),
        b.material(lambert("red", Vec3::new(0.570_068, 0.043_013_5, 0.044_370_6))),
        b.material(lambert("green", Vec3::new(0.105_421, 0.377_98, 0.076_425))),
        b.material(emitter("light", white_rgb, Vec3::new(18.387, 13.9873, 6.753_57))),
    ]
}

/// The Cornell box walls of Mitsuba's `cornell_box()` ([-1, 1]^3, open toward +Z, normals
/// inward) with its light quad, and a camera at (0, 0, 3.9).
fn cornell_walls(b: &mut GltfBuilder, white: usize, red: usize, green: usize, light: usize) {
    let v = Vec3::new;
    quad(b, "floor", [v(-1., -1., 1.), v(1., -1., 1.), v(1., -1., -1.), v(-1., -1., -1.)], white);
    quad(b, "ceiling", [v(-1., 1., -1.), v(1., 1., -1.), v(1., 1., 1.), v(-1., 1., 1.)], white);
    quad(b, "back", [v(-1., -1., -1.), v(1., -1., -1.), v(1., 1., -1.), v(-1., 1., -1.)], white);
    quad(b, "green-wall", [v(1., -1., -1.), v(1., -1., 1.), v(1., 1., 1.), v(1., 1., -1.)], green);
    quad(b, "red-wall", [v(-1., -1., 1.), v(-1., -1., -1.), v(-1., 1., -1.), v(-1., 1., 1.)], red);
    quad(b, "light", [v(-0.23, 0.99, -0.18), v(0.23, 0.99, -0.18), v(0.23, 0.99, 0.20), v(-0.23, 0.99, 0.20)], light);
    b.camera(v(0.0, 0.0, 3.9), v(0.0, 0.0, 0.0), Vec3::Y, 0.686_048_8, 1.0);
}

/// The demo scene: the Cornell box with a Blinn-glossy tall box and an anisotropic
/// Ashikhmin-Shirley short box, so the lecture's microfacet models show.
pub fn cornell_demo_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let [white, red, green, light] = mitsuba_cornell_materials(&mut b);
    let mut blinn = lambert("blinn-gold", Vec3::new(0.95, 0.75, 0.35));
    blinn["extras"] = json!({"pathfarm": {"model": "blinn", "exponent": 60.0}});
    let blinn = b.material(blinn);
    let mut aniso = lambert("ashikhmin-shirley-steel", Vec3::new(0.8, 0.82, 0.85));
    aniso["extras"] = json!({"pathfarm": {"model": "ashikhmin_shirley", "exponent_x": 400.0, "exponent_y": 8.0}});
    let aniso = b.material(aniso);
    cornell_walls(&mut b, white, red, green, light);
    turned_box(&mut b, "tall-box-blinn", Vec3::new(-0.33, -0.4, -0.28), Vec3::new(0.6, 1.2, 0.6), 0.3185, blinn);
    turned_box(&mut b, "short-box-ashikhmin-shirley", Vec3::new(0.335, -0.7, 0.38), Vec3::splat(0.6), -0.2967, aniso);
    b.to_glb()
}

/// The demo Cornell box, animated over one second: the short box slides 0.3 to the left
/// (LINEAR translation) and the tall box turns a quarter turn about +Y (LINEAR rotation, slerped).
/// At 24 fps frame f is at f / 24 s, so every frame of 0-24 differs. The sequence tests render it.
pub fn cornell_animated_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let [white, red, green, light] = mitsuba_cornell_materials(&mut b);
    let mut blinn = lambert("blinn-gold", Vec3::new(0.95, 0.75, 0.35));
    blinn["extras"] = json!({"pathfarm": {"model": "blinn", "exponent": 60.0}});
    let blinn = b.material(blinn);
    cornell_walls(&mut b, white, red, green, light);
    // Boxes built at the origin, placed by their nodes' animated transforms.
    let tall = turned_box(&mut b, "tall-box", Vec3::new(0.0, -0.4, 0.0), Vec3::new(0.6, 1.2, 0.6), 0.0, blinn);
    let short = turned_box(&mut b, "short-box", Vec3::new(0.0, -0.7, 0.0), Vec3::splat(0.6), 0.0, white);
    b.node_mut(tall)["translation"] = json!([-0.33, 0.0, -0.28]);
    let q0 = Quat::from_rotation_y(0.3185);
    let q1 = Quat::from_rotation_y(0.3185 + std::f32::consts::FRAC_PI_2);
    let rot: Vec<f32> = [q0, q1].iter().flat_map(|q| q.to_array()).collect();
    b.animate("shot", json!({"node": tall, "path": "rotation"}), "LINEAR", &[0.0, 1.0], &rot, "VEC4");
    let path = [0.335, 0.0, 0.38, 0.035, 0.0, 0.38];
    b.animate("shot", json!({"node": short, "path": "translation"}), "LINEAR", &[0.0, 1.0], &path, "VEC3");
    b.to_glb()
}

/// Mitsuba 3's built-in Cornell box (`mitsuba.cornell_box()`), every number as in its scene
/// dictionary: Lambertian walls and boxes (one-sided), the one-sided light quad (radiance
/// 18.387, 13.9873, 6.75357, also white-reflecting), a pinhole camera at (0, 0, 3.9). The
/// tests' Mitsuba reference (`reference/cornell_mitsuba_box_16384spp.exr`, rendered by
/// `scripts/make-reference.py`) shows this scene; `reference/cornell_mitsuba.glb` is this file.
pub fn cornell_mitsuba_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let [white, red, green, light] = mitsuba_cornell_materials(&mut b);
    cornell_walls(&mut b, white, red, green, light);
    // Mitsuba `cube`s: translate . rotate(+Y, degrees) . scale, with the [-1, 1]^3 cube.
    turned_box(&mut b, "small-box", Vec3::new(0.335, -0.7, 0.38), Vec3::splat(0.6), (-17f32).to_radians(), white);
    let large = Vec3::new(0.6, 1.22, 0.6);
    turned_box(&mut b, "large-box", Vec3::new(-0.33, -0.4, -0.28), large, 18.25f32.to_radians(), white);
    b.to_glb()
}

/// Centre and radius of the mirror and glass spheres of [`cornell_spheres_glb`].
pub const CORNELL_MIRROR_SPHERE: (Vec3, f32) = (Vec3::new(-0.45, -0.6, -0.3), 0.4);
pub const CORNELL_GLASS_SPHERE: (Vec3, f32) = (Vec3::new(0.42, -0.62, 0.32), 0.38);

/// Mitsuba's Cornell box walls and light with a perfect mirror sphere (glTF metal, base colour 1,
/// roughness 0: reflectance 1 at every angle) and a solid glass sphere (transmission 1, ior 1.5,
/// `KHR_materials_volume` with the sphere's diameter as thickness, no absorption). Both spheres are
/// faceted (one normal per triangle, level-3 icospheres) so that no shading-normal convention
/// differs between renderers. `reference/cornell_spheres.glb` is this file and
/// `scripts/make-reference.py --glb` renders it with Mitsuba 3 for the tests.
pub fn cornell_spheres_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let [white, red, green, light] = mitsuba_cornell_materials(&mut b);
    let mirror = b.material(json!({"name": "mirror",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 1.0, "roughnessFactor": 0.0}}));
    let (_, r) = CORNELL_GLASS_SPHERE;
    let glass = b.material(json!({"name": "glass",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.5},
            "KHR_materials_volume": {"thicknessFactor": 2.0 * r}}}));
    cornell_walls(&mut b, white, red, green, light);
    for (name, (c, r), m) in
        [("mirror-sphere", CORNELL_MIRROR_SPHERE, mirror), ("glass-sphere", CORNELL_GLASS_SPHERE, glass)]
    {
        let (p, _, i) = inward_sphere(1.0, 3);
        // Outward and faceted: every triangle gets its own three vertices and its face normal.
        let (mut pos, mut nrm, mut idx) = (Vec::new(), Vec::new(), Vec::new());
        for t in i.chunks(3) {
            let v = [p[t[0] as usize], p[t[2] as usize], p[t[1] as usize]].map(|x| c + x * r);
            let n = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
            let base = pos.len() as u32;
            pos.extend_from_slice(&v);
            nrm.extend_from_slice(&[n; 3]);
            idx.extend_from_slice(&[base, base + 1, base + 2]);
        }
        b.mesh(name, &pos, &nrm, &idx, m);
    }
    b.to_glb()
}

/// An icosphere of radius `r` subdivided `level` times; normals point inward (toward the centre)
/// and triangles wind counter-clockwise seen from inside.
pub fn inward_sphere(r: f32, level: u32) -> (Vec<Vec3>, Vec<Vec3>, Vec<u32>) {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        (-1., t, 0.),
        (1., t, 0.),
        (-1., -t, 0.),
        (1., -t, 0.),
        (0., -1., t),
        (0., 1., t),
        (0., -1., -t),
        (0., 1., -t),
        (t, 0., -1.),
        (t, 0., 1.),
        (-t, 0., -1.),
        (-t, 0., 1.),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::with_capacity(f.len() * 4);
        let mut midpoint = |a: u32, b: u32, v: &mut Vec<Vec3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                (v.len() - 1) as u32
            })
        };
        for [a, b, c] in f {
            let ab = midpoint(a, b, &mut v);
            let bc = midpoint(b, c, &mut v);
            let ca = midpoint(c, a, &mut v);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = next;
    }
    let normals = v.iter().map(|p| -*p).collect();
    let positions = v.iter().map(|p| *p * r).collect();
    // Reverse the outward-facing winding so the front faces the inside.
    let indices = f.iter().flat_map(|&[a, b, c]| [a, c, b]).collect();
    (positions, normals, indices)
}

/// The white furnace: the inside of a sphere of radius 1 whose surface emits `le` and reflects
/// with Lambertian albedo `rho`; the camera sits inside. Every pixel's exact value is
/// `le / (1 - rho)`.
pub fn furnace_glb(le: f32, rho: f32) -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let m = b.material(emitter("furnace", Vec3::splat(rho), Vec3::splat(le)));
    let (p, n, i) = inward_sphere(1.0, 3);
    b.mesh("sphere", &p, &n, &i, m);
    b.camera(Vec3::new(0.0, 0.0, 0.3), Vec3::new(0.0, 0.0, -1.0), Vec3::Y, 1.2, 1.0);
    b.to_glb()
}

/// A lossless solid glass sphere (ior 1.5, radius 0.3, `KHR_materials_volume`) at the centre of an emitting, non-reflecting
/// enclosure of radiance `le`: every camera ray, however often it reflects or refracts, ends on
/// the enclosure, so every pixel reads `le`. The camera (0, 0, 0.9) sees the whole sphere with
/// its grazing rim.
pub fn glass_furnace_glb(le: f32) -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let wall = b.material(emitter("furnace", Vec3::ZERO, Vec3::splat(le)));
    let glass = b.material(json!({"name": "glass",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.5},
            "KHR_materials_volume": {"thicknessFactor": 0.6}}}));
    let (p, n, i) = inward_sphere(2.0, 3);
    b.mesh("enclosure", &p, &n, &i, wall);
    let (p, n, i) = inward_sphere(0.3, 4);
    let n: Vec<Vec3> = n.iter().map(|&x| -x).collect();
    let i: Vec<u32> = i.chunks(3).flat_map(|t| [t[0], t[2], t[1]]).collect();
    b.mesh("glass-sphere", &p, &n, &i, glass);
    b.camera(Vec3::new(0.0, 0.0, 0.9), Vec3::ZERO, Vec3::Y, 0.7, 1.0);
    b.to_glb()
}

/// pbrt's analytic scene: a point light of intensity `intensity` at the centre of a Lambertian
/// sphere of radius `r` and albedo `rho`. Every wall point has radiance
/// `rho / pi * intensity / r^2 / (1 - rho)`.
pub fn point_furnace_glb(intensity: f32, rho: f32, r: f32) -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let m = b.material(lambert("wall", Vec3::splat(rho)));
    let (p, n, i) = inward_sphere(r, 5);
    b.mesh("sphere", &p, &n, &i, m);
    b.point_light(Vec3::ZERO, Vec3::ONE, intensity);
    b.camera(Vec3::new(0.0, 0.0, 0.3 * r), Vec3::new(0.0, 0.0, -r), Vec3::Y, 1.2, 1.0);
    b.to_glb()
}

/// Caustics: a solid glass sphere (`KHR_materials_volume`) on a diffuse floor lit by a small, bright area light, in a box.
pub fn caustics_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let white = b.material(lambert("white", Vec3::splat(0.75)));
    let light = b.material(emitter("light", Vec3::splat(0.75), Vec3::splat(400.0)));
    let glass = b.material(json!({"name": "glass",
        "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": 1.5},
            "KHR_materials_volume": {"thicknessFactor": 0.7}}}));
    let v = Vec3::new;
    quad(&mut b, "floor", [v(-1., -1., 1.), v(1., -1., 1.), v(1., -1., -1.), v(-1., -1., -1.)], white);
    quad(&mut b, "ceiling", [v(-1., 1., -1.), v(1., 1., -1.), v(1., 1., 1.), v(-1., 1., 1.)], white);
    quad(&mut b, "back", [v(-1., -1., -1.), v(1., -1., -1.), v(1., 1., -1.), v(-1., 1., -1.)], white);
    quad(&mut b, "right", [v(1., -1., -1.), v(1., -1., 1.), v(1., 1., 1.), v(1., 1., -1.)], white);
    quad(&mut b, "left", [v(-1., -1., 1.), v(-1., -1., -1.), v(-1., 1., -1.), v(-1., 1., 1.)], white);
    let s = 0.06;
    quad(&mut b, "light", [v(-s, 0.99, -s), v(s, 0.99, -s), v(s, 0.99, s), v(-s, 0.99, s)], light);
    let (p, n, i) = inward_sphere(0.35, 3);
    // Outward sphere: flip the inward one back.
    let c = v(0.0, -0.65, 0.0);
    let p: Vec<Vec3> = p.iter().map(|&x| x + c).collect();
    let n: Vec<Vec3> = n.iter().map(|&x| -x).collect();
    let i: Vec<u32> = i.chunks(3).flat_map(|t| [t[0], t[2], t[1]]).collect();
    b.mesh("glass-sphere", &p, &n, &i, glass);
    b.camera(v(0.0, 0.0, 3.9), v(0.0, 0.0, 0.0), Vec3::Y, 0.686_048_8, 1.0);
    b.to_glb()
}

/// Base colour of the mirror in [`gltf_mirror_glb`] (its albedo AOV tags the mirror's pixels).
pub const GLTF_MIRROR_BASE: Vec3 = Vec3::new(0.9, 0.85, 0.8);

/// A glTF mirror (core metallic-roughness: metallic 1, roughness 0, base colour
/// [`GLTF_MIRROR_BASE`]) lying on the floor of the Mitsuba Cornell box walls (Lambertian,
/// one ceiling light of radiance (18.387, 13.9873, 6.75357)). From the camera the mirror shows
/// the lower back wall.
pub fn gltf_mirror_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let [white, red, green, light] = mitsuba_cornell_materials(&mut b);
    let c = GLTF_MIRROR_BASE;
    let mirror = b.material(json!({"name": "gltf-mirror",
        "pbrMetallicRoughness": {"baseColorFactor": [c.x, c.y, c.z, 1.0], "metallicFactor": 1.0, "roughnessFactor": 0.0}}));
    cornell_walls(&mut b, white, red, green, light);
    let v = Vec3::new;
    let (s, y) = (0.7, -0.995);
    quad(&mut b, "mirror", [v(-s, y, s), v(s, y, s), v(s, y, -s), v(-s, y, -s)], mirror);
    b.to_glb()
}

/// Veach's multiple-importance-sampling scene, flattened: four floor strips from rough to near
/// mirror (Blinn exponents 2, 40, 600, 12000; base colours tagged 0.5, 0.6, 0.7, 0.8 in red so
/// tests can tell them apart by the albedo layer), lit by a small bright and a large dim light.
pub fn mis_glb() -> Vec<u8> {
    let mut b = GltfBuilder::new();
    let v = Vec3::new;
    for (k, exponent) in [2.0f32, 40.0, 600.0, 12_000.0].into_iter().enumerate() {
        let mut m = lambert("strip", Vec3::new(0.5 + 0.1 * k as f32, 0.7, 0.7));
        m["extras"] = json!({"pathfarm": {"model": "blinn", "exponent": exponent}});
        let m = b.material(m);
        let z0 = 1.0 - 0.5 * k as f32;
        quad(&mut b, "strip", [v(-2.0, 0.0, z0), v(2.0, 0.0, z0), v(2.0, 0.0, z0 - 0.45), v(-2.0, 0.0, z0 - 0.45)], m);
    }
    let small = b.material(emitter("small-light", Vec3::ZERO, Vec3::splat(900.0)));
    let large = b.material(emitter("large-light", Vec3::ZERO, Vec3::splat(1.5)));
    // Lights face the strips (normals toward -z and down).
    let (s, l) = (0.03, 0.6);
    quad(
        &mut b,
        "small",
        [
            v(-0.8 - s, 1.0 - s, -1.5),
            v(-0.8 + s, 1.0 - s, -1.5),
            v(-0.8 + s, 1.0 + s, -1.5),
            v(-0.8 - s, 1.0 + s, -1.5),
        ],
        small,
    );
    quad(
        &mut b,
        "large",
        [v(0.8 - l, 1.0 - l, -1.5), v(0.8 + l, 1.0 - l, -1.5), v(0.8 + l, 1.0 + l, -1.5), v(0.8 - l, 1.0 + l, -1.5)],
        large,
    );
    b.camera(v(0.0, 1.2, 2.6), v(0.0, 0.0, -0.3), Vec3::Y, 0.7, 1.0);
    b.to_glb()
}

/// The Cornell box as Blender's "glTF Separate" export would write it: `cornell.gltf` with its
/// buffer in `cornell.bin` and a `checker.png` base-colour texture (16 x 16) on the back wall;
/// camera 0 is the usual pinhole, camera 1 an orthographic view of the same box. The files
/// (name, bytes) go into a scene bundle with [`super::bundle::tar_bundle`].
pub fn cornell_separate_files() -> Vec<(String, Vec<u8>)> {
    let mut b = GltfBuilder::new();
    let white = b.material(lambert("white", Vec3::new(0.8, 0.8, 0.8)));
    let red = b.material(lambert("red", Vec3::new(0.6, 0.05, 0.05)));
    let green = b.material(lambert("green", Vec3::new(0.1, 0.4, 0.08)));
    let light = b.material(emitter("light", Vec3::splat(0.8), Vec3::new(18.0, 14.0, 7.0)));
    cornell_walls(&mut b, white, red, green, light);
    let mut doc = b.document(Some("cornell.bin"));
    doc["materials"][white]["pbrMetallicRoughness"]["baseColorTexture"] = json!({"index": 0});
    doc["textures"] = json!([{"source": 0, "sampler": 0}]);
    doc["samplers"] = json!([{"magFilter": 9728, "minFilter": 9728}]);
    doc["images"] = json!([{"uri": "checker.png", "mimeType": "image/png"}]);
    if let Some(cameras) = doc["cameras"].as_array_mut() {
        cameras.push(
            json!({"type": "orthographic", "orthographic": {"xmag": 1.1, "ymag": 1.1, "znear": 0.01, "zfar": 100.0}}),
        );
    }
    if let Some(nodes) = doc["nodes"].as_array_mut() {
        nodes.push(json!({"name": "ortho-camera", "camera": 1, "translation": [0.0, 0.0, 3.9]}));
        let count = nodes.len();
        doc["scenes"][0]["nodes"] = json!((0..count).collect::<Vec<_>>());
    }
    let checker = image::RgbaImage::from_fn(16, 16, |x, y| {
        if (x / 4 + y / 4) % 2 == 0 { image::Rgba([230, 230, 230, 255]) } else { image::Rgba([60, 60, 200, 255]) }
    });
    let mut png = Vec::new();
    // Encoding an in-memory image into a Vec cannot fail.
    let _ = checker.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png);
    vec![
        ("cornell.gltf".to_string(), serde_json::to_vec_pretty(&doc).unwrap_or_default()),
        ("cornell.bin".to_string(), b.bin().to_vec()),
        ("checker.png".to_string(), png),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glb_header_is_consistent() {
        for glb in
            [cornell_demo_glb(), furnace_glb(1.0, 0.5), point_furnace_glb(1.0, 0.5, 1.0), caustics_glb(), mis_glb()]
        {
            assert_eq!(&glb[0..4], b"glTF");
            assert_eq!(u32::from_le_bytes([glb[8], glb[9], glb[10], glb[11]]) as usize, glb.len());
            let gltf = gltf::Gltf::from_slice(&glb).expect("valid glTF");
            assert!(gltf.meshes().count() > 0);
        }
    }

    #[test]
    fn inward_sphere_faces_inward() {
        let (p, _, i) = inward_sphere(2.0, 2);
        for t in i.chunks(3) {
            let (a, b, c) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
            let n = (b - a).cross(c - a);
            assert!(n.dot(a + b + c) < 0.0, "geometric normal must point to the centre");
        }
    }
}
