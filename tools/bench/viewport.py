#!/usr/bin/env python3
"""Viewport (Rendered shading) responsiveness, and the cost of a second NeRF in a frame.

    .venv/bin/python tools/bench/viewport.py        # demo_out/demo.blend (what `make demo` writes)
    .venv/bin/python tools/bench/viewport.py --blend shot.blend --width 1280 --height 720

Runs the add-on in the bpy module with its real worker (the Python that finds torch: the
repository's .venv, or $NERF_DEFORM_PYTHON), on a .blend with a NeRF object that has a cage and
handles (the demo's). The view is the scene camera's, as a 3D View of --width x --height pixels
looking through it (camera view, the frame filling the region) sees it; the viewport logic is the
add-on's own (`viewport.ViewportRender`), answers collected as the add-on's drain timer does.

- pose change → first image (1/8 resolution) and → full-resolution image: the NeRF's first handle
  is moved (--poses distinct moves, each waited for to the end), the depsgraph updated, and the
  viewport told (view_update); times from the change to each image being ready to draw.
- continuous pose changes: the handle moved at --drag-hz for --seconds (a drag), answers drained
  every 50 ms (the drain timer while busy): images shown per second (all 1/8: a drag never lets a
  render refine), and their lag (time from the pose an image shows to its being shown).
- one frame (F12's path, `frame_render.render_frame`, the scene's render resolution) with the NeRF
  alone and with a second NeRF object of the same checkpoint placed beside it (at rest).
- `--second-nerf`: that second NeRF object is in view from the start, so every figure is with two.

Every figure follows a warm-up (worker start, checkpoint load, ARAP factorization, kernels).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

DRAIN_S = 0.05  # worker_client's drain timer interval while busy


def _camera_view(bpy, camera, width, height):
    from blender_nerf_deform.addon.render.viewport import pinhole_from_view

    scene = bpy.context.scene
    window = camera.calc_matrix_camera(
        bpy.context.evaluated_depsgraph_get(),
        x=width,
        y=height,
        scale_x=scene.render.pixel_aspect_x,
        scale_y=scene.render.pixel_aspect_y,
    )
    return pinhole_from_view(camera.matrix_world.inverted(), window, width, height)


class Shown:
    """The viewport's redraws: (time, render, downscale) of each image made ready to draw."""

    def __init__(self):
        self.viewport = None
        self.events = []

    def __call__(self):
        if self.viewport.image is not None:
            self.events.append((time.perf_counter(), self.viewport.render, self.viewport.shown_downscale))


def _find(bpy, nerf_name):
    from blender_nerf_deform.addon.data.properties import handles_of

    nerfs = sorted((o for o in bpy.data.objects if o.nerf_deform.role == "NERF"), key=lambda o: o.name)
    nerfs = [o for o in nerfs if nerf_name in (None, o.name)]
    for nerf in nerfs:
        handles = handles_of(nerf)
        if handles:
            return nerf, handles[0]
    raise SystemExit("no NeRF object with handles in the file" + (f" named {nerf_name!r}" if nerf_name else ""))


def _pump_until(client, done, timeout=600.0, interval=0.001):
    deadline = time.perf_counter() + timeout
    while not done():
        if time.perf_counter() > deadline:
            raise SystemExit("timed out waiting for the worker")
        client.drain()
        time.sleep(interval)


def _add_second(bpy, nerf, camera, size):
    """A second NeRF object of the same checkpoint (at rest), half a box to the camera's right and a
    box further away: both in view."""
    from mathutils import Vector

    second = bpy.data.objects.new(f"{nerf.name} second", None)
    second.nerf_deform.role, second.nerf_deform.checkpoint = "NERF", nerf.nerf_deform.checkpoint
    second.nerf_deform.aabb = nerf.nerf_deform.aabb
    bpy.context.scene.collection.objects.link(second)
    right, back = camera.matrix_world.to_3x3() @ Vector((1, 0, 0)), camera.matrix_world.to_3x3() @ Vector((0, 0, -1))
    second.matrix_world = nerf.matrix_world.copy()
    second.location = nerf.matrix_world.translation + 0.5 * size * right + size * back
    bpy.context.view_layer.update()
    return second


