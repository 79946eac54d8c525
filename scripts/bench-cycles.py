"""Time to quality in Cycles, for issue 14's comparison with pathfarm (worker/examples/clean_frames.rs).

    # first ours (writes the GLB, our reference and results.json into --out):
    cargo run --release -p pathfarm-worker --features denoise --example clean_frames -- --out DIR ...
    # then Cycles on the same GLB; run WITHOUT pyoidn's LD_LIBRARY_PATH (it breaks `import bpy`):
    env -u LD_LIBRARY_PATH python3.11 scripts/bench-cycles.py --glb DIR/cornell.glb --size 64 \
        --ref-spp 8192 --compare DIR/cornell_64px_16384spp.exr --ours DIR/results.json

Cycles: bpy (Blender 4.5 as a Python module, `pip install bpy`), CPU, `--threads` threads, the
GLB imported by Blender's glTF importer and then made the scene pathfarm renders:
- our Lambertian materials (glTF `extras` say `lambert`, which the importer ignores) lose the
  Principled BSDF's default specular layer (Specular IOR Level 0; metals and glass keep theirs);
- single-sided glTF materials (all of the Cornell box's) are black from behind and emitters emit
  only in front, as in pathfarm: Cycles shades and emits on both sides, and the light quad's
  back, 1 cm under the ceiling, lit the gap between them, which leaked through its edges
  (the image 20% / 12% / 11% too bright in R / G / B, up to 26% at the top, and fireflies from
  paths that found the gap);
- box pixel filter 1 px, view transform "Standard" (look None, exposure 0, gamma 1), linear
  float EXR, path segments as ours (max_depth 8 = 7 bounces), no clamping, light sampling
  threshold 0, reflective and refractive caustics on, no glossy blur, black world.
The reference: `--ref-spp` samples, no adaptive sampling, no denoising (cached in --out);
`--compare` prints our reference's image and 4 x 4 region means over Cycles'. Then adaptive
sampling (`--threshold`, `--min-spp`) and, with `--denoise on`, OIDN (albedo + normal, prefilter
"Accurate") at 16, 32, 64, ... samples until the relMSE against Cycles' own reference (mean over
pixels and channels of (x - r)^2 / (r^2 + 1e-2), the same as ours) drops below `--target`, then a
bisection of the sample count between the last miss and the first hit. The time is the wall time
of `bpy.ops.render.render` (scene sync, BVH, render, denoise), the counterpart of ours
(preparation + render + one denoise). Equal time: the relMSE of the most samples tried that
rendered within `--budget-s`. With `--ours`, prints the time ratio ours / Cycles and our
equal-time relMSE for the same configuration (adaptive+oidn, or adaptive with `--denoise off`)
of `--scene`. Writes NAME_cycles_CONFIG.json into --out.
"""

import argparse
import json
import os
import time

try:
    import bpy
    import numpy as np
    import OpenEXR
except ImportError as e:
    raise SystemExit(f"{e}: needs Python 3.11 with `pip install bpy==4.5.* numpy OpenEXR`; run it without "
                     "pyoidn's lib folder on LD_LIBRARY_PATH (its libraries break `import bpy`)")


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


def rel_mse(x, r):
    x = np.where(np.isfinite(x), x, 1e3)
    return float(np.mean((x - r) ** 2 / (r * r + 1e-2)))


