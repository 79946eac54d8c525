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
"""
import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "..", "reference", "cornell_mitsuba_box_16384spp.exr")


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

    scene_dict = mi.cornell_box()
    scene_dict["sensor"]["film"]["width"] = args.res
    scene_dict["sensor"]["film"]["height"] = args.res
    scene_dict["sensor"]["film"]["rfilter"] = {"type": "box"}
    scene_dict["integrator"] = {"type": "path", "max_depth": args.max_depth}
    scene = mi.load_dict(scene_dict)

    passes = args.spp // args.spp_per_pass
    times = []
    image = None
    for repeat in range(max(1, args.repeats)):
        acc = np.zeros((args.res, args.res, 3), dtype=np.float64)
        t0 = time.perf_counter()
        for p in range(passes):
            img = mi.render(scene, spp=args.spp_per_pass, seed=args.seed + p)
            dr.eval(img)
            dr.sync_thread()
            acc += np.array(img, dtype=np.float64)
            if passes > 1:
                print(f"pass {p + 1}/{passes}: {time.perf_counter() - t0:.1f} s", flush=True)
        times.append(time.perf_counter() - t0)
        if image is None:
            image = (acc / passes).astype(np.float32)
    seconds = sorted(times)[len(times) // 2]

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    bitmap = mi.Bitmap(image, mi.Bitmap.PixelFormat.RGB)
    bitmap.write(args.out)
    meta = {
        "renderer": "mitsuba",
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
        "mean_rgb": [float(x) for x in image.reshape(-1, 3).mean(axis=0)],
    }
    with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
        json.dump(meta, f, indent=1)
        f.write("\n")
    print("RESULT " + json.dumps(meta), flush=True)


if __name__ == "__main__":
    main()
