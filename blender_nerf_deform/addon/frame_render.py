"""One rendered frame of the scene's NeRF: the worker request built from the depsgraph, and the passes.

What the RenderEngine class hands over to (as Cycles' engine class hands over
to its module): `frame_request` turns the scene at the frame being rendered
into one worker request (camera in the NeRF's frame, checkpoint, the pose:
handle transforms, the modifier-deformed cage, or rest) whose shared content
(cage, embedding, regions) the worker already holds after the first frame;
`render_frame` sends it, waits while Blender's progress bar and Esc work, and
turns the answer into Blender's passes:

- Combined: RGBA, premultiplied as Blender's render buffers are, in scene
  linear (the NeRF's sRGB colours decoded), so the "Standard" view transform
  gives back exactly the colours the NeRF learnt.
- Depth: distance from the camera plane in world units, as Cycles writes it;
  1e10 where nothing was hit.
- Alpha: coverage, one channel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy
import numpy as np

from . import jobs
from .camera import CameraError, pinhole_from_blender
from .deformation import frame_pose
from .nerf_ops import checkpoint_path
from .properties import to_nerf_frame
from .worker_client import WorkerError

NO_HIT_DEPTH = 1e10


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def nerfs_to_render(scene) -> list:
    return sorted(
        (o for o in scene.objects if o.nerf_deform.role == "NERF" and not o.hide_render), key=lambda o: o.name
    )


@dataclass
class FrameRequest:
    params: dict
    arrays: dict
    shared: dict
    depth_factor: np.ndarray  # per pixel: engine depth (NeRF units along unit rays) → Blender's planar depth


def frame_request(depsgraph, nerf, downscale: int = 1) -> FrameRequest:
    """The worker request that renders `nerf` from the scene camera at the depsgraph's frame."""
    scene = depsgraph.scene
    if scene.camera is None:
        raise CameraError(f"scene '{scene.name}' has no active camera")
    camera = scene.camera.evaluated_get(depsgraph)
    nerf_eval = nerf.evaluated_get(depsgraph)
    pinhole = pinhole_from_blender(scene, camera).downscaled(downscale)
    to_nerf = np.array(to_nerf_frame(nerf, nerf_eval.matrix_world), dtype=np.float64)
    c2w = to_nerf @ np.array(pinhole.camera_to_world, dtype=np.float64)
    # Camera-space ray of each pixel has z = -1: its planar depth is 1 per unit of that vector.
    i = np.arange(pinhole.width) + 0.5
    j = np.arange(pinhole.height) + 0.5
    jj, ii = np.meshgrid(j, i, indexing="ij")
    d_cam = np.stack([(ii - pinhole.cx) / pinhole.fx, -(jj - pinhole.cy) / pinhole.fy, -np.ones_like(ii)], -1)
    length_in_nerf = np.linalg.norm(d_cam @ c2w[:3, :3].T, axis=-1)
    pose, arrays, shared = frame_pose(nerf, depsgraph)
    params = {
        "checkpoint": checkpoint_path(nerf),
        "camera": {**pinhole.as_dict(), "camera_to_world": c2w.tolist()},
        "pose": pose,
    }
    return FrameRequest(params, arrays, shared, 1.0 / length_in_nerf)


@dataclass
class Frame:
    """The passes of one frame (rows top-down), and what to tell the user."""

    rgba: np.ndarray
    depth: np.ndarray
    warnings: list[str] = field(default_factory=list)
    error: str = ""
    cancelled: bool = False  # by Blender (Esc): write nothing, report nothing


def empty_frame(width: int, height: int) -> Frame:
    return Frame(np.zeros((height, width, 4), dtype=np.float32), np.full((height, width), NO_HIT_DEPTH, dtype=np.float32))


def passes(out: dict, depth_factor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The worker's straight-alpha sRGB RGBA and ray depth → Blender's premultiplied linear RGBA and planar depth."""
    rgba = out["rgba"]
    alpha = rgba[..., 3]
    depth = np.where(alpha > 1e-6, out["depth"] * depth_factor, NO_HIT_DEPTH).astype(np.float32)
    linear = np.concatenate([srgb_to_linear(rgba[..., :3]) * alpha[..., None], alpha[..., None]], axis=-1)
    return linear.astype(np.float32), depth


def render_frame(depsgraph, width: int, height: int, *, on_progress=None, should_cancel=None, on_status=None) -> Frame:
    """Render the scene's NeRF at the depsgraph's frame; errors come back in the Frame, never raised."""
    scene = depsgraph.scene
    frame = empty_frame(width, height)
    try:
        nerfs = nerfs_to_render(scene)
        if not nerfs:
            raise ValueError("no NeRF object in the scene to render: use Load NeRF first")
        if len(nerfs) > 1:
            frame.warnings.append(f"NeRF Deform renders one NeRF per scene; rendering {nerfs[0].name}")
        request = frame_request(depsgraph, nerfs[0])
        if on_status:
            on_status(f"NeRF Deform: rendering {nerfs[0].name}, frame {scene.frame_current}")
        result, out = jobs.worker(bpy.context).call(
            "render", request.params, request.arrays, shared=request.shared,
            on_progress=on_progress, should_cancel=should_cancel,
        )
        if result.get("inverted_tets") or result.get("degenerate_tets"):
            frame.warnings.append(f"NeRF Deform: frame {scene.frame_current}: {result['inverted_tets']} inverted and "
                                  f"{result['degenerate_tets']} degenerate cage tets (folds show the folded content)")
        frame.rgba, frame.depth = passes(out, request.depth_factor)
    except (CameraError, ValueError, WorkerError) as error:  # PlacementError is a ValueError
        if isinstance(error, WorkerError) and error.kind == "cancelled":
            if should_cancel is not None and should_cancel():
                frame.cancelled = True  # Esc: Blender asked, and stops the render itself
                return frame
            # Cancelled without Blender asking (the worker was stopped or restarted): an empty
            # frame must not pass for a rendered one.
            error = f"the render of frame {scene.frame_current} was cancelled in the NeRF worker ({error})"
        frame.error = f"NeRF Deform: {error}"
    return frame
