"""OpenVDB files of a baked NeRF, through the `openvdb` module Blender ships.

Two grids, as Blender's volume attributes and other applications read them:
`density` (a fog volume: extinction per unit length of the Blender world) and
`color` (scene-linear RGB). Each is written from the sparse voxels the worker
baked, a slab of i-layers at a time (bounded memory whatever the grid); empty
voxels stay inactive (OpenVDB stores nothing there). The grids' transform maps
voxel indices into the NeRF's frame, so the Volume object sits under the NeRF
object with no offset.

Written to a temporary file and renamed, so a file is either whole or absent.
OpenVDB stamps a random UUID in every file's header; it is replaced by one made
from the file's content, so a frame's file is the same bytes whichever process
baked it (a farm's split ranges, a re-bake): readers use the UUID only to tell
files apart, which a content hash does.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import bpy
import numpy as np

SLAB_VOXELS = 1 << 24  # voxels per dense slab handed to OpenVDB (64 MiB of float32)
_UUID_AT, _UUID_LENGTH = 21, 36  # after the magic, file version, library version and offsets flag


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
    raise VolumeFileError(f"this Blender ({bpy.app.version_string}) has no OpenVDB Python module to write volumes with "
                          "(Blender's own builds ship one; some bpy module wheels do not)")


def write_vdb(path, shape, index_to_local: np.ndarray, index: np.ndarray, density: np.ndarray, color: np.ndarray) -> None:
    """Write `density` (N,) and `color` (N, 3) of the voxels `index` (N, 3) of a grid of `shape` to `path`.
    `index_to_local`: 4x4, a voxel index (its centre) to the Volume object's local coordinates."""
    vdb = openvdb_module()
    path = Path(path)
    nx, ny, nz = (int(s) for s in shape)
    density_grid, color_grid = vdb.FloatGrid(), vdb.Vec3SGrid()
    density_grid.name, color_grid.name = "density", "color"
    density_grid.gridClass = vdb.GridClass.FOG_VOLUME
    matrix = np.asarray(index_to_local, dtype=np.float64).T.tolist()  # OpenVDB's row-vector convention
    density_grid.transform = vdb.createLinearTransform(matrix)
    color_grid.transform = vdb.createLinearTransform(matrix)
    index = np.asarray(index)
    order = np.argsort(index[:, 0], kind="stable")
    index, density, color = index[order], np.asarray(density, np.float32)[order], np.asarray(color, np.float32)[order]
    layers = max(1, SLAB_VOXELS // max(1, ny * nz))
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
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        vdb.write(str(partial), grids=[density_grid, color_grid])
        _content_uuid(partial)
        os.replace(partial, path)
    except OSError as exc:
        raise VolumeFileError(f"cannot write {path}: {exc.strerror or exc}") from None
    finally:
        if partial.exists():
            partial.unlink()


def _content_uuid(path: Path) -> None:
    """Replace the file's random UUID by one derived from the rest of its bytes."""
    data = bytearray(path.read_bytes())
    field = bytes(data[_UUID_AT: _UUID_AT + _UUID_LENGTH])
    if not data.startswith(b" BDV") or field.count(b"-") != 4:
        return  # not the header layout this was written for: leave the file as OpenVDB wrote it
    digest = hashlib.sha256(bytes(data[:_UUID_AT]) + bytes(data[_UUID_AT + _UUID_LENGTH:])).hexdigest().upper()
    uuid = f"{digest[:8]}-{digest[8:12]}-{digest[12:16]}-{digest[16:20]}-{digest[20:32]}".encode()
    with open(path, "r+b") as f:
        f.seek(_UUID_AT)
        f.write(uuid)
