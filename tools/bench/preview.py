#!/usr/bin/env python3
"""Live preview update rate: handle change → worker solve → deformed mesh in the "NeRF Deform" shape key.

    .venv/bin/python tools/bench/preview.py                      # the default bench scene (built once, cached)
    .venv/bin/python tools/bench/preview.py --blend demo.blend   # any .blend with a NeRF, its cage and handles

Runs the add-on in the bpy module with its real worker (the same Python that finds torch: the
repository's .venv, or $NERF_DEFORM_PYTHON). One handle of the NeRF (--handle, default: the first by
name) is moved along a closed path of --count distinct poses (translation up to 10% of the cage's
size, plus a turn), two ways:

- frame changes: the path keyed on the handle over --count frames (its own animation replaced in
  memory; the file is never saved) and played with scene.frame_set, as keyframe playback does;
- direct moves: the handle's location and rotation set and the view layer updated, as a gizmo drag does.

Each way is measured twice:

- awaited: every change waits until its solve is in the shape key, the worker's answers collected as
  fast as possible. Latency = change to shape key written; updates/s = changes / total time: the
  rate the preview sustains when every pose must be shown.
- streamed: changes arrive at a fixed rate (--drag-hz for moves, the scene's fps for playback) and
  answers are collected at the cadence of the add-on's drain timer (its own return value: 50 ms while
  busy), as in Blender's UI, for --seconds (the path repeating). Only the newest waiting pose is
  solved (AsyncSolver), so updates/s = shape keys written per second while the input runs.

Also printed: the worker's own solve time (the "solve" op's solve_s), the main thread's time per
change (depsgraph update + the add-on's handler, which builds and sends the request) and per applied
answer (embedding applied, shape key written), and the first solve's cost (ARAP precomputation).

The default bench scene (in --work, default runs/bench_preview/; remade only when missing): the
project's procedural default scene (tools/default_scene.py), a dataset of it (tools/make_dataset.py,
40 views at 64 px), a NeRF trained --steps steps, Load NeRF, Extract Mesh at --resolution, Build
Cage, the base pinned and two handles (the arm's tip, the flag), saved as bench_preview.blend.
"""

from __future__ import annotations

import argparse
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


# -- the default bench scene -------------------------------------------------------


def _run(*cmd) -> None:
    proc = subprocess.run([str(c) for c in cmd], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(
            f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
        )


def _select_vertices(bpy, surface, indices) -> None:
    """Select exactly the vertices `indices` of `surface` in Edit Mode (as an artist's selection)."""
    import bmesh

    bpy.context.view_layer.objects.active = surface
    if surface.mode != "EDIT":
        bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(surface.data)
    bm.verts.ensure_lookup_table()
    for element in (*bm.faces, *bm.edges, *bm.verts):
        element.select = False
    for i in indices:
        bm.verts[int(i)].select = True
    bmesh.update_edit_mesh(surface.data)


def _in_box(points, box):
    import numpy as np

    lo, hi = np.asarray(box[0]) - 0.03, np.asarray(box[1]) + 0.03  # the NeRF's surface sits near the true one
    return np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))


