"""The requests the worker serves, one handler per op (registered with `registry.op`).

Each handler builds its request with `from_wire` (requests.py: the protocol, every field checked
there) and hands it to the stage functions the command line calls too; their results go back as
plain data and arrays. No stage logic and no checks of the wire here. Loaded NeRFs are cached by
path and modification time; cages, embeddings and regions live in the worker session (session.py)
under the keys Blender gave them, with what is built from them.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import NamedTuple

import numpy as np

from ..bend.baked_volume import check_volume_memory, volume_grid
from ..bend.posed import PosedRenderer
from ..bend.volume import bake_box
from ..errors import EngineError
from ..geometry.cage_build import build_surface_cage
from ..geometry.deform import split_regions
from ..geometry.embedding import Embedding
from ..geometry.extract import density_fn_of, extract_nerf_mesh, extract_nerf_regions, first_dense_point
from ..geometry.handle_pose import RegionDeformer
from ..geometry.surface_map import SurfaceMap
from ..nerf.camera import Camera
from ..nerf.checkpoint import load_nerf
from ..nerf.model import device_summary
from .registry import Cancelled, Job, op
from .requests import (
    BakeVolumeRequest,
    CageRequest,
    ExtractRequest,
    FirstSurfaceRequest,
    HandlesPose,
    LoadRequest,
    Op,
    PrepareRequest,
    RenderRequest,
    RestPose,
    SolveAnswer,
    SolveRequest,
    TrainingPreviewRequest,
    TrainRequest,
    WarmRequest,
    check_embedding,
)
from .session import SESSION

logger = logging.getLogger(__name__)

_models: dict[tuple[str, str], tuple[float, object]] = {}


def cached_model(path: str, device: str | None = "auto"):
    """The NeRF at `path`, loaded once per (path, device) and reloaded when the file changes."""
    device = device or "auto"
    try:
        mtime = os.path.getmtime(path)
    except (OSError, TypeError, ValueError):
        raise EngineError(f"NeRF checkpoint {path} does not exist or cannot be read") from None
    key = (os.path.abspath(path), device)
    cached = _models.get(key)
    if cached is None or cached[0] != mtime:
        _models[key] = (mtime, load_nerf(path, device=device))
    return _models[key][1]


def _box(model) -> np.ndarray:
    return model.aabb.detach().cpu().double().numpy().reshape(2, 3)


@op(Op.INFO)
def info(job: Job) -> dict:
    return {"python": sys.executable, "pid": os.getpid(), **device_summary()}


@op(Op.LOAD)
def load(job: Job) -> dict:
    """Read a checkpoint: its bounds and configuration, for placing it in the scene."""
    request = LoadRequest.from_wire(job.params, job.arrays)
    model = cached_model(request.path, request.device)
    return {
        "aabb": [float(x) for x in model.aabb.reshape(-1).tolist()],
        "config": model.config.to_dict(),
        "device": str(model.device),
    }


@op(Op.EXTRACT)
def extract(job: Job) -> tuple[dict, dict]:
    """The NeRF's surface: marching cubes of its density, floaters dropped, vertex colours."""
    request = ExtractRequest.from_wire(job.params, job.arrays)
    model = cached_model(request.checkpoint, request.device)
    job.progress(0.05, "sampling the density grid")
    regions, pick = request.edit_regions(), request.pick_point()
    options = {"resolution": request.resolution, "threshold": request.threshold, "min_volume": request.min_volume}
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


def _training_progress(job: Job, trainer, request: TrainRequest, last: list) -> None:
    """Send the training's progress (steps, batch PSNR, elapsed, an estimate of what is left), at most
    every PROGRESS_EVERY_S."""
    now = time.perf_counter()
    if now - last[0] < PROGRESS_EVERY_S:
        return
    last[0] = now
    done, elapsed = trainer.step_count, trainer.elapsed
    if request.steps:
        fraction = done / request.steps
    else:
        fraction = elapsed / request.max_seconds if request.max_seconds else 0.0
    fraction = min(max(fraction, 0.0), 1.0)
    left = (elapsed / fraction - elapsed) if fraction > 0 else float("nan")
    psnr = trainer.last.get("psnr", float("nan")) if trainer.last else float("nan")
    message = f"step {done}, PSNR {psnr:.1f} dB, {elapsed:.0f} s" + (
        f", about {left:.0f} s left" if left == left else ""
    )
    job.worker.send({"type": "progress", "id": job.id, "fraction": fraction, "message": message})


