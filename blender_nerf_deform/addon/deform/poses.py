"""Poses of a NeRF's cage as worker requests: for a frame's render, and for the live preview.

Determinism (a render farm, F12 and the viewport agree): the request is built
from the depsgraph-evaluated handles and NeRF at the frame being shown or
rendered, and the worker's solve depends on nothing else.
"""

from __future__ import annotations

import logging

import numpy as np

from ...engine.service.protocol import content_key
from ...engine.service.requests import CagePose, DeformMode, HandlesPose, Pose, RestPose, SolveAnswer, SolveRequest
from ..data.cage_store import (
    CageDataError,
    cage_pins,
    deformed_cage_in_nerf_frame,
    has_cage,
    load_cage,
    shared_cage,
    shared_embedding,
)
from ..data.properties import PIN_GROUP, PlacementError, handles_of
from .handles import handle_target, region_vertices

logger = logging.getLogger(__name__)


def handle_pose(nerf, depsgraph, to_nerf=None) -> tuple[HandlesPose, dict] | None:
    """`nerf`'s handles at this frame as (pose, shared content), or None without a handle.
    `to_nerf`: the NeRF's evaluated world -> NeRF frame Matrix when the caller has it.

    The pose (mode, one 4x4 transform per handle in the NeRF's frame, their names) is
    all that changes from frame to frame; the cage, the surface's embedding, the handles'
    regions and the cage's pins at the cut travel as shared content, by key (sent to a worker once).
    """
    s = nerf.nerf_deform
    handles = handles_of(nerf)
    surface = s.surface
    if not handles or surface is None or s.cage is None:
        return None
    if surface.type != "MESH":  # a script set it: the handles' vertex groups are on no mesh
        article = "an" if surface.type[0] in "AEIOU" else "a"
        raise CageDataError(
            f"NeRF object '{nerf.name}': its extracted mesh is set to '{surface.name}', "
            f"{article} {surface.type.lower()}, not a mesh; set it back to the mesh (or Extract Mesh and "
            "Build Cage again)"
        )
    regions = [region_vertices(surface, h.nerf_deform.region) for h in handles]
    for handle, region in zip(handles, regions):
        if not len(region):
            group = h_name = handle.nerf_deform.region
            if surface.vertex_groups.get(group) is None:
                why = f"names vertex group '{h_name}', which '{surface.name}' does not have (renamed or deleted?)"
            else:
                why = f"has no vertices: its vertex group '{group}' of '{surface.name}' is empty"
            raise PlacementError(
                f"handle '{handle.name}' {why}: name the group back, or remove the handle and add it "
                "again on a selection"
            )
    region_arrays = {
        "handle_index": np.concatenate(regions) if regions else np.zeros(0, np.int64),
        "handle_counts": np.array([len(r) for r in regions], dtype=np.int64),
        "pin_index": region_vertices(surface, PIN_GROUP),
        # Cage vertices pinned where the edit region cut the scene: ARAP keeps them at rest (a
        # handle's region wins over them); in Affine Regions only the handles' regions move anyway.
        "cage_pin_index": cage_pins(s.cage),
    }
    pose = HandlesPose(
        DeformMode(s.deformation_mode),
        tuple(handle_target(h, nerf, depsgraph, to_nerf) for h in handles),
        tuple(h.name for h in handles),
    )
    shared = {
        "cage": shared_cage(s.cage.data),
        "embedding": shared_embedding(surface.data, s.cage.data),
        "regions": (content_key(*region_arrays.values()), lambda: region_arrays),
    }
    return pose, shared


def frame_pose(nerf, depsgraph, to_nerf=None) -> tuple[Pose, dict]:
    """What a frame renders `nerf` at: (pose, shared content) for the worker's render.
    `to_nerf`: the NeRF's evaluated world -> NeRF frame (a Matrix) when the caller has it (a render
    computes it once per NeRF and frame); computed here otherwise.

    Handles: solved in the worker with the frame (ARAP or affine). Cage Modifiers: the cage's
    vertices as its modifiers deform them. No cage, or no handle: the rest pose.
    """
    s = nerf.nerf_deform
    if s.cage is None:
        return RestPose(), {}
    if s.cage.type != "MESH" or not has_cage(s.cage.data):  # set by a script, or its mesh swapped: not a render at rest
        raise CageDataError(
            f"NeRF object '{nerf.name}': its cage is set to '{s.cage.name}', which holds no NeRF cage "
            "(not one Build Cage made); select the NeRF and run Build Cage again"
        )
    if s.deformation_mode == "MODIFIERS":
        deformed = deformed_cage_in_nerf_frame(nerf, s.cage, depsgraph, to_nerf)
        return CagePose(deformed), {"cage": shared_cage(s.cage.data)}
    request = handle_pose(nerf, depsgraph, to_nerf)
    if request is None:
        return RestPose(), {}
    return request


def deformed_cage(nerf, depsgraph, client) -> np.ndarray | None:
    """The cage's vertices (NeRF frame) as the frame being shown deforms them, solved as a render
    solves them (scripts, tests); None when the NeRF has no cage."""
    s = nerf.nerf_deform
    if s.cage is None or not has_cage(s.cage.data):
        return None
    pose, shared = frame_pose(nerf, depsgraph)
    if isinstance(pose, CagePose):
        return pose.deformed_vertices
    if isinstance(pose, RestPose):
        return load_cage(s.cage.data)[0]
    params, arrays = SolveRequest(pose).to_wire()
    _result, out = client.call("solve", params, arrays, shared=shared)
    return out["deformed_vertices"]


class AsyncSolver:
    """Preview solves for one NeRF: one request in flight, the newest pose waiting behind it.
    Each asks the worker for the deformed surface itself (answer "surface"), the preview's shape key."""

    def __init__(self, client, on_result):
        self.client = client
        self.on_result = on_result
        self.in_flight = False
        self.waiting: tuple[HandlesPose, dict] | None = None
        self.last_error = ""

    def request(self, pose: HandlesPose, shared: dict) -> None:
        if self.in_flight:
            self.waiting = (pose, shared)  # only the newest pose matters
            return
        self.in_flight = True
        params, arrays = SolveRequest(pose, SolveAnswer.SURFACE).to_wire()
        self.client.submit("solve", params, arrays, shared=shared, on_done=self._done, on_error=self._failed)

    def _next(self) -> None:
        self.in_flight = False
        if self.waiting is not None:
            pending, self.waiting = self.waiting, None
            self.request(*pending)

    def _done(self, result: dict, arrays: dict) -> None:
        self.last_error = ""
        self.on_result(result, arrays["surface"])
        self._next()

    def _failed(self, error) -> None:
        if error.kind != "cancelled" and str(error) != self.last_error:
            self.last_error = str(error)
            logger.warning("NeRF Deform preview: %s", error)
        self._next()
