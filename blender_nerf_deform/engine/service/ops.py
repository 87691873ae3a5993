"""The requests the worker serves, one handler per op (registered with `registry.op`).

Each handler turns plain params and numpy arrays into calls of the stage
functions (the same ones the command line calls) and their results back into
plain data: no stage logic here. Loaded NeRFs are cached by path and
modification time; cages, embeddings and regions live in the worker session
(session.py) under the keys Blender gave them, with what is built from them.

    info                                  the worker's Python, torch and devices
    load     checkpoint                   bounds and configuration of a NeRF
    extract  checkpoint, threshold, ... [regions (or region), pick]
                                          the surface mesh (vertices, faces, colors, cut,
                                          part: the edit region of each vertex)
    cage     vertices + faces [+ cut, part, refine] [checkpoint, threshold, margin, pin_cut,
             refine_edge, ...]            the rest cage (one per part, in one), the
                                          surface's embedding in it, the cage vertices
                                          pinned at the regions' cuts; with `refine` (flags of
                                          surface vertices) made finer around those
    train    data, out [steps, max_seconds, device, downscale, resume, overwrite, scene]
                                          a NeRF trained into out/nerf.ckpt, with progress;
                                          cancelling keeps the checkpoint; answers the
                                          training_preview requests of its run between steps
    training_preview  checkpoint, camera (or null + size [w, h]: a view of the NeRF's box)
                                          a small frame of a run: of the model being trained
                                          when its training runs (a side op, answered between
                                          steps), else of the checkpoint file
    prepare  images, out [matcher, max_size, seed]
                                          photos -> a transforms.json dataset in out by structure
                                          from motion, with progress; cancel stops pycolmap
                                          midway and leaves nothing written
    first_surface  checkpoint, origin, direction [threshold]
                                          where a ray first meets the density (a click's pick)
    solve    shared cage/embedding/regions, mode, transforms, answer
                                          a pose: deformed cage vertices, or (answer
                                          "surface") the deformed surface for the preview
    render   checkpoint, camera, pose [substeps]
                                          one frame, solved and rendered in one go:
             pose {"kind": "rest"} | {"kind": "cage"} + deformed_vertices (shared cage)
                  | {"kind": "handles", mode, transforms, handle_names} (shared cage,
                  embedding, regions)
    warm     checkpoints                  NeRFs loaded ahead of their first frame (Blender asks when a
                                          file with NeRFs opens): each into the cache `render`
                                          reads, and a small view of its box run through the
                                          frame's kernels, so the first F12 waits for neither
    bake_volume  checkpoint, pose, extent, resolution [supersample]
                                          the NeRF at that pose sampled on a voxel grid over
                                          its box, the posed cage's box or an edit region: the
                                          voxels that hold anything, for an OpenVDB file
"""

from __future__ import annotations

import os
import sys
from typing import NamedTuple

import numpy as np

from ..bend.baked_volume import check_volume_memory, volume_grid
from ..bend.posed import PosedRenderer
from ..bend.volume import bake_box
from ..errors import EngineError
from ..geometry.cage import build_cage, build_nerf_cage, build_part_cages, cut_pins, part_cut_pins
from ..geometry.cage_refine import extend_vertex_labels, refine_around
from ..geometry.deform import split_regions
from ..geometry.embedding import Embedding, embed_points, embed_points_by_part
from ..geometry.extract import density_fn_of, extract_nerf_mesh, extract_nerf_regions, first_dense_point
from ..geometry.handle_pose import RegionDeformer
from ..geometry.poses import check_coordinates
from ..geometry.region import region_from_dict
from ..geometry.surface_map import SurfaceMap
from ..nerf.camera import Camera
from ..nerf.checkpoint import load_nerf
from ..nerf.model import device_summary
from ..nerf.silhouettes import MASK_MEANINGS
from ..nerf.substeps import check_substeps
from .registry import Cancelled, Job, op
from .session import SESSION

_models: dict[tuple[str, str], tuple[float, object]] = {}


