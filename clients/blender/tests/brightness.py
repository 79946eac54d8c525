"""Blender's brightness: the same Blender scene rendered by Cycles and by pathfarm from the GLB
Blender's glTF exporter writes, with each light alone and all together.

    python3 clients/blender/tests/brightness.py --worker target/release/pathfarm-worker --out DIR

Cycles: CPU, path tracing, no denoising, no adaptive sampling, no clamping, no light threshold,
box pixel filter, view transform "Standard" (exposure 0, gamma 1), linear float EXR. pathfarm:
`pathfarm-worker render` with the path integrator at the same bounce limit. Both images are
read as linear float (OpenEXR + numpy). Passes when every channel's image mean is within
`--tolerance` (default 3%) of Cycles' for every configuration; prints one JSON line per
configuration (means, ratios) and exits 1 naming the failures otherwise.
"""

import argparse
import json
import os
import subprocess

import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))  # the add-on package `pathfarm`

import bpy  # noqa: E402
import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402

import testscene  # noqa: E402

CONFIGS = {"point": ("point",), "sun": ("sun",), "panel": ("panel",), "all": ("point", "sun", "panel")}
# Every light, walls with the Principled BSDF's default specular layer.
DEFAULT_WALLS = "all_default_walls"
CONFIGS[DEFAULT_WALLS] = CONFIGS["all"]
BOUNCES = 12


def read_rgb(path):
    with OpenEXR.File(path) as f:
        channels = f.channels()
        if "RGB" in channels:
            rgb = channels["RGB"].pixels
        elif "RGBA" in channels:
            rgb = channels["RGBA"].pixels[..., :3]
        else:
            rgb = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
    return np.asarray(rgb, dtype=np.float64)


def object_mask(size):
    """The object the camera sees first through each pixel's centre (rows top to bottom), by
    ray casts in Blender: which pixels show the metal box, the glass ball, the walls."""
    from mathutils import Vector

    scene = bpy.context.scene
    cam = scene.camera
    depsgraph = bpy.context.evaluated_depsgraph_get()
    tr, br, bl, tl = (cam.matrix_world @ v for v in cam.data.view_frame(scene=scene))
    origin = cam.matrix_world.translation
    names = np.empty((size, size), dtype=object)
    for row in range(size):
        v = (row + 0.5) / size
        left, right = tl.lerp(bl, v), tr.lerp(br, v)
        for col in range(size):
            target = left.lerp(right, (col + 0.5) / size)
            hit, _, _, _, ob, _ = scene.ray_cast(depsgraph, origin, Vector(target - origin).normalized())
            names[row, col] = ob.name if hit else ""
    return names


def render_cycles(path, size, spp, threads):
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = spp
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = 1
    c.max_bounces = BOUNCES
    c.diffuse_bounces = BOUNCES
    c.glossy_bounces = BOUNCES
    c.transmission_bounces = BOUNCES
    c.transparent_max_bounces = BOUNCES
    c.volume_bounces = 0
    c.caustics_reflective = True
    c.caustics_refractive = True
    c.blur_glossy = 0.0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.light_sampling_threshold = 0.0
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    scene.render.resolution_x = size
    scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads
    scene.render.film_transparent = False
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    s = scene.render.image_settings
    s.file_format = "OPEN_EXR"
    s.color_depth = "32"
    s.color_mode = "RGB"
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    return read_rgb(path)


def render_pathfarm(worker, glb, exr, size, spp, threads):
    cmd = [worker, "render", glb, "--width", str(size), "--height", str(size), "--spp", str(spp)]
    cmd += ["--integrator", "path", "--max-depth", str(BOUNCES + 1), "--threads", str(threads), "--out", exr]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=testscene.worker_env())
    return read_rgb(exr)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worker", required=True, help="the pathfarm-worker binary")
    ap.add_argument("--out", required=True, help="folder for the GLBs and EXRs")
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--tolerance", type=float, default=0.03)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    failures = []
    for name in args.configs.split(","):
        t0 = time.time()
        testscene.cornell(CONFIGS[name], size=(args.size, args.size), default_walls=name == DEFAULT_WALLS)
        glb = os.path.join(args.out, f"{name}.glb")
        testscene.export_glb(glb, animation=False)
        cycles = render_cycles(os.path.join(args.out, f"{name}_cycles.exr"), args.size, args.spp, args.threads)
        t1 = time.time()
        ours = render_pathfarm(
            args.worker, glb, os.path.join(args.out, f"{name}_pathfarm.exr"), args.size, args.spp, args.threads
        )
        t2 = time.time()
        mc = cycles.reshape(-1, 3).mean(axis=0)
        mp = ours.reshape(-1, 3).mean(axis=0)
        ratio = mp / np.maximum(mc, 1e-12)
        ok = bool(np.all(np.abs(ratio - 1.0) <= args.tolerance))
        # Where the two differ by design (Principled BSDF vs glTF's BRDF), per object seen:
        # reported, not checked.
        mask = object_mask(args.size)
        objects = {}
        for ob in ("metal box", "glass ball", "back", "floor", "left", "right"):
            sel = mask == ob
            if sel.sum() >= 4:
                r = ours[sel].mean(axis=0) / np.maximum(cycles[sel].mean(axis=0), 1e-12)
                objects[ob] = [round(float(x), 3) for x in r]
        print(
            json.dumps(
                {
                    "config": name,
                    "cycles_mean": [round(float(v), 5) for v in mc],
                    "pathfarm_mean": [round(float(v), 5) for v in mp],
                    "ratio": [round(float(v), 4) for v in ratio],
                    "ok": ok,
                    "ratio_by_object_seen": objects,
                    "cycles_s": round(t1 - t0, 1),
                    "pathfarm_s": round(t2 - t1, 1),
                }
            ),
            flush=True,
        )
        if not ok:
            failures.append(f"{name}: pathfarm/Cycles mean ratio per channel {ratio.round(4).tolist()}")
    if failures:
        print(f"FAIL: image means differ by more than {args.tolerance:.0%}: " + "; ".join(failures), flush=True)
        sys.exit(1)
    print("PASS", flush=True)


if __name__ == "__main__":
    main()
