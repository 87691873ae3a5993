"""Rendered frames of the scene's NeRFs: the worker requests built from the depsgraph, and the passes.

What the RenderEngine class hands over to (as Cycles' engine class hands over
to its module). Each NeRF object the depsgraph shows (hidden ones, `hide_render`
or in an excluded collection, are not in a render's depsgraph) is one worker
request: `nerf_pose` reads what the frame renders it at (checkpoint, placement,
the pose: handle transforms, the modifier-deformed cage, or rest, with shared
content, cage, embedding and regions, that the worker holds after the first
frame), `camera_request` adds a camera in the NeRF's frame. `render_frame`
sends them one after the other, waits while Blender's progress bar and Esc
work, and turns the answers into Blender's passes, several NeRFs merged by
`depth_compositing` (front to back by depth, per pixel):

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

from ...engine.errors import unexpected_error
from ...engine.service.protocol import content_key
from ...engine.service.requests import Pose, RenderRequest, WireCamera
from ..data.camera import CameraError, Pinhole, pinhole_from_blender
from ..data.depth_compositing import HIT_ALPHA, NO_HIT_DEPTH, composite_by_depth
from ..data.images import srgb_to_linear
from ..data.paths import checkpoint_path
from ..data.properties import Role, to_nerf_frame
from ..deform.poses import frame_pose
from ..worker import jobs
from ..worker.client import WorkerError


def nerfs_to_render(depsgraph) -> list[bpy.types.Object]:
    """The NeRF objects the depsgraph shows (originals, by name). A render's depsgraph leaves out
    `hide_render` objects and excluded or render-disabled collections; the viewport's, the hidden ones."""
    nerfs = {o.original.name: o.original for o in depsgraph.objects if o.original.nerf_deform.role == Role.NERF}
    return [nerfs[name] for name in sorted(nerfs)]


@dataclass
class NerfPose:
    """One NeRF as a frame renders it, the camera aside (the viewport keeps it while the view moves)."""

    name: str
    to_nerf: np.ndarray  # 4x4: world → the NeRF's frame
    checkpoint: str
    pose: Pose
    substeps: int  # the NeRF's Render Substeps
    shared: dict

    def signature(self) -> str:
        """Changes whenever what this NeRF renders does (placement, checkpoint, pose, content)."""
        shared_keys = sorted((slot, key) for slot, (key, _load) in self.shared.items())
        pose, arrays = self.pose.to_wire()
        header = repr((self.name, self.checkpoint, pose, self.substeps, shared_keys, sorted(arrays))).encode()
        return content_key(np.frombuffer(header, np.uint8), self.to_nerf, *(arrays[k] for k in sorted(arrays)))


def nerf_pose(depsgraph, nerf) -> NerfPose:
    """What `nerf` renders at, at the depsgraph's frame."""
    # World -> NeRF frame, computed once per NeRF and frame: the camera, the handles and the
    # cage's placement all use it.
    to_nerf = to_nerf_frame(nerf, nerf.evaluated_get(depsgraph).matrix_world)
    pose, shared = frame_pose(nerf, depsgraph, to_nerf)
    return NerfPose(
        nerf.name,
        np.array(to_nerf, dtype=np.float64),
        checkpoint_path(nerf),
        pose,
        nerf.nerf_deform.render_substeps,
        shared,
    )


@dataclass
class FrameRequest:
    params: dict
    arrays: dict
    shared: dict
    depth_factor: np.ndarray  # per pixel: engine depth (NeRF units along unit rays) → Blender's planar depth


def camera_request(posed: NerfPose, pinhole: Pinhole, substeps: int | None = None) -> FrameRequest:
    """The worker request that renders `posed` through `pinhole` (a camera in world coordinates), at the
    NeRF's Render Substeps or at `substeps` when given (a progressive render's coarse images)."""
    c2w = posed.to_nerf @ np.array(pinhole.camera_to_world, dtype=np.float64)
    # Camera-space ray of each pixel has z = -1: its planar depth is 1 per unit of that vector.
    i = np.arange(pinhole.width) + 0.5
    j = np.arange(pinhole.height) + 0.5
    jj, ii = np.meshgrid(j, i, indexing="ij")
    d_cam = np.stack([(ii - pinhole.cx) / pinhole.fx, -(jj - pinhole.cy) / pinhole.fy, -np.ones_like(ii)], -1)
    length_in_nerf = np.linalg.norm(d_cam @ c2w[:3, :3].T, axis=-1)
    camera = WireCamera.from_pinhole(pinhole, c2w)
    request = RenderRequest(
        posed.checkpoint, camera, posed.pose, substeps=posed.substeps if substeps is None else substeps
    )
    params, arrays = request.to_wire()
    return FrameRequest(params, arrays, posed.shared, 1.0 / length_in_nerf)


