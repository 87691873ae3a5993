"""The Triton kernels of the device path, run on CPU tensors under Triton's interpreter: the same values and
gradients as the torch formulation, one launch each, and frames that agree with the CPU kernels'."""

import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from fixtures import REPO
from fixtures.ball_model import ball_model
from fixtures.sphere_data import look_at

from blender_nerf_deform.engine import backend
from blender_nerf_deform.engine.launch_count import LaunchCounter
from blender_nerf_deform.engine.nerf.encoding import HashEncoding
from blender_nerf_deform.engine.nerf.renderer import Camera, render_image

pytestmark = pytest.mark.skipif(not backend.HAVE_TRITON, reason="triton is not installed")


# Triton fixes its mode when a kernel module is first imported, and the suite imports them earlier without
# the interpreter: the kernels' tests run in a fresh process started under it.
INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"


@pytest.fixture(autouse=True)
def interpreter(request):
    if not INTERPRETED and request.node.name != "test_the_kernels_in_a_fresh_process_under_the_interpreter":
        pytest.skip("runs in a fresh process under the interpreter (the test below)")
    with backend.forced("torch"):
        yield


def test_the_kernels_in_a_fresh_process_under_the_interpreter():
    if INTERPRETED:
        pytest.skip("this is that process")
    env = dict(os.environ, TRITON_INTERPRET="1")
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", __file__],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0 and " failed" not in proc.stdout, proc.stdout[-4000:] + proc.stderr[-2000:]
    passed = re.search(r"(\d+) passed", proc.stdout)
    assert passed and int(passed.group(1)) >= 10, proc.stdout[-2000:]