def cached_model(path: str, device: str = "auto"):
    """The NeRF at `path`, loaded once per (path, device) and reloaded when the file changes."""
    try:
        mtime = os.path.getmtime(path)
    except (OSError, TypeError, ValueError):
        raise EngineError(f"NeRF checkpoint {path} does not exist or cannot be read") from None
    key = (os.path.abspath(path), device)
    cached = _models.get(key)
    if cached is None or cached[0] != mtime:
        _models[key] = (mtime, load_nerf(path, device=device))
    return _models[key][1]


def _model(params: dict):
    return cached_model(params.get("checkpoint"), params.get("device", "auto"))


@op("info")
def info(job: Job) -> dict:
    return {"python": sys.executable, "pid": os.getpid(), **device_summary()}


@op("load")
def load(job: Job) -> dict:
    """Read a checkpoint: its bounds and configuration, for placing it in the scene."""
    model = cached_model(job.params["path"], job.params.get("device", "auto"))
    return {
        "aabb": [float(x) for x in model.aabb.reshape(-1).tolist()],
        "config": model.config.to_dict(),
        "device": str(model.device),
    }


@op("extract")
def extract(job: Job) -> tuple[dict, dict]:
    """The NeRF's surface: marching cubes of its density, floaters dropped, vertex colours."""
    p = job.params
    model = _model(p)
    job.progress(0.05, "sampling the density grid")
    listed = p.get("regions") or ([p["region"]] if p.get("region") is not None else [])
    if not isinstance(listed, list):
        raise EngineError(f"`regions` must be a list of edit regions, got {type(listed).__name__}")
    regions = [region_from_dict(r, where=f"edit region {i + 1}") for i, r in enumerate(listed)]
    pick = p.get("pick")
    if pick is not None:
        pick = np.asarray(pick, dtype=np.float64)
        if pick.shape != (3,) or not np.isfinite(pick).all():
            raise EngineError(f"the pick point must be three finite numbers, got {p.get('pick')!r}")
    options = {"resolution": p.get("resolution"), "threshold": p.get("threshold"), "min_volume": p.get("min_volume")}
    if regions:
        res = extract_nerf_regions(model, regions, pick=pick, **options)
    else:
        res = extract_nerf_mesh(model, pick=pick, **options)
    colors = res.colors if res.colors is not None else np.full((len(res.vertices), 3), 0.8)
    part = res.part if res.part is not None else np.zeros(len(res.vertices), dtype=np.int64)
    summary = {
        "report": res.report(),
        "kept": len(res.kept),
        "dropped": res.dropped_count,
        "timings": res.timings,
        "n_cut": int(res.cut.sum()),
        "n_parts": int(part.max()) + 1 if len(part) else 0,
    }
    return summary, {
        "vertices": res.vertices,
        "faces": res.faces,
        "colors": np.asarray(colors, dtype=np.float32),
        "cut": res.cut.astype(np.uint8),
        "part": part.astype(np.int32),
    }


PROGRESS_EVERY_S = 0.5


