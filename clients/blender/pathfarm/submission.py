"""One submission: upload the exported scene, submit its frames, follow them, download the EXRs.

The HTTP runs in a thread (`Submission.start`); Blender's main thread only reads `snapshot()`
from a timer, so the UI never waits on the network. No bpy here.

Frame ranges: one sequence job (`frames`, e.g. "1-24", with `fps`): the farm renders the frames
in order, writes each as it finishes, and the submission downloads each frame's EXR
(`/jobs/{id}/frames/{n}/image.exr`) as soon as the job lists it done. A single frame is a plain
job with `frame` set, whose image is `/jobs/{id}/image.exr`.
"""

import os
import threading
import time

from .api import PathfarmError

FINISHED = ("completed", "failed", "cancelled")


def frame_path(out_dir, name, frame):
    """`NAME_0001.exr`: Blender reads a folder of these as one image sequence."""
    return os.path.join(out_dir, f"{name}_{frame:04d}.exr")


def frame_spec(frames):
    """The job's `frames` string: runs of consecutive frames as ranges ("1-24", "1-3,7")."""
    frames = sorted(set(int(f) for f in frames))
    runs, start, prev = [], frames[0], frames[0]
    for f in frames[1:] + [None]:
        if f is not None and f == prev + 1:
            prev = f
            continue
        runs.append(f"{start}" if start == prev else f"{start}-{prev}")
        if f is not None:
            start = prev = f
    return ",".join(runs)


def submit_frames(client, scene_id, job, frames):
    """Submits `job` (a `POST /jobs` body without `scene_id`/`frame`) for `frames`: one job, a
    sequence when there are several. Returns the job id."""
    body = dict(job, scene_id=scene_id)
    if len(frames) == 1:
        body["frame"] = int(frames[0])
    else:
        body["frames"] = frame_spec(frames)
    return client.submit(body)


class Submission:
    """`scene`: the .glb bytes; `job`: the job body (settings, name, priority); `frames`: frame
    numbers; EXRs go to `out_dir` as `name_####.exr`."""

    def __init__(self, client, scene, job, frames, out_dir, name, poll_s=0.5):
        self.client = client
        self.scene = scene
        self.job = job
        self.frames = list(frames)
        self.out_dir = out_dir
        self.name = name
        self.poll_s = poll_s
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._state = {
            "status": "exporting",
            "progress": 0.0,
            "jobs": [],
            "done": [],
            "error": None,
            "finished": False,
        }
        self._thread = None

    def start(self):
        self._thread = threading.Thread(target=self._run, name="pathfarm-submission", daemon=True)
        self._thread.start()
        return self

    def cancel(self):
        self._cancel.set()

    def snapshot(self):
        """A copy of the state: status text, progress 0..1, job ids, finished frames
        `[(frame, path)]`, error (text for the artist) and whether the thread is done."""
        with self._lock:
            s = dict(self._state)
            s["jobs"] = list(s["jobs"])
            s["done"] = list(s["done"])
            return s

    def wait(self, timeout=None):
        if self._thread is not None:
            self._thread.join(timeout)
        return self.snapshot()

    def _set(self, **kw):
        with self._lock:
            self._state.update(kw)

    def _run(self):
        try:
            self._set(status=f"uploading the scene ({len(self.scene) / 1e6:.1f} MB)")
            created = self.client.upload_scene(self.scene)
            self._set(status="submitting")
            job_id = submit_frames(self.client, created["scene_id"], self.job, self.frames)
            self._set(jobs=[job_id], status=f"job {job_id} queued")
            self._follow(job_id)
        except PathfarmError as e:
            self._set(error=str(e), status="failed")
        except Exception as e:  # noqa: BLE001 - anything else still reaches the artist in words
            self._set(error=f"pathfarm submission failed: {type(e).__name__}: {e}", status="failed")
        finally:
            self._set(finished=True)

    def _follow(self, job_id):
        os.makedirs(self.out_dir, exist_ok=True)
        sequence = len(self.frames) > 1
        pending = set(int(f) for f in self.frames)
        total = len(pending)
        while True:
            if self._cancel.is_set():
                try:
                    self.client.cancel(job_id)
                except PathfarmError:
                    pass
                raise PathfarmError(f"pathfarm: submission cancelled; job {job_id} was cancelled")
            info = self.client.job(job_id)
            state = info.get("state")
            if state in FINISHED and state != "completed":
                why = info.get("error") or state
                raise PathfarmError(f"pathfarm job {job_id} {state}: {why}")
            if sequence:
                ready = [f["frame"] for f in self.client.frames(job_id) if f["state"] == "done" and f["frame"] in pending]
            else:
                ready = list(pending) if state == "completed" else []
            for frame in sorted(ready):
                data = self.client.frame_exr(job_id, frame) if sequence else self.client.image_exr(job_id)
                path = frame_path(self.out_dir, self.name, frame)
                tmp = path + ".part"
                with open(tmp, "wb") as f:
                    f.write(data)
                os.replace(tmp, path)
                pending.discard(frame)
                with self._lock:
                    self._state["done"].append((frame, path))
            progress = float(info.get("progress", 0.0))
            self._set(progress=progress,
                      status=f"rendering: {progress:.0%}, {total - len(pending)}/{total} frames done")
            if not pending:
                break
            time.sleep(self.poll_s)
        self._set(progress=1.0, status=f"done: {total} frame(s) in {self.out_dir}")
