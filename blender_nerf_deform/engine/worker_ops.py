"""The requests the worker serves, one handler per op (registered with `worker.op`).

Each handler turns plain params and numpy arrays into an engine call. Loaded
models are cached by path and modification time, so a render per frame does
not re-read the checkpoint.
"""

from __future__ import annotations

import os

from .errors import EngineError
from .worker import Job, op

_models: dict[tuple[str, str], tuple[float, object]] = {}


def cached_model(path: str, device: str = "auto"):
    """The NeRF at `path`, loaded once per (path, device) and reloaded when the file changes."""
    from .checkpoint import load_nerf

    try:
        mtime = os.path.getmtime(path)
    except OSError:
        raise EngineError(f"NeRF checkpoint {path} does not exist or cannot be read") from None
    key = (os.path.abspath(path), device)
    cached = _models.get(key)
    if cached is None or cached[0] != mtime:
        _models[key] = (mtime, load_nerf(path, device=device))
    return _models[key][1]


_bends: dict[tuple, object] = {}


def cached_bend(checkpoint: str, model, rest_vertices, tets):
    """The ray bender of one rest cage, built once (its rest-cage locator) and reused every frame."""
    import hashlib

    import numpy as np

    from .bending import CageBend

    rest = np.ascontiguousarray(rest_vertices, dtype=np.float64)
    tets = np.ascontiguousarray(tets, dtype=np.int64)
    key = (os.path.abspath(checkpoint), hashlib.sha1(rest.tobytes() + tets.tobytes()).hexdigest())
    if key not in _bends or _bends[key].model is not model:
        _bends.clear()  # one cage at a time: a new cage frees the last one's memory
        _bends[key] = CageBend(model, rest, tets)
    return _bends[key]


@op("load")
def load(job: Job) -> dict:
    """Read a checkpoint: its bounds and configuration, for placing it in the scene."""
    model = cached_model(job.params["path"], job.params.get("device", "auto"))
    return {
        "aabb": [float(x) for x in model.aabb.reshape(-1).tolist()],
        "config": model.config.to_dict(),
        "device": str(model.device),
    }


@op("render")
def render(job: Job) -> tuple[dict, dict]:
    """Render one frame of a NeRF from a pinhole camera given in the NeRF's frame.

    params: checkpoint, camera {width, height, fx, fy, cx, cy, camera_to_world}, device.
    arrays (optional, for a deformed pose): rest_vertices (N,3), tets (M,4), deformed_vertices (N,3).
    Returns arrays `rgba` (H,W,4) float32 straight alpha, rows top-down, and `depth`
    (H,W) float32: expected distance along each unit ray, NeRF units, 0 where empty.
    """
    import numpy as np

    from .renderer import Camera, render_image

    params = job.params
    model = cached_model(params["checkpoint"], params.get("device", "auto"))
    bending = {}
    if "deformed_vertices" in job.arrays:
        bend = cached_bend(params["checkpoint"], model, job.arrays["rest_vertices"], job.arrays["tets"])
        bend.set_deformed(job.arrays["deformed_vertices"])
        bending = {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}
    cam = params["camera"]
    camera = Camera(
        c2w=np.asarray(cam["camera_to_world"], dtype=np.float64),
        fx=float(cam["fx"]),
        fy=float(cam["fy"]),
        cx=float(cam["cx"]),
        cy=float(cam["cy"]),
        width=int(cam["width"]),
        height=int(cam["height"]),
    )
    out = render_image(model, camera, progress=lambda done, total: job.progress(done / total, "rendering"), **bending)
    stats = {k: float(out[k]) for k in ("density_samples_per_ray", "color_samples_per_ray")}
    if bending:
        stats.update(inverted_tets=bend.inversion.n_inverted, degenerate_tets=bend.inversion.n_degenerate)
    return stats, {"rgba": out["rgba"].astype(np.float32), "depth": out["depth"].astype(np.float32)}


@op("cage")
def cage(job: Job) -> tuple[dict, dict]:
    """Build the tetrahedral cage around a surface mesh once, and embed the surface in it.

    arrays: vertices (V,3), faces (F,3) of the surface (the NeRF's frame).
    params: margin, edge_length, target_tets (each optional; None = automatic).
    Returns arrays vertices (N,3), tets (M,4), and the surface's embedding
    tet_ids (V,), weights (V,4).
    """
    import numpy as np

    from .cage import build_cage
    from .embedding import embed_points

    vertices = np.asarray(job.arrays["vertices"], dtype=np.float64)
    faces = np.asarray(job.arrays["faces"], dtype=np.int64)
    p = job.params
    job.progress(0.05, "tetrahedralizing")
    built = build_cage(vertices, faces, p.get("margin"), edge_length=p.get("edge_length"), target_tets=p.get("target_tets"))
    job.progress(0.9, "embedding the surface")
    embedding = embed_points(vertices, built.vertices, built.tets)
    result = {
        "n_vertices": int(len(built.vertices)),
        "n_tets": int(len(built.tets)),
        "margin": built.margin,
        "clearance": built.clearance,
        "n_outside": embedding.n_outside,
        "timings": built.timings,
    }
    return result, {
        "vertices": built.vertices,
        "tets": built.tets,
        "tet_ids": embedding.tet_ids,
        "weights": embedding.weights,
    }


