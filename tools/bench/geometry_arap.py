#!/usr/bin/env python3
"""ARAP on a ~20k-vertex cage: precompute time, per-frame solve time, converged solve.

Cages: the structured box cage (28^3 = 21,952 vertices, 118k tets) and, with
--cage, any cage .npz (e.g. an fTetWild cage from geometry_locate.py
--save-cage). Two handle regions at opposite ends: one pinned, one moved
along an animation (rotation + translation growing per frame).

Per frame the interactive preview runs `ArapDeformer.step` (warm-started
from the previous frame, `--iters` iterations); a render of an isolated frame
runs `solve` (from the linear blend, to tolerance). Both reported, per backend:
ours (numba local step + prefactored SuperLU, the default) and libigl's
arap_solve (the reference), side by side on the same cage and handles, with
the quality of each result (the elements ARAP energy, evaluated the same way
for both, and the mean relative change of edge lengths) so speed is not
bought with quality.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/geometry_arap.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from geometry_common import machine


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cage", help="cage .npz (default: 28^3 box cage)")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--iters", type=int, default=1)
    ap.add_argument(
        "--runs",
        default="numba:elements,igl:elements",
        help="backend:energy pairs (igl also runs spokes, spokes_and_rims)",
    )
    args = ap.parse_args()

    from blender_nerf_deform.engine.geometry.barycentric import inversion_report
    from blender_nerf_deform.engine.geometry.cage import box_cage
    from blender_nerf_deform.engine.geometry.deform import ArapDeformer, edge_length_distortion
    from blender_nerf_deform.engine.geometry.mesh_io import load_cage

    if args.cage:
        c = load_cage(args.cage)
        V, T = c["vertices"], c["tets"]
        name = args.cage
    else:
        V, T = box_cage((27, 27, 27))
        name = "box 27^3"
    lo, hi = V.min(0), V.max(0)
    axis = int(np.argmax(hi - lo))
    span = hi[axis] - lo[axis]
    pin = np.flatnonzero(V[:, axis] < lo[axis] + 0.1 * span)
    handle = np.flatnonzero(V[:, axis] > hi[axis] - 0.1 * span)
    centre = V[handle].mean(0)
    print(
        f"machine: {machine()}; cage {name}: {len(V)} vertices, {len(T)} tets; "
        f"handle {len(handle)}, pinned {len(pin)} vertices"
    )

    def transform(f):
        a = 0.6 * f / args.frames
        c, s = np.cos(a), np.sin(a)
        R = np.eye(3)
        o = [i for i in range(3) if i != axis]
        R[o[0], o[0]], R[o[0], axis], R[axis, o[0]], R[axis, axis] = c, -s, s, c
        A = np.eye(4)
        A[:3, :3] = R
        A[:3, 3] = centre - R @ centre + 0.1 * span * f / args.frames * np.eye(3)[o[1]]
        return A

    # Elements energy of any result, evaluated by one code path for every backend.
    judge = ArapDeformer(V, T, handles=[handle], pins=[pin], backend="numba")
    judge.step([np.eye(4)])  # JIT compile / load the cached kernels outside the timings
    for run in args.runs.split(","):
        backend, energy = run.split(":")
        t0 = time.perf_counter()
        arap = ArapDeformer(V, T, handles=[handle], pins=[pin], energy=energy, backend=backend)
        pre = time.perf_counter() - t0
        per = []
        for f in range(1, args.frames + 1):
            r = arap.step([transform(f)], iterations=args.iters)
            per.append(r.seconds)
        per = np.array(per)
        stepped = r.vertices
        # ARAP with pinned cage vertices (the add-on's fold-free surface ARAP: tools/bench/arap_injectivity.py).
        conv = arap.solve([transform(args.frames)], max_iter=200, tol=1e-4)
        inv = inversion_report(V, conv.vertices, T)
        print(
            f"{backend} {energy}: precompute {pre:.2f} s; per-frame step ({args.iters} iteration(s), warm start) "
            f"median {np.median(per) * 1e3:.0f} ms, max {per.max() * 1e3:.0f} ms over {args.frames} frames "
            f"(last frame: elements energy {judge.energy(stepped):.5g}, "
            f"edge distortion {edge_length_distortion(V, stepped, T):.4f}); "
            f"converged solve of the last frame: {conv.iterations} iterations, {conv.seconds:.2f} s "
            f"({conv.seconds / conv.iterations * 1e3:.0f} ms/iteration), converged={conv.converged}, "
            f"elements energy {judge.energy(conv.vertices):.5g}, "
            f"edge distortion {edge_length_distortion(V, conv.vertices, T):.4f}, {inv.summary()}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
