"""One frame of a NeRF, at rest or ray-bent through a pose of its cage: what `render` and the worker both run.

`PosedRenderer(model, rest_vertices, tets)` builds the cage's `CageBend` once
(its rest-cage locator); `render(camera, deformed)` poses it only when the pose
differs from the last one (a still pose over many frames is prepared once) and
renders; `bake(grid, deformed)` samples the posed NeRF on a voxel grid instead
(volume.py). Without a cage it renders the NeRF as trained.
"""

from __future__ import annotations

import numpy as np

from ..nerf.renderer import render_image
from .cage_bend import CageBend
from .volume import bake_volume


class PosedRenderer:
    def __init__(self, model, rest_vertices=None, tets=None):
        self.model = model
        self.bend = CageBend(model, rest_vertices, tets) if rest_vertices is not None else None
        self._pose: np.ndarray | None = None

    def pose(self, deformed_vertices=None) -> CageBend | None:
        """The cage's map posed at `deformed_vertices` (None: at rest, no map)."""
        if deformed_vertices is None:
            return None
        if self.bend is None:
            raise ValueError("a deformed pose needs the rest cage it deforms")
        pose = np.asarray(deformed_vertices, dtype=np.float64)
        if self._pose is None or self._pose.shape != pose.shape or not np.array_equal(self._pose, pose):
            self.bend.set_deformed(pose)
            self._pose = pose.copy()
        return self.bend

    def render(self, camera, deformed_vertices=None, progress=None, substeps: int = 1) -> dict:
        """`render_image`'s result (`substeps` samples per step of the march), plus `inversion` (the pose's
        InversionReport, or None at rest)."""
        bend = self.pose(deformed_vertices)
        extra = bend.render_kwargs() if bend is not None else {}
        out = render_image(self.model, camera, progress=progress, substeps=substeps, **extra)
        out["inversion"] = bend.inversion if bend is not None else None
        return out

    def bake(self, grid, deformed_vertices=None, supersample: int = 1, progress=None):
        """The NeRF at this pose sampled on a voxel grid (`volume.bake_volume`), plus its inversion report."""
        bend = self.pose(deformed_vertices)
        baked = bake_volume(self.model, grid, bend, supersample=supersample, progress=progress)
        return baked, (bend.inversion if bend is not None else None)