_TRAIN_SUMMARY = ("steps", "seconds", "psnr", "loss", "checkpoint", "device", "images", "width", "height", "masks")


@op(Op.TRAIN)
def train(job: Job) -> dict:
    """Train a NeRF on a dataset folder (every format `train` reads) into a run folder, as the
    `train` command does, with progress. Cancelling stops after the current step and still writes
    the checkpoint (the result says `cancelled`); `resume` continues a run folder's checkpoint.
    Previews of this run (`training_preview`) are answered between steps."""
    from ..nerf.trainer import run_training

    request = TrainRequest.from_wire(job.params, job.arrays)
    last = [0.0]
    checkpoint = _same_path_key(os.path.join(request.out, "nerf.ckpt"))

    def ours(side: Job) -> bool:  # a preview of this run
        run = TrainingPreviewRequest.run_of(side.params)
        return run is not None and _same_path_key(run) == checkpoint

    def report(trainer):
        job.serve_side_requests(lambda side: _training_preview_of(side, trainer))
        _training_progress(job, trainer, request, last)

    with job.serving_side_requests(ours):
        summary = run_training(
            request.data,
            request.out,
            max_seconds=request.max_seconds,
            steps=request.steps,
            device=request.device,
            downscale=request.downscale,
            resume=request.resume,
            overwrite=request.overwrite,
            progress=False,
            callback=report,
            should_stop=job.cancel_event.is_set,
            scene_model=str(request.scene),
            masks=str(request.masks),
        )
    keep = (*_TRAIN_SUMMARY, "masks_reason")
    return {**{k: summary[k] for k in keep if k in summary}, "cancelled": job.cancel_event.is_set()}


def _same_path_key(path: str) -> str:
    return os.path.normcase(os.path.realpath(os.path.abspath(path)))


def _preview_camera(request: TrainingPreviewRequest, aabb) -> Camera:
    """The preview's camera: the request's, or without one a view of the NeRF's box of its size."""
    if request.camera is not None:
        return request.camera.camera()
    width, height = request.size
    return Camera.looking_at_box(np.asarray(aabb, dtype=np.float64).reshape(2, 3), width, height)


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


def _training_preview_of(side: Job, trainer) -> tuple[dict, dict]:
    """A preview of the model being trained, between two steps (`Trainer.render_preview`: the
    training goes on exactly as without it)."""
    request = TrainingPreviewRequest.from_wire(side.params, side.arrays)
    camera = _preview_camera(request, trainer.model.aabb.detach().cpu().numpy())
    psnr = trainer.last.get("psnr") if trainer.last else None
    return _preview_frame(
        side,
        camera,
        {"source": "training", "step": trainer.step_count, "seconds": trainer.elapsed, "psnr": psnr},
        trainer=trainer,
    )


@op(Op.TRAINING_PREVIEW, side=True)
def training_preview(job: Job) -> tuple[dict, dict]:
    """A small frame of a training run. While the run's training runs in this worker, that training
    answers it between steps with the model as it is (`_training_preview_of`); otherwise (the
    training ended, or runs elsewhere) it renders the run's checkpoint file."""
    request = TrainingPreviewRequest.from_wire(job.params, job.arrays)
    path = request.checkpoint
    if not os.path.isfile(path):
        raise EngineError(
            f"no training of {os.path.dirname(path) or path} runs in this worker and {path} does not "
            "exist yet: start the training, or wait for its first checkpoint"
        )
    model = cached_model(path, request.device)
    camera = _preview_camera(request, model.aabb.detach().cpu().numpy())
    return _preview_frame(job, camera, {"source": "checkpoint", "checkpoint": path}, model=model)


@op(Op.PREPARE)
def prepare_photos(job: Job) -> dict:
    """Photos -> a transforms.json dataset by structure from motion, as the `prepare` command does, with
    progress per stage (features, matching, mapping: each photo registered). Cancelling stops pycolmap
    midway (its cancellation token) and removes the work folder: nothing is written."""
    from ..sfm.prepare import PrepareCancelled, prepare

    request = PrepareRequest.from_wire(job.params, job.arrays)
    try:
        summary = prepare(
            request.images,
            request.out,
            matcher=str(request.matcher),
            log=logger.info,
            progress=job.progress,
            should_stop=job.cancel_event.is_set,
            max_size=request.max_size,
            seed=request.seed,
        )
    except PrepareCancelled:
        raise Cancelled() from None
    return {**summary, "dataset": request.out}


