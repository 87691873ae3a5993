#!/usr/bin/env python3
"""Benchmark: the peak memory of one frame per pixel, what `renderer.FRAME_BYTES_PER_PIXEL` is set from.

Renders one camera of the NeRF's box at two sizes with the `render` command, each in its own process
(peak RSS from the kernel), and prints the difference per pixel: the frame's outputs, its tile order and
the PNG's copy, without the process's start-up.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/frame_memory.py --nerf RUN/nerf.ckpt [--sizes 500 3000]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def peak_rss(nerf: str, size: int, folder: Path) -> int:
    """Peak RSS in bytes of `render` of one size x size frame looking at the origin from +Y."""
    cams = folder / f"cams_{size}.json"
    c2w = [[1, 0, 0, 0], [0, 0, 1, 4], [0, -1, 0, 0], [0, 0, 0, 1]]  # at (0, 4, 0), looking down -Y
    cams.write_text(
        json.dumps(
            {
                "camera_angle_x": 0.69,
                "w": size,
                "h": size,
                "frames": [{"file_path": "./frame", "transform_matrix": c2w}],
            }
        )
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "blender_nerf_deform.engine",
            "render",
            "--nerf",
            nerf,
            "--cameras",
            str(cams),
            "--out",
            str(folder / f"out_{size}"),
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    err = proc.stderr.read().decode(errors="replace")
    if status != 0:
        raise SystemExit(f"render of {size}x{size} failed: {err.strip().splitlines()[-1:]}")
    return usage.ru_maxrss * 1024


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nerf", required=True)
    ap.add_argument("--sizes", type=int, nargs=2, default=[500, 3000])
    args = ap.parse_args()
    small, large = args.sizes
    with tempfile.TemporaryDirectory() as tmp:
        a, b = peak_rss(args.nerf, small, Path(tmp)), peak_rss(args.nerf, large, Path(tmp))
    per_pixel = (b - a) / (large**2 - small**2)
    print(
        f"peak RSS {small}x{small}: {a / 2**20:.0f} MiB; {large}x{large}: {b / 2**20:.0f} MiB; "
        f"{per_pixel:.0f} bytes per pixel"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
