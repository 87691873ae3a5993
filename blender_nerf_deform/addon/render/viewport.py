"""The NeRFs in the 3D View's Rendered shading: progressive renders that follow the view and the pose.

What the RenderEngine's `view_update` / `view_draw` hand over to (the class
itself only draws the image). A `ViewportRender` belongs to one 3D View:

- `update_scene(depsgraph)` (from `view_update`, after every depsgraph change)
  reads what each visible NeRF renders at (`frame.nerf_pose`: placement,
  checkpoint, the pose of its handles or its modifier-deformed cage);
- `update_view(pinhole)` (from `view_draw`) gives the view's camera, built by
  `pinhole_from_view` from the region's view and window matrices: in the camera
  view those are the scene camera's, so the frame inside the camera border is
  F12's.

When either differs from what the current render shows, a new
`ProgressiveRender` starts: 1/8 of the view's resolution first (an image
within a fraction of a second while the artist drags a handle or orbits),
then 1/4, 1/2 and full while nothing changes (the coarse images at one sample per
step of the march, the full one at the NeRF's Render Substeps: F12's frame). A render that was refining is
cancelled in the worker; one whose coarse step is in flight lands first
(ViewportRender says why). Answers of a replaced render are dropped, so a
stale image never replaces a newer one. The worker's answers reach Blender's
main thread through the client's timer; each image tags the view for a redraw.

`ProgressiveRender` is also what "Preview Render" runs (preview_render.py),
through the scene camera into an Image.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..data.camera import CameraError, Pinhole
from ..data.depth_compositing import composite_by_depth
from ..worker import jobs
from ..worker.client import WorkerError
from .frame import NerfPose, camera_request, nerf_pose, nerfs_to_render, passes

DOWNSCALES = (8, 4, 2, 1)
ORTHOGRAPHIC = (
    "NeRF Deform draws perspective views only; this view is orthographic (View > Perspective/Orthographic, or numpad 5)"
)


def pinhole_from_view(
    view_matrix, window_matrix, width: int, height: int, clip_start: float = 0.01, clip_end: float = 1000.0
) -> Pinhole:
    """The pinhole camera of a 3D View: `view_matrix` (world → view) and `window_matrix` (the
    OpenGL projection) of its RegionView3D, for a region of width x height pixels.

    A perspective projection maps a view-space point (x, y, z), z < 0, to normalized device
    coordinates ndc_x = P00 x / -z - P02 (likewise y with P11, P12), and pixels to
    ((ndc_x + 1) W / 2, (1 - ndc_y) H / 2) counted from the top row: so fx = P00 W / 2,
    cx = (1 - P02) W / 2, fy = P11 H / 2, cy = (1 + P12) H / 2 (the shift and zoom of the
    camera view are in P02, P12)."""
    projection = np.array(window_matrix, dtype=np.float64)
    if abs(projection[3, 3]) > 1e-12 or abs(projection[3, 2] + 1.0) > 1e-9:  # last row (0, 0, -1, 0): perspective
        raise CameraError(ORTHOGRAPHIC)
    if width < 1 or height < 1:
        raise CameraError(f"the view has no pixels ({width}x{height})")
    view_to_world = np.linalg.inv(np.array(view_matrix, dtype=np.float64))
    # Unit rotation columns, as every Pinhole has (a view matrix is rigid up to rounding).
    view_to_world[:3, :3] /= np.linalg.norm(view_to_world[:3, :3], axis=0)
    return Pinhole(
        width=int(width),
        height=int(height),
        fx=float(projection[0, 0] * width / 2),
        fy=float(projection[1, 1] * height / 2),
        cx=float((1.0 - projection[0, 2]) * width / 2),
        cy=float((1.0 + projection[1, 2]) * height / 2),
        camera_to_world=tuple(map(tuple, view_to_world)),
        clip_start=float(clip_start),
        clip_end=float(clip_end),
    )


class ProgressiveRender:
    """Renders of some NeRFs through one camera, coarse to fine (one worker request per NeRF per
    step, submitted together); each step's answers are merged by depth and handed to `on_image`
    (premultiplied scene-linear RGBA and planar depth, rows top-down), then the next step is sent.

    States: running; finished (the last step shown); superseded (`end_after_step` asked it to
    stop once the step under way is shown); cancelled; failed (with `error`). Callbacks get the
    render first: `on_image(render, rgba, depth, downscale)` (the state already says whether more
    steps follow), `on_failed(render, message)`, also called with "" when a superseded render was
    cancelled by the worker (stopped or restarted), so that its successor can start."""

    def __init__(
        self,
        client,
        poses: list[NerfPose],
        pinhole: Pinhole,
        on_image: Callable,
        on_failed: Callable | None = None,
        downscales=DOWNSCALES,
    ):
        self.client = client
        self.poses = poses
        self.pinhole = pinhole
        self.on_image = on_image
        self.on_failed = on_failed
        self.downscales = tuple(downscales)
        self.state = "running"
        self.error = ""
        self.step = 0  # the step under way
        self.delivered: list[tuple[int, int]] = []  # (width, height) of each image handed over
        self.sent: list[int] = []  # request ids, in order
        self._pending: set[int] = set()
        self._layers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._end_after_step = False

    def start(self) -> ProgressiveRender:
        if not self.poses:
            self.state = "finished"
        else:
            self._send(0)
        return self

    def _send(self, step: int) -> None:
        self.step = step
        pinhole = self.pinhole.downscaled(self.downscales[step])
        self._layers = {}
        try:
            for index, posed in enumerate(self.poses):
                # Coarse images march one sample per step (speed); the last, full-size one is F12's.
                request = camera_request(posed, pinhole, substeps=None if step + 1 == len(self.downscales) else 1)
                request_id = self.client.submit(
                    "render",
                    request.params,
                    request.arrays,
                    shared=request.shared,
                    on_done=lambda _result, out, step=step, index=index, factor=request.depth_factor: self._arrived(
                        step, index, passes(out, factor)
                    ),
                    on_error=self._failed,
                )
                self._pending.add(request_id)
                self.sent.append(request_id)
        except (ValueError, WorkerError) as error:  # the worker cannot start, content cannot load
            self._fail(str(error))

    def _arrived(self, step: int, index: int, layer: tuple[np.ndarray, np.ndarray]) -> None:
        if self.state != "running":
            return  # cancelled: a newer render owns the image
        self._layers[index] = layer
        if len(self._layers) < len(self.poses):
            return
        self._pending.clear()
        rgba, depth = composite_by_depth([self._layers[k] for k in range(len(self.poses))])
        self.delivered.append((rgba.shape[1], rgba.shape[0]))
        if self._end_after_step:
            self.state = "superseded"
        elif step + 1 == len(self.downscales):
            self.state = "finished"
        self.on_image(self, rgba, depth, self.downscales[step])
        if self.state == "running":  # neither the last step nor cancelled by on_image
            self._send(step + 1)

    def end_after_step(self) -> None:
        """Stop once the step under way has arrived and been shown (no finer step)."""
        self._end_after_step = True

    @property
    def coarse_in_flight(self) -> bool:
        """Whether the first step is under way: no image of this render has been shown yet."""
        return self.state == "running" and not self.delivered

    def _failed(self, error: WorkerError) -> None:
        if self.state != "running":
            return
        if error.kind == "cancelled":  # the worker was stopped or restarted
            self.cancel()
            if self._end_after_step and self.on_failed is not None:
                self.on_failed(self, "")
        else:
            self._fail(str(error))

    def _fail(self, message: str) -> None:
        self.cancel()
        self.state, self.error = "failed", message
        if self.on_failed is not None:
            self.on_failed(self, message)

    def cancel(self) -> None:
        """Stop: the worker drops the requests still queued or running, and answers are ignored."""
        if self.state != "running":
            return
        self.state = "cancelled"
        for request_id in sorted(self._pending):
            self.client.cancel(request_id)
        self._pending.clear()


class ViewportRender:
    """The progressive render of one 3D View (module docstring). `on_redraw` is called whenever
    `image` (premultiplied scene-linear RGBA, rows top-down, or None) or `message` changed.

    A change while a render refines cancels its request in the worker and starts the new state
    from coarse. A change while a render's first, coarse step is in flight lets that step land
    (it is shown, then the newest state starts, intermediate states skipped): during a drag whose
    changes come faster than a coarse image renders, cancelling every coarse step would show
    nothing until the drag stops. Either way no image is shown after a newer state's image."""

    def __init__(self, on_redraw: Callable[[], None] | None = None, client_for=None):
        self.on_redraw = on_redraw or (lambda: None)
        self._client_for = client_for or (lambda: jobs.worker(_context()))
        self.image: np.ndarray | None = None
        self.depth: np.ndarray | None = None
        self.image_version = 0
        self.shown_downscale: int | None = None  # of the image shown (8, 4, 2, 1)
        self.message = ""  # one line for the view's status text, "" when all is well
        self.render: ProgressiveRender | None = None
        self.restarts = 0  # renders started
        self._poses: list[NerfPose] = []
        self._pose_signatures: tuple = ()
        self._scene_error = ""
        self._pinhole: Pinhole | None = None
        self._view_error = ""
        self._wanted = None  # (pinhole, pose signatures) or ("error", message): what the view should show
        self._rendering = None  # what self.render renders
        self._reported: set[str] = set()

    # -- what Blender tells us ------------------------------------------------

    def update_scene(self, depsgraph) -> None:
        """The visible NeRFs and their poses at the depsgraph's frame (view_update)."""
        try:
            self._poses = [nerf_pose(depsgraph, nerf) for nerf in nerfs_to_render(depsgraph)]
            self._pose_signatures = tuple(p.signature() for p in self._poses)
            self._scene_error = ""
        except ValueError as error:  # a cage that cannot be used, a zero scale
            self._poses, self._pose_signatures, self._scene_error = [], ("error", str(error)), str(error)
        self._refresh()

    def update_view(self, pinhole: Pinhole) -> None:
        """The view's camera, at the region's full resolution (view_draw)."""
        self._pinhole, self._view_error = pinhole, ""
        self._refresh()

    def refuse_view(self, message: str) -> None:
        """A view that cannot be rendered (orthographic): draw nothing, say why once."""
        self._pinhole, self._view_error = None, message
        self._refresh()

    def stop(self) -> None:
        """The view stopped rendering (the engine is freed): cancel what the worker still does."""
        if self.render is not None:
            self.render.cancel()

    # -- what follows from it -------------------------------------------------

    def _refresh(self) -> None:
        error = self._view_error or self._scene_error
        wanted = ("error", error) if error else (self._pinhole, self._pose_signatures)
        if wanted == self._wanted:
            return
        self._wanted = wanted
        render = self.render
        if render is not None and render.coarse_in_flight and not error and self._pinhole is not None and self._poses:
            render.end_after_step()  # shown when it lands; then _start renders the newest state
            return
        self.stop()
        self._start()

    def _start(self) -> None:
        self.render, self._rendering = None, self._wanted
        error = self._view_error or self._scene_error
        if error or self._pinhole is None or not self._poses:
            self._show(None, None, None, self._say(error))
            return
        try:
            client = self._client_for()
        except WorkerError as worker_error:
            self._show(None, None, None, self._say(str(worker_error)))
            return
        self.restarts += 1
        self.message = ""
        self.render = ProgressiveRender(client, self._poses, self._pinhole, self._arrived, self._failed)
        self.render.start()

    def _arrived(self, render: ProgressiveRender, rgba, depth, downscale: int) -> None:
        if render is not self.render:
            return  # an answer of a render that a newer one replaced: never shown
        self._show(rgba, depth, downscale, "")
        if render.state == "superseded":
            self._start()

    def _failed(self, render: ProgressiveRender, message: str) -> None:
        if render is not self.render:
            return
        if self._rendering != self._wanted:  # a newer state waits: render it instead
            self._start()
        elif message:
            self._show(self.image, self.depth, self.shown_downscale, self._say(message))

    def _say(self, message: str) -> str:
        if message and message not in self._reported:  # once per view and message, not on every redraw
            self._reported.add(message)
            print(f"NeRF Deform viewport: {message}")
        return message

    def _show(self, rgba, depth, downscale, message: str) -> None:
        if rgba is None and self.image is None and message == self.message:
            return  # nothing was shown and nothing is: no redraw
        self.image, self.depth, self.shown_downscale, self.message = rgba, depth, downscale, message
        self.image_version += 1
        try:
            self.on_redraw()
        except ReferenceError:  # the engine was freed meanwhile
            pass

    @property
    def status(self) -> str:
        """The view's status line: the error, or how far the refinement got."""
        if self.message:
            return f"NeRF Deform: {self.message}"
        if self.render is None or self.shown_downscale is None:
            return ""
        if self.render.state == "running":
            return f"NeRF Deform: 1/{self.shown_downscale} resolution, refining"
        return "" if self.shown_downscale == 1 else f"NeRF Deform: 1/{self.shown_downscale} resolution"


def _context():
    import bpy

    return bpy.context


def viewport_pinhole(context) -> Pinhole:
    """The pinhole camera of the 3D View being drawn (`context.region`, `context.region_data`)."""
    region, view = context.region, context.region_data
    if not view.is_perspective:
        raise CameraError(ORTHOGRAPHIC)
    space = context.space_data
    clip = (getattr(space, "clip_start", 0.01), getattr(space, "clip_end", 1000.0))
    return pinhole_from_view(view.view_matrix, view.window_matrix, region.width, region.height, *clip)