_deformers: dict[str, object] = {}


def _split(index: "np.ndarray", counts: "np.ndarray") -> list:
    import numpy as np

    return np.split(np.asarray(index, dtype=np.int64), np.cumsum(counts)[:-1]) if len(counts) else []


@op("solve")
def solve(job: Job) -> tuple[dict, dict]:
    """Deformed cage vertices for handle poses: ARAP (handles + pins) or affine regions.

    params: mode "ARAP" | "AFFINE", transforms: one 4x4 per handle (NeRF frame).
    arrays: rest_vertices, tets, tet_ids + weights (the surface's embedding),
    handle_index + handle_counts (surface vertex indices of each handle's region,
    concatenated), pin_index (surface vertices pinned).
    The ARAP factorization is cached per cage and set of regions; every solve
    starts from the linear blend of the handles, so a pose depends only on the
    transforms given (viewport, F12 and batch renders agree).
    """
    import hashlib

    import numpy as np

    from .deform import ArapDeformer, affine_region, regions_to_cage
    from .embedding import Embedding

    a = job.arrays
    rest = np.ascontiguousarray(a["rest_vertices"], dtype=np.float64)
    tets = np.ascontiguousarray(a["tets"], dtype=np.int64)
    transforms = [np.asarray(t, dtype=np.float64) for t in job.params["transforms"]]
    handle_regions = _split(a["handle_index"], a["handle_counts"])
    pin_index = np.asarray(a.get("pin_index", np.zeros(0, np.int64)), dtype=np.int64)
    names = list(job.params.get("handle_names") or [f"handle {i}" for i in range(len(handle_regions))])
    surface_regions = handle_regions + ([pin_index] if len(pin_index) else [])
    names += ["the pinned region"] if len(pin_index) else []
    tet_ids = np.asarray(a["tet_ids"], dtype=np.int64)
    embedding = Embedding(tet_ids=tet_ids, corners=tets[tet_ids], weights=np.asarray(a["weights"], dtype=np.float64), n_outside=0)

    key = hashlib.sha1(b"".join(np.ascontiguousarray(x).tobytes() for x in (rest, tets, a["handle_index"], a["handle_counts"], pin_index))).hexdigest()
    stats = {}
    if job.params["mode"] == "AFFINE":
        cage_regions = regions_to_cage(embedding, surface_regions, len(rest), names)
        deformed = rest
        for region, transform in zip(cage_regions, transforms):
            deformed = affine_region(deformed, region, transform)
    else:
        deformer = _deformers.get(key)
        if deformer is None:
            job.progress(0.1, "ARAP precomputation")
            cage_regions = regions_to_cage(embedding, surface_regions, len(rest), names)
            n_handles = len(handle_regions)
            deformer = ArapDeformer(rest, tets, cage_regions[:n_handles], cage_regions[n_handles:])
            _deformers.clear()  # one set of handles at a time
            _deformers[key] = deformer
            stats["precompute_s"] = deformer.precompute_s
        result = deformer.solve(transforms)
        deformed = result.vertices
        stats.update(iterations=result.iterations, converged=bool(result.converged), solve_s=result.seconds)
    return stats, {"deformed_vertices": np.asarray(deformed, dtype=np.float64)}


@op("extract")
def extract(job: Job) -> tuple[dict, dict]:
    """The NeRF's surface: marching cubes of its density, floaters dropped, vertex colours.

    params: checkpoint, threshold, resolution, min_volume (None or 0: automatic).
    Returns arrays vertices (N,3), faces (F,3), colors (N,3), NeRF frame; result has the report.
    """
    import numpy as np

    from .extract import DEFAULT_RESOLUTION, DEFAULT_THRESHOLD, colour_fn_of, density_fn_of, extract_mesh

    p = job.params
    model = cached_model(p["checkpoint"], p.get("device", "auto"))
    job.progress(0.05, "sampling the density grid")
    res = extract_mesh(
        density_fn_of(model),
        model.aabb.detach().cpu().numpy().reshape(2, 3),
        resolution=int(p.get("resolution") or DEFAULT_RESOLUTION),
        threshold=float(p["threshold"]) if p.get("threshold") is not None else DEFAULT_THRESHOLD,
        min_volume=float(p["min_volume"]) if p.get("min_volume") else None,
        colour_fn=colour_fn_of(model),
    )
    colors = res.colors if res.colors is not None else np.full((len(res.vertices), 3), 0.8)
    summary = {"report": res.report(), "kept": len(res.kept), "dropped": res.dropped_count, "timings": res.timings}
    return summary, {"vertices": res.vertices, "faces": res.faces, "colors": np.asarray(colors, dtype=np.float32)}
