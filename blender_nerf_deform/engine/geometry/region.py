"""Edit regions: an oriented box in the NeRF's world frame that limits extraction and the cage.

A real capture never holds the object alone (the fox hangs on a plaque on a wall,
a statue stands on a floor). The artist puts a box around the object; extraction
samples only inside it (its resolution spent there), the floater filter and the
pick work inside it, and the cage wraps only what was kept. Where the box cuts
through the scene the extracted surface is closed along the cut (see
`extract.py`), and the cut is remembered so that the cage can be pinned there.

REGION.json (the command line's `--region`, what the add-on sends the worker):

    {"center": [x, y, z], "size": [sx, sy, sz], "rotation_euler": [rx, ry, rz]}

`size` is the full side lengths; `rotation_euler` is in radians, XYZ order as
Blender's Euler (the matrix is Rz @ Ry @ Rx), and the box's local axes are the
columns of that matrix.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import EngineError

KEYS = ("center", "size", "rotation_euler")


def euler_xyz_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """Blender's XYZ Euler as a rotation matrix (X applied first): Rz @ Ry @ Rx."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class EditRegion:
    center: np.ndarray  # (3,) world
    size: np.ndarray  # (3,) full side lengths, > 0
    rotation: np.ndarray  # (3, 3) local → world (orthonormal columns: the box's axes)

    @property
    def half(self) -> np.ndarray:
        return 0.5 * self.size

    def to_local(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - self.center) @ self.rotation

    def to_world(self, local: np.ndarray) -> np.ndarray:
        return np.asarray(local, dtype=np.float64) @ self.rotation.T + self.center

    def contains(self, points: np.ndarray, pad: float = 0.0) -> np.ndarray:
        """Whether each point lies in the box grown by `pad` on every side."""
        return np.all(np.abs(self.to_local(points)) <= self.half + pad, axis=-1)

    def corners(self) -> np.ndarray:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        return self.to_world(signs * self.half)

    def world_bounds(self) -> np.ndarray:
        c = self.corners()
        return np.stack([c.min(0), c.max(0)])

    def overlaps_box(self, bounds: np.ndarray) -> bool:
        """Whether the oriented box meets the axis-aligned box `bounds` (2,3)."""
        b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        return self.overlaps(EditRegion(center=0.5 * (b[0] + b[1]), size=b[1] - b[0], rotation=np.eye(3)))

    def overlaps(self, other: EditRegion) -> bool:
        """Whether two oriented boxes share interior: the separating axis test (their 3 + 3 face
        normals and the 9 cross products of their edges); touching faces do not overlap."""
        A, B, d = self.rotation, other.rotation, other.center - self.center
        axes = [A[:, i] for i in range(3)] + [B[:, i] for i in range(3)]
        axes += [np.cross(A[:, i], B[:, j]) for i in range(3) for j in range(3)]
        for axis in axes:
            n = np.linalg.norm(axis)
            if n < 1e-12:
                continue
            axis = axis / n
            reach = float(np.abs(axis @ A) @ self.half) + float(np.abs(axis @ B) @ other.half)
            if abs(float(axis @ d)) >= reach * (1 - 1e-12):
                return False
        return True

    def to_dict(self) -> dict:
        R = self.rotation
        # XYZ Euler back from Rz @ Ry @ Rx (the region as the user gave it, for reports and files).
        ry = math.asin(max(-1.0, min(1.0, -R[2, 0])))
        if abs(R[2, 0]) < 1 - 1e-9:
            rx, rz = math.atan2(R[2, 1], R[2, 2]), math.atan2(R[1, 0], R[0, 0])
        else:  # gimbal lock: put it all in x
            rx, rz = math.atan2(-R[1, 2], R[1, 1]), 0.0
        return {
            "center": [float(x) for x in self.center],
            "size": [float(x) for x in self.size],
            "rotation_euler": [rx, ry, rz],
        }

    def describe(self) -> str:
        c, s = self.center, self.size
        return f"region centred at ({c[0]:.3g}, {c[1]:.3g}, {c[2]:.3g}), size {s[0]:.3g} x {s[1]:.3g} x {s[2]:.3g}"


def _vector(value, key: str, where: str) -> np.ndarray:
    if (
        not isinstance(value, (list, tuple))
        or len(value) != 3
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    ):
        raise EngineError(f"{where}: `{key}` must be a list of three numbers, got {value!r}")
    v = np.asarray(value, dtype=np.float64)
    if not np.isfinite(v).all():
        raise EngineError(f"{where}: `{key}` must be finite, got {value!r}")
    return v


def region_from_dict(data, where: str = "edit region") -> EditRegion:
    """An EditRegion from REGION.json's content, every key checked (a clear error naming it)."""
    if not isinstance(data, dict):
        raise EngineError(f"{where} must be a JSON object with {', '.join(KEYS)}, got {type(data).__name__}")
    missing = [k for k in KEYS if k not in data]
    if missing:
        raise EngineError(
            f"{where} lacks {', '.join(f'`{k}`' for k in missing)} "
            '(expected {"center": [x, y, z], "size": [sx, sy, sz], "rotation_euler": [rx, ry, rz]})'
        )
    center = _vector(data["center"], "center", where)
    size = _vector(data["size"], "size", where)
    euler = _vector(data["rotation_euler"], "rotation_euler", where)
    if not np.all(size > 0):
        raise EngineError(f"{where} is degenerate: its `size` {data['size']!r} must be positive on every axis")
    return EditRegion(center=center, size=size, rotation=euler_xyz_matrix(*euler))


def load_region(path) -> EditRegion:
    """REGION.json from disk (plain JSON: nothing runs)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise EngineError(f"region file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EngineError(f"cannot read region file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise EngineError(f"region file {path} is not valid JSON: {exc.msg} at line {exc.lineno}") from None
    return region_from_dict(data, where=f"region file {path}")


def check_region_in_box(region: EditRegion, bounds: np.ndarray, what: str = "the NeRF's box") -> None:
    """EngineError when the region lies entirely outside `bounds` (nothing there to edit)."""
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    if not region.overlaps_box(b):
        raise EngineError(
            f"the {region.describe()} lies outside {what} "
            f"[{', '.join(f'{x:.3g}' for x in b[0])}] - [{', '.join(f'{x:.3g}' for x in b[1])}]: "
            "move it onto the object"
        )


def check_regions_apart(regions: list) -> None:
    """EngineError when two edit regions of one NeRF overlap (their cages would claim the same space)."""
    for i in range(len(regions)):
        for j in range(i + 1, len(regions)):
            if regions[i].overlaps(regions[j]):
                raise EngineError(
                    f"edit regions {i + 1} and {j + 1} overlap ({regions[i].describe()}; "
                    f"{regions[j].describe()}): each object needs its own space, move them apart"
                )
