#!/usr/bin/env python3
"""Capture Dataset's time on the demo scene, against tools/make_dataset.py's code run in-process.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/capture.py [--views 100] [--test-views 8] \
        [--size 200] [--samples 16] [--work DIR]

The demo's dataset settings (tools/demo.py: 100 views of 200 px + 8 test views, radius 4, seed 0,
Cycles on the CPU with 16 samples) on the demo's scene (tools/default_scene.py), made twice in
one run, one after the other:

  operator    `bpy.ops.nerf_deform.capture_dataset(engine="CYCLES", ...)` with the scene's three
              objects selected: the execute path (blocking), so the copy of the file, the start
              of a second Blender (the bpy module's Python) that opens it, the renders and the
              swap into place are all counted;
  in-process  `make_dataset(blend=None, ...)` (what tools/make_dataset.py runs) on the scene loaded
              in this process, with the operator's target (the selection's centre) and box.

Prints both times, the ratio, and the largest pixel difference between the two datasets (the
same code and Cycles seed: they should be the same images).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", type=int, default=100)
    p.add_argument("--test-views", type=int, default=8)
    p.add_argument("--size", type=int, default=200)
    p.add_argument("--samples", type=int, default=16)
    p.add_argument(
        "--work", type=Path, default=None, help="folder for the scene and datasets (default: a temporary one)"
    )
    args = p.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_capture_"))
    work.mkdir(parents=True, exist_ok=True)

    import bpy  # noqa: PLC0415

    from PIL import Image  # noqa: PLC0415

    import blender_nerf_deform  # noqa: PLC0415
    from tools.default_scene import save  # noqa: PLC0415
    from tools.make_dataset import make_dataset  # noqa: PLC0415

    save(work / "scene.blend", bpy)
    blender_nerf_deform.register()
    try:
        bpy.ops.object.select_all(action="DESELECT")
        objects = [o for o in bpy.context.scene.objects if o.type == "MESH"]
        for obj in objects:
            obj.select_set(True)
        bpy.context.view_layer.objects.active = objects[0]
        total = args.views + args.test_views
        common = dict(count=args.views, test_count=args.test_views, radius=4.0, seed=0, samples=args.samples)

        t0 = time.perf_counter()
        result = bpy.ops.nerf_deform.capture_dataset(
            output=str(work / "operator"), resolution=(args.size, args.size), engine="CYCLES", **common
        )
        operator_s = time.perf_counter() - t0
        assert result == {"FINISHED"}, result
        meta = json.loads((work / "operator" / "transforms.json").read_text())
        gen = meta["generator"]

        t0 = time.perf_counter()
        make_dataset(
            work / "in_process",
            blend=None,
            progress=None,
            resolution=args.size,
            target=tuple(gen["target"]),
            aabb=tuple(map(tuple, meta["aabb"])),
            **common,
        )
        in_process_s = time.perf_counter() - t0
    finally:
        blender_nerf_deform.unregister()

    worst = 0
    for split in ("", "test"):
        for frame in json.loads((work / "operator" / split / "transforms.json").read_text())["frames"]:
            a, b = (
                np.asarray(Image.open(work / run / split / frame["file_path"]), dtype=np.int16)
                for run in ("operator", "in_process")
            )
            worst = max(worst, int(np.abs(a - b).max()))
    print(
        f"scene: {[o.name for o in objects]}, {total} views ({args.views} + {args.test_views} test) of "
        f"{args.size} px, Cycles CPU {args.samples} samples, radius 4, seed 0"
    )
    print(f"operator (Capture Dataset, execute):  {operator_s:.1f} s  ({operator_s / total:.3f} s/view)")
    print(f"in-process (make_dataset):            {in_process_s:.1f} s  ({in_process_s / total:.3f} s/view)")
    print(f"ratio operator / in-process:          {operator_s / in_process_s:.3f}")
    print(f"largest pixel difference between the two datasets: {worst} (of 255)")
    print(f"work folder: {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