@op(Op.FIRST_SURFACE)
def first_surface(job: Job) -> dict:
    """Where a ray (NeRF frame) first meets the NeRF's density above the threshold, in its box:
    what a click on the NeRF picks (the 3D cursor put on the object)."""
    request = FirstSurfaceRequest.from_wire(job.params, job.arrays)
    model = cached_model(request.checkpoint, request.device)
    threshold = request.threshold
    point, distance, densest = first_dense_point(
        density_fn_of(model), list(request.origin), list(request.direction), _box(model), threshold
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


@op(Op.CAGE)
def cage(job: Job) -> tuple[dict, dict]:
    """Build the cage around a surface mesh once, and embed the surface in it (geometry/cage_build.py,
    what the `cage` command calls too). With a checkpoint the margin is widened where the NeRF's
    density is still soft."""
    request = CageRequest.from_wire(job.params, job.arrays)
    vertices = np.asarray(request.vertices, dtype=np.float64)
    job.progress(0.05, "tetrahedralizing")
    built = build_surface_cage(
        vertices,
        np.asarray(request.faces, dtype=np.int64),
        cached_model(request.checkpoint, request.device) if request.checkpoint else None,
        margin=request.margin,
        threshold=request.threshold,
        edge_length=request.edge_length,
        target_tets=request.target_tets,
        cut=request.cut,
        part=request.part,
        refine_points=None if request.refine is None else vertices[np.asarray(request.refine, dtype=bool)],
        refine_edge=request.refine_edge,
        refine_box=request.refine_box,
        pin_cut=request.pin_cut,
        log=logger.info,
        progress=job.progress,
    )
    c, refined = built.cage, built.refined
    if refined is not None and refined["box"] is not None:
        refined = {**refined, "box": refined["box"].tolist()}
    result = {
        "n_vertices": int(len(c.vertices)),
        "n_tets": int(len(c.tets)),
        "margin": c.margin,
        "clearance": c.clearance,
        "n_outside": built.embedding.n_outside,
        "timings": c.timings,
        "n_cut": int(np.count_nonzero(request.cut)) if request.cut is not None else 0,
        "n_pinned": int(len(built.pinned)),
        "warnings": list(c.warnings),
        "refined": refined,
    }
    return result, {
        "vertices": c.vertices,
        "tets": c.tets,
        "tet_ids": built.embedding.tet_ids,
        "weights": built.embedding.weights,
        "pinned_vertices": built.pinned,
    }


def _embedding(cage_arrays: dict, embedding_arrays: dict) -> Embedding:
    tets, tet_ids, weights = cage_arrays["tets"], embedding_arrays["tet_ids"], embedding_arrays["weights"]
    check_embedding(tets, tet_ids, weights)
    return Embedding(tet_ids=tet_ids, corners=tets[tet_ids], weights=weights, n_outside=0)


class HandlePose(NamedTuple):
    cage_key: str
    cage: dict  # the rest cage's arrays
    embedding_key: tuple  # (cage key, embedding key)
    embedding: Embedding
    deformed: np.ndarray  # the cage's vertices at this pose
    stats: dict


def _handle_pose(job: Job, pose: HandlesPose) -> HandlePose:
    """Solve the handles' pose with the shared cage, embedding and regions the request names."""
    shared = SESSION.shared(job, "cage", "embedding", "regions")
    (cage_key, cage_arrays), (emb_key, emb_arrays), (reg_key, reg) = (
        shared["cage"],
        shared["embedding"],
        shared["regions"],
    )
    embedding = SESSION.derived("embedding", (cage_key, emb_key), lambda: _embedding(cage_arrays, emb_arrays))
    mode, names = str(pose.mode), list(pose.handle_names)

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
    deformed, stats = deformer.solve(list(pose.transforms))
    if fresh:
        stats["precompute_s"] = deformer.precompute_s
    return HandlePose(cage_key, cage_arrays, (cage_key, emb_key), embedding, deformed, stats)


@op(Op.SOLVE)
def solve(job: Job) -> tuple[dict, dict]:
    """A pose of the handles: the deformed cage vertices, or with answer "surface" the deformed
    extracted mesh (float32, its vertex order), which is all the live preview draws."""
    request = SolveRequest.from_wire(job.params, job.arrays)
    posed = _handle_pose(job, request.pose)
    if request.answer == SolveAnswer.SURFACE:
        surface = SESSION.derived(
            "surface map", posed.embedding_key, lambda: SurfaceMap(posed.embedding, len(posed.deformed)), keep=2
        )
        return posed.stats, {"surface": surface.apply(posed.deformed).astype(np.float32)}
    return posed.stats, {"deformed_vertices": np.asarray(posed.deformed, dtype=np.float64)}


def _posed(job: Job, model, pose) -> tuple[PosedRenderer, np.ndarray | None, dict]:
    """(PosedRenderer, deformed cage vertices or None at rest, stats) of a request's pose."""
    if isinstance(pose, RestPose):
        return PosedRenderer(model), None, {}
    if isinstance(pose, HandlesPose):
        posed = _handle_pose(job, pose)
        cage_key, cage_arrays, deformed, stats = posed.cage_key, posed.cage, posed.deformed, posed.stats
    else:
        cage_key, cage_arrays = SESSION.shared(job, "cage")["cage"]
        pose.check_cage(cage_arrays["vertices"], where=f"{job.op} request")
        deformed, stats = pose.deformed_vertices, {}
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


@op(Op.RENDER)
def render(job: Job) -> tuple[dict, dict]:
    """One frame from a pinhole camera in the NeRF's frame, at the pose given, solved here: arrays
    `rgba` (H,W,4) float32 straight alpha, rows top-down, and `depth` (H,W) float32, the expected
    distance along each unit ray in NeRF units, 0 where empty."""
    request = RenderRequest.from_wire(job.params, job.arrays)
    model = cached_model(request.checkpoint, request.device)
    renderer, deformed, stats = _posed(job, model, request.pose)
    out = renderer.render(
        request.camera.camera(),
        deformed,
        progress=lambda done, total: job.progress(done / total, "rendering"),
        substeps=request.substeps if request.substeps is not None else 1,
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


@op(Op.WARM)
def warm(job: Job) -> dict:
    """Load each checkpoint and render a small view of its box: what a file's first frame would otherwise
    wait for (the file read, numba's first run of the frame's kernels). Returns each view's colour samples
    per ray (0: the view met nothing, so not every kernel ran). Ray bending's kernels are left to the
    first bent frame: warming them on a stand-in cage costs the cage's set-up, more than it saves."""
    request = WarmRequest.from_wire(job.params, job.arrays)
    samples = []
    for k, path in enumerate(request.checkpoints):
        model = cached_model(path)
        camera = Camera.looking_at_box(model.aabb.cpu().numpy(), WARM_VIEW, WARM_VIEW)
        samples.append(float(PosedRenderer(model).render(camera)["color_samples_per_ray"]))
        job.progress((k + 1) / len(request.checkpoints), f"loaded {os.path.basename(path)}")
    return {"color_samples_per_ray": samples}


@op(Op.BAKE_VOLUME)
def bake_volume(job: Job) -> tuple[dict, dict]:
    """The NeRF at the pose given sampled on a voxel grid (bend/volume.py), for an OpenVDB file: `shape`
    and `index_to_nerf` (4x4, voxel index -> the NeRF's frame) with the stats, and arrays `index` (N,3)
    int32, `density` (N,) float32 per NeRF unit, `color` (N,3) float32 sRGB: the voxels that hold anything.
    """
    request = BakeVolumeRequest.from_wire(job.params, job.arrays)
    model = cached_model(request.checkpoint, request.device)
    renderer, deformed, stats = _posed(job, model, request.pose)
    box = bake_box(request.extent_value(), model, deformed)
    grid = volume_grid(box, request.resolution, content=model.aabb.detach().cpu().double().reshape(2, 3).numpy())
    check_volume_memory(grid)
    job.progress(0.0, "baking")
    baked, inversion = renderer.bake(
        grid,
        deformed,
        supersample=request.supersample,
        progress=lambda done, total: job.progress(done / total, "baking"),
    )
    stats.update(baked.stats, shape=list(grid.shape), index_to_nerf=grid.index_to_nerf.tolist())
    _inversion_stats(stats, inversion)
    return stats, {"index": baked.index, "density": baked.density, "color": baked.color}