def one_sided(m):
    """Black from behind, as a glTF material without doubleSided is in pathfarm: Cycles shades
    (and, for emitters, emits from) both sides of every surface. The importer marks single-sided
    materials with use_backface_culling, which only the viewport reads; here the Material Output
    gets Mix(Backfacing, surface, black) and emitters are importance-sampled on their front only."""
    nt = m.node_tree
    out = next((n for n in nt.nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None)
    if out is None or not out.inputs["Surface"].links:
        return
    surface = out.inputs["Surface"].links[0].from_socket
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    black = nt.nodes.new("ShaderNodeBsdfDiffuse")
    black.inputs["Color"].default_value = (0, 0, 0, 1)
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(geo.outputs["Backfacing"], mix.inputs["Fac"])
    nt.links.new(surface, mix.inputs[1])
    nt.links.new(black.outputs["BSDF"], mix.inputs[2])
    nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    m.cycles.emission_sampling = "FRONT"


def compare(cycles, ours, what):
    """The cross check of the two references: image mean and 4 x 4 region means per channel,
    ours / Cycles."""
    if cycles.shape != ours.shape:
        raise SystemExit(f"{what}: {ours.shape[1]}x{ours.shape[0]}, Cycles' reference {cycles.shape[1]}x{cycles.shape[0]}")
    k = 4
    h, w = cycles.shape[0] // k, cycles.shape[1] // k
    ratios = np.array([[ours[i * h:(i + 1) * h, j * w:(j + 1) * w].mean(axis=(0, 1))
                        / np.maximum(cycles[i * h:(i + 1) * h, j * w:(j + 1) * w].mean(axis=(0, 1)), 1e-12)
                        for j in range(k)] for i in range(k)])
    mean = ours.reshape(-1, 3).mean(axis=0) / np.maximum(cycles.reshape(-1, 3).mean(axis=0), 1e-12)
    print(json.dumps({"compare": what, "mean_ratio_ours_over_cycles": mean.round(4).tolist(),
                      "region_ratio_min": float(ratios.min().round(4)), "region_ratio_max": float(ratios.max().round(4)),
                      "rel_mse_ours_vs_cycles_reference": rel_mse(ours, cycles)}), flush=True)


def setup(glb, size, threads, max_depth, fixes=("specular", "one_sided", "light_threshold")):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=glb)
    scene = bpy.context.scene
    cams = [o for o in scene.objects if o.type == "CAMERA"]
    if not cams:
        raise SystemExit(f"{glb}: no camera")
    scene.camera = cams[0]
    for m in bpy.data.materials:
        p = m.node_tree.nodes.get("Principled BSDF") if m.use_nodes and m.node_tree else None
        # Our Lambertian materials (glTF `extras` say `lambert`, which Blender's importer
        # ignores) come in as Principled BSDFs with the default dielectric specular layer: make
        # them the pure Lambertians they are (glass and metals keep theirs).
        if "specular" in fixes and p is not None and p.inputs["Metallic"].default_value == 0.0 and \
                p.inputs["Transmission Weight"].default_value == 0.0:
            p.inputs["Specular IOR Level"].default_value = 0.0
        if "one_sided" in fixes and m.use_nodes and m.node_tree and m.use_backface_culling:
            one_sided(m)
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.seed = 1
    bounces = max_depth - 1
    c.max_bounces = bounces
    c.diffuse_bounces = bounces
    c.glossy_bounces = bounces
    c.transmission_bounces = bounces
    c.transparent_max_bounces = bounces
    c.volume_bounces = 0
    c.caustics_reflective = True
    c.caustics_refractive = True
    c.blur_glossy = 0.0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    if "light_threshold" in fixes:
        c.light_sampling_threshold = 0.0
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    c.time_limit = 0.0
    scene.render.resolution_x = size
    scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads
    scene.render.film_transparent = False
    if scene.world is None:
        scene.world = bpy.data.worlds.new("black")
    scene.world.use_nodes = True
    bg = scene.world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0, 0, 0, 1)
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    s = scene.render.image_settings
    s.file_format = "OPEN_EXR"
    s.color_depth = "32"
    s.color_mode = "RGB"
    # Albedo and normal for OIDN.
    vl = scene.view_layers[0]
    vl.cycles.denoising_store_passes = False
    return scene