@op("train")
def train(job: Job) -> dict:
    """Train a NeRF on a dataset folder (every format `train` reads) into a run folder, as the
    `train` command does, with progress (steps, batch PSNR, elapsed, an estimate of what is left).
    Cancelling stops after the current step and still writes the checkpoint (the result says
    `cancelled`); `resume` continues a run folder's checkpoint."""
    import time

    from ..nerf.trainer import run_training

    p = job.params
    for key in ("data", "out"):
        if not isinstance(p.get(key), str) or not p[key]:
            raise EngineError(f"train needs `{key}`, a folder path")
    steps, seconds = p.get("steps"), p.get("max_seconds")
    downscale = p.get("downscale", 1)
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise EngineError(f"train's `downscale` must be a whole number >= 1, got {downscale!r}")
    masks = p.get("masks", "auto")
    if masks not in MASK_MEANINGS:
        raise EngineError(f"train's `masks` must be one of {', '.join(MASK_MEANINGS)}, got {masks!r}")
    last = [0.0]
    checkpoint = _same_path_key(os.path.join(p["out"], "nerf.ckpt"))

    def ours(side: Job) -> bool:  # a preview of this run
        return (
            isinstance(side.params.get("checkpoint"), str) and _same_path_key(side.params["checkpoint"]) == checkpoint
        )

    def report(trainer):
        job.serve_side_requests(lambda side: _training_preview_of(side, trainer))
        now = time.perf_counter()
        if now - last[0] < PROGRESS_EVERY_S:
            return
        last[0] = now
        done, elapsed = trainer.step_count, trainer.elapsed
        if steps:
            fraction = done / steps
        else:
            fraction = elapsed / seconds if seconds else 0.0
        fraction = min(max(fraction, 0.0), 1.0)
        left = (elapsed / fraction - elapsed) if fraction > 0 else float("nan")
        psnr = trainer.last.get("psnr", float("nan")) if trainer.last else float("nan")
        message = f"step {done}, PSNR {psnr:.1f} dB, {elapsed:.0f} s" + (
            f", about {left:.0f} s left" if left == left else ""
        )
        job.worker.send({"type": "progress", "id": job.id, "fraction": fraction, "message": message})

    with job.serving_side_requests(ours):
        summary = run_training(
            p["data"],
            p["out"],
            max_seconds=seconds,
            steps=steps,
            device=p.get("device", "auto"),
            downscale=downscale,
            resume=bool(p.get("resume")),
            overwrite=bool(p.get("overwrite")),
            progress=False,
            callback=report,
            should_stop=job.cancel_event.is_set,
            scene_model=p.get("scene", "auto"),
            masks=masks,
        )
    keep = (
        "steps",
        "seconds",
        "psnr",
        "loss",
        "checkpoint",
        "device",
        "images",
        "width",
        "height",
        "masks",
        "masks_reason",
    )
    return {**{k: summary[k] for k in keep if k in summary}, "cancelled": job.cancel_event.is_set()}


def _same_path_key(path: str) -> str:
    return os.path.normcase(os.path.realpath(os.path.abspath(path)))


PREVIEW_MAX_SIDE = 1024  # a preview is small: the training waits while it renders


def _preview_camera(p: dict, aabb) -> Camera:
    """The preview's camera: the request's (a pinhole in the NeRF's frame), or with `camera` null a
    view of the NeRF's box (`Camera.looking_at_box`) of `size` [width, height]."""
    cam = p.get("camera")
    if cam is None:
        size = p.get("size")
        if not (
            isinstance(size, list)
            and len(size) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in size)
        ):
            raise EngineError(
                f"training_preview without a camera needs `size`, [width, height] in pixels, got {size!r}"
            )
        camera = Camera.looking_at_box(np.asarray(aabb, dtype=np.float64).reshape(2, 3), size[0], size[1])
    elif isinstance(cam, dict):
        camera = _camera(cam)
    else:
        raise EngineError(
            f"training_preview: `camera` must be a camera (a dict) or null for a view of the NeRF's box, "
            f"got {type(cam).__name__}"
        )
    if not (1 <= camera.width <= PREVIEW_MAX_SIDE and 1 <= camera.height <= PREVIEW_MAX_SIDE):
        raise EngineError(
            f"a training preview is at most {PREVIEW_MAX_SIDE}x{PREVIEW_MAX_SIDE} pixels, got "
            f"{camera.width}x{camera.height}"
        )
    if not (np.isfinite(camera.c2w).all() and all(np.isfinite(v) and v != 0 for v in (camera.fx, camera.fy))):
        raise EngineError(
            "bad camera in the training preview: its matrix or focal lengths are not finite non-zero numbers"
        )
    return camera


def _preview_frame(job: Job, camera: Camera, stats: dict, model=None, trainer=None) -> tuple[dict, dict]:
    """The frame of a checkpoint's model, or of the model a trainer is training (between two steps)."""
    progress = lambda done, total: job.progress(done / total, "rendering the preview")  # noqa: E731
    out = (
        trainer.render_preview(camera, progress)
        if trainer is not None
        else PosedRenderer(model).render(camera, None, progress=progress)
    )
    stats.update(
        width=camera.width,
        height=camera.height,
        **{k: float(out[k]) for k in ("density_samples_per_ray", "color_samples_per_ray")},
    )
    return stats, {
        "rgba": out["rgba"].astype(np.float32, copy=False),
        "depth": out["depth"].astype(np.float32, copy=False),
    }


