"""`cage`: the tetrahedral cage around a NeRF's extracted mesh, built once, as CAGE.npz.

    python -m blender_nerf_deform.engine cage --nerf CKPT --mesh MESH.ply --out CAGE.npz
        [--margin M] [--edge-length L] [--target-tets N] [--threshold T]
        [--region REGION.json] [--no-pin-cut] [--refine-edge L [--refine-box XMIN YMIN ZMIN XMAX YMAX ZMAX]]

--refine-edge refines the built cage where a pose will stretch (geometry.cage_refine.refine_cage),
in --refine-box or everywhere: the tets stay fixed over an animation, so a finer cage is chosen
here, once. The cage is built by geometry.cage_build.build_surface_cage, as the worker's Build Cage.

Where the mesh was closed along an edit region's cut (its `nerf_cut` vertices, or with
--region its vertices on the region's boundary), the cage vertices there are pinned
(`pinned_vertices` in CAGE.npz), unless --no-pin-cut.
"""

from __future__ import annotations

import sys

import numpy as np

from ..errors import EngineError
from ..files import check_writable
from ..geometry.cage import check_cage_options, cut_from_region, vertices_outside
from ..geometry.cage_build import build_surface_cage
from ..geometry.mesh_io import read_ply, save_cage
from ..geometry.region import load_region
from ..nerf.checkpoint import load_nerf
from ..service.requests import CageRequest


def _request(args) -> tuple[CageRequest, object]:
    """The `cage` request of the options (the worker's, with the mesh read from the PLY), and the region."""
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
    request = CageRequest(
        verts,
        faces,
        cut=cut,
        part=part,
        checkpoint=args.nerf,
        threshold=args.threshold,
        margin=args.margin,
        edge_length=args.edge_length,
        target_tets=args.target_tets,
        pin_cut=not args.no_pin_cut,
        refine_edge=refine_edge,
        refine_box=box,
    )
    return request, region


def main(args) -> int:
    request, region = _request(args)
    nerf = load_nerf(request.checkpoint)
    built = build_surface_cage(
        request.vertices,
        request.faces,
        nerf,
        margin=request.margin,
        threshold=request.threshold,
        edge_length=request.edge_length,
        target_tets=request.target_tets,
        cut=request.cut,
        part=request.part,
        refine_edge=request.refine_edge,
        refine_box=request.refine_box,
        refine_all=request.refine_edge is not None and request.refine_box is None,
        pin_cut=request.pin_cut,
        embed=False,
        name=f"mesh {args.mesh}",
    )
    cage, cut, refined = built.cage, request.cut, built.refined
    if refined is not None:
        print(
            f"cage: refined to longest edges <= {refined['edge']:g}"
            + ("" if refined["box"] is None else " in the box")
            + f": {refined['tets_before']} -> {len(cage.tets)} tets"
        )
    aabb = nerf.aabb.detach().cpu().double().numpy().reshape(2, 3)
    extra = {} if built.part is None else {"vertex_part": built.part}
    extra.update({"margin": cage.margin, "clearance": cage.clearance, "bounds": aabb, "pinned_vertices": built.pinned})
    if region is not None:
        extra.update({f"region_{k}": np.asarray(v) for k, v in region.to_dict().items()})
    save_cage(args.out, cage.vertices, cage.tets, **extra)
    print(
        f"cage: {len(cage.tets)} tets, {len(cage.vertices)} vertices, margin {cage.margin:.4g}, "
        f"clearance {cage.clearance:.4g}, {vertices_outside(cage.vertices, aabb)} vertices outside the NeRF's "
        f"bounds; envelope {cage.timings['envelope_s']:.1f}s, tetrahedralize {cage.timings['tetrahedralize_s']:.1f}s "
        f"-> {args.out}"
    )
    for line in cage.warnings:
        print(f"warning: {line}", file=sys.stderr)
    if cut is not None and cut.any():
        print(
            f"cut: {int(cut.sum())} mesh vertices close the region's cut; "
            + ("not pinned (--no-pin-cut)" if args.no_pin_cut else f"{len(built.pinned)} cage vertices pinned there")
        )
    return 0
