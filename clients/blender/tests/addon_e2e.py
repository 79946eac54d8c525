"""The add-on in real Blender (bpy), against a real coordinator and worker the caller started.

    BLENDER_USER_RESOURCES=TMP python3 clients/blender/tests/addon_e2e.py \
        --url http://127.0.0.1:PORT --token CLIENT_TOKEN --worker target/release/pathfarm-worker --out DIR

1. Installs the add-on as Blender installs extensions (a zip of clients/blender/pathfarm through
   `extensions.package_install_files`) and enables it.
2. Builds the test box, submits the current frame with the Submit operator, waits (Blender as a
   module has no event loop, so the operator waits for its thread), and checks the image it
   loaded: its file is bit for bit the EXR `pathfarm-worker render` makes of the GLB the add-on's
   exporter writes, with the same settings, and Blender reads its pixels.
3. Animates the point light over frames 1-3 and submits the range: three EXRs come back, each
   equal to a local render of its frame, loaded as one image sequence (source SEQUENCE, its file frame 1's).
4. A job over the coordinator's limits (422) and a wrong token (401): the operator fails with
   the coordinator's message and words about the token, nothing loaded.

Prints PASS at the end; any failed check raises (exit 1).
"""

import argparse
import os
import subprocess

import sys
import tempfile
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
CLIENT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import bpy  # noqa: E402

import testscene  # noqa: E402

W, H, SPP = 40, 32, 8


def install_addon(tmp):
    zpath = os.path.join(tmp, "pathfarm.zip")
    with zipfile.ZipFile(zpath, "w") as z:
        root = os.path.join(CLIENT, "pathfarm")
        for dirpath, dirnames, files in os.walk(root):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            for f in files:
                full = os.path.join(dirpath, f)
                z.write(full, os.path.join("pathfarm", os.path.relpath(full, root)))
    result = bpy.ops.extensions.package_install_files(filepath=zpath, repo="user_default", enable_on_install=True)
    assert result == {"FINISHED"}, result
    names = [m for m in bpy.context.preferences.addons.keys() if m.endswith(".pathfarm")]
    assert names, f"the add-on is not enabled: {list(bpy.context.preferences.addons.keys())}"
    return names[0]


def renders_frames(worker):
    """Whether this `pathfarm-worker render` takes `--frame` (glTF animation)."""
    out = subprocess.run([worker, "render", "--help"], check=True, capture_output=True, text=True, env=testscene.worker_env()).stdout
    return "--frame" in out


def local_render(worker, glb, out, frame):
    cmd = [worker, "render", glb, "--width", str(W), "--height", str(H), "--spp", str(SPP), "--seed", "0"]
    cmd += ["--integrator", "path", "--max-depth", "6", "--threads", "1", "--out", out]
    if frame is not None and renders_frames(worker):
        cmd += ["--frame", str(frame), "--fps", "24"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=testscene.worker_env())
    with open(out, "rb") as f:
        return f.read()


def blender_rgb(image, w, h):
    """The image's colour as Blender decodes it: an image texture (its ImageUser on the first
    layer and pass, R, G, B) evaluated at every pixel centre, rows top to bottom."""
    tex = bpy.data.textures.new("pathfarm-test", "IMAGE")
    tex.image = image
    tex.use_interpolation = False
    tex.use_mipmap = False
    tex.filter_type = "BOX"
    tex.filter_size = 0.1
    tex.extension = "EXTEND"
    rows = []
    for r in range(h):
        y = (h - r - 0.5) / h * 2.0 - 1.0
        rows.append([tuple(tex.evaluate(((c + 0.5) / w * 2.0 - 1.0, y, 0.0)))[:3] for c in range(w)])
    bpy.data.textures.remove(tex)
    return rows


def exr_rgb(path):
    import OpenEXR

    with OpenEXR.File(path) as f:
        return f.channels()["RGB"].pixels


