"""A baked volume's lattice and its file, pure numpy: what the engine's bake writes and the add-on reads.

`VolumeGrid`: cubic voxels over an oriented box, `resolution` along its longest
side, and the map of voxel indices (a voxel's centre, OpenVDB's convention) to
the NeRF's frame. `BakedVolume`: one frame's voxels that hold anything (sparse):
index, density per NeRF unit, colour (sRGB); `.save` / `load_baked` as .npz
(`bake-volume`'s files; tools/vdb_from_npz.py turns them into OpenVDB). Sampling
the NeRF on the grid is volume.py's (torch); this module imports no torch, so
Blender's own Python reads the files.

Every input is checked where it enters: the box against the voxel size OpenVDB can
place (`volume_grid`), and a file's arrays, their dtypes, shapes and declared sizes
read from its headers, against the memory available before any is loaded
(`load_baked`), then their values (`check_baked_arrays`, which the add-on's writer
runs on what the worker sends too).
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
from ..geometry.poses import MAX_COORDINATE
from ..geometry.region import EditRegion
from ..memory import check_memory

MAX_RESOLUTION = 2048
# The smallest voxel (NeRF units) a grid may have: OpenVDB refuses a transform whose determinant is
# below 3e-15 as "nearly singular", which cubic voxels under 1.44e-5 are.
MIN_VOXEL_SIZE = 2e-5
ARRAYS = ("shape", "index_to_nerf", "index", "density", "color")
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
    if (
        isinstance(resolution, bool)
        or not isinstance(resolution, (int, np.integer))
        or not 1 <= resolution <= MAX_RESOLUTION
    ):
        raise EngineError(
            f"the volume's resolution must be a whole number of voxels from 1 to {MAX_RESOLUTION} "
            f"along the box's longest side, got {resolution!r}"
        )
    return int(resolution)


def volume_grid(box: EditRegion, resolution: int, content=None) -> VolumeGrid:
    """Cubic voxels over the oriented `box`, `resolution` along its longest side (at least one per axis).
    A box that is not finite, or whose voxels would be smaller than OpenVDB can place, is refused; with
    `content` (the NeRF's box, (2, 3) bounds), so is one whose voxels would be larger than all of it."""
    resolution = check_resolution(resolution)
    size = np.asarray(box.size, dtype=np.float64)
    described = " x ".join(f"{x:.3g}" for x in size)
    if not (np.isfinite(size).all() and np.isfinite(box.center).all() and (size > 0).all()):
        raise EngineError(
            f"the box to bake ({described} NeRF units, centred at "
            f"({', '.join(f'{x:.3g}' for x in box.center)})) must be finite and positive on every axis"
        )
    longest = float(size.max())
    if longest < MIN_VOXEL_SIZE:
        raise EngineError(
            f"the box to bake ({described} NeRF units) is too small for one voxel: OpenVDB places "
            f"voxels from {MIN_VOXEL_SIZE:g} NeRF units; bake a larger box"
        )
    voxel = longest / resolution
    # A relative slack: a box scaled in Blender arrives through float32 (0.002 as 0.0019999), and the
    # resolution suggested below must itself pass this test.
    if voxel < MIN_VOXEL_SIZE * (1 - 1e-6):
        most = int(longest / MIN_VOXEL_SIZE * (1 + 1e-6))
        raise EngineError(
            f"the box to bake ({described} NeRF units) at resolution {resolution} has voxels of "
            f"{voxel:.3g}, smaller than the {MIN_VOXEL_SIZE:g} OpenVDB can place: bake it at a "
            f"resolution of at most {most}, or a larger box"
        )
    if content is not None:
        # A box far larger than the NeRF (a region scaled by mistake, a cage posed far out) samples the
        # NeRF at a handful of points or none: an empty or meaningless volume, not an error, without this.
        c = np.asarray(content, dtype=np.float64).reshape(2, 3)
        nerf_side = float((c[1] - c[0]).max())
        if voxel > nerf_side:
            least = math.ceil(longest / nerf_side)
            advice = (
                f"bake it at a resolution of at least {least}, or a smaller box"
                if least <= MAX_RESOLUTION
                else "bake a smaller box"
            )
            raise EngineError(
                f"the box to bake ({described} NeRF units) at resolution {resolution} has voxels of "
                f"{voxel:.3g}, larger than the NeRF's whole box ({nerf_side:.3g} across), which would "
                f"fill less than one voxel: {advice}"
            )
    shape = tuple(int(max(1, math.ceil(s / voxel - 1e-9))) for s in size)
    lo_local = -0.5 * voxel * np.asarray(shape, dtype=np.float64)  # centred on the box
    m = np.eye(4)
    m[:3, :3] = box.rotation * voxel
    m[:3, 3] = box.to_world(lo_local + 0.5 * voxel)  # voxel (0,0,0)'s centre
    if not np.isfinite(m).all():
        raise EngineError(f"the box to bake ({described} NeRF units) lies too far out to place its voxels")
    return VolumeGrid(shape, m)


def box_of_bounds(bounds) -> EditRegion:
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    size = b[1] - b[0]
    if not (np.isfinite(b).all() and np.all(size > 0)):
        raise EngineError(f"the box to bake must have a positive size on every axis, got {b.tolist()}")
    return EditRegion(center=0.5 * (b[0] + b[1]), size=size, rotation=np.eye(3))


def check_volume_memory(grid: VolumeGrid) -> None:
    nx, ny, nz = grid.shape
    check_memory(
        float(grid.n_voxels) * BYTES_PER_VOXEL,
        f"a {nx}x{ny}x{nz} volume",
        "bake it at a lower resolution, or over a smaller box (an edit region, or the cage's box)",
    )


@dataclass
class BakedVolume:
    """One frame's grid: the voxels that hold anything (sparse), density per NeRF unit, colour sRGB."""

    grid: VolumeGrid
    index: np.ndarray  # (N, 3) int32 voxel indices (i, j, k)
    density: np.ndarray  # (N,) float32
    color: np.ndarray  # (N, 3) float32 in [0, 1]
    stats: dict

    def write(self, f) -> None:
        """The .npz into the file object `f` (readable with allow_pickle=False)."""
        np.savez_compressed(
            f,
            shape=np.asarray(self.grid.shape, dtype=np.int64),
            index_to_nerf=self.grid.index_to_nerf,
            index=self.index,
            density=self.density,
            color=self.color,
        )

    def save(self, path) -> None:
        """The .npz written atomically (a temporary file renamed)."""
        atomic_write(Path(path), self.write)


def is_baked_volume_file(path) -> bool:
    """Whether `path` is an .npz archive holding a baked volume's arrays (what a bake may replace)."""
    if not Path(path).is_file():  # a pipe would block the read forever
        return False
    try:
        with zipfile.ZipFile(path) as z:
            return {f"{name}.npy" for name in ARRAYS} <= set(z.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def check_baked_arrays(shape, index_to_nerf, index, density, color, where: str) -> None:
    """EngineError naming `where` (a file, a frame) unless the arrays describe a baked volume: a grid of at
    most MAX_RESOLUTION voxels a side, an index -> NeRF map OpenVDB can place, voxel indices inside the
    grid, and finite values (density not negative), one per voxel."""

    def refuse(what):
        raise EngineError(f"{where}: {what}; it is not a volume `bake-volume` wrote (bake it again)")

    arrays = {"shape": shape, "index_to_nerf": index_to_nerf, "index": index, "density": density, "color": color}
    for name, a in arrays.items():
        kind = "iu" if name in ("shape", "index") else "fiu"
        if not isinstance(a, np.ndarray) or a.dtype.kind not in kind:
            refuse(
                f"`{name}` holds {getattr(a, 'dtype', type(a).__name__)}, not "
                f"{'integers' if kind == 'iu' else 'numbers'}"
            )
    n = len(index) if index.ndim else -1
    wanted = {"shape": (3,), "index_to_nerf": (4, 4), "index": (n, 3), "density": (n,), "color": (n, 3)}
    for name, a in arrays.items():
        if a.shape != wanted[name]:
            refuse(f"`{name}` has shape {a.shape}, not {tuple('N' if d == n else d for d in wanted[name])}")
    if (shape < 1).any() or (shape > MAX_RESOLUTION).any():
        refuse(
            f"its grid is {' x '.join(str(int(x)) for x in shape)} voxels: each side must be from 1 to {MAX_RESOLUTION}"
        )
    if n > int(np.prod(shape.astype(np.int64))):
        refuse(f"it lists {n} voxels, more than its {' x '.join(str(int(x)) for x in shape)} grid holds")
    m = index_to_nerf.astype(np.float64)
    if not np.isfinite(m).all() or not (m[3] == [0, 0, 0, 1]).all():  # exactly: OpenVDB takes no projection
        refuse("`index_to_nerf` is not a finite affine 4x4 matrix")
    if np.abs(m).max() > MAX_COORDINATE:
        refuse(
            f"`index_to_nerf` places its voxels beyond {MAX_COORDINATE:g} NeRF units (its largest entry is "
            f"{np.abs(m).max():.3g})"
        )
    if abs(np.linalg.det(m[:3, :3])) < MIN_VOXEL_SIZE**3:
        refuse(
            f"`index_to_nerf` makes voxels smaller than {MIN_VOXEL_SIZE:g} NeRF units (or flat), which OpenVDB "
            "cannot place"
        )
    if n and ((index < 0).any() or (index >= shape.astype(index.dtype)).any()):
        refuse("voxel indices in `index` lie outside its grid")
    if n > 1:
        # Two values for one voxel: OpenVDB would keep whichever came last, without a word.
        ny, nz = (int(x) for x in shape[1:])
        flat = (index[:, 0].astype(np.int64) * ny + index[:, 1]) * nz + index[:, 2]
        order = np.argsort(flat, kind="stable")
        twice = np.flatnonzero(flat[order][1:] == flat[order][:-1])
        if len(twice):
            refuse(f"`index` lists voxel {index[order[twice[0]]].tolist()} more than once ({len(twice)} repeats)")
    for name in ("density", "color"):
        bad = np.flatnonzero(~np.isfinite(arrays[name]).reshape(n, -1).all(axis=1)) if n else ()
        if len(bad):
            refuse(f"`{name}` holds NaN or inf at {len(bad)} voxels (first: voxel {int(bad[0])})")
    if n and (density < 0).any():
        refuse(f"`density` is negative at {int((density < 0).sum())} voxels")


def _declared(z: np.lib.npyio.NpzFile, path) -> dict[str, tuple[tuple, np.dtype]]:
    """(shape, dtype) of each array of the archive, read from its header alone (nothing allocated)."""
    declared = {}
    for name in ARRAYS:
        member = f"{name}.npy"
        if member not in z.zip.namelist():
            raise EngineError(f"{path} is not a baked volume: it has no `{name}` ({', '.join(ARRAYS)} expected)")
        with z.zip.open(member) as f:
            version = np.lib.format.read_magic(f)
            read_header = getattr(np.lib.format, f"read_array_header_{version[0]}_{version[1]}", None)
            if read_header is None:
                raise EngineError(
                    f"{path}: `{name}` is in .npy format version {version}, which this reader does not know"
                )
            shape, _fortran, dtype = read_header(f)
        if dtype.hasobject:
            raise EngineError(f"{path}: `{name}` holds Python objects, not numbers; it is not a baked volume")
        declared[name] = (shape, dtype)
    return declared


def load_baked(path) -> BakedVolume:
    """A baked frame's .npz, every array checked (a clear error naming the file): dtypes, shapes and the
    memory they need from the archive's headers before any is loaded, then their values."""
    if Path(path).exists() and not Path(path).is_dir() and not Path(path).is_file():  # a pipe would block forever
        raise EngineError(f"baked volume {path} is not a file (a pipe or a device?)")
    try:
        z = np.load(path, mmap_mode="r", allow_pickle=False)  # a .npy: mapped, not read (it is refused)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a single array (.npy) holds no file open
            raise EngineError(f"{path} is not a baked volume: a single array, not an .npz archive")
        with z:
            declared = _declared(z, path)
            need = sum(float(np.prod(shape, dtype=np.float64)) * dtype.itemsize for shape, dtype in declared.values())
            check_memory(
                need, f"baked volume {path}", "this file cannot be a volume `bake-volume` wrote (bake it again)"
            )
            arrays = {k: z[k] for k in ARRAYS}
    except FileNotFoundError:
        raise EngineError(f"baked volume {path} does not exist") from None
    except IsADirectoryError:
        raise EngineError(f"baked volume {path} is a folder") from None
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise EngineError(
            f"{path} is not a baked volume (shape, index_to_nerf, index, density, color): {exc}"
        ) from None
    check_baked_arrays(*(arrays[k] for k in ARRAYS), where=str(path))
    grid = VolumeGrid(tuple(int(s) for s in arrays["shape"]), arrays["index_to_nerf"].astype(np.float64))
    return BakedVolume(
        grid,
        arrays["index"].astype(np.int32),
        arrays["density"].astype(np.float32),
        arrays["color"].astype(np.float32),
        {},
    )