def _checked_preview(p: dict) -> str:
    if not isinstance(p.get("checkpoint"), str) or not p["checkpoint"]:
        raise EngineError(
            f"training_preview needs `checkpoint`, the path of the run's nerf.ckpt, got {p.get('checkpoint')!r}"
        )
    if "camera" not in p:
        raise EngineError("training_preview needs `camera`: a camera (a dict), or null for a view of the NeRF's box")
    return p["checkpoint"]


def _training_preview_of(side: Job, trainer) -> tuple[dict, dict]:
    """A preview of the model being trained, between two steps (`Trainer.render_preview`: the
    training goes on exactly as without it)."""
    _checked_preview(side.params)
    camera = _preview_camera(side.params, trainer.model.aabb.detach().cpu().numpy())
    psnr = trainer.last.get("psnr") if trainer.last else None
    return _preview_frame(
        side,
        camera,
        {"source": "training", "step": trainer.step_count, "seconds": trainer.elapsed, "psnr": psnr},
        trainer=trainer,
    )


@op("training_preview", side=True)
def training_preview(job: Job) -> tuple[dict, dict]:
    """A small frame of a training run. While the run's training runs in this worker, that training
    answers it between steps with the model as it is (`_training_preview_of`); otherwise (the
    training ended, or runs elsewhere) it renders the run's checkpoint file."""
    path = _checked_preview(job.params)
    if not os.path.isfile(path):
        raise EngineError(
            f"no training of {os.path.dirname(path) or path} runs in this worker and {path} does not "
            "exist yet: start the training, or wait for its first checkpoint"
        )
    model = cached_model(path, job.params.get("device", "auto"))
    camera = _preview_camera(job.params, model.aabb.detach().cpu().numpy())
    return _preview_frame(job, camera, {"source": "checkpoint", "checkpoint": path}, model=model)


@op("prepare")
def prepare_photos(job: Job) -> dict:
    """Photos -> a transforms.json dataset by structure from motion, as the `prepare` command does, with
    progress per stage (features, matching, mapping: each photo registered). Cancelling stops pycolmap
    midway (its cancellation token) and removes the work folder: nothing is written."""
    from ..sfm.prepare import MATCHERS, PrepareCancelled, prepare

    p = job.params
    for key in ("images", "out"):
        if not isinstance(p.get(key), str) or not p[key]:
            raise EngineError(f"prepare needs `{key}`, a folder path, got {p.get(key)!r}")
    matcher = p.get("matcher", "exhaustive")
    if matcher not in MATCHERS:
        raise EngineError(f"prepare: `matcher` must be one of {', '.join(MATCHERS)}, got {matcher!r}")
    options = {}
    for key, default in (("max_size", 1600), ("seed", 0)):
        value = p.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise EngineError(f"prepare: `{key}` must be an integer, got {value!r}")
        options[key] = value
    try:
        summary = prepare(
            p["images"],
            p["out"],
            matcher=matcher,
            log=lambda line: print(line, file=sys.stderr),
            progress=job.progress,
            should_stop=job.cancel_event.is_set,
            **options,
        )
    except PrepareCancelled:
        raise Cancelled() from None
    return {**summary, "dataset": p["out"]}


@op("first_surface")
def first_surface(job: Job) -> dict:
    """Where a ray (NeRF frame) first meets the NeRF's density above the threshold, in its box:
    what a click on the NeRF picks (the 3D cursor put on the object)."""
    p = job.params
    model = _model(p)
    threshold = float(p.get("threshold", 10.0))
    box = model.aabb.detach().cpu().double().numpy().reshape(2, 3)
    point, distance, densest = first_dense_point(
        density_fn_of(model), p.get("origin"), p.get("direction"), box, threshold
    )
    if point is None:
        return {"hit": False, "max_density": densest, "threshold": threshold}
    return {
        "hit": True,
        "point": [float(x) for x in point],
        "distance": distance,
        "max_density": densest,
        "threshold": threshold,
    }