def configure(scene, out_dir, animation):
    s = scene.pathfarm
    bpy.ops.pathfarm.sync()
    s.integrator = "path"
    s.max_depth = 6
    s.samples = SPP
    s.width, s.height = W, H
    s.animation = animation
    s.output_dir = out_dir


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--token", required=True)
    ap.add_argument("--worker", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    tmp = tempfile.mkdtemp(dir=args.out)

    module = install_addon(tmp)
    prefs = bpy.context.preferences.addons[module].preferences
    prefs.coordinator_url = args.url
    prefs.client_token = args.token
    from importlib import import_module

    export = import_module(module + ".export")
    assert bpy.ops.pathfarm.check() == {"FINISHED"}, "Check connection failed"
    print("installed and enabled", module, flush=True)

    # 2. One frame.
    scene = testscene.cornell(size=(W, H))
    configure(scene, os.path.join(args.out, "still"), animation=False)
    assert bpy.ops.pathfarm.submit() == {"FINISHED"}
    image = bpy.data.images[f"pathfarm_{scene.name}"]
    path = bpy.path.abspath(image.filepath)
    with open(path, "rb") as f:
        farm = f.read()
    glb = os.path.join(tmp, "still.glb")
    scene.render.resolution_x, scene.render.resolution_y = W, H
    export.export_glb(glb, animation=False)
    local = local_render(args.worker, glb, os.path.join(tmp, "still_local.exr"), None)
    assert farm == local, f"the farm's EXR {path} ({len(farm)} bytes) differs from a local render ({len(local)} bytes)"
    # Blender recognized our EXR's layers (colour, albedo, normal, depth, samples, variance): the
    # Image Editor shows them by layer and pass.
    image.size[:]  # reads the file's header
    assert image.type == "MULTILAYER", image.type
    # And decodes the colour layer: Blender's texture sampling of it equals the EXR's float
    # pixels (read by OpenEXR) to 1e-5 relative (the sampler's arithmetic; the file is bit-exact).
    expected = exr_rgb(path)
    got = blender_rgb(image, W, H)
    worst = max(
        abs(got[r][c][k] - float(expected[r, c, k])) / max(abs(float(expected[r, c, k])), 1e-3)
        for r in range(H)
        for c in range(W)
        for k in range(3)
    )
    assert worst < 1e-5, f"Blender decodes the EXR differently: worst relative difference {worst}"
    assert max(v for row in got for px in row for v in px) > 0.0, "Blender sees a black image"
    print(f"still: {path} equals the local render bit for bit ({len(farm)} bytes)", flush=True)

    # 3. Three frames of an animation.
    scene = testscene.cornell(size=(W, H))
    testscene.animate_point_light((1, 3))
    configure(scene, os.path.join(args.out, "anim"), animation=True)
    assert (scene.pathfarm.frame_start, scene.pathfarm.frame_end) == (1, 3)
    assert bpy.ops.pathfarm.submit() == {"FINISHED"}
    image = bpy.data.images[f"pathfarm_{scene.name}"]
    assert image.source == "SEQUENCE", image.source
    glb = os.path.join(tmp, "anim.glb")
    export.export_glb(glb, animation=True)
    frames = []
    for frame in (1, 2, 3):
        path = os.path.join(args.out, "anim", f"pathfarm_{scene.name}_{frame:04d}.exr")
        with open(path, "rb") as f:
            farm = f.read()
        local = local_render(args.worker, glb, os.path.join(tmp, f"anim_local_{frame}.exr"), frame)
        assert farm == local, f"frame {frame}: the farm's EXR differs from a local render"
        frames.append(farm)
    if renders_frames(args.worker):
        assert frames[0] != frames[2], "the animation did not move the light"
    else:
        print("this pathfarm-worker has no --frame (no glTF animation): frames not compared", flush=True)
    # Blender's sequence: the first frame's file; frames 2 and 3 are found by their numbers.
    first = os.path.join(args.out, "anim", f"pathfarm_{scene.name}_0001.exr")
    assert os.path.samefile(bpy.path.abspath(image.filepath), first), image.filepath
    print("animation: 3 frames, each equal to a local render of its frame; one image sequence", flush=True)

    # 4. The coordinator's refusals, in words: a job over its limits (422, its message), a wrong
    # token (401).
    def refusal():
        before = len(bpy.data.images)
        try:
            bpy.ops.pathfarm.submit()
        except RuntimeError as e:
            assert len(bpy.data.images) == before, "an image was loaded after a failed submission"
            return str(e).strip()
        raise AssertionError("the submission succeeded")

    scene.pathfarm.samples = (1 << 20) + 1
    message = refusal()
    assert "422" in message and "spp" in message, message
    print(f"too many samples: {message}", flush=True)
    scene.pathfarm.samples = SPP
    prefs.client_token = "not-the-token"
    message = refusal()
    assert "client token" in message and "401" in message, message
    print(f"bad token: {message}", flush=True)
    try:
        bpy.ops.pathfarm.check()
    except RuntimeError as e:
        assert "client token" in str(e), e
    else:
        raise AssertionError("Check connection passed with a wrong token")
    print("PASS", flush=True)


if __name__ == "__main__":
    main()
