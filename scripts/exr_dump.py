#!/usr/bin/env python3
"""Dump every channel of an OpenEXR file as JSON, read with the independent `OpenEXR` package.

Usage: exr_dump.py FILE.exr  ->  {"width": W, "height": H, "channels": {"R": [...], ...}}
Used by the tests to check that our EXR files open in another reader with the same values.
"""
import json
import sys

import numpy as np
import OpenEXR


def main() -> None:
    with OpenEXR.File(sys.argv[1], separate_channels=True) as f:
        channels = f.channels()
        out = {"channels": {}}
        for name, ch in channels.items():
            px = np.asarray(ch.pixels)
            out["height"], out["width"] = int(px.shape[0]), int(px.shape[1])
            out["channels"][name] = {
                "dtype": str(px.dtype),
                # float32 -> Python float is exact, so values compare bit for bit.
                "values": [float(v) if np.isfinite(v) else str(v) for v in px.astype(np.float32).ravel()],
            }
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