def build_default_scene(bpy, work: Path, steps: int, resolution: int) -> Path:
    """The bench scene's .blend in `work`, made once (each stage reused when its output exists)."""
    import numpy as np

    from tools.default_scene import REGIONS

    blend = work / "bench_preview.blend"
    if blend.is_file():
        return blend
    work.mkdir(parents=True, exist_ok=True)
    python = sys.executable
    if not (work / "scene.blend").is_file():
        print("building the default scene ...", flush=True)
        _run(python, REPO / "tools" / "default_scene.py", "--out", work / "scene.blend")
    if not (work / "data" / "transforms.json").is_file():
        print("rendering its dataset (40 views, 64 px) ...", flush=True)
        _run(
            python,
            REPO / "tools" / "make_dataset.py",
            "--blend",
            work / "scene.blend",
            "--out",
            work / "data",
            "--count",
            40,
            "--resolution",
            64,
            "--radius",
            4.0,
            "--threads",
            2,
        )
    ckpt = work / "run" / "nerf.ckpt"
    if not ckpt.is_file():
        print(f"training a NeRF for {steps} steps ...", flush=True)
        _run(
            python,
            "-m",
            "blender_nerf_deform.engine",
            "train",
            "--data",
            work / "data",
            "--out",
            work / "run",
            "--steps",
            steps,
        )

    print(f"Load NeRF, Extract Mesh (resolution {resolution}), Build Cage, pin and two handles ...", flush=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    _ok(bpy.ops.nerf_deform.load_nerf(filepath=str(ckpt)), "Load NeRF")
    nerf = bpy.context.active_object
    nerf.nerf_deform.resolution = resolution
    _ok(bpy.ops.nerf_deform.extract_mesh(), "Extract Mesh")
    bpy.context.view_layer.objects.active = nerf
    _ok(bpy.ops.nerf_deform.build_cage(), "Build Cage")
    surface = nerf.nerf_deform.surface
    co = np.empty(3 * len(surface.data.vertices), dtype=np.float32)
    surface.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)  # the NeRF's frame = the dataset's world frame = the default scene's
    tip_lo, tip_hi = REGIONS["arm_tip"]["bounds"]
    regions = {
        "pin": _in_box(co, REGIONS["base"]["bounds"]),
        "arm tip": _in_box(co, (tip_lo, (0.2, tip_hi[1], tip_hi[2]))),
        "flag": _in_box(co, ((0.3, tip_lo[1], tip_lo[2]), tip_hi)),
    }
    for name, indices in regions.items():
        if len(indices) == 0:
            raise SystemExit(f"the extracted mesh has no vertex in the {name} region: train longer (--steps)")
        _select_vertices(bpy, surface, indices)
        _ok(bpy.ops.nerf_deform.pin_selection() if name == "pin" else bpy.ops.nerf_deform.add_handle(), name)
        _settle(bpy)  # the preview's solve for this step is answered here, not in the measurements
    if surface.mode == "EDIT":
        bpy.context.view_layer.objects.active = surface
        bpy.ops.object.mode_set(mode="OBJECT")
    _settle(bpy)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend


def _settle(bpy, timeout=600.0) -> None:
    """Let the live preview finish what it was sent (its answers drained as Blender's timer would)."""
    from blender_nerf_deform.addon.deform import live_preview as preview
    from blender_nerf_deform.addon.worker import client as worker_client

    bpy.context.view_layer.update()
    deadline = time.perf_counter() + timeout
    while any(s.in_flight or s.waiting is not None for s in preview._solvers.values()):
        if time.perf_counter() > deadline:
            raise SystemExit("the live preview did not finish a solve within 10 minutes")
        worker_client._drain_timer()
        time.sleep(0.005)


def _ok(result, what):
    if result != {"FINISHED"}:
        raise SystemExit(f"{what} did not finish: {result}")


# -- measuring -----------------------------------------------------------------------


class Probe:
    """Counts and times the preview's applied answers (wraps the NeRF's AsyncSolver callback)."""

    def __init__(self, solver):
        self.solver = solver
        self.applied: list[float] = []  # time each shape key was written
        self.apply_s: list[float] = []  # main thread: embedding applied + shape key written
        self.solve_s: list[float] = []  # worker: the solve itself
        inner = solver.on_result

        def on_result(result, deformed):
            t0 = time.perf_counter()
            inner(result, deformed)
            t1 = time.perf_counter()
            self.applied.append(t1)
            self.apply_s.append(t1 - t0)
            if "solve_s" in result:
                self.solve_s.append(float(result["solve_s"]))

        solver.on_result = on_result

    @property
    def idle(self) -> bool:
        return not self.solver.in_flight and self.solver.waiting is None

    def reset(self) -> None:
        self.applied.clear()
        self.apply_s.clear()
        self.solve_s.clear()