@op("cage")
def cage(job: Job) -> tuple[dict, dict]:
    """Build the cage around a surface mesh once, and embed the surface in it. With a checkpoint
    the margin is widened where the NeRF's density is still soft (as the `cage` command does)."""
    vertices = np.asarray(job.arrays["vertices"], dtype=np.float64)
    faces = np.asarray(job.arrays["faces"], dtype=np.int64)
    p = job.params
    size = {"edge_length": p.get("edge_length"), "target_tets": p.get("target_tets")}
    cut, part = job.arrays.get("cut"), job.arrays.get("part")
    refine = job.arrays.get("refine")  # flags: the surface vertices around which the cage is made finer
    for name, flags in (("cut flags", cut), ("part labels", part), ("refinement flags", refine)):
        if flags is not None and len(flags) != len(vertices):
            raise EngineError(f"{len(flags)} {name} for a mesh of {len(vertices)} vertices")
    refine_edge = p.get("refine_edge") or None  # None: refine_around's default
    if refine_edge is not None and not (
        isinstance(refine_edge, (int, float)) and not isinstance(refine_edge, bool) and refine_edge > 0
    ):
        raise EngineError(f"refine_edge must be a positive length, got {refine_edge!r}")
    job.progress(0.05, "tetrahedralizing")

    _part_vertices = {} if part is None else {int(i): np.flatnonzero(part == i) for i in np.unique(part)}

    def build_one(V, F, _index=None):
        if p.get("checkpoint"):
            own_cut = None if cut is None else (cut if _index is None else cut[_part_vertices[_index]])
            return build_nerf_cage(
                V,
                F,
                _model(p),
                p.get("margin"),
                p.get("threshold"),
                **size,
                log=lambda line: print(line, file=sys.stderr),
                cut=own_cut,
            )
        return build_cage(V, F, p.get("margin"), **size)

    several = part is not None and len(np.unique(part)) > 1
    if several:  # one cage per edit region's object, in one cage
        built, cage_part = build_part_cages(vertices, faces, part, build_one)
    else:
        built = build_one(vertices, faces)
    refined = None
    if refine is not None:
        job.progress(0.8, "refining the cage around the selection")
        n_before = len(built.tets)
        built.vertices, built.tets, edge, box = refine_around(
            built.vertices, built.tets, vertices[np.asarray(refine, dtype=bool)], built.margin, refine_edge
        )
        if several:
            cage_part = extend_vertex_labels(cage_part, built.tets, len(built.vertices))
        refined = {"edge": edge, "box": box.tolist(), "tets_before": int(n_before)}
    job.progress(0.9, "embedding the surface")
    if several:
        embedding = embed_points_by_part(vertices, part, built.vertices, built.tets, cage_part)
        pinned = part_cut_pins(built.vertices, cage_part, vertices, part, cut, built.margin)
    else:
        embedding = embed_points(vertices, built.vertices, built.tets)
        pinned = cut_pins(built.vertices, vertices, cut, built.margin)
    if not p.get("pin_cut", True):
        pinned = np.zeros(0, dtype=np.int64)
    result = {
        "n_vertices": int(len(built.vertices)),
        "n_tets": int(len(built.tets)),
        "margin": built.margin,
        "clearance": built.clearance,
        "n_outside": embedding.n_outside,
        "timings": built.timings,
        "n_cut": int(np.count_nonzero(cut)) if cut is not None else 0,
        "n_pinned": int(len(pinned)),
        "warnings": list(built.warnings),
        "refined": refined,
    }
    return result, {
        "vertices": built.vertices,
        "tets": built.tets,
        "tet_ids": embedding.tet_ids,
        "weights": embedding.weights,
        "pinned_vertices": pinned,
    }


def _embedding(cage_arrays: dict, embedding_arrays: dict) -> Embedding:
    tets, tet_ids = cage_arrays["tets"], embedding_arrays["tet_ids"]
    if len(tet_ids) != len(embedding_arrays["weights"]):
        raise EngineError(f"the embedding has {len(tet_ids)} tets for {len(embedding_arrays['weights'])} weight rows")
    if len(tet_ids) and tet_ids.max() >= len(tets):
        raise EngineError(f"the embedding names tets outside the cage's 0..{len(tets) - 1}: rebuild the cage")
    return Embedding(tet_ids=tet_ids, corners=tets[tet_ids], weights=embedding_arrays["weights"], n_outside=0)


class HandlePose(NamedTuple):
    cage_key: str
    cage: dict  # the rest cage's arrays
    embedding_key: tuple  # (cage key, embedding key)
    embedding: Embedding
    deformed: np.ndarray  # the cage's vertices at this pose
    stats: dict


