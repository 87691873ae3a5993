"""A Blender camera as a pinhole camera: the intrinsics the engine renders with.

Follows Blender's own view plane (BKE_camera_params_compute_viewplane): the
sensor fit picks which image side the sensor spans (AUTO: the larger one, in
aspect-corrected pixels), shift moves the view plane in units of that side,
pixel aspect stretches rows (ycor = yasp / xasp), and the resolution
percentage scales the pixel grid. Rays go through pixel centres and the
camera looks down its local -Z with +Y up (docs/ARCHITECTURE.md, Conventions), so pixel (i, j),
j counted from the top row, has the camera-space direction

    ((i + 0.5 - cx) / fx, -(j + 0.5 - cy) / fy, -1)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np


class CameraError(ValueError):
    """The camera cannot be rendered by ray bending (orthographic, panoramic, degenerate)."""


@dataclass(frozen=True)
class Pinhole:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_to_world: tuple  # 4x4, rows, rotation columns of unit length
    clip_start: float
    clip_end: float

    def as_dict(self) -> dict:
        return asdict(self)

    def downscaled(self, factor: int) -> Pinhole:
        """The same view on a pixel grid `factor` times coarser (for progressive previews)."""
        width, height = max(1, self.width // factor), max(1, self.height // factor)
        sx, sy = width / self.width, height / self.height
        return replace(
            self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy
        )

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(N,3) world points → (N,2) pixel coordinates (x right, y down, pixel centres at .5)."""
        world_to_camera = np.linalg.inv(np.asarray(self.camera_to_world, dtype=np.float64))
        p = np.c_[points_world, np.ones(len(points_world))] @ world_to_camera.T
        depth = -p[:, 2]
        return np.stack([self.cx + self.fx * p[:, 0] / depth, self.cy - self.fy * p[:, 1] / depth], axis=1)


def render_size(render) -> tuple[int, int]:
    """Pixel size of the rendered image, resolution percentage applied (as Blender rounds it)."""
    scale = render.resolution_percentage / 100.0
    return int(render.resolution_x * scale), int(render.resolution_y * scale)


def pinhole_from_blender(scene, camera_object) -> Pinhole:
    """The pinhole camera of `camera_object` (evaluated, for animated lenses) as `scene` renders it."""
    cam = camera_object.data
    if cam.type != "PERSP":
        kind = {"ORTHO": "orthographic", "PANO": "panoramic"}.get(cam.type, cam.type)
        raise CameraError(
            f"camera '{camera_object.name}' is {kind}; NeRF Deform renders perspective cameras only "
            "(set Camera > Lens > Type to Perspective)"
        )
    render = scene.render
    width, height = render_size(render)
    if width < 1 or height < 1 or cam.lens <= 0:
        raise CameraError(f"camera '{camera_object.name}' has an empty image ({width}x{height}) or lens {cam.lens}")
    xasp, yasp = render.pixel_aspect_x, render.pixel_aspect_y
    ycor = yasp / xasp

    fit = cam.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if xasp * width >= yasp * height else "VERTICAL"
    sensor = cam.sensor_height if cam.sensor_fit == "VERTICAL" else cam.sensor_width
    viewfac = width if fit == "HORIZONTAL" else ycor * height
    # Size of one pixel on the plane at distance 1 in front of the camera.
    pixsize = sensor / cam.lens / viewfac

    matrix = np.array(camera_object.matrix_world.normalized(), dtype=np.float64)
    return Pinhole(
        width=width,
        height=height,
        fx=1.0 / pixsize,
        fy=1.0 / (pixsize * ycor),
        cx=0.5 * width - cam.shift_x * viewfac,
        cy=0.5 * height + cam.shift_y * viewfac / ycor,
        camera_to_world=tuple(map(tuple, matrix)),
        clip_start=cam.clip_start,
        clip_end=cam.clip_end,
    )
