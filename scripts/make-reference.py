#!/usr/bin/env python3
"""Render the Mitsuba 3 references that pathfarm's tests compare against.

The scene is Mitsuba 3's built-in Cornell box (`mitsuba.cornell_box()`), the same scene that
`pathfarm_common::scene::demo::cornell_mitsuba_glb()` writes as glTF (reference/cornell_mitsuba.glb,
made by `cargo run --release -p pathfarm-worker --example make_scenes`). Settings (as the tests
assume them): 256 x 256, path integrator, max_depth 8, rr_depth 5 (Mitsuba's default), a 1-pixel
box reconstruction filter, llvm_ad_rgb, 16,384 spp rendered as 16 passes of 1,024 spp with seeds
0..15 and averaged. Output: linear float32 RGB EXR plus a JSON file with the settings, timing and
the mean of each channel.

    pip install mitsuba && apt-get install libllvm19
    python3 scripts/make-reference.py                     # reference/cornell_mitsuba_box_16384spp.exr
    python3 scripts/make-reference.py --spp 1024 --out /tmp/cb1024.exr
    python3 scripts/make-reference.py --variant scalar_rgb --spp 64 --spp-per-pass 64 --repeats 3 \
        --threads 2 --out /tmp/cb.exr      # timing for the renderer benchmark (RESULT {json} line)

On a 2-core machine the 16,384-spp render takes about 8 minutes.

With `--glb FILE` the scene is one our exporter wrote (reference/cornell_spheres.glb: the box's
walls with a mirror and a glass sphere), converted here to Mitsuba: every triangle mesh becomes a
PLY file (written next to the output in a `<out>.ply/` folder, removed afterwards unless
`--keep-ply`), glTF materials map to Mitsuba BSDFs (Lambertian with KHR_materials_specular 0 ->
`diffuse`; metallic 1, roughness 0, base colour 1 -> `conductor` with `material: none`, a perfect
mirror; transmission 1, roughness 0 -> `dielectric` with the glTF ior), emissive materials get an
`area` emitter of radiance emissiveFactor x emissiveStrength, and the first camera becomes a
perspective sensor. Anything else is refused rather than approximated.

    python3 scripts/make-reference.py --glb reference/cornell_spheres.glb --max-depth 16 \
        --spp 8192 --spp-per-pass 512 --out reference/cornell_spheres_8192spp.exr

With `--gltf FILE` (the renderer benchmark's 130k-triangle `01_vertex_count_32bit`) the script
times a plain .gltf as pathfarm renders it without camera or lights: the default camera and a
constant environment (`--env`); its material becomes Mitsuba's `principled` BSDF, which is close
to pathfarm's glTF BSDF but not the same, so only the throughput compares. Every run also reports
the CPU time of all its threads (`cpu_s`, `samples_per_cpu_s_median`).
"""
import argparse
import json
import math
import os
import shutil
import struct
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "..", "reference", "cornell_mitsuba_box_16384spp.exr")


def read_glb(path):
    """The JSON document and binary chunk of a .glb file."""
    with open(path, "rb") as f:
        data = f.read()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        sys.exit(f"{path}: not a glTF 2.0 binary")
    offset, doc, binary = 12, None, b""
    while offset < length:
        chunk_len, chunk_type = struct.unpack_from("<II", data, offset)
        chunk = data[offset + 8: offset + 8 + chunk_len]
        if chunk_type == 0x4E4F534A:
            doc = json.loads(chunk)
        elif chunk_type == 0x004E4942:
            binary = chunk
        offset += 8 + chunk_len
    return doc, binary


