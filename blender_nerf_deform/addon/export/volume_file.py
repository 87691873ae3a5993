"""OpenVDB files of a baked NeRF, through the `openvdb` module Blender ships.

Two grids, as Blender's volume attributes and other applications read them:
`density` (a fog volume: extinction per unit length of the Blender world) and
`color` (scene-linear RGB). Each is written from the sparse voxels the worker
baked, a slab of i-layers at a time (bounded memory whatever the grid); empty
voxels stay inactive (OpenVDB stores nothing there). The grids' transform maps
voxel indices into the NeRF's frame, so the Volume object sits under the NeRF
object with no offset.

`write_vdb` writes the path it is given: its callers write every file of a run to
temporary files that take their place together at the end (engine/files.py,
StagedFiles), so a file is whole or absent and a failed run leaves nothing. Its
input is checked first (the arrays as `bake-volume`'s files are checked, the memory
of the slabs, a transform OpenVDB can place). Each grid names the NeRF it was baked
from (metadata `nerf_deform_nerf`), so a later bake replaces its own earlier files
and nothing else (`check_vdb_replaceable`).

OpenVDB stamps a random UUID in every file's header; it is replaced by one made
from the file's content, so a frame's file is the same bytes whichever process
baked it (a farm's split ranges, a re-bake): readers use the UUID only to tell
files apart, which a content hash does.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import bpy

import numpy as np

from ...engine.bend.baked_volume import check_baked_arrays
from ...engine.errors import EngineError
from ...engine.memory import check_memory

SLAB_VOXELS = 1 << 24  # voxels per dense slab handed to OpenVDB (64 MiB of float32)
_UUID_AT, _UUID_LENGTH = 21, 36  # after the magic, file version, library version and offsets flag
OPENVDB_MAGIC = b" BDV"  # the first bytes of every OpenVDB file
OWNER_KEY = "nerf_deform_nerf"  # grid metadata: the name of the NeRF object a bake was made from
GRID_NAMES = ("color", "density")


class VolumeFileError(ValueError):
    pass


def openvdb_module():
    """Blender's OpenVDB module: `openvdb` (Blender 4.4+), `pyopenvdb` (before); in the bpy module it
    sits in Blender's own site-packages, which is not on sys.path."""
    for name in ("openvdb", "pyopenvdb"):
        try:
            return __import__(name)
        except ImportError:
            pass
    resource = bpy.utils.system_resource("PYTHON")  # "" in some bpy wheels (4.2's, which has no OpenVDB module)
    sites = sorted((Path(resource) / "lib").glob("python3*/site-packages")) if resource else []
    for site in sites:
        if str(site) not in sys.path:
            sys.path.append(str(site))
        for name in ("openvdb", "pyopenvdb"):
            try:
                return __import__(name)
            except ImportError:
                pass
    raise VolumeFileError(
        f"this Blender ({bpy.app.version_string}) has no OpenVDB Python module to write volumes with "
        "(Blender's own builds ship one; some bpy module wheels do not)"
    )


