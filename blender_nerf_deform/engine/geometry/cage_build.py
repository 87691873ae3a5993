"""The cage of an extracted surface, as Build Cage and the `cage` command make it: one function for both.

Steps, in this order:

1. one cage per part (the objects of several edit regions, `build_part_cages`), each around its
   own mesh: with a NeRF its margin is widened where the density is still soft
   (`build_nerf_cage`), without one the plain margin (`build_cage`);
2. optionally refined (`cage_refine.refine_cage`, the one refiner): in the box of a selection of
   surface vertices widened by the margin and the edge length (Build Cage's Refine Selected; the
   edge defaults to half the cage's median edge), or in a given box (`cage --refine-box`), or
   everywhere. Refinement runs once on the cage of all parts, after they are merged, as the
   worker's Build Cage always did (the command line used to refine each part before merging):
   no tet joins two parts and a bisection only spreads across shared edges, so each part's tets
   are split as they would be alone; only the numbering of the new vertices differs;
3. the cage vertices pinned where an edit region cut the scene (`cut_pins`, part by part);
4. optionally the surface embedded in it (what the add-on stores beside the cage).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .cage import Cage, build_cage, build_nerf_cage, build_part_cages, cut_pins, part_cut_pins
from .cage_refine import extend_vertex_labels, median_edge, refine_cage, selection_box
from .embedding import Embedding, embed_points, embed_points_by_part


@dataclass
class SurfaceCage:
    cage: Cage  # vertices and tets (refined), margin, clearance, timings, warnings
    part: np.ndarray | None  # (N,) the part of each cage vertex; None for a cage of one part
    pinned: np.ndarray  # the cage vertices pinned at the cut (sorted)
    embedding: Embedding | None  # the surface in the cage, when asked for
    refined: dict | None  # {"edge", "box" ((2, 3) or None: everywhere), "tets_before"} when refined


def _no_progress(fraction: float, message: str) -> None:
    pass


def build_surface_cage(
    vertices: np.ndarray,
    faces: np.ndarray,
    nerf=None,
    *,
    margin: float | None = None,
    threshold: float | None = None,
    edge_length: float | None = None,
    target_tets: int | None = None,
    cut: np.ndarray | None = None,
    part: np.ndarray | None = None,
    refine_points: np.ndarray | None = None,
    refine_edge: float | None = None,
    refine_box: np.ndarray | None = None,
    refine_all: bool = False,
    pin_cut: bool = True,
    embed: bool = True,
    name: str = "mesh",
    log: Callable[[str], None] = print,
    progress: Callable[[float, str], None] = _no_progress,
) -> SurfaceCage:
    """The cage around a surface mesh (float64 vertices, int64 faces): see the module docstring.

    Refinement: `refine_points` (the surface vertices the user will stretch; `refine_edge` None:
    half the cage's median edge), or `refine_box` with `refine_edge`, or `refine_all` with
    `refine_edge`; none of them: no refinement."""
    size = {"edge_length": edge_length, "target_tets": target_tets}
    several = part is not None and len(np.unique(part)) > 1
    part_vertices = {int(i): np.flatnonzero(part == i) for i in np.unique(part)} if several else {}

    def build_one(V, F, index=None):
        if nerf is None:
            return build_cage(V, F, margin, **size)
        own_cut = None if cut is None else (cut if index is None else cut[part_vertices[index]])
        label = name if index is None else f"{name} (edit region {index + 1})"
        return build_nerf_cage(V, F, nerf, margin, threshold, **size, name=label, log=log, cut=own_cut)

    if several:  # one cage per edit region's object, in one cage
        built, cage_part = build_part_cages(vertices, faces, part, build_one)
    else:
        built, cage_part = build_one(vertices, faces), None
    refined = None
    if refine_points is not None or refine_box is not None or refine_all:
        progress(0.8, "refining the cage around the selection" if refine_points is not None else "refining the cage")
        n_before = len(built.tets)
        V, T = np.asarray(built.vertices, dtype=np.float64), np.asarray(built.tets, dtype=np.int64)
        box = refine_box
        if refine_points is not None:
            edge = refine_edge if refine_edge is not None else 0.5 * median_edge(V, T)
            box = selection_box(refine_points, built.margin, edge)
        else:
            edge = refine_edge
        built.vertices, built.tets = refine_cage(V, T, float(edge), box)
        if several:
            cage_part = extend_vertex_labels(cage_part, built.tets, len(built.vertices))
        refined = {"edge": float(edge), "box": None if box is None else np.asarray(box), "tets_before": int(n_before)}
    embedding = None
    if embed:
        progress(0.9, "embedding the surface")
        if several:
            embedding = embed_points_by_part(vertices, part, built.vertices, built.tets, cage_part)
        else:
            embedding = embed_points(vertices, built.vertices, built.tets)
    if not pin_cut:
        pinned = np.zeros(0, dtype=np.int64)
    elif several:
        pinned = part_cut_pins(built.vertices, cage_part, vertices, part, cut, built.margin)
    else:
        pinned = cut_pins(built.vertices, vertices, cut, built.margin)
    return SurfaceCage(built, cage_part, pinned, embedding, refined)
