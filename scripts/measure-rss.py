#!/usr/bin/env python3
"""Peak RSS (VmHWM) of the real coordinator binary in three cases (issue 17):

  a) one 3840x2160 job, leased and merged by simulated workers (`coordinator/examples/load.rs`);
  b) 100 queued 1920x1080 jobs, no worker;
  c) a restart of a coordinator holding both (the finished 4K job and the 100 queued jobs).

Each case is its own coordinator process, so each VmHWM is that case's alone.

    cargo build --release -p pathfarm-coordinator --bins --example load
    scripts/measure-rss.py [--coordinator target/release/pathfarm-coordinator] [--load target/release/examples/load]

`--coordinator` may name another build (e.g. one of an older commit) to compare; the load tool
only speaks HTTP to it.
"""

import argparse
import json
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request

ROOT = pathlib.Path(__file__).resolve().parent.parent
API = "/api/v1"


def hwm_mib(pid):
    """VmHWM (peak resident set) of `pid` in MiB."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM")


class Coordinator:
    def __init__(self, binary, data_dir, extra=()):
        self.data_dir = pathlib.Path(data_dir)
        addr_file = self.data_dir / "coordinator.addr"
        if addr_file.exists():
            addr_file.unlink()
        self.proc = subprocess.Popen(
            [binary, "--listen", "127.0.0.1:0", "--no-auth", "--register-per-minute", "0",
             "--lease-timeout-ms", "60000", "--data-dir", str(self.data_dir), *extra],
            env={**os.environ, "RUST_LOG": "warn"},
        )
        t0 = time.time()
        while not (addr_file.exists() and addr_file.read_text().strip()):
            if self.proc.poll() is not None:
                raise RuntimeError(f"the coordinator exited with {self.proc.returncode}")
            if time.time() - t0 > 120:
                raise RuntimeError("the coordinator did not start")
            time.sleep(0.05)
        self.url = "http://" + addr_file.read_text().strip()

    def request(self, method, path, body=None, content_type="application/json"):
        data = json.dumps(body).encode() if isinstance(body, dict) else body
        req = urllib.request.Request(self.url + API + path, data=data, method=method)
        if data is not None:
            req.add_header("Content-Type", content_type)
        with urllib.request.urlopen(req, timeout=120) as r:
            return json.loads(r.read() or b"null")

    def hwm(self):
        return hwm_mib(self.proc.pid)

    def stop(self):
        """SIGTERM: the coordinator checkpoints and exits."""
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=300)


def case_4k(args, data_dir):
    c = Coordinator(args.coordinator, data_dir)
    try:
        out = subprocess.run(
            [args.load, "--url", c.url, "--workers", str(args.workers), "--width", "3840", "--height", "2160",
             "--tile", "64", "--spp", str(args.spp)],
            check=True, capture_output=True, text=True,
        )
        sys.stderr.write(out.stderr[-2000:])
        time.sleep(args.settle)  # final output and checkpoint
        return c.hwm()
    finally:
        c.stop()


def queue_jobs(c, n):
    scene = c.request("POST", "/scenes", (ROOT / "reference" / "cornell_mitsuba.glb").read_bytes(),
                      "application/octet-stream")["scene_id"]
    for _ in range(n):
        c.request("POST", "/jobs", {"scene_id": scene, "width": 1920, "height": 1080, "spp": 16, "tile_size": 64})


def case_queued(args, data_dir):
    c = Coordinator(args.coordinator, data_dir)
    try:
        queue_jobs(c, args.jobs)
        time.sleep(args.settle)  # checkpoint loop, output loop
        return c.hwm()
    finally:
        c.stop()


def case_restart(args, data_dir):
    """`data_dir` holds the finished 4K job; 100 queued jobs are added, then a fresh process
    restores both."""
    c = Coordinator(args.coordinator, data_dir)
    try:
        queue_jobs(c, args.jobs)
        time.sleep(args.settle)
    finally:
        c.stop()
    c = Coordinator(args.coordinator, data_dir)
    try:
        time.sleep(args.settle)
        jobs = c.request("GET", "/jobs?limit=500")
        n = len(jobs) if isinstance(jobs, list) else len(jobs.get("jobs", []))
        return c.hwm(), n
    finally:
        c.stop()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    target = pathlib.Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target")) / "release"
    p.add_argument("--coordinator", default=str(target / "pathfarm-coordinator"))
    p.add_argument("--load", default=str(target / "examples" / "load"))
    p.add_argument("--workers", type=int, default=8)
    p.add_argument("--spp", type=int, default=4, help="passes of the 4K job (1 spp each)")
    p.add_argument("--jobs", type=int, default=100)
    p.add_argument("--settle", type=float, default=4.0, help="seconds to wait for the loops")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as d:
        d = pathlib.Path(d)
        a = case_4k(args, d / "a")
        print(f"a) 3840x2160 job, {args.workers} workers, {args.spp} passes: peak RSS {a:.0f} MiB", flush=True)
        b = case_queued(args, d / "b")
        print(f"b) {args.jobs} queued 1920x1080 jobs: peak RSS {b:.0f} MiB", flush=True)
        c, n = case_restart(args, d / "a")
        print(f"c) restart holding the 4K job and {args.jobs} queued jobs ({n} jobs listed): peak RSS {c:.0f} MiB",
              flush=True)


if __name__ == "__main__":
    main()
