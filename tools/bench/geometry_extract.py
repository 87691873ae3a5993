#!/usr/bin/env python3
"""Extraction at 256^3 and tetrahedralization of the extracted mesh, timed stage by stage.

With --nerf CKPT (e.g. a lego trained by `train`), the NeRF's density is
sampled; without, the analytic lego-sized object of geometry_common.py.
Then the cage is built once around the filtered mesh (envelope, fTetWild,
clearance check) and its size reported.

    flock /tmp/nerf_cpu.lock .venv/bin/python tools/bench/geometry_extract.py --nerf RUN/nerf.ckpt
"""

from __future__ import annotations

import argparse
import time

from geometry_common import BOUNDS, analytic_density, machine


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--nerf")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--threshold", type=float, default=None)
    ap.add_argument("--target-tets", type=int, default=None)
    ap.add_argument("--out-mesh", help="also write the filtered mesh (PLY)")
    args = ap.parse_args()

    from blender_nerf_deform.engine.geometry.cage import build_cage
    from blender_nerf_deform.engine.geometry.extract import DEFAULT_THRESHOLD, colour_fn_of, density_fn_of, extract_mesh
    from blender_nerf_deform.engine.geometry.mesh_io import write_ply

    colour = None
    if args.nerf:
        from blender_nerf_deform.engine.nerf.checkpoint import load_nerf

        nerf = load_nerf(args.nerf, device="cpu")
        density = density_fn_of(nerf)
        colour = colour_fn_of(nerf)
        bounds = nerf.aabb.cpu().numpy()
        source = f"NeRF {args.nerf}"
    else:
        density, bounds, source = analytic_density, BOUNDS, "analytic object"
    t0 = time.perf_counter()
    res = extract_mesh(
        density, bounds, resolution=args.resolution, threshold=args.threshold or DEFAULT_THRESHOLD, colour_fn=colour
    )
    total = time.perf_counter() - t0
    t = res.timings
    print(f"machine: {machine()}; source: {source}")
    print(
        f"extract {args.resolution}^3: total {total:.1f} s (density grid {t['grid_s']:.1f} s = "
        f"{args.resolution**3 / t['grid_s'] / 1e6:.2f} M samples/s, marching cubes {t['marching_cubes_s']:.2f} s, "
        f"filter {t['filter_s']:.2f} s, colours {t.get('colour_s', 0):.2f} s)"
    )
    print(res.report())
    if args.out_mesh:
        write_ply(args.out_mesh, res.vertices, res.faces, res.colors)
    t0 = time.perf_counter()
    cage = build_cage(res.vertices, res.faces, target_tets=args.target_tets)
    total = time.perf_counter() - t0
    ct = cage.timings
    print(
        f"cage: total {total:.1f} s (closed-mesh check + envelope {ct['envelope_s']:.1f} s, "
        f"fTetWild {ct['tetrahedralize_s']:.1f} s, "
        f"clearance check {ct['clearance_check_s']:.2f} s): {len(cage.tets)} tets, {len(cage.vertices)} vertices, "
        f"margin {cage.margin:.4f}, clearance {cage.clearance:.4f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
