"""One submission: upload the exported scene, submit its frames, follow them, download the EXRs.

The HTTP runs in a thread (`Submission.start`); Blender's main thread only reads `snapshot()`
from a timer, so the UI never waits on the network. No bpy here.

Frame ranges: one job per frame, each with `frame` and `fps` set (`submit_frames`). When the
coordinator's job body gains a `frames` field this is the one function to switch.
"""

import os
import threading
import time

from .api import PathfarmError

FINISHED = ("completed", "failed", "cancelled")


def frame_path(out_dir, name, frame):
    """`NAME_0001.exr`: Blender reads a folder of these as one image sequence."""
    return os.path.join(out_dir, f"{name}_{frame:04d}.exr")


def submit_frames(client, scene_id, job, frames):
    """Submits `job` (a `POST /jobs` body without `scene_id`/`frame`) for every frame in
    `frames`; returns `[(frame, job_id)]`."""
    ids = []
    for f in frames:
        body = dict(job, scene_id=scene_id, frame=int(f))
        if len(frames) > 1:
            body["name"] = f"{job.get('name', 'blender')} frame {f}"
        ids.append((f, client.submit(body)))
    return ids


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
            jobs = submit_frames(self.client, created["scene_id"], self.job, self.frames)
            self._set(jobs=[j for _, j in jobs], status=f"job {jobs[0][1]} queued")
            self._follow(jobs)
        except PathfarmError as e:
            self._set(error=str(e), status="failed")
        except Exception as e:  # noqa: BLE001 - anything else still reaches the artist in words
            self._set(error=f"pathfarm submission failed: {type(e).__name__}: {e}", status="failed")
        finally:
            self._set(finished=True)

    def _follow(self, jobs):
        os.makedirs(self.out_dir, exist_ok=True)
        pending = dict(jobs)  # frame -> job id
        progress = {f: 0.0 for f in pending}
        while pending:
            if self._cancel.is_set():
                for job_id in pending.values():
                    try:
                        self.client.cancel(job_id)
                    except PathfarmError:
                        pass
                raise PathfarmError("pathfarm: submission cancelled; its jobs were cancelled")
            for frame, job_id in list(pending.items()):
                info = self.client.job(job_id)
                progress[frame] = float(info.get("progress", 0.0))
                state = info.get("state")
                if state in FINISHED:
                    if state != "completed":
                        why = info.get("error") or state
                        raise PathfarmError(f"pathfarm job {job_id} (frame {frame}) {state}: {why}")
                    path = frame_path(self.out_dir, self.name, frame)
                    tmp = path + ".part"
                    with open(tmp, "wb") as f:
                        f.write(self.client.image_exr(job_id))
                    os.replace(tmp, path)
                    del pending[frame]
                    with self._lock:
                        self._state["done"].append((frame, path))
            total = sum(progress.values()) / max(len(progress), 1)
            n_done = len(jobs) - len(pending)
            self._set(progress=total, status=f"rendering: {total:.0%}, {n_done}/{len(jobs)} frames done")
            if pending:
                time.sleep(self.poll_s)
        self._set(progress=1.0, status=f"done: {len(jobs)} frame(s) in {self.out_dir}")
