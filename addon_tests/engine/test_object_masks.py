"""Masks with two meanings: object masks train the object alone (transparent around it, in the box its
silhouettes carve), ignore masks only skip pixels; `auto` tells them apart by their shape and says so."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from fixtures import REPO
from fixtures.sphere_data import RADIUS, render_sphere, sphere_cameras
from fixtures.turntable_data import SIZE, write_turntable

from blender_nerf_deform.engine.errors import EngineError
from blender_nerf_deform.engine.nerf.dataset import load_dataset
from blender_nerf_deform.engine.nerf.model import NerfModel
from blender_nerf_deform.engine.nerf.renderer import render_image
from blender_nerf_deform.engine.nerf.silhouettes import carve, mask_meaning
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions, config_for


@pytest.fixture(scope="module")
def turntable(tmp_path_factory):
    return write_turntable(tmp_path_factory.mktemp("turntable"))


def test_object_masks_become_alpha_and_carve_the_box(turntable):
    ds = load_dataset(turntable)
    assert ds.mask_meaning == "object" and "empty space" in ds.mask_reason and ds.masks is None
    silhouettes = np.stack([render_sphere(c, SIZE)[..., 3] > 0.5 for c in sphere_cameras(24)])
    np.testing.assert_array_equal(ds.images[..., 3] > 0.5, silhouettes)  # outside the mask: alpha 0
    assert ds.has_alpha and config_for(ds).contraction == "none" and config_for(ds).masks == "object"
    # The box holds the sphere and little else: the cameras stand 3 away, instant-ngp's cube would be 4x wider.
    assert (ds.aabb[0] <= -RADIUS).all() and (ds.aabb[1] >= RADIUS).all()
    assert (ds.aabb[1] - ds.aabb[0]).max() < 2 * RADIUS * 1.5
    np.testing.assert_array_equal(ds.inner_aabb, ds.aabb)
    # Downscaled, the mask's edge pixels keep a fractional alpha (box filter of the silhouette).
    small = load_dataset(turntable, downscale=2)
    assert small.mask_meaning == "object" and ((small.images[..., 3] > 0.1) & (small.images[..., 3] < 0.9)).any()


def test_the_same_masks_read_as_pixels_to_skip(turntable):
    ds = load_dataset(turntable, masks="ignore")
    assert ds.mask_meaning == "ignore" and ds.mask_reason == "as asked"
    assert ds.masks is not None and (ds.images[..., 3] == 1).all() and not ds.has_alpha
    assert config_for(ds).contraction == "linf" and config_for(ds).masks == "ignore"
    with pytest.raises(EngineError, match=r"--masks 'sky': one of auto, object, ignore"):
        load_dataset(turntable, masks="sky")


def test_masks_that_keep_most_of_the_photo_are_pixels_to_skip(tmp_path):
    ds = load_dataset(write_turntable(tmp_path / "passers_by", n_views=6, ignore_style=True))
    assert ds.mask_meaning == "ignore" and "keep most of the photo" in ds.mask_reason
    assert ds.masks is not None and not ds.masks.all()
    assert mask_meaning([np.ones((4, 4), bool)], "object") == ("object", "as asked")


def test_the_hull_keeps_the_object_and_carves_what_the_photos_see_around_it(turntable):
    ds = load_dataset(turntable)
    silhouettes = [img[..., 3] > 0.5 for img in ds.images]
    axis = np.linspace(-1.4, 1.4, 15)
    pts = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    inside = carve(pts, ds.cameras, silhouettes)
    r = np.linalg.norm(pts, axis=1)
    assert inside[r < 0.9 * RADIUS].all()  # the object (the masks are widened a little: the edge may stay)
    assert not inside[r > 1.35 * RADIUS].any()


def test_object_masks_train_an_object_transparent_around_it(turntable):
    """The fog the masks used to leave: trained as pixels to skip, nothing tells the NeRF that the space around the
    object is empty; trained as the object alone, a new view is transparent where the object is not."""
    small = {"log2_table_size": 14, "finest_resolution": 128, "occ_resolution": 32, "steps_per_diagonal": 256}
    test_cams = sphere_cameras(3, seed=9)
    truth = np.stack([render_sphere(c, SIZE)[..., 3] for c in test_cams])
    fog = {}
    for meaning in ("object", "ignore"):
        ds = load_dataset(turntable, masks=meaning)
        cfg = config_for(ds)
        for k, v in small.items():
            setattr(cfg, k, v)
        torch.manual_seed(0)
        model = NerfModel(cfg)
        Trainer(model, ds, TrainOptions(steps=150, seed=0)).train(progress=False)
        if meaning == "object":  # nothing outside the silhouettes' hull is ever occupied
            grid = model.occupancy
            centres = grid.cell_centers(torch.arange(grid.resolution**3), jitter=False).numpy()
            hull = carve(centres, ds.cameras, [img[..., 3] > 0.5 for img in ds.images])
            assert grid.mask.any() and not (grid.mask.numpy() & ~hull).any()
        cam = ds.cameras[0]
        alphas = []
        for c2w in test_cams:
            cam.c2w = c2w
            alphas.append(render_image(model.eval(), cam)["rgba"][..., 3])
        fog[meaning] = float(np.mean(np.stack(alphas)[truth < 0.01]))
        if meaning == "object":
            assert float(np.mean(np.abs(np.stack(alphas) - truth))) < 0.08
    assert fog["object"] < 0.03 < fog["ignore"], fog


def test_train_names_the_meaning_it_used(turntable, tmp_path):
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "blender_nerf_deform.engine",
            "train",
            "--data",
            str(turntable),
            "--out",
            str(tmp_path / "run"),
            "--steps",
            "3",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert re.search(
        r"masks: object masks \(the object alone, transparent around it\): the masks keep a shape", run.stderr
    )
    summary = json.loads((tmp_path / "run" / "train.json").read_text())
    assert summary["masks"] == "object"
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "blender_nerf_deform.engine",
            "train",
            "--data",
            str(turntable),
            "--out",
            str(tmp_path / "bad"),
            "--steps",
            "3",
            "--masks",
            "sky",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "invalid choice: 'sky'" in bad.stderr and "Traceback" not in bad.stderr