def write_vdb(
    path,
    shape,
    index_to_local: np.ndarray,
    index: np.ndarray,
    density: np.ndarray,
    color: np.ndarray,
    where: str = "",
    owner: str | None = None,
) -> None:
    """Write `density` (N,) and `color` (N, 3) of the voxels `index` (N, 3) of a grid of `shape` to `path`.
    `index_to_local`: 4x4, a voxel index (its centre) to the Volume object's local coordinates. `where`
    names the input in errors (a file, a frame); `owner`, the NeRF's name, is recorded in the grids."""
    path = Path(path)
    where = where or str(path)
    arrays = [np.asarray(a) for a in (shape, index_to_local, index, density, color)]
    try:
        check_baked_arrays(*arrays, where=where)
        shape, index_to_local, index, density, color = arrays
        nx, ny, nz = (int(s) for s in shape)
        layers = max(1, SLAB_VOXELS // max(1, ny * nz))
        # The largest slab (colour), the sorted copies of the voxels and OpenVDB's trees (about 32 bytes a voxel).
        check_memory(
            12.0 * layers * ny * nz + 60.0 * len(index),
            f"the OpenVDB file of {where}",
            "bake it at a lower resolution, or over a smaller box",
        )
    except EngineError as error:
        raise VolumeFileError(str(error)) from None
    vdb = openvdb_module()
    density_grid, color_grid = vdb.FloatGrid(), vdb.Vec3SGrid()
    density_grid.name, color_grid.name = "density", "color"
    density_grid.gridClass = vdb.GridClass.FOG_VOLUME
    matrix = np.asarray(index_to_local, dtype=np.float64).T.tolist()  # OpenVDB's row-vector convention
    try:
        density_grid.transform = vdb.createLinearTransform(matrix)
        color_grid.transform = vdb.createLinearTransform(matrix)
    except (ArithmeticError, RuntimeError, ValueError, TypeError) as error:
        raise VolumeFileError(
            f"{where}: OpenVDB cannot place its voxels ({error}); bake a larger box or at a lower resolution"
        ) from None
    if owner is not None:
        for grid in (density_grid, color_grid):
            grid[OWNER_KEY] = str(owner)
    order = np.argsort(index[:, 0], kind="stable")
    index, density, color = index[order], np.asarray(density, np.float32)[order], np.asarray(color, np.float32)[order]
    bounds = np.searchsorted(index[:, 0], np.arange(0, nx + layers, layers))
    for s, i0 in enumerate(range(0, nx, layers)):
        i1 = min(nx, i0 + layers)
        a, b = bounds[s], bounds[s + 1]
        if a == b:
            continue
        rows = (index[a:b, 0] - i0, index[a:b, 1], index[a:b, 2])
        slab = np.zeros((i1 - i0, ny, nz), dtype=np.float32)
        slab[rows] = density[a:b]
        density_grid.copyFromArray(slab, ijk=(i0, 0, 0))
        del slab
        slab = np.zeros((i1 - i0, ny, nz, 3), dtype=np.float32)
        slab[rows] = color[a:b]
        color_grid.copyFromArray(slab, ijk=(i0, 0, 0))
        del slab
    try:
        vdb.write(str(path), grids=[density_grid, color_grid])
        _content_uuid(path)
    except (OSError, RuntimeError) as exc:  # OpenVDB's IoError arrives as a RuntimeError
        raise VolumeFileError(f"cannot write {path}: {getattr(exc, 'strerror', None) or exc}") from None


def scaled_density(density: np.ndarray, scale: float, where: str) -> np.ndarray:
    """`density` (per NeRF unit) divided by `scale` (world units per NeRF unit) as float32; VolumeFileError
    naming `where` when a tiny scale makes it overflow (float32 holds up to 3.4e38)."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        scaled = (np.asarray(density, dtype=np.float64) / scale).astype(np.float32)
    if len(scaled) and not np.isfinite(scaled).all() and np.isfinite(density).all():  # (NaN input: its own error)
        largest = float(np.max(density))
        with np.errstate(over="ignore"):
            per_world = np.float64(largest) / scale
        raise VolumeFileError(
            f"{where}: a scale of {scale:.3g} world units per NeRF unit makes the density "
            f"{largest:.3g} per NeRF unit overflow float32 ({per_world:.3g} per "
            "world unit): give the volume a larger scale"
        )
    return scaled


def check_vdb_replaceable(path, owner: str | None = None) -> None:
    """VolumeFileError unless `path` is free or holds what a bake may replace: an OpenVDB file, and with
    `owner` one baked from that NeRF (its grids name it; a bake from before they did has exactly the grids
    `density` and `color`). A folder there is an error too."""
    path = Path(path)
    if path.is_dir():
        raise VolumeFileError(f"cannot write {path}: it is a folder; move it, or bake into another folder")
    if not path.exists():
        return
    if not path.is_file():  # reading a pipe would block forever
        raise VolumeFileError(
            f"cannot write {path}: it is not a file (a pipe, a socket or a device): it is left "
            "alone; move it, or bake into another folder"
        )
    try:
        with open(path, "rb") as f:
            magic = f.read(len(OPENVDB_MAGIC))
    except OSError as exc:
        raise VolumeFileError(
            f"cannot read {path} to see whether a bake may replace it: {exc.strerror or exc}"
        ) from None
    if magic != OPENVDB_MAGIC:
        raise VolumeFileError(
            f"{path} exists and is not an OpenVDB file: it is left alone; move it, or bake into another folder"
        )
    if owner is None:
        return
    try:
        grids = openvdb_module().readAllGridMetadata(str(path))
        owners = {str(g[OWNER_KEY]) for g in grids if OWNER_KEY in g.metadata}
        names = tuple(sorted(g.name for g in grids))
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as exc:
        raise VolumeFileError(
            f"{path} exists and cannot be read as OpenVDB ({exc}): it is left alone; move it, or "
            "bake into another folder"
        ) from None
    if owners == {owner} or (not owners and names == GRID_NAMES):
        return
    whose = f"a bake of {sorted(owners)[0]!r}" if owners else f"a volume of other grids ({', '.join(names) or 'none'})"
    raise VolumeFileError(
        f"{path} exists and is {whose}, not of {owner!r}: it is left alone; move it, or bake into another folder"
    )


def _content_uuid(path: Path) -> None:
    """Replace the file's random UUID by one derived from the rest of its bytes."""
    data = bytearray(path.read_bytes())
    field = bytes(data[_UUID_AT : _UUID_AT + _UUID_LENGTH])
    if not data.startswith(b" BDV") or field.count(b"-") != 4:
        return  # not the header layout this was written for: leave the file as OpenVDB wrote it
    digest = hashlib.sha256(bytes(data[:_UUID_AT]) + bytes(data[_UUID_AT + _UUID_LENGTH :])).hexdigest().upper()
    uuid = f"{digest[:8]}-{digest[8:12]}-{digest[12:16]}-{digest[16:20]}-{digest[20:32]}".encode()
    with open(path, "r+b") as f:
        f.seek(_UUID_AT)
        f.write(uuid)
