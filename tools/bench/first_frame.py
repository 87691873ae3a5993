#!/usr/bin/env python3
"""The first F12 after opening a file with a NeRF, with and without Start Worker on Open.

    .venv/bin/python tools/bench/first_frame.py --nerf FOX.ckpt --cameras VIEW.json [--downscale 4] [--repeats 3]

Builds once (in --work) a .blend holding the NeRF (Load NeRF) and a camera at the first frame of
--cameras (its pinhole: Blender's camera has no lens distortion) at that frame's size / --downscale. Then,
alternating, each in a fresh Blender (the bpy module, the add-on registered, its real worker on this
Python), the file opened and:

- cold: F12 at once: the frame waits for the worker's start, the checkpoint's load and numba's first
  run of the frame's kernels, as without the preference (and in `blender -b`);
- prewarmed: what opening the file in Blender's UI does with Start Worker on Open (addon/render/prewarm.py),
  run here explicitly, since background mode skips it; the artist then looks at the scene until the
  worker has loaded the NeRF (`prewarm_s`: how long that takes from opening), then F12.

Each Blender then renders a second F12 (the frame alone on a warm worker). Prints the medians and
writes them as JSON (--json).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def _blender():
    """The bpy module with the add-on registered, its worker on this Python."""
    os.environ.setdefault("NERF_DEFORM_PYTHON", sys.executable)
    import bpy

    import blender_nerf_deform

    blender_nerf_deform.register()
    return bpy


def build(blend: Path, nerf: Path, cameras: Path, downscale: float) -> None:
    """The bench's .blend: the NeRF and a camera at the first frame of `cameras`."""
    bpy = _blender()
    from mathutils import Matrix  # Blender's, importable once bpy is

    bpy.ops.wm.read_factory_settings(use_empty=True)
    meta = json.loads(cameras.read_text())
    frame = meta["frames"][0]
    width = round(float(frame.get("w", meta["w"])) / downscale)
    height = round(float(frame.get("h", meta["h"])) / downscale)
    assert bpy.ops.nerf_deform.load_nerf(filepath=str(nerf)) == {"FINISHED"}
    nerf_obj = bpy.context.active_object
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle_x = meta.get("camera_angle_x") or 2.0 * math.atan(0.5 * float(meta["w"]) / float(meta["fl_x"]))
    camera = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.matrix_world = nerf_obj.matrix_world @ Matrix(frame["transform_matrix"])
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    blend.parent.mkdir(parents=True, exist_ok=True)
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {"FINISHED"}
    from blender_nerf_deform.addon.worker import client as worker_client

    worker_client.shutdown()


def measure(blend: Path, mode: str) -> dict:
    """One fresh Blender: open, [prewarm and wait for it], F12, F12 again."""
    bpy = _blender()
    from blender_nerf_deform.addon.worker import jobs

    opened = time.perf_counter()
    assert bpy.ops.wm.open_mainfile(filepath=str(blend)) == {"FINISHED"}
    result = {"mode": mode, "open_s": time.perf_counter() - opened}
    client = jobs.worker(bpy.context)
    if mode == "prewarmed":
        from blender_nerf_deform.addon.render import prewarm

        prewarm.start(client, prewarm.file_nerfs()).join()
        client.call("info")  # answered after `warm`: the worker serves in order
        result["prewarm_s"] = time.perf_counter() - opened
    for key in ("f12_s", "second_f12_s"):
        start = time.perf_counter()
        assert bpy.ops.render.render() == {"FINISHED"}
        result[key] = time.perf_counter() - start
    client.drain()
    from blender_nerf_deform.addon.worker import client as worker_client

    worker_client.shutdown()
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nerf", type=Path, required=True, help="a NeRF checkpoint")
    parser.add_argument("--cameras", type=Path, required=True, help="a transforms.json: its first frame is the view")
    parser.add_argument("--downscale", type=float, default=1.0, help="the frame's size divided by this (default 1)")
    parser.add_argument("--repeats", type=int, default=3, help="fresh Blenders per mode (default 3)")
    parser.add_argument(
        "--work", type=Path, default=REPO / "runs" / "bench_first_frame", help="where the .blend is made"
    )
    parser.add_argument(
        "--modes",
        nargs="+",
        choices=("cold", "prewarmed"),
        default=["cold", "prewarmed"],
        help="what to measure (default both; an add-on before Start Worker on Open has only cold)",
    )
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--child", choices=("build", "cold", "prewarmed"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    blend = (args.work / "first_frame.blend").resolve()
    if args.child == "build":
        build(blend, args.nerf.resolve(), args.cameras, args.downscale)
        return 0
    if args.child:
        print("RESULT " + json.dumps(measure(blend, args.child)), flush=True)
        return 0
    for path in (args.nerf, args.cameras):
        if not path.is_file():
            parser.error(f"{path}: no such file")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")

    def child(kind: str) -> dict | None:
        cmd = [
            sys.executable,
            __file__,
            "--nerf",
            str(args.nerf),
            "--cameras",
            str(args.cameras),
            "--downscale",
            str(args.downscale),
            "--work",
            str(args.work),
            "--child",
            kind,
        ]
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"{kind} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        return json.loads(lines[-1][len("RESULT ") :]) if lines else None

    child("build")
    runs = []
    for _ in range(args.repeats):
        for mode in args.modes:
            runs.append(child(mode))
            print(json.dumps(runs[-1]), flush=True)
    summary = {}
    for mode in args.modes:
        mine = [r for r in runs if r["mode"] == mode]
        summary[mode] = {k: statistics.median(r[k] for r in mine) for k in mine[0] if k != "mode"}
        print(f"{mode:10s} " + ", ".join(f"{k} {v:.2f}" for k, v in summary[mode].items()))
    if args.json:
        args.json.write_text(json.dumps({"runs": runs, "median": summary}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
