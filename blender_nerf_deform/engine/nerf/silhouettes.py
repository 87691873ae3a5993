"""Object masks: what a capture's masks mean, and the space their silhouettes leave for the object.

Masks have two meanings (docs/ARCHITECTURE.md, "Real captures"):

- *object* masks (NeRD, turntable and product captures): the object alone is real. Outside the mask
  is empty space, alpha 0; the NeRF is an object to composite, bounded by what the silhouettes carve.
- *ignore* masks (nerfstudio's `mask_path`): the pixels a mask removes (passers-by) are not trained;
  the rest of the photo, room included, is.

Which one a capture's masks are is told by their shape: an object mask keeps a blob and drops the
photo's border (what surrounds the object); an ignore mask keeps the photo and drops a few patches, so
it keeps most of the border. `mask_meaning` decides on the median frame and says why.

The visual hull (Laurentini's silhouette carving): a point of the object projects inside the object's
mask in every photo that frames it. Masks drawn by hand and poses from structure from motion are a
few pixels off, so the masks are widened by `MASK_MARGIN` of the image and a point may fall outside
a few of them (`OUTSIDE_TOLERANCE` of the views that frame it) before it is carved away.
"""

from __future__ import annotations

import numpy as np

from ..errors import EngineError

MASK_MEANINGS = ("auto", "object", "ignore")
MASK_LABELS = {
    "object": "object masks (the object alone, transparent around it)",
    "ignore": "ignore masks (the masked-out pixels are skipped)",
}
BORDER_KEPT_OBJECT = 0.5  # a mask that keeps less than this fraction of its photo's border is an object mask
MASK_MARGIN = 0.01  # silhouettes widened by this fraction of the image's larger side
OUTSIDE_TOLERANCE = 0.1  # a point survives outside this fraction of the masks that frame it (at least one)
MAIN_PIECE = 0.2  # a piece of the hull smaller than this fraction of the largest is a speck, not the object
MIN_FRAMING_FRACTION = 0.25  # a point framed by fewer of the photos is no part of the object they all frame


def border_kept(mask: np.ndarray) -> float:
    """Fraction of the mask's border pixels that are kept (True)."""
    border = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(border.mean()) if border.size else 1.0


def mask_meaning(masks: list, asked: str = "auto") -> tuple[str, str]:
    """("object" | "ignore", why): `asked` unless it is "auto", else what the masks' shape says."""
    if asked not in MASK_MEANINGS:
        raise EngineError(f"--masks {asked!r}: one of {', '.join(MASK_MEANINGS)}")
    if asked != "auto":
        return asked, "as asked"
    kept = float(np.median([border_kept(m) for m in masks]))
    if kept < BORDER_KEPT_OBJECT:
        return "object", (
            f"the masks keep a shape inside the photo ({kept:.0%} of the border, median): the object "
            "alone is real, outside the masks is empty space"
        )
    return "ignore", (
        f"the masks keep most of the photo ({kept:.0%} of the border, median): the pixels they remove "
        "are not trained, the rest of the photo is"
    )


def _widened(mask: np.ndarray, pixels: int) -> np.ndarray:
    if pixels < 1:
        return mask
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=pixels)


def carve(points: np.ndarray, cameras: list, masks: list, chunk: int = 1 << 17) -> np.ndarray:
    """(N,) bool: the world points (N, 3) that lie inside the visual hull of the masks (module docstring)."""
    points = np.asarray(points, dtype=np.float64)
    outside = np.zeros(len(points), np.int32)
    framing = np.zeros(len(points), np.int32)
    for cam, mask in zip(cameras, masks):
        h, w = mask.shape
        wide = _widened(mask, int(round(MASK_MARGIN * max(h, w))))
        rot, origin = cam.c2w[:3, :3], cam.c2w[:3, 3]
        for s in range(0, len(points), chunk):
            q = (points[s : s + chunk] - origin) @ rot  # camera space: looking down -Z, +Y up
            z = -q[:, 2]
            front = z > 1e-9
            zs = np.where(front, z, 1.0)
            i = np.floor(cam.fx * q[:, 0] / zs + cam.cx)
            j = np.floor(-cam.fy * q[:, 1] / zs + cam.cy)
            framed = front & (i >= 0) & (i < w) & (j >= 0) & (j < h)
            ii, jj = i[framed].astype(np.int64), j[framed].astype(np.int64)
            where = np.flatnonzero(framed) + s
            framing[where] += 1
            outside[where] += ~wide[jj, ii]
    allowed = np.maximum(1, np.floor(OUTSIDE_TOLERANCE * framing))
    return (framing >= max(3, MIN_FRAMING_FRACTION * len(cameras))) & (outside <= allowed)


def grid_points(box: np.ndarray, resolution: int) -> np.ndarray:
    """Centres (R^3, 3) of a resolution^3 grid over the box (2, 3), x fastest."""
    box = np.asarray(box, dtype=np.float64).reshape(2, 3)
    axis = (np.arange(resolution) + 0.5) / resolution
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    return box[0] + np.stack([x, y, z], axis=-1).reshape(-1, 3) * (box[1] - box[0])


def hull_box(
    cameras: list, masks: list, search: np.ndarray, resolution: int = 96, margin: float = 0.1
) -> np.ndarray | None:
    """The box (2, 3) of the visual hull within the box `search`, grown by `margin` of its size on every side
    (and one search cell), or None when the masks carve everything away."""
    from scipy.ndimage import label

    search = np.asarray(search, dtype=np.float64).reshape(2, 3)
    pts = grid_points(search, resolution)
    inside = carve(pts, cameras, masks)
    if not inside.any():
        return None
    # The object, not the specks that a few photos leave unconstrained far from it: the hull's large pieces.
    pieces, _ = label(inside.reshape((resolution,) * 3))
    sizes = np.bincount(pieces.ravel())
    sizes[0] = 0
    kept = pts[(sizes >= MAIN_PIECE * sizes.max())[pieces.ravel()]]
    lo, hi = kept.min(axis=0), kept.max(axis=0)
    cell = (search[1] - search[0]) / resolution
    grow = margin * (hi - lo) + cell
    return np.stack([np.maximum(lo - grow, search[0]), np.minimum(hi + grow, search[1])]).astype(np.float32)
