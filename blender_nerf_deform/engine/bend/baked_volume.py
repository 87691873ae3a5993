"""A baked volume's lattice and its file, pure numpy: what the engine's bake writes and the add-on reads.

`VolumeGrid`: cubic voxels over an oriented box, `resolution` along its longest
side, and the map of voxel indices (a voxel's centre, OpenVDB's convention) to
the NeRF's frame. `BakedVolume`: one frame's voxels that hold anything (sparse):
index, density per NeRF unit, colour (sRGB); `.save` / `load_baked` as .npz
(`bake-volume`'s files; tools/vdb_from_npz.py turns them into OpenVDB). Sampling
the NeRF on the grid is volume.py's (torch); this module imports no torch, so
Blender's own Python reads the files.
"""

from __future__ import annotations

import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import EngineError
from ..files import atomic_write
from ..geometry.region import EditRegion
from ..memory import check_memory

MAX_RESOLUTION = 2048
# What a voxel costs while baking: density and weight (float32), colour (3 float32), masks, and the
# sparse copy of the result (index int32 x3, density, colour).
BYTES_PER_VOXEL = 4 + 4 + 12 + 2 + 28
@dataclass(frozen=True)
class VolumeGrid:
    """A lattice of cubic voxels: `shape` (nx, ny, nz) and the 4x4 index → NeRF-frame map of voxel centres."""

    shape: tuple[int, int, int]
    index_to_nerf: np.ndarray

    @property
    def voxel_size(self) -> float:
        return float(np.linalg.norm(self.index_to_nerf[:3, 0]))

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def points(self, ijk: np.ndarray) -> np.ndarray:
        """NeRF-frame positions of (fractional) index coordinates (N, 3)."""
        return ijk @ self.index_to_nerf[:3, :3].T + self.index_to_nerf[:3, 3]


def check_resolution(resolution) -> int:
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or not 1 <= resolution <= MAX_RESOLUTION:
        raise EngineError(f"the volume's resolution must be a whole number of voxels from 1 to {MAX_RESOLUTION} "
                          f"along the box's longest side, got {resolution!r}")
    return int(resolution)


def volume_grid(box: EditRegion, resolution: int) -> VolumeGrid:
    """Cubic voxels over the oriented `box`, `resolution` along its longest side (at least one per axis)."""
    resolution = check_resolution(resolution)
    voxel = float(np.max(box.size)) / resolution
    shape = tuple(int(max(1, math.ceil(s / voxel - 1e-9))) for s in box.size)
    lo_local = -0.5 * voxel * np.asarray(shape, dtype=np.float64)  # centred on the box
    m = np.eye(4)
    m[:3, :3] = box.rotation * voxel
    m[:3, 3] = box.to_world(lo_local + 0.5 * voxel)  # voxel (0,0,0)'s centre
    return VolumeGrid(shape, m)


def box_of_bounds(bounds) -> EditRegion:
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    size = b[1] - b[0]
    if not (np.isfinite(b).all() and np.all(size > 0)):
        raise EngineError(f"the box to bake must have a positive size on every axis, got {b.tolist()}")
    return EditRegion(center=0.5 * (b[0] + b[1]), size=size, rotation=np.eye(3))


def check_volume_memory(grid: VolumeGrid) -> None:
    nx, ny, nz = grid.shape
    check_memory(float(grid.n_voxels) * BYTES_PER_VOXEL, f"a {nx}x{ny}x{nz} volume",
                 "bake it at a lower resolution, or over a smaller box (an edit region, or the cage's box)")


@dataclass
class BakedVolume:
    """One frame's grid: the voxels that hold anything (sparse), density per NeRF unit, colour sRGB."""

    grid: VolumeGrid
    index: np.ndarray  # (N, 3) int32 voxel indices (i, j, k)
    density: np.ndarray  # (N,) float32
    color: np.ndarray  # (N, 3) float32 in [0, 1]
    stats: dict

    def save(self, path) -> None:
        """An .npz written atomically (a temporary file renamed), readable with allow_pickle=False."""
        arrays = {"shape": np.asarray(self.grid.shape, dtype=np.int64), "index_to_nerf": self.grid.index_to_nerf,
                  "index": self.index, "density": self.density, "color": self.color}
        atomic_write(Path(path), lambda f: np.savez_compressed(f, **arrays))


def load_baked(path) -> BakedVolume:
    """A baked frame's .npz, every array checked (a clear error naming the file)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("shape", "index_to_nerf", "index", "density", "color")}
    except FileNotFoundError:
        raise EngineError(f"baked volume {path} does not exist") from None
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise EngineError(f"{path} is not a baked volume (shape, index_to_nerf, index, density, color): {exc}") from None
    shape, m, index = arrays["shape"], arrays["index_to_nerf"], arrays["index"]
    n = len(index)
    if (shape.shape != (3,) or (shape < 1).any() or m.shape != (4, 4) or not np.isfinite(m).all()
            or index.ndim != 2 or index.shape[1] != 3 or arrays["density"].shape != (n,)
            or arrays["color"].shape != (n, 3) or (n and ((index < 0).any() or (index >= shape).any()))):
        raise EngineError(f"{path}: its arrays do not describe a baked volume (shapes or indices out of range)")
    grid = VolumeGrid(tuple(int(s) for s in shape), m.astype(np.float64))
    return BakedVolume(grid, index.astype(np.int32), arrays["density"].astype(np.float32),
                       arrays["color"].astype(np.float32), {})
