"""COLMAP's cameras and image poses in this project's conventions (docs/ARCHITECTURE.md, Conventions: Blender/OpenGL).

COLMAP stores, per image, `cam_from_world` (world-to-camera, OpenCV axes: x right, y down,
z forward) and, per camera, a model with its parameters. Here each image becomes a
camera-to-world 4x4 in the OpenGL convention (the camera looks down -z, +y up: flip
COLMAP's y and z axes) and each camera the intrinsics and distortion keys of an
instant-ngp / nerfstudio transforms.json.
"""

from __future__ import annotations

import numpy as np

from ..errors import EngineError

# COLMAP model → (nerfstudio camera_model, names of its parameters in COLMAP's order).
MODELS = {
    "SIMPLE_PINHOLE": ("PINHOLE", ("f", "cx", "cy")),
    "PINHOLE": ("PINHOLE", ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": ("OPENCV", ("f", "cx", "cy", "k1")),
    "RADIAL": ("OPENCV", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": None,  # rational k4-k6 terms: not modelled
    "SIMPLE_RADIAL_FISHEYE": ("OPENCV_FISHEYE", ("f", "cx", "cy", "k1")),
    "RADIAL_FISHEYE": ("OPENCV_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
}
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def camera_intrinsics(model: str, params, width: int, height: int, where: str = "camera") -> dict:
    """transforms.json keys (camera_model, fl_x, fl_y, cx, cy, w, h, k1.., p1..) of a COLMAP camera."""
    entry = MODELS.get(model)
    if entry is None:
        supported = ", ".join(m for m, e in MODELS.items() if e)
        raise EngineError(f"{where}: COLMAP camera model {model} is not supported (supported: {supported})")
    camera_model, names = entry
    values = dict(zip(names, (float(p) for p in params)))
    if len(values) != len(names):
        raise EngineError(f"{where}: a {model} camera has {len(names)} parameters, got {len(list(params))}")
    f = values.pop("f", None)
    out = {
        "camera_model": camera_model,
        "fl_x": values.pop("fx", f),
        "fl_y": values.pop("fy", f),
        "cx": values.pop("cx"),
        "cy": values.pop("cy"),
        "w": int(width),
        "h": int(height),
    }
    out.update(values)  # k1.., p1..
    bad = [k for k, v in out.items() if isinstance(v, float) and not np.isfinite(v)]
    if bad:
        raise EngineError(f"{where}: non-finite camera parameters {', '.join(bad)}")
    return out


def camera_to_world(rotation_world_to_cam: np.ndarray, translation_world_to_cam: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world 4x4 from COLMAP's world-to-camera rotation (3x3) and translation (3,)."""
    w2c = np.eye(4)
    w2c[:3, :3] = rotation_world_to_cam
    w2c[:3, 3] = translation_world_to_cam
    return np.linalg.inv(w2c) @ _OPENCV_TO_OPENGL


def reconstruction_cameras(reconstruction) -> list[dict]:
    """[{name, c2w (OpenGL), intrinsics}] of the registered images of a pycolmap.Reconstruction, by name."""
    out = []
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        cam = image.camera
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        rotation, translation = np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)
        if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
            raise EngineError(
                f"image {image.name} (id {image.image_id}): its pose (cam_from_world) has non-finite values"
            )
        c2w = camera_to_world(rotation, translation)
        out.append(
            {
                "name": image.name,
                "c2w": c2w,
                "intrinsics": camera_intrinsics(
                    cam.model.name,
                    cam.params,
                    cam.width,
                    cam.height,
                    where=f"camera {cam.camera_id} of image {image.name}",
                ),
            }
        )
    return sorted(out, key=lambda c: c["name"])


def reconstruction_points(reconstruction) -> np.ndarray | None:
    """(N, 3) positions of a pycolmap.Reconstruction's sparse points, None when it has none."""
    if not reconstruction.num_points3D():
        return None
    return np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float64)
