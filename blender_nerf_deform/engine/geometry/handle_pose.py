"""The cage pose of handle transforms: what a frame's render and the live preview solve.

`RegionDeformer` is built once per cage, embedding and set of regions (the worker keeps it in its
session) and solved per frame from that frame's transforms alone, so F12, a render farm's split
`-s/-e` and the viewport agree:
- "ARAP": surface_arap.SurfaceArap. The handles' regions (surface vertices) follow their handles'
  affines in a least-squares sense, the pinned region and the cut's cage vertices stay, the rest of
  the cage moves as rigidly as possible, and no tet ever inverts.
- "AFFINE": each handle's region, mapped to the cage vertices it rests on, takes its handle's affine;
  the rest of the cage stays.
"""

from __future__ import annotations

import numpy as np

from ..errors import EngineError
from .deform import affine_region, regions_to_cage
from .poses import MAX_COORDINATE
from .surface_arap import SurfaceArap


class RegionDeformer:
    """The cage pose of handle transforms: regions of the extracted mesh moved by their handles."""

    MODES = ("ARAP", "AFFINE")

    def __init__(
        self,
        rest_vertices: np.ndarray,
        tets: np.ndarray,
        embedding,
        handle_regions: list,
        pin_region: np.ndarray | None = None,
        names: list[str] | None = None,
        mode: str = "ARAP",
        cage_pins: np.ndarray | None = None,
    ):
        """`handle_regions`: surface vertex indices per handle; `pin_region`: surface vertices the artist
        pinned; `cage_pins`: cage vertices pinned where an edit region cut the scene (cage.cut_pins)."""
        if mode not in self.MODES:
            raise EngineError(f"unknown deformation mode {mode!r}: ARAP or AFFINE")
        self.mode = mode
        self.rest = np.asarray(rest_vertices, dtype=np.float64)
        self.names = list(names or [f"handle {i}" for i in range(len(handle_regions))])
        self.n_handles = len(handle_regions)
        if mode == "ARAP":
            self.surface = SurfaceArap(self.rest, tets, embedding, handle_regions, pin_region, cage_pins, self.names)
            self.precompute_s = self.surface.precompute_s
            return
        pins = [np.asarray(pin_region, dtype=np.int64)] if pin_region is not None and len(pin_region) else []
        regions = regions_to_cage(
            embedding, list(handle_regions) + pins, len(self.rest), self.names + ["the pinned region"] * len(pins)
        )
        self.cage_regions = regions[: self.n_handles]
        self.precompute_s = 0.0

    @staticmethod
    def _checked(name: str, transform) -> np.ndarray:
        """A handle's 4x4 (or 3x4) transform as float64; EngineError naming the handle when it is not finite
        or moves its region beyond MAX_COORDINATE."""
        try:
            t = np.asarray(transform, dtype=np.float64)
        except (TypeError, ValueError):
            raise EngineError(f"handle {name!r}: its transform is not a matrix of numbers") from None
        if t.shape not in ((4, 4), (3, 4)):
            raise EngineError(f"handle {name!r}: its transform must be a 4x4 matrix, got shape {t.shape}")
        if not np.isfinite(t).all():
            raise EngineError(
                f"handle {name!r} has a non-finite transform (location {t[:3, 3].tolist()}): "
                "give it a finite location, rotation and scale"
            )
        if np.abs(t[:3]).max() > MAX_COORDINATE:
            raise EngineError(
                f"handle {name!r} moves its region beyond {MAX_COORDINATE:g} NeRF units (location "
                f"{', '.join(f'{x:.3g}' for x in t[:3, 3])}): bring it back near the NeRF"
            )
        return t

    def solve(self, transforms: list) -> tuple[np.ndarray, dict]:
        """(deformed cage vertices, stats) for one 4x4 transform per handle."""
        if len(transforms) != self.n_handles:
            raise EngineError(f"{len(transforms)} handle transforms for {self.n_handles} handles")
        transforms = [self._checked(name, t) for name, t in zip(self.names, transforms)]
        if self.mode == "AFFINE":
            deformed = self.rest
            for region, transform in zip(self.cage_regions, transforms):
                deformed = affine_region(deformed, region, transform)
            return deformed, {}
        pose = self.surface.solve(transforms)
        stats = {
            "iterations": pose.iterations,
            "converged": bool(pose.converged),
            "solve_s": pose.seconds,
            "surface_residual": pose.surface_residual,
            "min_det_f": pose.min_det,
            "barrier_tets": pose.barrier_tets,
        }
        if pose.reflected:
            stats["reflected_handles"] = pose.reflected
        return pose.vertices, stats
