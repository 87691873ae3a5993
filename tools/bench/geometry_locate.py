#!/usr/bin/env python3
"""Point location: our grid locator vs libigl's `in_element` + `AABB`, side by side in one run.

A cage of about 50k tets (fTetWild, built by `engine.cage.build_cage` around
an analytic object's extracted mesh) is bent smoothly (a fresh deformed cage,
no inverted tets); 1M uniform random points in its bounds are located in it.
Each timing includes building the search structure for the deformed cage
(our grid / igl's AABB tree), as a renderer must every frame. Reports best of
`--repeat` runs, the throughput ratio, and the agreement of the containing
tet: wherever the answers differ, the point must lie within 1e-9 (barycentric)
of a tet boundary.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/geometry_locate.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from geometry_common import extracted_mesh, machine, timed


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tets", type=int, default=50000)
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cage", help="reuse a cage .npz instead of building one")
    ap.add_argument("--save-cage", help="write the built cage here")
    ap.add_argument("--cuda", action="store_true", help="also time the torch path on CUDA (points and cage on the GPU)")
    args = ap.parse_args()

    import igl
    import torch

    from blender_nerf_deform.engine.geometry.barycentric import inversion_report, tet_inverses
    from blender_nerf_deform.engine.geometry.cage import build_cage
    from blender_nerf_deform.engine.geometry.locate import TetLocator
    from blender_nerf_deform.engine.geometry.mesh_io import load_cage, save_cage

    if args.cage:
        c = load_cage(args.cage)
        V, T = c["vertices"], c["tets"]
    else:
        mesh = extracted_mesh(128)
        t0 = time.perf_counter()
        cage = build_cage(mesh.vertices, mesh.faces, margin=0.05, target_tets=args.tets)
        print(
            f"cage: {len(cage.tets)} tets, {len(cage.vertices)} vertices, "
            f"built in {time.perf_counter() - t0:.1f}s {cage.timings}"
        )
        V, T = cage.vertices, cage.tets
        if args.save_cage:
            save_cage(args.save_cage, V, T)
    # A fresh deformed cage: a smooth bend and twist.
    Vd = V.copy()
    Vd[:, 2] += 0.25 * np.sin(1.5 * V[:, 0])
    ang = 0.3 * V[:, 2]
    Vd[:, 0], Vd[:, 1] = np.cos(ang) * V[:, 0] - np.sin(ang) * V[:, 1], np.sin(ang) * V[:, 0] + np.cos(ang) * V[:, 1]
    rep = inversion_report(V, Vd, T)
    print(f"deformed cage: {rep.summary()}")
    rng = np.random.default_rng(0)
    lo, hi = Vd.min(0), Vd.max(0)
    Q = rng.uniform(lo, hi, (args.points, 3))
    Qt = torch.as_tensor(Q)

    def run_igl():
        tree = igl.AABB()
        tree.init(Vd, T)
        return igl.in_element(Vd, T, Q, tree)

    def run_ours(backend, dtype=torch.float64, device="cpu"):
        Qd = Qt.to(device=device, dtype=dtype)  # the points already on the device, as the renderer's samples are

        def f():
            loc = TetLocator(Vd, T, backend=backend, dtype=dtype, device=device)
            out = loc.locate(Qd)
            if device != "cpu":
                torch.cuda.synchronize()
            return out.cpu().numpy()

        return f

    run_ours("numba")()  # JIT compile / load the cached kernels outside the timing
    results = {}
    t_igl, ref = timed(run_igl, args.repeat)
    results["igl"] = t_igl
    rows = []
    variants = [
        ("numba (CPU kernels)", run_ours("numba")),
        ("torch float32", run_ours("torch", torch.float32)),
        ("torch float64", run_ours("torch")),
    ]
    if args.cuda:
        run_ours("torch", torch.float32, "cuda")()  # CUDA context and kernels warmed up outside the timing
        variants += [
            ("torch float32 on CUDA", run_ours("torch", torch.float32, "cuda")),
            ("torch float64 on CUDA", run_ours("torch", torch.float64, "cuda")),
        ]
    for name, fn in variants:
        t, got = timed(fn, args.repeat if ("numba" in name or "CUDA" in name) else max(1, args.repeat // 2))
        differ = np.flatnonzero(got != ref)
        Minv = tet_inverses(Vd, T)
        tol = 1e-9 if "float32" not in name else 1e-4
        boundary = 0
        for i in differ:
            m = []
            for t_ in (got[i], ref[i]):
                if t_ >= 0:
                    m.append(
                        (Minv[t_] @ np.append(Q[i], 1.0)).min()
                    )  # the point's smallest barycentric coordinate in tet t_
            boundary += all(abs(x) < tol for x in m)
        rows.append((name, t, len(differ), boundary))
    print(
        f"machine: {machine()}; torch threads {torch.get_num_threads()}; {len(T)} tets; {args.points} points; "
        f"inside {np.mean(ref >= 0):.1%}"
    )
    print(f"igl AABB+in_element: {t_igl * 1e3:.0f} ms  ({args.points / t_igl / 1e6:.2f} M points/s)")
    for name, t, nd, nb in rows:
        print(
            f"{name}: {t * 1e3:.0f} ms ({args.points / t / 1e6:.2f} M points/s) = {t_igl / t:.2f}x igl; "
            f"{nd} answers differ from igl, {nb} of them within tolerance of a tet boundary"
        )
    # Build/query split of the default backend.
    loc_t, loc = timed(lambda: TetLocator(Vd, T), args.repeat)
    q_t, _ = timed(lambda: loc.locate(Qt), args.repeat)
    print(f"default ({loc.backend}) split: build {loc_t * 1e3:.0f} ms, query {q_t * 1e3:.0f} ms; {loc.stats}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
