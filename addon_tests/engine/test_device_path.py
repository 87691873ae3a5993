"""The CUDA code path, run on the CPU (`backend.forced("torch")`) with its torch formulations (no Triton): a
training step waits for the device once, a frame once per render round (and once per chunk for its counts)
besides the torch march's reads; its frames agree with the CPU kernels'."""

import numpy as np
import pytest
import torch
from fixtures.ball_model import ball_model
from fixtures.sphere_data import look_at, write_sphere_dataset

from blender_nerf_deform.engine import backend
from blender_nerf_deform.engine.geometry.cage import box_cage
from blender_nerf_deform.engine.launch_count import LaunchCounter
from blender_nerf_deform.engine.nerf import march_kernels
from blender_nerf_deform.engine.nerf.dataset import load_dataset
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
from blender_nerf_deform.engine.nerf.renderer import Camera, render_image
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions

TINY = {"log2_table_size": 12, "finest_resolution": 64, "occ_resolution": 16, "steps_per_diagonal": 64}


@pytest.fixture(scope="module")
def model():
    return ball_model(3, radius=0.9, table_noise=0.3, feature_noise=0.5)


def _camera(width=32, height=24):
    return Camera.from_fov(look_at((0.4, -2.4, 0.8)), width, height, 0.75, name="cam")


def _twist(model):
    from blender_nerf_deform.engine.bend.cage_bend import CageBend

    rest, tets = box_cage((3, 3, 3), lo=(-1.0,) * 3, hi=(1.0,) * 3)
    a = 0.5 * np.clip(rest[:, 2], 0, None)
    deformed = np.stack(
        [np.cos(a) * rest[:, 0] - np.sin(a) * rest[:, 1], np.sin(a) * rest[:, 0] + np.cos(a) * rest[:, 1], rest[:, 2]],
        axis=1,
    )
    bend = CageBend(model, rest, tets).set_deformed(deformed)
    return {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}


def _psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


class _Rounds:
    """Counts the rounds of the device march (each call runs the real march)."""

    def __init__(self, monkeypatch):
        self.n = 0
        original = march_kernels.march_round_device

        def counted(*args, **kwargs):
            self.n += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(march_kernels, "march_round_device", counted)


def test_a_frame_waits_once_per_round_and_agrees_with_the_cpu_kernels(model, monkeypatch):
    camera = _camera()
    kernels = render_image(model, camera) if backend.HAVE_NUMBA else None
    rounds = _Rounds(monkeypatch)
    with backend.forced("torch"), LaunchCounter() as counter:
        device = render_image(model, camera, chunk=300)
    chunks = -(-camera.width * camera.height // 300)
    assert rounds.n >= 2 * chunks  # rays end in different rounds
    # One read back per round, per chunk one for its counts and one copy of its pixels; and without Triton
    # (here) the torch march's reads between blocks (test_triton_kernels counts a frame on the Triton path).
    assert set(counter.syncs_by_op) == {"read_back", "to_host", "_local_scalar_dense"}, counter.summary()
    assert counter.syncs_by_op["read_back"] == rounds.n + chunks and counter.syncs_by_op["to_host"] == chunks
    alpha = device["rgba"][..., 3]
    assert alpha.max() > 0.9 and alpha.min() < 0.01
    if kernels is not None:
        assert _psnr(device["rgba"], kernels["rgba"]) >= 60
        assert device["density_samples_per_ray"] == kernels["density_samples_per_ray"]
        assert device["color_samples_per_ray"] == kernels["color_samples_per_ray"]


def test_a_bent_frame_on_the_device_path_agrees_with_the_cpu_kernels(model):
    if not backend.HAVE_NUMBA:
        pytest.skip("numba is not installed: the torch path is the only one")
    camera = _camera()
    kernels = render_image(model, camera, **_twist(model))
    with backend.forced("torch"):
        device = render_image(model, camera, **_twist(model))
    assert _psnr(device["rgba"], kernels["rgba"]) >= 60


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    return load_dataset(write_sphere_dataset(tmp_path_factory.mktemp("sphere") / "train", n_views=6, size=16, seed=0))


def test_a_training_step_waits_for_the_device_once(sphere):
    torch.manual_seed(0)
    with backend.forced("torch"):
        model = NerfModel(NerfConfig(aabb=sphere.aabb.reshape(-1).tolist(), **TINY))
        trainer = Trainer(
            model,
            sphere,
            TrainOptions(
                steps=40, target_samples=1 << 10, occ_warmup_steps=4, occ_update_every=2, distortion_weight=0.01
            ),
        )
        assert not trainer.lazy_table
        for step in range(6):  # occupancy updates in warm-up and after (every cell, then drawn cells)
            with LaunchCounter() as counter:
                info = trainer.step()
            assert counter.syncs == 1, (step, counter.summary())
            assert np.isfinite(info["loss"]) and info["samples_per_ray"] > 0
        assert trainer.sample_cap is not None
