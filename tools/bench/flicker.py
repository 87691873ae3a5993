#!/usr/bin/env python3
"""Benchmark (issue 18): does a slow bent animation flicker? Temporal differences of consecutive frames.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/flicker.py [--demo demo_out] \\
        [--frames 48] [--orbit-degrees 20] [--work /work/runs/flicker]

Needs `make demo`'s output (demo_out/demo.blend, its checkpoint, cage and the extension installed
into demo_out/blender_user). Two animations of the same length, rendered as `blender -b -a` does
(a fresh Blender with the extension enabled, Render Animation through the "NeRF Deform" engine),
from demo.blend opened in memory (nothing in demo_out is written):

  bend   the demo's bend, retimed to span --frames frames (its two keyframes moved to 1 and N,
         the same Bezier ease in and out), from the demo's fixed camera;
  orbit  the rest pose (the handles held at their frame-1 keyframes), the camera turned about the
         vertical axis through the demo's camera target by --orbit-degrees over the same frames
         (keyed every frame on the circle, eased in and out by a smoothstep): an undeformed
         animation whose picture changes as smoothly as the camera moves, the reference for what
         "no flicker" looks like in this renderer.

Figures per animation, frames composited on white, in 8-bit units (0-255):
  d_t      mean |I_t - I_{t-1}| over the pixels: how much consecutive frames differ;
  jerk_t   mean |I_{t+1} - 2 I_t + I_{t-1}|: the part of the change that is not smooth in time
           (a smooth motion sampled densely has a small second difference; a pose that jumps, a
           fold that opens and closes or noise that changes per frame make it large), reported as
           its mean and max over frames relative to the mean d (scale-free, so a bend and an orbit
           that move different amounts compare; where edges move a pixel or more per frame the
           second difference is as large as the first, so ~1 is what smooth motion gives: the
           orbit's value is the reference);
  spike    the largest d_t / ((d_{t-1} + d_{t+1}) / 2) over interior frames: a frame whose
           difference spikes above its neighbours (> 1.5 flagged);
  rough    mean |d_{t+1} - 2 d_t + d_{t-1}| / mean d: how far the series of differences is from a
           smooth curve (an eased motion gives a smooth bell; a pose that jitters, a ragged one).
The engine's per-frame report of inverted and flat cage tets is collected from the console.
Writes results.json and the frames in --work.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

SPIKE_FLAG = 1.5


def _retime(action_owner, old_end: int, new_end: int, hold_rest: bool) -> None:
    """Move the keyframes at `old_end` to `new_end`; with `hold_rest`, give them the frame-1 values."""
    anim = action_owner.animation_data
    if anim is None or anim.action is None:
        return
    for fcurve in _fcurves(anim.action):
        points = fcurve.keyframe_points
        first = min(points, key=lambda k: k.co[0])
        for key in points:
            if abs(key.co[0] - old_end) < 1e-6:
                key.co[0] = new_end
                if hold_rest:
                    key.co[1] = first.co[1]
        for key in points:
            key.handle_left_type = key.handle_right_type = "AUTO_CLAMPED"
        fcurve.update()


def _fcurves(action):
    """An action's F-curves: `action.fcurves` before Blender 5, the layered action's channelbags from 5.0."""
    if hasattr(action, "fcurves"):
        return list(action.fcurves)
    curves = []
    for layer in action.layers:
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves.extend(bag.fcurves)
    return curves


def child(config: dict) -> int:
    """In a fresh Blender (the extension enabled from demo_out's user folder): render one animation."""
    import bpy

    from mathutils import Matrix, Vector

    bpy.ops.wm.read_userpref()
    if not hasattr(bpy.types.Object, "nerf_deform"):
        raise SystemExit(f"bench_flicker: the extension is not enabled in {os.environ.get('BLENDER_USER_RESOURCES')}")
    bpy.ops.wm.open_mainfile(filepath=config["blend"])
    scene = bpy.context.scene
    old_end, frames = scene.frame_end, config["frames"]
    orbit = config["mode"] == "orbit"
    handles = [ob for ob in scene.objects if ob.animation_data is not None and ob.animation_data.action is not None]
    if not handles:
        raise SystemExit("bench_flicker: demo.blend has no animated handles; rerun `make demo`")
    for ob in handles:
        _retime(ob, old_end, frames, hold_rest=orbit)
    cam = scene.camera
    if orbit:
        target = Vector(config["target"])
        start = cam.matrix_world.copy()
        for frame in range(1, frames + 1):  # keyed every frame: on the circle, eased in and out
            s = (frame - 1) / (frames - 1)
            degrees = config["orbit_degrees"] * s * s * (3.0 - 2.0 * s)
            turn = (
                Matrix.Translation(target)
                @ Matrix.Rotation(math.radians(degrees), 4, "Z")
                @ Matrix.Translation(-target)
            )
            cam.matrix_world = turn @ start
            cam.keyframe_insert("location", frame=frame)
            cam.keyframe_insert("rotation_euler", frame=frame)
    scene.frame_start, scene.frame_end = 1, frames
    scene.render.filepath = str(Path(config["out"]) / "frame_")
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    result = bpy.ops.render.render(animation=True)
    if result != {"FINISHED"}:
        raise SystemExit(f"bench_flicker: Render Animation returned {result}")
    return 0


def load_frames(folder: Path, frames: int) -> np.ndarray:
    from PIL import Image

    out = []
    for f in range(1, frames + 1):
        rgba = np.asarray(Image.open(folder / f"frame_{f:04d}.png").convert("RGBA"), dtype=np.float64) / 255.0
        out.append(255.0 * (rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])))  # straight alpha over white
    return np.stack(out)


