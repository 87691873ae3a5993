#!/usr/bin/env python3
"""Bytes the add-on sends to its worker: per F12 frame and per live-preview update.

    .venv/bin/python tools/bench/worker_bytes.py --blend demo_out/demo.blend [--handle "Tip Handle"] [--frames 3]

Opens the .blend in the bpy module with the add-on registered and its real worker, wraps the
client's message writer to count every byte written to the worker's stdin (headers and
arrays), then:

- renders --frames frames with F12 (`bpy.ops.render.render()`, at --percentage of the scene's
  resolution: the request does not depend on it), each on a frame of the scene's animation:
  the first on a fresh worker, the others after it. A frame's bytes are the render's own
  messages (up to its "render" request); what the live preview sends when the render is over
  is printed apart;
- moves one handle (--handle, default the NeRF's first) --moves times, waiting each time for
  the preview's answer, as a gizmo drag does.

Prints the bytes of each F12 frame and of each preview update (the first update, on a worker
that holds nothing yet, apart from the rest). Works on any version of the add-on that sends
through `worker_client.write_message`, so the same command measures before and after a change.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--blend", type=Path, required=True)
    parser.add_argument("--handle", help="handle to move for preview updates (default: the NeRF's first)")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--moves", type=int, default=5)
    parser.add_argument("--percentage", type=int, default=25, help="render resolution percentage (default 25)")
    args = parser.parse_args(argv)
    os.environ.setdefault("NERF_DEFORM_PYTHON", sys.executable)
    import bpy

    import blender_nerf_deform
    from blender_nerf_deform.addon.data.properties import handles_of
    from blender_nerf_deform.addon.deform import live_preview as preview
    from blender_nerf_deform.addon.worker import client as worker_client

    log: list[tuple[str, int]] = []
    write = worker_client.write_message

    def counting(stream, header, arrays=None):
        class Counter:
            n = 0

            def write(self, data):
                Counter.n += len(data)
                return stream.write(data)

            def flush(self):
                return stream.flush()

        write(Counter(), header, arrays)
        log.append((header.get("op") or header.get("type"), Counter.n))
        return Counter.n

    worker_client.write_message = counting
    blender_nerf_deform.register()
    try:
        bpy.ops.wm.open_mainfile(filepath=str(args.blend.resolve()))
        scene = bpy.context.scene
        scene.render.resolution_percentage = args.percentage
        nerf = next(
            o for o in sorted(bpy.data.objects, key=lambda o: o.name) if o.nerf_deform.role == "NERF" and handles_of(o)
        )
        handles = handles_of(nerf)
        handle = next((h for h in handles if h.name == args.handle), handles[0]) if args.handle else handles[0]
        print(
            f"scene {args.blend}: NeRF {nerf.name}, mode {nerf.nerf_deform.deformation_mode}, "
            f"surface {len(nerf.nerf_deform.surface.data.vertices)} vertices, "
            f"cage {len(nerf.nerf_deform.cage.data.vertices)} vertices"
        )

        frames = []
        span = max(1, scene.frame_end - scene.frame_start)
        for k in range(args.frames):
            scene.frame_set(scene.frame_start + (k * span) // max(1, args.frames - 1))
            preview_settle(bpy, preview, worker_client)
            if k == 0 and worker_client._client is not None:
                worker_client._client.stop()  # the first frame on a fresh worker, as in `blender -b`
            log.clear()
            assert bpy.ops.render.render() == {"FINISHED"}
            # The render's own messages end with its "render" request; after it the preview catches up.
            last = max(i for i, (op, _n) in enumerate(log) if op == "render")
            frames.append(sum(n for _op, n in log[: last + 1]))
            print(
                f"F12 frame {scene.frame_current}: {frames[-1]:,} bytes in the render's {last + 1} messages "
                f"({', '.join(op for op, _ in log[: last + 1])}); "
                f"after it {sum(n for _op, n in log[last + 1 :]):,} bytes "
                f"({', '.join(op for op, _ in log[last + 1 :]) or 'none'})"
            )

        updates = []
        base = handle.location.copy()
        for k in range(args.moves):
            log.clear()
            handle.location = base + type(base)((0.02 * (k + 1), 0.0, 0.01 * (k + 1)))
            bpy.context.view_layer.update()
            preview_settle(bpy, preview, worker_client)
            updates.append(sum(n for _op, n in log))
            print(f"preview update {k + 1}: {updates[-1]:,} bytes in {len(log)} messages")
        steady_f = statistics.median(frames[1:]) if len(frames) > 1 else frames[0]
        steady_u = statistics.median(updates[1:]) if len(updates) > 1 else updates[0]
        print(
            f"SUMMARY bytes: F12 first frame {frames[0]:,}, later frames {steady_f:,.0f} (median); "
            f"preview first update {updates[0]:,}, later updates {steady_u:,.0f} (median)"
        )
    finally:
        blender_nerf_deform.unregister()
        worker_client.write_message = write
    return 0


def preview_settle(bpy, preview, worker_client) -> None:
    """Let the live preview finish what it was sent, and deliver its answer."""
    from tools.bench.preview import _settle

    _settle(bpy)
    worker_client._drain_timer()


if __name__ == "__main__":
    raise SystemExit(main())