def bench(bpy, args) -> None:
    from mathutils import Vector

    from blender_nerf_deform.addon.render.frame import render_frame
    from blender_nerf_deform.addon.render.viewport import ViewportRender
    from blender_nerf_deform.addon.worker import jobs

    nerf, handle = _find(bpy, args.nerf_object)
    scene = bpy.context.scene
    camera = scene.camera
    client = jobs.worker(bpy.context)
    print(
        f"{args.blend.name}: {nerf.name}, moving {handle.name}; view {args.width}x{args.height} through "
        f"{camera.name}; worker {client.ensure_started().get('python')}"
    )
    shown = Shown()
    viewport = shown.viewport = ViewportRender(shown)
    view = _camera_view(bpy, camera, args.width, args.height)
    size = max(nerf.nerf_deform.aabb[3 + k] - nerf.nerf_deform.aabb[k] for k in range(3)) * max(
        nerf.matrix_world.to_scale()
    )
    rest = handle.location.copy()
    if args.second_nerf:  # the viewport figures with two NeRF objects in view (the second at rest)
        _add_second(bpy, nerf, camera, size)
        print("a second NeRF object in view")

    def move(step: int, amplitude: float = 0.04) -> None:
        offsets = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (-1, 0, 0), (0, -1, 0), (0, 0, -1))
        handle.location = rest + Vector(offsets[step % 6]) * amplitude * size * (1 + step // 6)
        bpy.context.view_layer.update()
        viewport.update_scene(bpy.context.evaluated_depsgraph_get())

    # Warm-up: the first view renders to the end.
    started = time.perf_counter()
    viewport.update_scene(bpy.context.evaluated_depsgraph_get())
    viewport.update_view(view)
    _pump_until(client, lambda: viewport.render.state != "running")
    if viewport.render.state != "finished":
        raise SystemExit(f"the warm-up render {viewport.render.state}: {viewport.render.error}")
    print(f"warm-up (worker start, load, factorization, full refinement): {time.perf_counter() - started:.2f} s")

    # Pose change → coarse → full.
    coarse, full = [], []
    for k in range(args.poses):
        shown.events.clear()
        t0 = time.perf_counter()
        move(k + 1)
        render = viewport.render
        _pump_until(client, lambda render=render: render.state != "running")
        if render.state != "finished":
            raise SystemExit(f"the render {render.state}: {render.error}")
        mine = [(t, d) for t, r, d in shown.events if r is render]
        coarse.append(mine[0][0] - t0)
        full.append(mine[-1][0] - t0)
        assert [d for _t, d in mine] == list(render.downscales)
    print(
        f"pose change -> first image (1/8, {view.width // 8}x{view.height // 8}): "
        f"median {1e3 * statistics.median(coarse):.0f} ms "
        f"({', '.join(f'{1e3 * c:.0f}' for c in coarse)})"
    )
    print(
        f"pose change -> full image ({view.width}x{view.height}): median {statistics.median(full):.2f} s "
        f"({', '.join(f'{f:.2f}' for f in full)})"
    )

    # A drag: changes at drag_hz, answers drained at the timer's cadence.
    shown.events.clear()
    changes: list[tuple[float, object]] = []  # (time, render started for it or None)
    t_start = time.perf_counter()
    next_change = next_drain = t_start
    k = 0
    while (now := time.perf_counter()) - t_start < args.seconds:
        if now >= next_change:
            move(k % 12 + 1, amplitude=0.02)
            changes.append((now, viewport.render))
            k += 1
            next_change += 1.0 / args.drag_hz
        if now >= next_drain:
            client.drain()
            next_drain += DRAIN_S
        time.sleep(0.001)
    elapsed = time.perf_counter() - t_start
    images = [(t, r, d) for t, r, d in shown.events]
    # The lag of an image: from the first change its render started for to its being shown.
    started_at = {}
    for t, render in changes:
        started_at.setdefault(id(render), t)
    lags = [t - started_at[id(r)] for t, r, _d in images if id(r) in started_at]
    by_size = {d: sum(1 for *_x, dd in images if dd == d) for d in sorted({d for *_x, d in images}, reverse=True)}
    print(
        f"drag at {args.drag_hz:g} Hz for {elapsed:.1f} s ({len(changes)} pose changes): "
        f"{len(images) / elapsed:.1f} images/s shown "
        f"(by downscale {by_size}), {sum(1 for *_x, d in images if d == 8) / elapsed:.1f} coarse/s; lag median "
        f"{1e3 * statistics.median(lags):.0f} ms"
        if lags
        else "no image shown during the drag"
    )
    handle.location = rest
    bpy.context.view_layer.update()
    viewport.stop()
    _pump_until(client, lambda: not client.busy, timeout=120)

    # One frame with one NeRF, then with a second one beside it.
    scale = scene.render.resolution_percentage / 100
    width, height = int(scene.render.resolution_x * scale), int(scene.render.resolution_y * scale)

    def frame_seconds(count=3):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        render_frame(depsgraph, width, height)  # warm-up (a new NeRF object's first frame)
        times = []
        for _ in range(count):
            t0 = time.perf_counter()
            frame = render_frame(depsgraph, width, height)
            times.append(time.perf_counter() - t0)
            if frame.error:
                raise SystemExit(frame.error)
        return statistics.median(times), frame

    one, frame_one = frame_seconds()
    if args.second_nerf:
        print(f"frame {width}x{height} (F12's path), two NeRFs: {one:.2f} s")
        return
    _add_second(bpy, nerf, camera, size)
    two, frame_two = frame_seconds()
    covered = lambda f: float((f.rgba[..., 3] > 0.5).mean())  # noqa: E731
    print(
        f"frame {width}x{height} (F12's path): one NeRF {one:.2f} s, two NeRFs {two:.2f} s ({two / one:.2f}x); "
        f"pixels covered {100 * covered(frame_one):.0f}% and {100 * covered(frame_two):.0f}%"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--second-nerf",
        action="store_true",
        help="measure with a second NeRF object of the same checkpoint in view (at rest)",
    )
    parser.add_argument(
        "--blend",
        type=Path,
        default=Path("demo_out/demo.blend"),
        help="a .blend with a NeRF object, its cage and handles (default: the one make demo writes)",
    )
    parser.add_argument("--nerf-object", help="which NeRF object (default: the first, by name, with handles)")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--poses", type=int, default=5, help="pose changes waited for to the full image (default 5)")
    parser.add_argument("--seconds", type=float, default=5.0, help="length of the drag (default 5)")
    parser.add_argument(
        "--drag-hz", type=float, default=30.0, help="pose changes per second during the drag (default 30)"
    )
    args = parser.parse_args(argv)
    if not args.blend.is_file():
        raise SystemExit(f"{args.blend} does not exist")

    import bpy

    import blender_nerf_deform

    blender_nerf_deform.register()
    try:
        bpy.ops.wm.open_mainfile(filepath=str(args.blend))
        bench(bpy, args)
    finally:
        blender_nerf_deform.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