def flicker_figures(images: np.ndarray) -> dict:
    """The temporal figures of a (T, H, W, 3) sequence (see the module's docstring)."""
    d = np.abs(np.diff(images, axis=0)).mean(axis=(1, 2, 3))  # d[t-1] = |I_t - I_{t-1}|
    jerk = np.abs(images[2:] - 2.0 * images[1:-1] + images[:-2]).mean(axis=(1, 2, 3))
    neighbours = 0.5 * (d[:-2] + d[2:])
    spikes = d[1:-1] / np.maximum(neighbours, 1e-9)
    worst = int(np.argmax(spikes))
    mean_d = float(d.mean())
    rough = float(np.abs(d[2:] - 2.0 * d[1:-1] + d[:-2]).mean() / max(mean_d, 1e-9))
    return {
        "mean_d": mean_d,
        "max_d": float(d.max()),
        "jerk_mean_rel": float(jerk.mean() / max(mean_d, 1e-9)),
        "jerk_max_rel": float(jerk.max() / max(mean_d, 1e-9)),
        "spike_max": float(spikes[worst]),
        "spike_frame": worst + 2,  # the frame whose difference to its previous spikes
        "spike_frames_flagged": [int(i + 2) for i in np.flatnonzero(spikes > SPIKE_FLAG)],
        "rough": rough,
        "d": [float(x) for x in d],
    }


def _inversions(log: str) -> dict:
    """The engine's per-frame warnings ("frame N: K inverted and ...") in a render's console."""
    inverted = [int(n) for n in re.findall(r"frame \d+: (\d+) inverted", log)]
    return {"frames_reporting_inverted_tets": len(inverted), "max_inverted_tets": max(inverted, default=0)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--demo", type=Path, default=REPO / "demo_out")
    p.add_argument("--frames", type=int, default=48)
    p.add_argument("--orbit-degrees", type=float, default=20.0)
    p.add_argument("--work", type=Path, default=Path("/work/runs/flicker"))
    p.add_argument("--reuse", action="store_true", help="score the frames already in --work, render nothing")
    p.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(json.loads(args.child.read_text()))
    blend = (args.demo / "demo.blend").resolve()
    user = (args.demo / "blender_user").resolve()
    if not blend.is_file() or not user.is_dir():
        raise SystemExit(f"bench_flicker: {blend} or {user} is missing; run `make demo` first")
    if args.frames < 4:
        raise SystemExit("bench_flicker: --frames must be at least 4")
    if not args.reuse:
        shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True, exist_ok=True)
    results = {"frames": args.frames, "orbit_degrees": args.orbit_degrees, "blend": str(blend)}
    for mode in ("bend", "orbit"):
        out = args.work / mode
        if args.reuse:
            log = (args.work / f"{mode}.log").read_text()
            figures = flicker_figures(load_frames(out, args.frames))
            figures.update(_inversions(log))
            results[mode] = figures
            continue
        out.mkdir()
        config = {
            "blend": str(blend),
            "frames": args.frames,
            "mode": mode,
            "out": str(out),
            "orbit_degrees": args.orbit_degrees,
            "target": [-0.25, 0.0, 0.05],
        }  # tools/demo.py's camera target
        config_path = args.work / f"{mode}.json"
        config_path.write_text(json.dumps(config))
        proc = subprocess.run(
            [sys.executable, __file__, "--child", str(config_path)],
            cwd=REPO,
            text=True,
            env={**os.environ, "BLENDER_USER_RESOURCES": str(user)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        (args.work / f"{mode}.log").write_text(proc.stdout)
        if proc.returncode != 0:
            raise SystemExit(
                f"bench_flicker: the {mode} render failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}"
            )
        figures = flicker_figures(load_frames(out, args.frames))
        figures.update(_inversions(proc.stdout))
        results[mode] = figures
    (args.work / "results.json").write_text(json.dumps(results, indent=1))
    print(f"{args.frames} frames each; the orbit turns {args.orbit_degrees:g} degrees (8-bit units, on white)")
    print(
        f"{'animation':10s} {'mean d':>8s} {'max d':>8s} {'jerk mean/d':>12s} {'jerk max/d':>11s} "
        f"{'spike max (frame)':>18s} {'flagged':>8s} {'rough':>7s} "
        f"{'inverted (frames, max)':>23s}"
    )
    for mode in ("bend", "orbit"):
        r = results[mode]
        print(
            f"{mode:10s} {r['mean_d']:8.3f} {r['max_d']:8.3f} {r['jerk_mean_rel']:12.3f} {r['jerk_max_rel']:11.3f} "
            f"{r['spike_max']:11.2f} ({r['spike_frame']:2d})  {len(r['spike_frames_flagged']):8d} {r['rough']:7.3f} "
            f"{r['frames_reporting_inverted_tets']:13d}, {r['max_inverted_tets']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
