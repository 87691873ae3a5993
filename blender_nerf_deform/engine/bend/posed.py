"""One frame of a NeRF, at rest or ray-bent through a pose of its cage: what `render` and the worker both run.

`PosedRenderer(model, rest_vertices, tets)` builds the cage's `CageBend` once
(its rest-cage locator); `render(camera, deformed)` poses it only when the pose
differs from the last one (a still pose over many frames is prepared once) and
renders. Without a cage it renders the NeRF as trained.
"""

from __future__ import annotations

import numpy as np

from ..nerf.renderer import render_image
from .cage_bend import CageBend


class PosedRenderer:
    def __init__(self, model, rest_vertices=None, tets=None):
        self.model = model
        self.bend = CageBend(model, rest_vertices, tets) if rest_vertices is not None else None
        self._pose: np.ndarray | None = None

    def render(self, camera, deformed_vertices=None, progress=None) -> dict:
        """`render_image`'s result, plus `inversion` (the pose's InversionReport, or None at rest)."""
        extra = {}
        if deformed_vertices is not None:
            if self.bend is None:
                raise ValueError("a deformed pose needs the rest cage it deforms")
            pose = np.asarray(deformed_vertices, dtype=np.float64)
            if self._pose is None or self._pose.shape != pose.shape or not np.array_equal(self._pose, pose):
                self.bend.set_deformed(pose)
                self._pose = pose.copy()
            extra = self.bend.render_kwargs()
        out = render_image(self.model, camera, progress=progress, **extra)
        out["inversion"] = self.bend.inversion if extra else None
        return out