def poses(count: int, amplitude: float):
    """`count` distinct (offset, angles) on a closed path: a loop in x/z and a turn about x and y."""
    out = []
    for i in range(count):
        a = 2 * math.pi * (i + 1) / (count + 1)  # never the rest pose (which would need no solve)
        offset = (amplitude * math.sin(a), 0.3 * amplitude * math.sin(2 * a), amplitude * (1 - math.cos(a)))
        angles = (0.3 * math.sin(a), 0.15 * math.sin(2 * a), 0.0)
        out.append((offset, angles))
    return out


def _pump_until_idle(worker_client, probe, timeout=600.0):
    deadline = time.perf_counter() + timeout
    while not probe.idle:
        if time.perf_counter() > deadline:
            raise SystemExit("the preview did not finish a solve within 10 minutes")
        worker_client._drain_timer()
        time.sleep(0.0005)


def awaited(worker_client, probe, changes) -> dict:
    """Each change waits for its shape key: latencies and the main thread's share."""
    probe.reset()
    latencies, handler_s = [], []
    start = time.perf_counter()
    for change in changes:
        t0 = time.perf_counter()
        change()
        handler_s.append(time.perf_counter() - t0)
        _pump_until_idle(worker_client, probe)
        latencies.append(time.perf_counter() - t0)
    total = time.perf_counter() - start
    if len(probe.applied) != len(changes):
        raise SystemExit(f"{len(changes)} changes but {len(probe.applied)} previews: a change did not reach the solver")
    return {
        "n": len(changes),
        "rate": len(changes) / total,
        "latency": latencies,
        "handler": handler_s,
        "apply": list(probe.apply_s),
        "solve": list(probe.solve_s),
    }


def streamed(worker_client, probe, changes, input_hz: float) -> dict:
    """Changes at `input_hz`, answers drained at the add-on timer's own cadence, as in Blender's UI."""
    probe.reset()
    period = 1.0 / input_hz
    start = time.perf_counter()
    next_input, next_timer, i = start, start + worker_client._DRAIN_BUSY_S, 0
    while i < len(changes) or not probe.idle:
        now = time.perf_counter()
        if i < len(changes) and now >= next_input:
            changes[i]()
            i += 1
            next_input += period
            continue
        if now >= next_timer:
            next_timer = now + worker_client._drain_timer()
            continue
        wake = min(next_timer, next_input) if i < len(changes) else next_timer
        time.sleep(max(0.0, wake - time.perf_counter()))
    inputs_end = start + len(changes) * period
    shown_during = [t for t in probe.applied if t <= inputs_end]
    return {
        "n": len(changes),
        "shown": len(probe.applied),
        "rate": len(shown_during) / (inputs_end - start),
        "input_hz": input_hz,
    }


def _ms(values) -> str:
    if not values:
        return "n/a"
    ordered = sorted(values)
    p90 = ordered[min(len(ordered) - 1, int(round(0.9 * (len(ordered) - 1))))]
    return f"median {1000 * statistics.median(values):.1f} ms (p90 {1000 * p90:.1f})"


def find_target(bpy, nerf_name: str | None, handle_name: str | None):
    from blender_nerf_deform.addon.data.cage_store import has_cage
    from blender_nerf_deform.addon.data.properties import handles_of

    candidates = [o for o in bpy.data.objects if o.nerf_deform.role == "NERF"]
    if nerf_name:
        candidates = [o for o in candidates if o.name == nerf_name]
    usable = [
        o
        for o in sorted(candidates, key=lambda o: o.name)
        if o.nerf_deform.cage is not None
        and has_cage(o.nerf_deform.cage.data)
        and o.nerf_deform.surface is not None
        and handles_of(o)
    ]
    if not usable:
        names = ", ".join(o.name for o in candidates) or "none"
        raise SystemExit(f"no NeRF object with a built cage, an extracted mesh and handles (NeRF objects: {names})")
    nerf = usable[0]
    handles = handles_of(nerf)
    if handle_name:
        handles = [h for h in handles if h.name == handle_name]
        if not handles:
            raise SystemExit(f"{nerf.name} has no handle named {handle_name!r}")
    return nerf, handles[0]


