"""Blender cameras map to the engine's pinhole exactly: checked against Blender's own projection."""

import numpy as np
import pytest

CASES = [
    # resolution, percentage, pixel aspect, lens, sensor fit, sensor w/h, shift
    ((200, 200), 100, (1, 1), 50, "AUTO", (36, 24), (0, 0)),
    ((320, 180), 50, (1, 1), 35, "AUTO", (36, 24), (0.1, -0.05)),
    ((180, 320), 100, (1, 1), 35, "AUTO", (36, 24), (-0.2, 0.15)),
    ((300, 200), 100, (2, 1), 28, "HORIZONTAL", (32, 18), (0.05, 0.1)),
    ((300, 200), 75, (1, 3), 80, "VERTICAL", (36, 20), (0.3, -0.2)),
    ((256, 400), 100, (1.5, 1), 24, "AUTO", (23.5, 15.6), (0, 0.25)),
]


@pytest.mark.parametrize("resolution,percent,aspect,lens,fit,sensor,shift", CASES)
def test_projection_matches_blender(blender, resolution, percent, aspect, lens, fit, sensor, shift):
    bpy = blender
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Euler, Vector

    from blender_nerf_deform.addon.data.camera import pinhole_from_blender

    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = percent
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    data = bpy.data.cameras.new("cam")
    data.lens, data.sensor_fit = lens, fit
    data.sensor_width, data.sensor_height = sensor
    data.shift_x, data.shift_y = shift
    cam = bpy.data.objects.new("cam", data)
    scene.collection.objects.link(cam)
    cam.location = (3.0, -4.0, 2.0)
    cam.rotation_euler = Euler((1.2, 0.1, 0.6))
    cam.scale = (1.7, 1.7, 1.7)  # object scale must not change the rays
    bpy.context.view_layer.update()

    pinhole = pinhole_from_blender(scene, cam)
    rng = np.random.default_rng(1)
    # Points in front of the camera, spread over (and beyond) its view.
    c2w = np.array(pinhole.camera_to_world)
    local = np.c_[rng.uniform(-1.5, 1.5, (50, 2)), -rng.uniform(2, 8, 50)]
    points = local @ c2w[:3, :3].T + c2w[:3, 3]
    ours = pinhole.project(points)
    for point, (u, v) in zip(points, ours):
        ndc = world_to_camera_view(scene, cam, Vector(point))
        # Blender's normalized view: x from the left edge, y from the bottom edge.
        assert u / pinhole.width == pytest.approx(ndc.x, abs=1e-5)
        assert 1 - v / pinhole.height == pytest.approx(ndc.y, abs=1e-5)
    assert (pinhole.width, pinhole.height) == (resolution[0] * percent // 100, resolution[1] * percent // 100)


def test_orthographic_camera_is_refused_with_a_clear_message(blender):
    bpy = blender
    from blender_nerf_deform.addon.data.camera import CameraError, pinhole_from_blender

    data = bpy.data.cameras.new("ortho")
    data.type = "ORTHO"
    cam = bpy.data.objects.new("Ortho Cam", data)
    with pytest.raises(CameraError, match="'Ortho Cam' is orthographic"):
        pinhole_from_blender(bpy.context.scene, cam)