def _handle_pose(job: Job, pose: dict) -> HandlePose:
    """Solve the handles' pose with the shared cage, embedding and regions the request names."""
    shared = SESSION.shared(job, "cage", "embedding", "regions")
    (cage_key, cage_arrays), (emb_key, emb_arrays), (reg_key, reg) = (
        shared["cage"],
        shared["embedding"],
        shared["regions"],
    )
    embedding = SESSION.derived("embedding", (cage_key, emb_key), lambda: _embedding(cage_arrays, emb_arrays))
    mode = pose.get("mode", "ARAP")
    names = list(pose.get("handle_names") or [])

    def build():
        job.progress(0.05, f"{mode} precomputation")
        regions = split_regions(reg["handle_index"], reg["handle_counts"])
        return RegionDeformer(
            cage_arrays["vertices"],
            cage_arrays["tets"],
            embedding,
            regions,
            reg["pin_index"],
            names or None,
            mode,
            cage_pins=reg.get("cage_pin_index"),
        )

    key = (cage_key, emb_key, reg_key, mode, tuple(names))
    fresh = not SESSION.has("deformer", key)
    deformer = SESSION.derived("deformer", key, build, keep=2)
    transforms = [np.asarray(t, dtype=np.float64) for t in pose.get("transforms", [])]
    deformed, stats = deformer.solve(transforms)
    if fresh:
        stats["precompute_s"] = deformer.precompute_s
    return HandlePose(cage_key, cage_arrays, (cage_key, emb_key), embedding, deformed, stats)


@op("solve")
def solve(job: Job) -> tuple[dict, dict]:
    """A pose of the handles: the deformed cage vertices, or with answer "surface" the deformed
    extracted mesh (float32, its vertex order), which is all the live preview draws."""
    posed = _handle_pose(job, job.params)
    if job.params.get("answer") == "surface":
        surface = SESSION.derived(
            "surface map", posed.embedding_key, lambda: SurfaceMap(posed.embedding, len(posed.deformed)), keep=2
        )
        return posed.stats, {"surface": surface.apply(posed.deformed).astype(np.float32)}
    return posed.stats, {"deformed_vertices": np.asarray(posed.deformed, dtype=np.float64)}


