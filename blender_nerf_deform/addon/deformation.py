"""Handle poses → the worker's solve request → deformed cage, for renders and for the live preview.

Determinism (a render farm, F12 and the viewport agree): the request is built
from the depsgraph-evaluated handles and NeRF at the frame being shown or
rendered, and the worker's solve depends on nothing else.
"""

from __future__ import annotations

import bpy
import numpy as np

from .cage_store import load_cage, load_embedding
from .handles import group_vertices, handle_target
from .properties import PIN_GROUP, handles_of

# Surface vertex indices of each region, by (mesh pointer, group name); vertex groups are edited
# in Edit Mode only, so the cache is dropped whenever a surface is there.
_region_cache: dict[tuple[int, str], np.ndarray] = {}


def region_vertices(surface: bpy.types.Object, group: str) -> np.ndarray:
    if surface.mode == "EDIT":
        _region_cache.clear()
        return group_vertices(surface, group)
    key = (surface.data.as_pointer(), group)
    if key not in _region_cache:
        _region_cache[key] = group_vertices(surface, group)
    return _region_cache[key]


def solve_request(nerf, depsgraph) -> tuple[dict, dict] | None:
    """The worker request for `nerf`'s handles at this frame, or None when it has no handle."""
    s = nerf.nerf_deform
    handles = handles_of(nerf)
    if not handles:
        return None
    surface = s.surface
    rest, tets = load_cage(s.cage.data)
    tet_ids, weights = load_embedding(surface.data)
    regions = [region_vertices(surface, h.nerf_deform.region) for h in handles]
    params = {
        "mode": s.deformation_mode,
        "transforms": [handle_target(h, nerf, depsgraph).tolist() for h in handles],
        "handle_names": [h.name for h in handles],
    }
    arrays = {
        "rest_vertices": rest,
        "tets": tets,
        "tet_ids": tet_ids,
        "weights": weights,
        "handle_index": np.concatenate(regions) if regions else np.zeros(0, np.int64),
        "handle_counts": np.array([len(r) for r in regions], dtype=np.int64),
        "pin_index": region_vertices(surface, PIN_GROUP),
    }
    return params, arrays


class AsyncSolver:
    """Preview solves for one NeRF: one request in flight, the newest pose waiting behind it."""

    def __init__(self, client, on_result):
        self.client = client
        self.on_result = on_result
        self.in_flight = False
        self.waiting: tuple[dict, dict] | None = None
        self.last_error = ""

    def request(self, params: dict, arrays: dict) -> None:
        if self.in_flight:
            self.waiting = (params, arrays)  # only the newest pose matters
            return
        self.in_flight = True
        self.client.submit("solve", params, arrays, on_done=self._done, on_error=self._failed)

    def _next(self) -> None:
        self.in_flight = False
        if self.waiting is not None:
            pending, self.waiting = self.waiting, None
            self.request(*pending)

    def _done(self, result: dict, arrays: dict) -> None:
        self.last_error = ""
        self.on_result(result, arrays["deformed_vertices"])
        self._next()

    def _failed(self, error) -> None:
        if error.kind != "cancelled" and str(error) != self.last_error:
            self.last_error = str(error)
            print(f"NeRF Deform preview: {error}")
        self._next()