def test_the_hash_encoding_kernels_give_the_torch_values_and_table_gradient():
    torch.manual_seed(0)
    enc = HashEncoding(
        n_levels=4, n_features=2, log2_table_size=10, base_resolution=4, finest_resolution=64, init_scale=1.0
    )
    assert enc.dense_levels[0] and not enc.dense_levels[-1]  # a dense level and hashed ones
    x = torch.rand(200, 3)
    x[0] = float("nan")
    x[1], x[2], x[3] = 1.0, 0.0, torch.tensor([1.0, 0.5, 1.5])  # faces of the cube, a point outside
    grad = torch.randn(200, enc.out_dim)
    with LaunchCounter() as counter:
        out = enc(x)
        out.backward(grad)
    assert counter.by_op["kernel:hash_forward"] == 1 and counter.by_op["kernel:hash_backward"] == 1
    assert counter.launches <= 3 and counter.syncs == 0  # the two kernels and the gradient's zeros
    table_grad, enc.table.grad = enc.table.grad.clone(), None
    reference = enc.torch_forward(x)
    reference.backward(grad)
    torch.testing.assert_close(out, reference, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(table_grad, enc.table.grad, atol=1e-5, rtol=1e-5)
    assert table_grad.abs().sum() > 0
    with backend.triton_enabled(False), LaunchCounter() as counter:
        enc(x).backward(grad)
    assert counter.launches > 10  # what the kernels replace


def test_reuse_runs_only_the_backward_kernel():
    torch.manual_seed(1)
    enc = HashEncoding(n_levels=3, n_features=4, log2_table_size=9, base_resolution=4, finest_resolution=32)
    x = torch.rand(50, 3)
    with torch.no_grad():
        encoded = enc(x)
    grad = torch.randn_like(encoded)
    with LaunchCounter() as counter:
        enc.reuse(encoded, x).backward(grad)
    assert "kernel:hash_forward" not in counter.by_op and counter.by_op["kernel:hash_backward"] == 1
    table_grad, enc.table.grad = enc.table.grad.clone(), None
    enc.torch_forward(x).backward(grad)
    torch.testing.assert_close(table_grad, enc.table.grad, atol=1e-5, rtol=1e-5)


def _twist(model):
    """Render arguments bending the model through a box cage twisted about z (more towards the top)."""
    from blender_nerf_deform.engine.bend.cage_bend import CageBend
    from blender_nerf_deform.engine.geometry.cage import box_cage

    rest, tets = box_cage((3, 3, 3), lo=(-1.0,) * 3, hi=(1.0,) * 3)
    a = 0.5 * np.clip(rest[:, 2], 0, None)
    deformed = np.stack(
        [np.cos(a) * rest[:, 0] - np.sin(a) * rest[:, 1], np.sin(a) * rest[:, 0] + np.cos(a) * rest[:, 1], rest[:, 2]],
        axis=1,
    )
    bend = CageBend(model, rest, tets).set_deformed(deformed)
    return {"sample_transform": bend.sample_transform, "occupancy": bend.occupancy}


@pytest.mark.parametrize("bent", [False, True])
def test_a_frame_with_the_kernels_agrees_with_the_cpu_kernels(bent):
    model = ball_model(3, radius=0.9, table_noise=0.3, feature_noise=0.5)
    model.config.steps_per_diagonal = 64  # (the interpreter's time goes with the lattice steps per round)
    camera = Camera.from_fov(look_at((0.4, -2.4, 0.8)), 12, 9, 0.75, name="cam")
    kwargs = _twist(model) if bent else {}
    with LaunchCounter() as counter:
        device = render_image(model, camera, **kwargs)
    for kernel in ("hash_forward", "march", "march_setup", "sh_encode", "composite"):
        assert counter.by_op["kernel:" + kernel] >= 1, kernel
    # The frame is one chunk: a read back per round (one march each), one for its counts, one copy of its pixels
    # (a bent frame's sample transform, the cage's point location, still waits for the device besides).
    assert counter.by_op["kernel:march"] >= 2
    assert counter.syncs_by_op["read_back"] == counter.by_op["kernel:march"] + 1
    assert counter.syncs_by_op["to_host"] == 1
    assert bent or counter.syncs == counter.by_op["kernel:march"] + 2
    with backend.forced("auto"):
        kernels = render_image(model, camera, **(_twist(model) if bent else {}))
    mse = float(np.mean((device["rgba"].astype(np.float64) - kernels["rgba"]) ** 2))
    assert kernels["rgba"][..., 3].max() > 0.5 and kernels["rgba"][..., 3].min() < 0.01
    assert mse == 0 or -10 * np.log10(mse) >= 60
    assert device["density_samples_per_ray"] == kernels["density_samples_per_ray"]
    assert device["color_samples_per_ray"] == kernels["color_samples_per_ray"]


def _march_both(model, o, d, k, box_steps):
    """One round of the device march by the Triton kernel and by the torch formulation, from the same start."""
    from blender_nerf_deform.engine.nerf import march_kernels, renderer

    grids = renderer._grids(model, model.occupancy, model.config.render_step, background=True)
    results = []
    for triton_on in (True, False):
        torch.manual_seed(5)  # the same random offsets u for both
        state = renderer.march_setup(o, d, model.occupancy, grids, 0.0, True)
        alive = torch.arange(o.shape[0])
        active = torch.arange(o.shape[0]) % 5 != 0  # some rays sit the round out
        with backend.triton_enabled(triton_on), LaunchCounter() as counter:
            ts, dts, counts = march_kernels.march_round_device(o, d, alive, active, state, k, grids, box_steps)
        results.append((ts, dts, counts, state, counter))
    return results


@pytest.mark.parametrize("unbounded", [False, True])
def test_the_march_kernel_places_the_torch_formulations_samples(unbounded):
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
    from blender_nerf_deform.engine.nerf.renderer import box_steps

    torch.manual_seed(2)
    if unbounded:
        model = NerfModel(
            NerfConfig(
                contraction="linf", log2_table_size=10, finest_resolution=32, occ_resolution=16, steps_per_diagonal=64
            )
        )
        with torch.no_grad():
            model.encoding.table.uniform_(-1, 1)
        model.occupancy.update(model.density, model.config.render_step, 0.0)
        model.background.update(model.density, model.config.render_step, 0.0)
        o = torch.tensor([[0.0, -2.5, 0.3]]).repeat(40, 1)
    else:
        model = ball_model(4, radius=0.7, table_noise=0.3)
        model.config.steps_per_diagonal = 96
        o = torch.tensor([[0.3, -2.2, 0.5]]).repeat(40, 1)
    model.eval()
    d = torch.nn.functional.normalize(torch.randn(40, 3) * 0.3 + (-o / o.norm(dim=1, keepdim=True)), dim=1)
    steps = box_steps(model.occupancy, model.config.render_step)
    for k in (3, 64):  # rays that fill up, and rays that end within the round
        (ts, dts, counts, state, counter), (ts0, dts0, counts0, state0, _) = _march_both(model, o, d, k, steps)
        assert counter.by_op["kernel:march"] == 1 and counter.launches <= 4 and counter.syncs == 0
        assert counts.sum() > 0 and torch.equal(counts, counts0)
        assert (counts[torch.arange(40) % 5 == 0] == 0).all()
        assert torch.equal(ts, ts0) and torch.equal(dts, dts0)
        assert torch.equal(state.phase, state0.phase) and torch.equal(state.j, state0.j)
        assert torch.equal(state.t, state0.t)
        if k == 3:
            assert (counts == 3).any() and (state.phase < 3).any()  # rays left to march on
        if unbounded:
            far = (o[:, None, :] + d[:, None, :] * ts[..., None]).abs().amax(-1) > 2.0
            assert (far & (torch.arange(k) < counts[:, None])).any()  # samples in the background


def test_the_spherical_harmonics_kernel_gives_the_torch_values():
    from blender_nerf_deform.engine.nerf.encoding import sh_encode

    d = torch.nn.functional.normalize(torch.randn(300, 3), dim=1)
    for degree in (1, 2, 3, 4):
        with LaunchCounter() as counter:
            out = sh_encode(d, degree)
        assert counter.by_op["kernel:sh_encode"] == 1 and counter.launches <= 2
        with backend.triton_enabled(False):
            reference = sh_encode(d, degree)
        torch.testing.assert_close(out, reference, atol=0, rtol=0)
    assert sh_encode(d.requires_grad_(), 4).requires_grad  # a gradient in the directions: the torch formulation


@pytest.mark.parametrize("unbounded", [False, True])
def test_the_march_setup_kernel_gives_the_torch_state(unbounded):
    from blender_nerf_deform.engine.nerf import renderer
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel

    torch.manual_seed(6)
    model = NerfModel(
        NerfConfig(
            contraction="linf" if unbounded else "none",
            log2_table_size=10,
            finest_resolution=32,
            occ_resolution=16,
            steps_per_diagonal=64,
        )
    )
    with torch.no_grad():
        model.occupancy.mask[:] = torch.rand(model.occupancy.mask.shape) < 0.02  # a few cells, off centre
    model.occupancy.mask[0] = True
    model.occupancy._bounds = None
    o = torch.randn(64, 3) * 2.0
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=1)
    d[0] = torch.tensor([0.0, 0.0, 1.0])  # axis-parallel: zero components
    o[1] = torch.tensor([float("nan"), 0.0, 0.0])
    grids = renderer._grids(model, model.occupancy, model.config.render_step, background=True)
    assert grids.has_bg == unbounded
    states = []
    for triton_on in (True, False):
        torch.manual_seed(7)
        with backend.triton_enabled(triton_on), LaunchCounter() as counter:
            states.append(renderer.march_setup(o, d, model.occupancy, grids, 0.05, True))
        if triton_on:
            assert counter.by_op["kernel:march_setup"] == 1 and counter.syncs == 0
    for name in ("phase", "j", "j_end", "t", "t_in", "t_out", "t_far", "u"):
        torch.testing.assert_close(
            getattr(states[0], name), getattr(states[1], name), atol=0, rtol=0, equal_nan=True, msg=name
        )
    assert (states[0].phase < 3).sum() > 5 and (states[0].phase == 3).any()