def _camera(cam: dict) -> Camera:
    try:
        return Camera(
            c2w=np.asarray(cam["camera_to_world"], dtype=np.float64).reshape(4, 4),
            fx=float(cam["fx"]),
            fy=float(cam["fy"]),
            cx=float(cam["cx"]),
            cy=float(cam["cy"]),
            width=int(cam["width"]),
            height=int(cam["height"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise EngineError(f"bad camera in the render request: {exc}") from None


def _posed(job: Job, model, pose: dict | None):
    """(PosedRenderer, deformed cage vertices or None at rest, stats) of the pose a request names."""
    pose = pose or {"kind": "rest"}
    kind, stats = pose.get("kind"), {}
    if kind == "rest":
        return PosedRenderer(model), None, stats
    if kind not in ("cage", "handles"):
        raise EngineError(f"unknown pose kind {kind!r}: rest, cage or handles")
    if kind == "handles":
        posed = _handle_pose(job, pose)
        cage_key, cage_arrays, deformed, stats = posed.cage_key, posed.cage, posed.deformed, posed.stats
    else:
        cage_key, cage_arrays = SESSION.shared(job, "cage")["cage"]
        if "deformed_vertices" not in job.arrays:
            raise EngineError("a cage pose needs its deformed_vertices")
        deformed = np.asarray(job.arrays["deformed_vertices"], dtype=np.float64)
        if deformed.shape != cage_arrays["vertices"].shape:
            raise EngineError(
                f"deformed cage vertices must be of the cage's shape {cage_arrays['vertices'].shape}, "
                f"got {deformed.shape}"
            )
        check_coordinates(deformed, "the cage as its modifiers deform it")
    renderer = SESSION.derived(
        "renderer",
        (id(model), cage_key),
        lambda: PosedRenderer(model, cage_arrays["vertices"], cage_arrays["tets"]),
        keep=2,
    )
    return renderer, deformed, stats


def _inversion_stats(stats: dict, inversion) -> None:
    if inversion is not None:
        stats.update(inverted_tets=inversion.n_inverted, degenerate_tets=inversion.n_degenerate)


@op("render")
def render(job: Job) -> tuple[dict, dict]:
    """One frame from a pinhole camera in the NeRF's frame, at the pose given, solved here.

    params: checkpoint, camera, pose, substeps (samples per step of the march: 1, a preview's, when absent;
    final frames send `substeps.FINAL_SUBSTEPS`). Returns arrays `rgba` (H,W,4) float32 straight alpha, rows
    top-down, and `depth` (H,W) float32: expected distance along each unit ray, NeRF units, 0 where empty.
    """
    params = job.params
    substeps = check_substeps(params.get("substeps", 1))
    model = _model(params)
    camera = _camera(params["camera"])
    renderer, deformed, stats = _posed(job, model, params.get("pose"))
    out = renderer.render(
        camera, deformed, progress=lambda done, total: job.progress(done / total, "rendering"), substeps=substeps
    )
    stats.update({k: float(out[k]) for k in ("density_samples_per_ray", "color_samples_per_ray")})
    _inversion_stats(stats, out["inversion"])
    return stats, {
        "rgba": out["rgba"].astype(np.float32, copy=False),
        "depth": out["depth"].astype(np.float32, copy=False),
    }


# Pixels per side of the view `warm` renders: rays enough to meet the NeRF's occupied cells and so run
# every kernel of a frame (march, hash encoding, compositing, colour); its time is the kernels' loading.
WARM_VIEW = 8


@op("warm")
def warm(job: Job) -> dict:
    """Load each checkpoint and render a small view of its box: what a file's first frame would otherwise
    wait for (the file read, numba's first run of the frame's kernels). params: checkpoints (paths).
    Returns each view's colour samples per ray (0: the view met nothing, so not every kernel ran).
    Ray bending's kernels are left to the first bent frame: warming them on a stand-in cage cost 1.1 s
    (the cage's set-up) to save 0.2 s on the fox."""
    paths = job.params.get("checkpoints")
    if not isinstance(paths, list) or not all(isinstance(p, str) for p in paths):
        raise EngineError(f"warm: `checkpoints` must be a list of checkpoint paths, got {paths!r:.120}")
    samples = []
    for k, path in enumerate(paths):
        model = cached_model(path)
        camera = Camera.looking_at_box(model.aabb.cpu().numpy(), WARM_VIEW, WARM_VIEW)
        samples.append(float(PosedRenderer(model).render(camera)["color_samples_per_ray"]))
        job.progress((k + 1) / len(paths), f"loaded {os.path.basename(path)}")
    return {"color_samples_per_ray": samples}


@op("bake_volume")
def bake_volume(job: Job) -> tuple[dict, dict]:
    """The NeRF at the pose given sampled on a voxel grid (bend/volume.py), for an OpenVDB file.

    params: checkpoint, pose (as `render`), extent ("nerf", "cage" or an edit region's dict),
    resolution, supersample. Returns `shape` and `index_to_nerf` (4x4, voxel index -> the NeRF's
    frame) with the stats, and arrays `index` (N,3) int32, `density` (N,) float32 per NeRF unit,
    `color` (N,3) float32 sRGB: the voxels that hold anything.
    """
    params = job.params
    extent = params.get("extent", "nerf")
    if isinstance(extent, dict):
        extent = region_from_dict(extent, where="the box to bake")
    model = _model(params)
    renderer, deformed, stats = _posed(job, model, params.get("pose"))
    box = bake_box(extent, model, deformed if deformed is not None else None)
    grid = volume_grid(
        box, params.get("resolution", 256), content=model.aabb.detach().cpu().double().reshape(2, 3).numpy()
    )
    check_volume_memory(grid)
    job.progress(0.0, "baking")
    baked, inversion = renderer.bake(
        grid,
        deformed,
        supersample=params.get("supersample", 1),
        progress=lambda done, total: job.progress(done / total, "baking"),
    )
    stats.update(baked.stats, shape=list(grid.shape), index_to_nerf=grid.index_to_nerf.tolist())
    _inversion_stats(stats, inversion)
    return stats, {"index": baked.index, "density": baked.density, "color": baked.color}
