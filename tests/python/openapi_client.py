"""A client generated from the coordinator's OpenAPI document works: openapi-python-client
generates it, then it uploads a scene (binary body), submits a job, waits for it, and downloads
the EXR (binary response), which must equal `pathfarm-worker render` of the same scene and
settings bit for bit.

    python3 tests/python/openapi_client.py --url URL --token CLIENT_TOKEN --scene cornell.glb \
        --worker target/release/pathfarm-worker --out DIR

The generator maps `image/x-exr` and `image/png` to bytes through its documented
`content_type_overrides` (it reads only application/octet-stream as binary by itself). Prints
PASS; any failed check raises.
"""

import argparse
import importlib
import json
import os
import subprocess
import sys
import time
import urllib.request

W, H, SPP = 40, 32, 4


def main():
    ap = argparse.ArgumentParser()
    for a in ("--url", "--token", "--scene", "--worker", "--out"):
        ap.add_argument(a, required=True)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    doc = os.path.join(args.out, "openapi.json")
    with urllib.request.urlopen(args.url + "/api/v1/openapi.json", timeout=30) as r, open(doc, "wb") as f:
        f.write(r.read())
    config = os.path.join(args.out, "config.yml")
    with open(config, "w") as f:
        f.write("content_type_overrides:\n  image/x-exr: application/octet-stream\n  image/png: application/octet-stream\n")
    gen = subprocess.run(
        ["openapi-python-client", "generate", "--path", doc, "--output-path", os.path.join(args.out, "pathfarm_api"),
         "--meta", "none", "--config", config, "--overwrite"],
        capture_output=True, text=True,
    )
    assert gen.returncode == 0, gen.stdout + gen.stderr
    for needed in ("upload_scene", "create_job", "get_job", "job_exr"):
        assert needed not in gen.stdout, f"the generator skipped {needed}:\n{gen.stdout}"
    sys.path.insert(0, args.out)
    api = importlib.import_module("pathfarm_api")
    upload_scene = importlib.import_module("pathfarm_api.api.scenes.upload_scene")
    create_job = importlib.import_module("pathfarm_api.api.jobs.create_job")
    get_job = importlib.import_module("pathfarm_api.api.jobs.get_job")
    job_exr = importlib.import_module("pathfarm_api.api.images.job_exr")
    models = importlib.import_module("pathfarm_api.models")
    types = importlib.import_module("pathfarm_api.types")

    client = api.AuthenticatedClient(base_url=args.url, token=args.token, raise_on_unexpected_status=True)
    with open(args.scene, "rb") as f:
        scene = f.read()
    created = upload_scene.sync(client=client, body=types.File(payload=scene, file_name="scene.glb"))
    assert isinstance(created, models.SceneCreated), created
    body = models.JobRequestBody.from_dict(
        {"scene_id": created.scene_id, "name": "generated client", "width": W, "height": H, "spp": SPP,
         "integrator": {"type": "path", "max_depth": 5}}
    )
    job = create_job.sync(client=client, body=body)
    assert isinstance(job, models.JobCreated), job
    t0 = time.time()
    while True:
        info = get_job.sync(client=client, id=job.id)
        assert isinstance(info, models.JobInfo), info
        if info.state.value in ("completed", "failed", "cancelled"):
            break
        assert time.time() - t0 < 120, f"job {job.id} not finished in 120 s: {info.state}"
        time.sleep(0.2)
    assert info.state.value == "completed", f"job {job.id} {info.state.value}: {info.error}"
    exr = job_exr.sync(client=client, id=job.id)
    assert isinstance(exr, types.File), exr
    farm = exr.payload.read()

    local_path = os.path.join(args.out, "local.exr")
    subprocess.run(
        [args.worker, "render", args.scene, "--width", str(W), "--height", str(H), "--spp", str(SPP),
         "--integrator", "path", "--max-depth", "5", "--threads", "1", "--out", local_path],
        check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    with open(local_path, "rb") as f:
        local = f.read()
    assert farm == local, f"the EXR from the generated client ({len(farm)} bytes) differs from a local render"
    print(json.dumps({"job": job.id, "exr_bytes": len(farm), "scene_id": created.scene_id}), flush=True)
    print("PASS", flush=True)


if __name__ == "__main__":
    main()