def test_the_training_composite_kernels_give_the_torch_values_and_gradients():
    from blender_nerf_deform.engine.nerf import renderer
    from blender_nerf_deform.engine.nerf.composite_triton import CompositeTrain

    torch.manual_seed(8)
    counts = torch.tensor([3, 0, 5, 1, 7, 2])
    n, total = counts.shape[0], int(counts.sum())
    size = total - 2  # the last ray's last samples cut, as a full training step cuts them
    alive = torch.arange(n)
    first = torch.cumsum(counts, 0) - counts
    row = torch.repeat_interleave(torch.arange(n), counts)[:size]
    sigma = (torch.rand(size) * 4).requires_grad_()
    rgb = torch.rand(size, 3).requires_grad_()
    dt, t = torch.rand(size) * 0.5, torch.rand(size).cumsum(0)
    g_color, g_alpha, g_depth, g_w = torch.randn(n, 3), torch.randn(n), torch.randn(n), torch.randn(size)

    def loss(color, alpha, depth, w):
        return (color * g_color).sum() + (alpha * g_alpha).sum() + (depth * g_depth).sum() + (w * g_w).sum()

    with LaunchCounter() as counter:
        out = CompositeTrain.apply(sigma, rgb, dt, t, first, counts, alive, n)
        loss(*out).backward()
    assert counter.by_op["kernel:composite_train"] == 1 and counter.by_op["kernel:composite_train_backward"] == 1
    assert counter.syncs == 0
    grads = sigma.grad.clone(), rgb.grad.clone()
    sigma.grad = rgb.grad = None
    tau = sigma * dt
    w = renderer._segment_exclusive(tau, row, first) * (1.0 - torch.exp(-tau))
    reference = (
        renderer._segment_sum(w[:, None] * rgb, row, n),
        renderer._segment_sum(w, row, n),
        renderer._segment_sum(w * t, row, n),
        w,
    )
    loss(*reference).backward()
    for got, want in zip(out, reference):
        torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(grads[0], sigma.grad, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(grads[1], rgb.grad, atol=1e-6, rtol=1e-5)
    assert grads[0].abs().sum() > 0 and grads[1].abs().sum() > 0


def test_a_training_step_with_the_kernels_waits_once_and_updates_like_the_torch_formulation(tmp_path):
    from fixtures.sphere_data import write_sphere_dataset

    from blender_nerf_deform.engine.nerf.dataset import load_dataset
    from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
    from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions

    data = load_dataset(write_sphere_dataset(tmp_path / "train", n_views=3, size=8, seed=0))
    tiny = {"log2_table_size": 10, "finest_resolution": 32, "occ_resolution": 16, "steps_per_diagonal": 48}
    results = []
    for triton_on in (True, False):
        torch.manual_seed(0)
        model = NerfModel(NerfConfig(aabb=data.aabb.reshape(-1).tolist(), **tiny))
        trainer = Trainer(model, data, TrainOptions(steps=10, target_samples=1 << 9, distortion_weight=0.01))
        with backend.triton_enabled(triton_on):
            for _ in range(2):
                with LaunchCounter() as counter:
                    info = trainer.step()
                assert counter.syncs == 1, counter.summary()
        kernels = {op for op in counter.by_op if op.startswith("kernel:")}
        assert kernels == (
            {
                "kernel:hash_forward",
                "kernel:hash_backward",
                "kernel:march",
                "kernel:march_setup",
                "kernel:sh_encode",
                "kernel:composite_train",
                "kernel:composite_train_backward",
            }
            if triton_on
            else set()
        )
        results.append((info, [p.detach().clone() for p in model.parameters()], counter.launches))
    (info, params, launches), (info0, params0, launches0) = results
    assert info["samples_per_ray"] == info0["samples_per_ray"] and info["loss"] == pytest.approx(
        info0["loss"], rel=1e-4
    )
    for p, p0 in zip(params, params0):
        torch.testing.assert_close(p, p0, atol=2e-4, rtol=1e-3)
    assert launches0 - launches > 200  # what the kernels replace