def accessor(doc, binary, index, np):
    """An accessor as a numpy array (float32 VEC3 or uint32/uint16 SCALAR, as our exporter writes)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(binary, dtype=dtype, count=acc["count"] * width, offset=start)
    return a.reshape(-1, width) if width > 1 else a


def write_ply(path, positions, normals, faces):
    """A binary little-endian PLY with per-vertex normals."""
    import numpy as np
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(positions)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(faces)}\nproperty list uchar uint vertex_indices\nend_header\n"
    )
    verts = np.hstack([positions, normals]).astype("<f4")
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<u4", (3,))])
    face_rec["n"] = 3
    face_rec["i"] = faces
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(verts.tobytes())
        f.write(face_rec.tobytes())


def quat_rotate(q, v):
    x, y, z, w = q
    u = (x, y, z)
    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    t = tuple(2 * c for c in cross(u, v))
    c2 = cross(u, t)
    return tuple(v[i] + w * t[i] + c2[i] for i in range(3))


def glb_scene_dict(path, ply_dir, res, max_depth):
    """Mitsuba scene dictionary of one of our exported .glb scenes (see the module doc)."""
    import numpy as np
    doc, binary = read_glb(path)
    os.makedirs(ply_dir, exist_ok=True)

    def bsdf_of(mat):
        pbr = mat.get("pbrMetallicRoughness", {})
        ext = mat.get("extensions", {})
        base = pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]
        metallic = pbr.get("metallicFactor", 1.0)
        rough = pbr.get("roughnessFactor", 1.0)
        transmission = ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0)
        name = mat.get("name", "?")
        if transmission > 0:
            if transmission != 1 or rough != 0 or metallic != 0:
                sys.exit(f"material {name}: only smooth, fully transmissive glass is converted")
            ior = ext.get("KHR_materials_ior", {}).get("ior", 1.5)
            if ext.get("KHR_materials_volume", {}).get("thicknessFactor", 0.0) > 0:
                return {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0}
            # glTF without a volume (or thickness 0): thin-walled, Mitsuba's thin dielectric.
            if base != [1, 1, 1]:
                sys.exit(f"material {name}: a thin-walled sheet must be white (Mitsuba's is untinted)")
            return {"type": "thindielectric", "int_ior": ior, "ext_ior": 1.0}
        if metallic == 1 and rough == 0:
            if base != [1, 1, 1]:
                sys.exit(f"material {name}: a mirror must have base colour 1 (Schlick = 1 at every angle)")
            return {"type": "conductor", "material": "none"}
        if ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0) == 0 and metallic == 0:
            return {"type": "diffuse", "reflectance": {"type": "rgb", "value": base}}
        sys.exit(f"material {name}: no exact Mitsuba equivalent")

    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth}}
    for n, node in enumerate(doc["nodes"]):
        if "mesh" in node:
            if any(k in node for k in ("translation", "rotation", "scale", "matrix")):
                sys.exit(f"node {n}: transformed meshes are not converted (our exporter writes world space)")
            for p, prim in enumerate(doc["meshes"][node["mesh"]]["primitives"]):
                pos = accessor(doc, binary, prim["attributes"]["POSITION"], np)
                nrm = accessor(doc, binary, prim["attributes"]["NORMAL"], np)
                faces = accessor(doc, binary, prim["indices"], np).reshape(-1, 3)
                ply = os.path.join(ply_dir, f"node{n}_{p}.ply")
                write_ply(ply, pos, nrm, faces)
                mat = doc["materials"][prim["material"]]
                shape = {"type": "ply", "filename": ply, "bsdf": bsdf_of(mat)}
                emissive = mat.get("emissiveFactor", [0, 0, 0])
                strength = mat.get("extensions", {}).get("KHR_materials_emissive_strength", {}).get(
                    "emissiveStrength", 1.0)
                if max(emissive) > 0:
                    shape["emitter"] = {"type": "area",
                                        "radiance": {"type": "rgb", "value": [c * strength for c in emissive]}}
                scene[f"shape_{n}_{p}"] = shape
        if "camera" in node and "sensor" not in scene:
            cam = doc["cameras"][node["camera"]]["perspective"]
            eye = node.get("translation", [0, 0, 0])
            q = node.get("rotation", [0, 0, 0, 1])
            fwd = quat_rotate(q, (0.0, 0.0, -1.0))
            up = quat_rotate(q, (0.0, 1.0, 0.0))
            import mitsuba as mi
            scene["sensor"] = {
                "type": "perspective",
                "fov": math.degrees(cam["yfov"]),
                "fov_axis": "y",
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=eye, target=[eye[i] + fwd[i] for i in range(3)], up=up),
                "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                         "pixel_format": "rgb"},
            }
    if "sensor" not in scene:
        sys.exit(f"{path}: no camera")
    return scene


def gltf_throughput_scene_dict(path, ply_dir, res, max_depth, env):
    """A throughput-comparison scene from a plain .gltf (external buffers; untransformed meshes
    with POSITION and NORMAL; metallic-roughness materials), as pathfarm renders it without a
    camera or lights: the default camera (`default_camera_for_bounds`: 40 degrees vertical, on
    the side of the bounds' thinnest axis, far enough that the bounding sphere fits) and a
    constant environment of radiance `env`. Materials become Mitsuba's `principled` BSDF with
    the glTF base colour, metallic and roughness: close to, not the same as, pathfarm's glTF
    BSDF, so the images are not compared, only the throughput."""
    import numpy as np
    with open(path) as f:
        doc = json.load(f)
    base_dir = os.path.dirname(os.path.abspath(path))
    buffers = []
    for b in doc["buffers"]:
        with open(os.path.join(base_dir, b["uri"]), "rb") as f:
            buffers.append(f.read())
    os.makedirs(ply_dir, exist_ok=True)
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth},
             "environment": {"type": "constant", "radiance": {"type": "rgb", "value": [env] * 3}}}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for n, node in enumerate(doc["nodes"]):
        if "mesh" not in node:
            continue
        if any(k in node for k in ("translation", "rotation", "scale", "matrix")):
            sys.exit(f"node {n}: transformed meshes are not converted")
        for p, prim in enumerate(doc["meshes"][node["mesh"]]["primitives"]):
            def get(index):
                view = doc["bufferViews"][doc["accessors"][index]["bufferView"]]
                return accessor(doc, buffers[view.get("buffer", 0)], index, np)
            pos = get(prim["attributes"]["POSITION"])
            nrm = get(prim["attributes"]["NORMAL"])
            faces = get(prim["indices"]).reshape(-1, 3)
            lo, hi = np.minimum(lo, pos.min(axis=0)), np.maximum(hi, pos.max(axis=0))
            ply = os.path.join(ply_dir, f"node{n}_{p}.ply")
            write_ply(ply, pos, nrm, faces)
            pbr = doc["materials"][prim["material"]].get("pbrMetallicRoughness", {}) if "material" in prim else {}
            bsdf = {"type": "principled",
                    "base_color": {"type": "rgb", "value": pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]},
                    "metallic": pbr.get("metallicFactor", 1.0), "roughness": pbr.get("roughnessFactor", 1.0)}
            scene[f"shape_{n}_{p}"] = {"type": "ply", "filename": ply, "bsdf": bsdf}
    # pathfarm_common::scene::default_camera_for_bounds at aspect 1.
    center, extent = (lo + hi) * 0.5, hi - lo
    radius = max(float(np.linalg.norm(extent)) * 0.5, 1e-3)
    yfov = math.radians(40.0)
    distance = radius / math.sin(yfov * 0.5)
    def thinner(a, b):
        return a < b * 0.99
    if thinner(extent[0], extent[2]) and extent[0] <= extent[1]:
        back, up = np.array([1.0, 0, 0]), [0, 1, 0]
    elif thinner(extent[1], extent[2]) and thinner(extent[1], extent[0]):
        back, up = np.array([0, 1.0, 0]), [0, 0, -1]
    else:
        back, up = np.array([0, 0, 1.0]), [0, 1, 0]
    import mitsuba as mi
    eye = center + back * distance
    scene["sensor"] = {
        "type": "perspective", "fov": 40.0, "fov_axis": "y",
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=center.tolist(), up=up),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }
    return scene


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--spp", type=int, default=16384)
    ap.add_argument("--spp-per-pass", type=int, default=1024)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="0 = all cores")
    ap.add_argument("--out", default=DEFAULT_OUT)
    ap.add_argument("--glb", help="render this .glb written by our exporter instead of mitsuba.cornell_box()")
    ap.add_argument("--gltf", help="time this plain .gltf (the corpus' 01_vertex_count_32bit) lit by a constant "
                    "environment (--env) from pathfarm's default camera; for throughput only")
    ap.add_argument("--env", type=float, default=1.0, help="--gltf: the environment's radiance")
    ap.add_argument("--keep-ply", action="store_true", help="keep the converted PLY meshes")
    ap.add_argument("--repeats", type=int, default=1,
                    help="render this many times (timing; the image is the first); the LLVM variant "
                         "compiles its kernels in the first repeat")
    args = ap.parse_args()
    if args.spp % args.spp_per_pass:
        sys.exit("--spp must be a multiple of --spp-per-pass")

    # Dr.Jit's LLVM backend needs a recent libLLVM; Debian 12's default (14/15) aborts on
    # fminimum. `apt-get install libllvm19` and point Dr.Jit at it unless told otherwise.
    llvm19 = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
    if args.variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(llvm19):
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm19

    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(args.variant)
    if args.threads > 0:
        dr.set_thread_count(args.threads)

    ply_dir = None
    if args.glb:
        ply_dir = os.path.splitext(os.path.abspath(args.out))[0] + ".ply"
        scene_dict = glb_scene_dict(args.glb, ply_dir, args.res, args.max_depth)
    elif args.gltf:
        ply_dir = os.path.splitext(os.path.abspath(args.out))[0] + ".ply"
        scene_dict = gltf_throughput_scene_dict(args.gltf, ply_dir, args.res, args.max_depth, args.env)
    else:
        scene_dict = mi.cornell_box()
        scene_dict["sensor"]["film"]["width"] = args.res
        scene_dict["sensor"]["film"]["height"] = args.res
        scene_dict["sensor"]["film"]["rfilter"] = {"type": "box"}
        scene_dict["integrator"] = {"type": "path", "max_depth": args.max_depth}
    scene = mi.load_dict(scene_dict)
    if ply_dir and not args.keep_ply:
        shutil.rmtree(ply_dir, ignore_errors=True)

    passes = args.spp // args.spp_per_pass
    times = []
    cpu_times = []
    image = None
    for repeat in range(max(1, args.repeats)):
        acc = np.zeros((args.res, args.res, 3), dtype=np.float64)
        t0 = time.perf_counter()
        c0 = time.process_time()
        for p in range(passes):
            img = mi.render(scene, spp=args.spp_per_pass, seed=args.seed + p)
            dr.eval(img)
            dr.sync_thread()
            acc += np.array(img, dtype=np.float64)
            if passes > 1:
                print(f"pass {p + 1}/{passes}: {time.perf_counter() - t0:.1f} s", flush=True)
        times.append(time.perf_counter() - t0)
        # CPU time of every thread of the process: on a loaded machine, samples per CPU-second
        # say more than wall time.
        cpu_times.append(time.process_time() - c0)
        if image is None:
            image = (acc / passes).astype(np.float32)
    seconds = sorted(times)[len(times) // 2]
    cpu_seconds = sorted(cpu_times)[len(cpu_times) // 2]

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    bitmap = mi.Bitmap(image, mi.Bitmap.PixelFormat.RGB)
    bitmap.write(args.out)
    meta = {
        "renderer": "mitsuba",
        "scene": os.path.basename(args.glb or args.gltf or "") or "mitsuba.cornell_box()",
        "mitsuba_version": mi.__version__,
        "variant": args.variant,
        "threads": dr.thread_count(),
        "res": args.res,
        "spp": args.spp,
        "spp_per_pass": args.spp_per_pass,
        "seeds": [args.seed, args.seed + passes - 1],
        "max_depth": args.max_depth,
        "rr_depth": 5,
        "rfilter": "box",
        "integrator": str(scene.integrator()).replace("\n", " "),
        "render_s": [round(t, 3) for t in times],
        "render_median_s": round(seconds, 3),
        "samples_per_s_median": round(args.res * args.res * args.spp / seconds, 1),
        "cpu_s": [round(t, 3) for t in cpu_times],
        "cpu_median_s": round(cpu_seconds, 3),
        "samples_per_cpu_s_median": round(args.res * args.res * args.spp / cpu_seconds, 1),
        "mean_rgb": [float(x) for x in image.reshape(-1, 3).mean(axis=0)],
    }
    with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
        json.dump(meta, f, indent=1)
        f.write("\n")
    print("RESULT " + json.dumps(meta), flush=True)


if __name__ == "__main__":
    main()