def scene_pinhole(depsgraph) -> Pinhole:
    """The scene camera as the depsgraph's frame renders it."""
    scene = depsgraph.scene
    if scene.camera is None:
        raise CameraError(f"scene '{scene.name}' has no active camera")
    return pinhole_from_blender(scene, scene.camera.evaluated_get(depsgraph))


@dataclass
class Frame:
    """The passes of one frame (rows top-down), and what to tell the user."""

    rgba: np.ndarray
    depth: np.ndarray
    warnings: list[str] = field(default_factory=list)
    error: str = ""
    cancelled: bool = False  # by Blender (Esc): write nothing, report nothing


def empty_frame(width: int, height: int) -> Frame:
    return Frame(
        np.zeros((height, width, 4), dtype=np.float32), np.full((height, width), NO_HIT_DEPTH, dtype=np.float32)
    )


def passes(out: dict, depth_factor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The worker's straight-alpha sRGB RGBA and ray depth → Blender's premultiplied linear RGBA and planar depth."""
    rgba = out["rgba"]
    alpha = rgba[..., 3]
    depth = np.where(alpha > HIT_ALPHA, out["depth"] * depth_factor, NO_HIT_DEPTH).astype(np.float32)
    linear = np.concatenate([srgb_to_linear(rgba[..., :3]) * alpha[..., None], alpha[..., None]], axis=-1)
    return linear.astype(np.float32), depth


def render_warnings(nerf_name: str, frame: int, result: dict) -> list[str]:
    """What the worker's answer for one NeRF's frame asks the artist to know: a mirrored handle (no
    fold-free pose can mirror a region), inverted or degenerate cage tets (Cage Modifiers can fold)."""
    warnings = []
    if mirrored := result.get("reflected_handles"):
        warnings.append(
            f"NeRF Deform: {nerf_name}, frame {frame}: handle{'s' if len(mirrored) > 1 else ''} "
            f"{', '.join(mirrored)} mirror{'' if len(mirrored) > 1 else 's'} its region (a negative scale); "
            "a deformation that never folds cannot mirror, so the region stays unmirrored: "
            "give the handle a positive scale"
        )
    if result.get("inverted_tets") or result.get("degenerate_tets"):
        warnings.append(
            f"NeRF Deform: {nerf_name}, frame {frame}: {result.get('inverted_tets', 0)} inverted and "
            f"{result.get('degenerate_tets', 0)} degenerate cage tets (folds show the folded content)"
        )
    return warnings


def render_frame(depsgraph, width: int, height: int, *, on_progress=None, should_cancel=None, on_status=None) -> Frame:
    """Render the scene's NeRFs at the depsgraph's frame, one after the other, merged by depth;
    errors come back in the Frame (naming the NeRF at fault), never raised."""
    scene = depsgraph.scene
    frame = empty_frame(width, height)
    nerfs, current = [], None
    try:
        nerfs = nerfs_to_render(depsgraph)
        if not nerfs:
            raise ValueError("no NeRF object in the scene to render: use Load NeRF first")
        pinhole = scene_pinhole(depsgraph)
        client = jobs.worker(bpy.context)
        layers = []
        for k, nerf in enumerate(nerfs):
            current = nerf
            if should_cancel is not None and should_cancel():
                frame.cancelled = True
                return frame
            request = camera_request(nerf_pose(depsgraph, nerf), pinhole)
            if on_status:
                count = f" ({k + 1} of {len(nerfs)})" if len(nerfs) > 1 else ""
                on_status(f"NeRF Deform: rendering {nerf.name}{count}, frame {scene.frame_current}")

            def progress(fraction, message, k=k):
                if on_progress:
                    on_progress((k + fraction) / len(nerfs), message)

            result, out = client.call(
                "render",
                request.params,
                request.arrays,
                shared=request.shared,
                on_progress=progress,
                should_cancel=should_cancel,
            )
            frame.warnings.extend(render_warnings(nerf.name, scene.frame_current, result))
            layers.append(passes(out, request.depth_factor))
        frame.rgba, frame.depth = composite_by_depth(layers)
    except (CameraError, ValueError, WorkerError) as error:
        if isinstance(error, WorkerError) and error.kind == "cancelled":
            if should_cancel is not None and should_cancel():
                frame.cancelled = True  # Esc: Blender asked, and stops the render itself
                return frame
            # Cancelled without Blender asking (the worker was stopped or restarted): an empty
            # frame must not pass for a rendered one.
            error = f"the render of frame {scene.frame_current} was cancelled in the NeRF worker ({error})"
        # Name the NeRF at fault when there are several (its checkpoint, its cage).
        where = (
            f"{current.name}: " if current is not None and len(nerfs) > 1 and not isinstance(error, CameraError) else ""
        )
        frame.error = f"NeRF Deform: {where}{error}"
    except Exception:  # a bug: the frame fails with one line naming the log of its traceback
        what = f"{current.name}, frame {scene.frame_current}" if current is not None else f"frame {scene.frame_current}"
        frame.error = f"NeRF Deform: {unexpected_error(what)}"
    return frame
