"""Cage poses on disk: `--deformed V.npy` (one (N,3) pose) or a folder of them (an animation).

A folder's `*.npy` files, in natural name order (digit runs compare as numbers,
so `pose_2` comes before `pose_10`), are the poses of the frames in order.
Every pose is read with `allow_pickle=False` and checked (shape, vertex count,
finite) before anything renders, so a bad file stops the run with nothing
half-done. Pure numpy.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import EngineError

# How far from the origin a cage vertex may lie, rest or posed (NeRF units): beyond it the ray bender's
# float32 maps and a tet's volume (a cube of its size) overflow into inf and NaN, which once reached a
# float -> int conversion. A billion scene units is no pose anyone meant.
MAX_COORDINATE = 1e9


def _natural_key(path: Path):
    return [(0, int(part), part) if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", path.name)]


def pose_files(deformed_path) -> list[Path]:
    """The pose file(s) named by --deformed: [V.npy], or a folder's *.npy in natural name order."""
    path = Path(deformed_path)
    if path.is_dir():
        files = sorted((p for p in path.glob("*.npy") if p.is_file()), key=_natural_key)
        if not files:
            raise EngineError(f"--deformed {path}: the folder holds no .npy pose files")
        return files
    if not path.exists():
        raise EngineError(f"deformed vertices {path} do not exist")
    if not path.is_file():  # a pipe or a device would block the read forever
        raise EngineError(f"deformed vertices {path} are not a file (a pipe or a device?)")
    return [path]


def load_pose(path, vertex_shape: tuple) -> np.ndarray:
    """One (N,3) pose of the cage's N vertices, checked; errors name the file."""
    try:
        deformed = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise EngineError(f"deformed vertices {path} do not exist") from None
    except (ValueError, OSError) as exc:
        raise EngineError(f"cannot read deformed vertices {path}: {exc}") from None
    if (
        not isinstance(deformed, np.ndarray)
        or deformed.ndim != 2
        or deformed.shape[1] != 3
        or not (np.issubdtype(deformed.dtype, np.floating) or np.issubdtype(deformed.dtype, np.integer))
    ):
        shape = getattr(deformed, "shape", None)
        dtype = getattr(deformed, "dtype", None)
        what = f"{shape}" if dtype is None or dtype.kind in "fiu" else f"a {shape} array of {dtype} (not numbers)"
        raise EngineError(
            f"{path}: deformed vertices must be a finite {vertex_shape} array, the cage's shape "
            f"(same vertices, same order), got {what}"
        )
    if deformed.shape != vertex_shape:
        raise EngineError(
            f"{path}: deformed vertices must be a finite {vertex_shape} array, the cage's shape "
            f"(same vertices, same order), got {deformed.shape}: {deformed.shape[0]} vertices, "
            f"the cage has {vertex_shape[0]}"
        )
    bad = np.flatnonzero(~np.isfinite(deformed).all(axis=1))
    if len(bad):
        raise EngineError(
            f"{path}: deformed vertices must be a finite {vertex_shape} array, but {len(bad)} of its "
            f"rows hold NaN or inf (first: vertex {bad[0]})"
        )
    check_coordinates(deformed, f"{path}: deformed vertices")
    return deformed.astype(np.float64)


def check_coordinates(vertices: np.ndarray, where: str) -> None:
    """EngineError naming `where` unless every vertex is finite and within MAX_COORDINATE of the origin."""
    v = np.asarray(vertices)
    bad = np.flatnonzero(~(np.isfinite(v) & (np.abs(v) <= MAX_COORDINATE)).all(axis=1)) if v.size else ()
    if len(bad):
        first = ", ".join(f"{x:.3g}" for x in np.asarray(v[bad[0]], dtype=np.float64))
        raise EngineError(
            f"{where}: vertex {bad[0]} lies at ({first}), not a finite point within {MAX_COORDINATE:g} "
            f"NeRF units of the origin ({len(bad)} of {len(v)} vertices do not)"
        )


def check_not_collapsed(path, rest_vertices: np.ndarray, deformed: np.ndarray, tets: np.ndarray) -> None:
    """EngineError when a pose flattens every tet of the cage: nothing could be located in it."""
    from .barycentric import inversion_report  # pure numpy

    report = inversion_report(rest_vertices, deformed, tets)
    if len(tets) and report.n_degenerate == len(tets):
        raise EngineError(
            f"{path}: the pose collapsed the cage: all {len(tets)} tets are degenerate (flattened "
            "to zero volume), so no sample can be mapped through it"
        )


def load_poses(
    cage_vertices: np.ndarray, deformed_path, n_frames: int, tets: np.ndarray | None = None
) -> list[np.ndarray]:
    """One checked pose per frame: a single file repeated, or a folder's files matched to frames in order.
    With the cage's `tets`, a pose that collapses the whole cage is refused too."""
    files = pose_files(deformed_path)
    if Path(deformed_path).is_dir() and len(files) != n_frames:
        raise EngineError(
            f"--deformed {deformed_path}: {len(files)} pose files (.npy) for {n_frames} camera frames "
            "in --cameras; give one pose per frame"
        )
    poses = [load_pose(f, cage_vertices.shape) for f in files]
    if tets is not None:
        for f, pose in zip(files, poses):
            check_not_collapsed(f, cage_vertices, pose, tets)
    return poses if len(poses) == n_frames else poses * n_frames