def render(scene, path, spp, adaptive, denoise, args):
    c = scene.cycles
    c.samples = spp
    c.use_adaptive_sampling = adaptive
    if adaptive:
        c.adaptive_threshold = args.threshold
        c.adaptive_min_samples = args.min_spp
    c.use_denoising = denoise
    if denoise:
        c.denoiser = "OPENIMAGEDENOISE"
        c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter = "ACCURATE"
    scene.render.filepath = path
    t = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    return time.perf_counter() - t, read_rgb(path)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--glb", required=True)
    ap.add_argument("--out", help="folder for the EXRs (default: the GLB's)")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--threshold", type=float, default=0.01)
    ap.add_argument("--min-spp", type=int, default=16)
    ap.add_argument("--target", type=float, default=1e-3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--max-spp", type=int, default=1 << 14)
    ap.add_argument("--budget-s", type=float, default=2.0,
                    help="equal time: report the relMSE of the most samples tried that rendered within it")
    ap.add_argument("--denoise", choices=["on", "off"], default="on", help="OIDN in the timed renders")
    ap.add_argument("--compare", help="our reference EXR (clean_frames' NAME_SIZEpx_SPPspp.exr): print region-mean ratios")
    ap.add_argument("--reference-only", action="store_true", help="stop after the reference (and --compare)")
    ap.add_argument("--ours", help="clean_frames' results.json: print the ratio")
    ap.add_argument("--scene", help="the scene's name in --ours (default: the GLB's file name)")
    args = ap.parse_args()
    if not os.path.isfile(args.glb):
        raise SystemExit(f"{args.glb}: no such file (clean_frames writes it into its --out)")
    if args.compare and not os.path.isfile(args.compare):
        raise SystemExit(f"{args.compare}: no such file (clean_frames writes NAME_SIZEpx_SPPspp.exr into its --out)")
    if args.ours and not os.path.isfile(args.ours):
        raise SystemExit(f"{args.ours}: no such file (clean_frames writes results.json into its --out)")
    out = args.out or os.path.dirname(os.path.abspath(args.glb))
    name = args.scene or os.path.splitext(os.path.basename(args.glb))[0]
    os.makedirs(out, exist_ok=True)
    scene = setup(args.glb, args.size, args.threads, args.max_depth)
    ref_path = os.path.join(out, f"{name}_cycles_{args.size}px_{args.ref_spp}spp.exr")
    if os.path.exists(ref_path):
        reference = read_rgb(ref_path)
    else:
        secs, reference = render(scene, ref_path, args.ref_spp, False, False, args)
        print(f"{name}: Cycles reference {args.ref_spp} spp in {secs:.1f} s", flush=True)
    if args.compare:
        compare(reference, read_rgb(args.compare), args.compare)
    if args.reference_only:
        return

    tries = {}
    denoise = args.denoise == "on"
    config = "adaptive+oidn" if denoise else "adaptive"

    def attempt(spp):
        secs, img = render(scene, os.path.join(out, f"{name}_cycles_{spp}.exr"), spp, True, denoise, args)
        e = rel_mse(img, reference)
        tries[spp] = (secs, e)
        print(f"{name}: Cycles {config} {spp} spp: {secs:.2f} s, relMSE {e:.6f}", flush=True)
        return e < args.target

    lo, hi = 0, 16
    while not attempt(hi):
        lo, hi = hi, hi * 2
        if hi > args.max_spp:
            raise SystemExit(f"{name}: relMSE stays above {args.target} up to {args.max_spp} spp")
    # Bisect the sample count (to ~12%) between the last miss and the first hit.
    while lo and hi - lo > max(1, hi // 8):
        mid = (lo + hi) // 2
        if attempt(mid):
            hi = mid
        else:
            lo = mid
    secs, e = tries[hi]
    # Equal time: the most samples tried whose render fit in --budget-s.
    fit = [(n, t, err) for n, (t, err) in tries.items() if t <= args.budget_s]
    equal = max(fit) if fit else None
    result = {"scene": name, "renderer": "cycles", "config": config, "size": args.size,
              "ref_spp": args.ref_spp, "threshold": args.threshold, "min_spp": args.min_spp,
              "target": args.target, "spp_at_quality": hi, "time_to_quality_s": secs, "rel_mse": e,
              "blender": bpy.app.version_string, "budget_s": args.budget_s,
              "equal_time_spp": equal and equal[0], "equal_time_s": equal and equal[1],
              "rel_mse_equal_time": equal and equal[2]}
    if args.ours:
        with open(args.ours) as f:
            ours = [r for r in json.load(f) if r["scene"] == name and r["config"] == config]
        if ours and ours[0].get("time_to_quality_s"):
            result["ours_time_to_quality_s"] = ours[0]["time_to_quality_s"]
            result["ratio_ours_over_cycles"] = ours[0]["time_to_quality_s"] / secs
        if ours:
            result["ours_rel_mse_equal_time"] = ours[0].get("rel_mse_equal_time")
            result["ours_budget_s"] = ours[0].get("budget_s")
    print(json.dumps(result), flush=True)
    with open(os.path.join(out, f"{name}_cycles_{config}.json"), "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
