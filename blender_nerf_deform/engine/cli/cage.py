"""`cage`: the tetrahedral cage around a NeRF's extracted mesh, built once, as CAGE.npz.

    python -m blender_nerf_deform.engine cage --nerf CKPT --mesh MESH.ply --out CAGE.npz
        [--margin M] [--edge-length L] [--target-tets N] [--threshold T]
        [--region REGION.json] [--no-pin-cut] [--refine-edge L [--refine-box XMIN YMIN ZMIN XMAX YMAX ZMAX]]

--refine-edge refines the built cage where a pose will stretch (geometry.cage_refine.refine_cage):
the tets stay fixed over an animation, so a finer cage is chosen here, once.

Where the mesh was closed along an edit region's cut (its `nerf_cut` vertices, or with
--region its vertices on the region's boundary), the cage vertices there are pinned
(`pinned_vertices` in CAGE.npz), unless --no-pin-cut.
"""

from __future__ import annotations

import sys

import numpy as np

from ..errors import EngineError
from ..files import check_writable
from ..geometry.cage import (
    build_nerf_cage,
    build_part_cages,
    check_cage_options,
    cut_from_region,
    cut_pins,
    part_cut_pins,
    vertices_outside,
)
from ..geometry.cage_refine import refine_cage
from ..geometry.mesh_io import read_ply, save_cage
from ..geometry.region import load_region
from ..nerf.checkpoint import load_nerf


def main(args) -> int:
    check_cage_options(args.margin, args.edge_length, args.target_tets, args.threshold)
    refine_edge, refine_box = getattr(args, "refine_edge", None), getattr(args, "refine_box", None)
    if refine_box is not None and refine_edge is None:
        raise EngineError("--refine-box needs --refine-edge (the edge length to refine to)")
    if refine_edge is not None and not refine_edge > 0:
        raise EngineError(f"--refine-edge must be a positive length, got {refine_edge}")
    box = None if refine_box is None else np.asarray(refine_box, dtype=np.float64).reshape(2, 3)
    region = load_region(args.region) if args.region else None
    check_writable(args.out)
    verts, faces, _, cut, part = read_ply(args.mesh, with_cut=True, with_part=True)
    if cut is None and region is not None:
        cut = cut_from_region(verts, region)
    nerf = load_nerf(args.nerf)

    def build_one(V, F, index=None):
        name = f"mesh {args.mesh}" + (f" (edit region {index + 1})" if index is not None else "")
        own_cut = cut if cut is None or index is None else cut[part == index]
        cage = build_nerf_cage(
            V,
            F,
            nerf,
            args.margin,
            args.threshold,
            edge_length=args.edge_length,
            target_tets=args.target_tets,
            name=name,
            cut=own_cut,
        )
        if refine_edge is not None:
            before = len(cage.tets)
            cage.vertices, cage.tets = refine_cage(cage.vertices, cage.tets, refine_edge, box)
            print(
                f"cage: refined to longest edges <= {refine_edge:g}"
                + ("" if box is None else " in the box")
                + f": {before} -> {len(cage.tets)} tets"
            )
        return cage

    aabb = nerf.aabb.detach().cpu().double().numpy().reshape(2, 3)
    extra = {}
    if part is not None and len(np.unique(part)) > 1:  # several edit regions: a cage per object, in one
        cage, cage_part = build_part_cages(verts, faces, part, build_one)
        pinned = part_cut_pins(cage.vertices, cage_part, verts, part, cut, cage.margin)
        extra["vertex_part"] = cage_part
    else:
        cage = build_one(verts, faces)
        pinned = cut_pins(cage.vertices, verts, cut, cage.margin)
    if args.no_pin_cut:
        pinned = np.zeros(0, dtype=np.int64)
    extra.update({"margin": cage.margin, "clearance": cage.clearance, "bounds": aabb, "pinned_vertices": pinned})
    if region is not None:
        extra.update({f"region_{k}": np.asarray(v) for k, v in region.to_dict().items()})
    save_cage(args.out, cage.vertices, cage.tets, **extra)
    print(
        f"cage: {len(cage.tets)} tets, {len(cage.vertices)} vertices, margin {cage.margin:.4g}, clearance {cage.clearance:.4g}, "
        f"{vertices_outside(cage.vertices, aabb)} vertices outside the NeRF's bounds; envelope {cage.timings['envelope_s']:.1f}s, "
        f"tetrahedralize {cage.timings['tetrahedralize_s']:.1f}s -> {args.out}"
    )
    for line in cage.warnings:
        print(f"warning: {line}", file=sys.stderr)
    if cut is not None and cut.any():
        print(
            f"cut: {int(cut.sum())} mesh vertices close the region's cut; "
            + ("not pinned (--no-pin-cut)" if args.no_pin_cut else f"{len(pinned)} cage vertices pinned there")
        )
    return 0
