"""tools/make_room_scene.py with tools/make_dataset.py --opaque: a 360-degree capture with the room behind the object.

Tiny renders (24x24, a few samples): a few seconds in all.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from tools import make_room_scene
from tools.make_dataset import DatasetError, camera_positions, make_dataset, project


def _corners(bounds):
    (x0, y0, z0), (x1, y1, z1) = bounds
    return np.array([(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], dtype=np.float64)


def test_opaque_views_inside_the_room_show_the_room_behind_the_object(blender, tmp_path):
    info = make_room_scene.build(blender)
    make_room_scene.check(blender)
    assert json.loads(blender.context.scene["nerf_room"])["room_bounds"] == [
        list(c) for c in make_room_scene.ROOM_BOUNDS
    ]
    out = tmp_path / "room"
    make_dataset(
        out,
        progress=None,
        opaque=True,
        count=2,
        resolution=24,
        samples=4,
        radius=2.7,
        min_elevation=-15.0,
        lens=35.0,
        aabb=make_room_scene.WORLD_BOX,
    )
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["aabb"] == [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]
    assert meta["generator"]["opaque"] is True and meta["generator"]["alpha"].startswith("none")

    (rx0, ry0, rz0), (rx1, ry1, rz1) = info["room_bounds"]
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        x, y, z = c2w[:3, 3]
        assert rx0 < x < rx1 and ry0 < y < ry1 and rz0 < z < rz1, "camera outside the room"
        assert math.isclose(float(np.linalg.norm(c2w[:3, 3])), 2.7, rel_tol=1e-6)

        with Image.open(out / frame["file_path"]) as im:
            assert im.mode == "RGB"  # no alpha channel: every pixel is part of the capture
            rgba = np.asarray(im.convert("RGBA"))
        assert (rgba[..., 3] == 255).all()
        rgb = rgba[..., :3].astype(np.float64)

        # Pixels outside the object's projected box see only the room: lit (not black) and textured.
        uv = project(_corners(make_room_scene.OBJECT_BOUNDS), c2w, meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
        i, j = np.meshgrid(np.arange(meta["w"]) + 0.5, np.arange(meta["h"]) + 0.5)
        inside = (i >= uv[:, 0].min()) & (i <= uv[:, 0].max()) & (j >= uv[:, 1].min()) & (j <= uv[:, 1].max())
        room = rgb[~inside]
        assert len(room) > 0.3 * meta["w"] * meta["h"], "the object fills the view: no room behind it"
        assert room.mean() > 40, f"the room is dark ({room.mean():.1f} / 255)"
        assert room.std(axis=0).max() > 10, "the room behind the object is uniform"
        assert rgb.reshape(-1, 3).std(axis=0).max() > 10


def test_min_elevation_bounds_the_cameras():
    for layout in ("spiral", "random"):
        pos = camera_positions(200, 2.7, (0.0, 0.0, 0.0), seed=3, layout=layout, min_elevation=-15.0)
        assert np.allclose(np.linalg.norm(pos, axis=1), 2.7)
        assert pos[:, 2].min() >= 2.7 * math.sin(math.radians(-15.0)) - 1e-9
        assert pos[:, 2].min() < 0.0  # some below the horizon
    hemi = camera_positions(50, 1.0, hemisphere=True, seed=1)
    assert np.allclose(hemi, camera_positions(50, 1.0, seed=1, min_elevation=0.0))


@pytest.mark.parametrize(
    "options, fault",
    [
        ({"hemisphere": True, "min_elevation": -10.0}, "--min-elevation"),
        ({"min_elevation": 90.0}, "--min-elevation"),
        ({"aabb": ((1.0, -1.0, -1.0), (-1.0, 1.0, 1.0))}, "--aabb"),
    ],
)
def test_bad_camera_options_are_named(tmp_path, options, fault):
    with pytest.raises(DatasetError, match=fault):
        make_dataset(tmp_path / "x", progress=None, **options)
