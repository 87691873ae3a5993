"""A keyframed ARAP animation rendered headless by Render Animation equals the engine's command line
rendering the same cage poses from the same camera.

The add-on side is what a user does: Load NeRF, Build Cage, Pin Selection, Add Handle, keyframes on
the handle, `bpy.ops.render.render(animation=True)`. The command-line side gets, per frame, the cage
pose the add-on's own path computes for that frame (deformation.deformed_cage after
frame_set: the worker's solve, as a render runs it), the rest cage as CAGE.npz, and the camera as
transforms.json written from the add-on's camera model (addon/data/camera.py), and runs
`python -m blender_nerf_deform.engine render --cage --deformed`. The poses are also checked against
the keyframes themselves, so a render that ignored the frame's handle pose (or the handles
altogether) could not pass.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from fixtures import REPO
from fixtures import psnr as _psnr
from fixtures.blender_objects import nerf_with_built_cage, select_in_edit_mode
from PIL import Image

SIZE = 48
FRAMES = (1, 2, 3)
# Handle pose per frame, relative to where it was made: (translation, rotation about X in radians).
KEYS = {1: ((0.0, 0.0, 0.0), 0.0), 2: ((0.1, 0.0, 0.15), 0.15), 3: ((0.2, -0.05, 0.3), 0.3)}


def _rotation_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _png(path):
    return np.asarray(Image.open(path).convert("RGBA"), dtype=np.int16)


@pytest.mark.slow
def test_keyframed_arap_animation_matches_the_engine_cli_frame_by_frame(addon, sphere_nerf, tmp_path):
    bpy = addon
    from mathutils import Matrix

    from blender_nerf_deform.addon.data.cage_store import load_cage, load_embedding
    from blender_nerf_deform.addon.data.camera import pinhole_from_blender
    from blender_nerf_deform.addon.deform.poses import deformed_cage
    from blender_nerf_deform.addon.worker import jobs
    from blender_nerf_deform.engine.geometry.mesh_io import save_cage

    ckpt, data = sphere_nerf
    meta = json.loads((data / "transforms.json").read_text())
    nerf, surface, rest_surface = nerf_with_built_cage(bpy, ckpt)
    # The NeRF placed away from the origin: poses and the camera must both go to its frame.
    nerf.matrix_world = Matrix.Translation((0.5, -0.25, 0.2))
    bpy.context.view_layer.update()
    nerf.nerf_deform.deformation_mode = "ARAP"
    z = rest_surface[:, 2]  # quarters of the mesh's own height: the fixture's mesh varies per session
    top, bottom = np.flatnonzero(z > z.min() + 0.75 * np.ptp(z)), np.flatnonzero(z < z.min() + 0.25 * np.ptp(z))
    select_in_edit_mode(bpy, surface, bottom)
    assert bpy.ops.nerf_deform.pin_selection() == {"FINISHED"}
    select_in_edit_mode(bpy, surface, top)
    assert bpy.ops.nerf_deform.add_handle() == {"FINISHED"}
    handle = bpy.context.active_object
    centroid = np.array(handle.location)  # local to the NeRF: the NeRF's frame
    for frame, (offset, angle) in KEYS.items():
        handle.location = (centroid + offset).tolist()
        handle.rotation_euler = (angle, 0.0, 0.0)
        handle.keyframe_insert("location", frame=frame)
        handle.keyframe_insert("rotation_euler", frame=frame)

    scene = bpy.context.scene
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.sensor_fit, camera.data.angle_x = "HORIZONTAL", meta["camera_angle_x"]
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.matrix_world = nerf.matrix_world @ Matrix(meta["frames"][3]["transform_matrix"])
    scene.render.resolution_x = scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    settings = scene.render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth = "PNG", "RGBA", "8"
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    scene.render.filepath = str(tmp_path / "blender" / "frame_")
    # The render solves each frame itself; the viewport preview asks the worker nothing meanwhile
    # (its requests would queue ahead of the render's on the one worker).
    from blender_nerf_deform.addon.deform import poses as deformation

    events = []
    original_request = deformation.AsyncSolver.request

    def counting_request(self, params, arrays):
        events.append(("preview solve", scene.frame_current))
        return original_request(self, params, arrays)

    def rendering(scene_, *_):
        events.append(("render", scene_.frame_current))

    deformation.AsyncSolver.request = counting_request
    bpy.app.handlers.render_pre.append(rendering)
    try:
        scene.frame_set(2)  # outside a render, a frame change does ask for a preview solve
        assert events == [("preview solve", 2)]
        events.clear()
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
        renders = [i for i, (what, _) in enumerate(events) if what == "render"]
        assert [events[i][1] for i in renders] == list(FRAMES)
        assert all(what == "render" for what, _ in events[renders[0] : renders[-1] + 1]), events
        # Only once the render is over does the preview catch up again (the restored frame 2).
        assert ("preview solve", 2) in events[renders[-1] :], events
    finally:
        bpy.app.handlers.render_pre.remove(rendering)
        deformation.AsyncSolver.request = original_request

    tet_ids, weights = load_embedding(surface.data)
    for frame in FRAMES:
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        rest, tets = load_cage(nerf.nerf_deform.cage.data)
        deformed = deformed_cage(nerf, depsgraph, jobs.worker(bpy.context))

        # The pose is the keyframe's: the handle's region, carried by the deformed cage, sits where
        # the keyed rotation and translation (about the handle's rest centroid) put it.
        offset, angle = KEYS[frame]
        keyed = (rest_surface[top] - centroid) @ _rotation_x(angle).T + centroid + offset
        carried = np.einsum("nk,nkc->nc", weights[top], deformed[tets[tet_ids[top]]])
        assert np.abs(carried - keyed).max() < 0.03, frame
        carried_pin = np.einsum("nk,nkc->nc", weights[bottom], deformed[tets[tet_ids[bottom]]])
        assert np.abs(carried_pin - rest_surface[bottom]).max() < 0.03, frame

        # The same pose and camera through the engine's command line.
        pinhole = pinhole_from_blender(scene, camera.evaluated_get(depsgraph))
        to_nerf = np.linalg.inv(np.array(nerf.evaluated_get(depsgraph).matrix_world, dtype=np.float64))
        c2w = to_nerf @ np.array(pinhole.camera_to_world, dtype=np.float64)
        cameras = {
            "w": pinhole.width,
            "h": pinhole.height,
            "fl_x": pinhole.fx,
            "fl_y": pinhole.fy,
            "cx": pinhole.cx,
            "cy": pinhole.cy,
            "frames": [{"file_path": f"frame_{frame:04d}", "transform_matrix": c2w.tolist()}],
        }
        pose_dir = tmp_path / f"pose_{frame}"
        pose_dir.mkdir()
        (pose_dir / "transforms.json").write_text(json.dumps(cameras))
        save_cage(pose_dir / "cage.npz", rest, tets)
        np.save(pose_dir / "deformed.npy", deformed)
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "blender_nerf_deform.engine",
                "render",
                "--nerf",
                str(ckpt),
                "--cameras",
                str(pose_dir / "transforms.json"),
                "--out",
                str(tmp_path / "cli"),
                "--cage",
                str(pose_dir / "cage.npz"),
                "--deformed",
                str(pose_dir / "deformed.npy"),
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]

    rendered = sorted(p.name for p in (tmp_path / "blender").iterdir())
    assert rendered == [f"frame_{f:04d}.png" for f in FRAMES]
    first = None
    for name in rendered:
        got, expected = _png(tmp_path / "blender" / name), _png(tmp_path / "cli" / name)
        assert got.shape == expected.shape == (SIZE, SIZE, 4)
        assert expected[..., 3].max() > 120 and expected[..., 3].min() < 20, name  # NeRF and empty space in view
        # Blender writes the PNG from its premultiplied linear float buffer through the Standard view
        # transform; the CLI rounds the straight-alpha sRGB floats directly. The two 8-bit roundings
        # differ by a level or two, more where alpha is tiny and colour is divided by it.
        visible = expected[..., 3] > 8
        assert np.abs(got[..., 3] - expected[..., 3]).max() <= 2, name
        assert np.abs(got[..., :3] - expected[..., :3])[visible].max() <= 3, name
        assert _psnr(got / 255.0, expected / 255.0) >= 40, name
        first = got if first is None else first
    # The animation is visible in the frames: the last pose is not the first.
    assert np.abs(got[..., 3] - first[..., 3]).max() > 60