def bench(bpy, args) -> None:
    import numpy as np

    from blender_nerf_deform.addon.data.cage_store import load_cage
    from blender_nerf_deform.addon.data.properties import PIN_GROUP, handles_of
    from blender_nerf_deform.addon.deform import live_preview as preview
    from blender_nerf_deform.addon.worker import client as worker_client
    from blender_nerf_deform.addon.worker import jobs

    nerf, handle = find_target(bpy, args.nerf_object, args.handle)
    s = nerf.nerf_deform
    if args.mode:
        s.deformation_mode = args.mode
    if s.deformation_mode == "MODIFIERS":
        raise SystemExit(
            f"{nerf.name} is in Cage Modifiers mode: its handles do not drive it (use --mode ARAP or AFFINE)"
        )
    surface = s.surface
    if surface.mode == "EDIT":
        bpy.context.view_layer.objects.active = surface
        bpy.ops.object.mode_set(mode="OBJECT")
    scene = bpy.context.scene
    rest, tets = load_cage(s.cage.data)
    size = float(np.linalg.norm(np.ptp(rest, axis=0)))
    hello = jobs.worker(bpy.context).ensure_started()
    pinned = surface.vertex_groups.get(PIN_GROUP) is not None
    print(
        f"NeRF '{nerf.name}': surface {len(surface.data.vertices)} vertices, "
        f"cage {len(rest)} vertices / {len(tets)} tets, "
        f"{len(handles_of(nerf))} handles{' + pinned region' if pinned else ''}, mode {s.deformation_mode}; "
        f"moving '{handle.name}' ({args.count} poses, up to {0.1 * size:.3g} NeRF units)"
    )
    print(f"worker: Python {hello.get('python', '?')}, torch {hello.get('torch', '?')}, cuda {hello.get('cuda', '?')}")

    base_location = handle.location.copy()
    base_rotation = handle.rotation_euler.copy()
    path = poses(args.count, 0.1 * size / max(max(nerf.matrix_world.to_scale()), 1e-9))

    def set_pose(i):
        offset, angles = path[i % len(path)]
        handle.location = base_location + type(base_location)(offset)
        handle.rotation_euler = (base_rotation.x + angles[0], base_rotation.y + angles[1], base_rotation.z + angles[2])

    # The first solve builds the ARAP factorization for this cage and these regions.
    preview._last_pose.clear()
    preview._solvers.clear()
    t0 = time.perf_counter()
    set_pose(len(path) // 2)
    bpy.context.view_layer.update()
    solver = preview._solvers.get(nerf.name)
    if solver is None:
        raise SystemExit("the live preview sent no solve: is the add-on's depsgraph handler registered?")
    probe = Probe(solver)
    _pump_until_idle(worker_client, probe)
    print(f"first solve (precomputation included): {1000 * (time.perf_counter() - t0):.0f} ms")

    def move(i):
        def change():
            set_pose(i)
            bpy.context.view_layer.update()

        return change

    # Keyframe playback: the path keyed on the handle, one pose per frame.
    handle.animation_data_clear()
    first_frame = scene.frame_start
    for i in range(args.count):
        set_pose(i)
        handle.keyframe_insert("location", frame=first_frame + i)
        handle.keyframe_insert("rotation_euler", frame=first_frame + i)

    def frame(i):
        return lambda: scene.frame_set(first_frame + i)

    fps = scene.render.fps / scene.render.fps_base
    scene.frame_set(first_frame + args.count)  # off the path: the first measured frame is a change
    _pump_until_idle(worker_client, probe)
    results = {}
    results["frames awaited"] = awaited(worker_client, probe, [frame(i) for i in range(args.count)])
    scene.frame_set(first_frame + args.count)
    _pump_until_idle(worker_client, probe)
    streamed_frames = [frame(i % args.count) for i in range(max(args.count, round(fps * args.seconds)))]
    results["frames streamed"] = streamed(worker_client, probe, streamed_frames, fps)
    handle.animation_data_clear()
    results["moves awaited"] = awaited(worker_client, probe, [move(i) for i in range(args.count)])
    streamed_moves = [move(i) for i in range(max(args.count, round(args.drag_hz * args.seconds)))]
    results["moves streamed"] = streamed(worker_client, probe, streamed_moves, args.drag_hz)

    for kind, label in (
        ("frames", "frame changes (keyframe playback)"),
        ("moves", "direct handle moves (as a gizmo drag)"),
    ):
        a, st = results[f"{kind} awaited"], results[f"{kind} streamed"]
        print(f"{label}:")
        print(
            f"  awaited:  {a['rate']:.1f} updates/s over {a['n']} changes; "
            f"latency change → shape key {_ms(a['latency'])}"
        )
        print(
            f"            worker solve {_ms(a['solve'])}; main thread per change {_ms(a['handler'])}, "
            f"per applied answer {_ms(a['apply'])}"
        )
        print(
            f"  streamed: {st['rate']:.1f} updates/s with changes at {st['input_hz']:.0f}/s "
            f"({st['shown']} of {st['n']} poses shown, newest wins; "
            f"drained every {1000 * worker_client._DRAIN_BUSY_S:.0f} ms)"
        )
    a = results["frames awaited"]
    print(
        f"SUMMARY preview updates/s: playback awaited {a['rate']:.1f}, "
        f"streamed {results['frames streamed']['rate']:.1f}; "
        f"moves awaited {results['moves awaited']['rate']:.1f}, streamed {results['moves streamed']['rate']:.1f}; "
        f"solve latency {_ms(a['latency'])}"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--blend", type=Path, help="a .blend with a NeRF object, its cage and handles (default: the bench scene)"
    )
    parser.add_argument(
        "--nerf-object", help="which NeRF object (default: the first, by name, that has a cage and handles)"
    )
    parser.add_argument("--handle", help="which handle to move (default: the NeRF's first, by name)")
    parser.add_argument("--count", type=int, default=30, help="poses (frames, moves) per measurement (default 30)")
    parser.add_argument(
        "--seconds", type=float, default=3.0, help="how long the streamed input runs (default 3; the path repeats)"
    )
    parser.add_argument("--drag-hz", type=float, default=60.0, help="rate of direct moves when streamed (default 60)")
    parser.add_argument("--mode", choices=("ARAP", "AFFINE"), help="deformation mode (default: the NeRF's own)")
    parser.add_argument(
        "--work", type=Path, default=REPO / "runs" / "bench_preview", help="where the bench scene is built and kept"
    )
    parser.add_argument(
        "--steps", type=int, default=1000, help="training steps of the bench scene's NeRF (default 1000)"
    )
    parser.add_argument(
        "--resolution", type=int, default=128, help="Extract Mesh resolution of the bench scene (default 128)"
    )
    args = parser.parse_args(argv)
    if args.count < 2:
        parser.error("--count must be at least 2")

    os.environ.setdefault("NERF_DEFORM_PYTHON", sys.executable)
    import bpy

    import blender_nerf_deform

    blender_nerf_deform.register()
    try:
        blend = args.blend
        if blend is None:
            blend = build_default_scene(bpy, args.work, args.steps, args.resolution)
            from blender_nerf_deform.addon.worker import client as worker_client

            worker_client.shutdown()  # measured on a fresh worker, as after opening the file in Blender
        if not Path(blend).is_file():
            raise SystemExit(f"--blend {blend}: no such file")
        bpy.ops.wm.open_mainfile(filepath=str(Path(blend).resolve()))
        print(f"scene: {blend}")
        bench(bpy, args)
    finally:
        blender_nerf_deform.unregister()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
