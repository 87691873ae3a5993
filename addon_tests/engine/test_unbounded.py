"""Unbounded scenes: the contraction, the background grid, marching in rounds, and training on a room."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from fixtures.room_data import write_room_dataset
from fixtures.sphere_data import look_at

from blender_nerf_deform.engine import backend
from blender_nerf_deform.engine.nerf import renderer
from blender_nerf_deform.engine.nerf.contraction import FAR_RADIUS, contract, uncontract
from blender_nerf_deform.engine.nerf.dataset import load_dataset
from blender_nerf_deform.engine.nerf.evaluate import evaluate
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
from blender_nerf_deform.engine.nerf.occupancy import ContractedGrid
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions, config_for

SMALL = dict(
    n_levels=4,
    n_features=2,
    log2_table_size=12,
    base_resolution=8,
    finest_resolution=64,
    density_hidden=16,
    geo_feat_dim=7,
    color_hidden=16,
    occ_resolution=32,
)


def test_contraction_is_continuous_at_the_inner_box_and_maps_infinity_inside_the_grid():
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=torch.float64), dim=1)
    on_box = dirs / dirs.abs().amax(dim=1, keepdim=True)  # |u|_inf = 1 exactly
    for eps in (1e-3, 1e-6):
        inside, outside = contract(on_box * (1 - eps)), contract(on_box * (1 + eps))
        assert (inside - outside).norm(dim=1).max() < 4 * eps
    assert torch.equal(contract(on_box * 0.7), on_box * 0.7)  # the inner box is untouched
    far = contract(on_box * 1e30)
    assert far.abs().amax(dim=1).max() <= 2.0 and far.abs().amax(dim=1).min() > 2.0 - 1e-6
    # Monotone along rays from the centre, and undone by uncontract.
    radii = torch.tensor([1.5, 3.0, 10.0, 100.0], dtype=torch.float64)
    c = torch.stack([contract(on_box * r).abs().amax(dim=1) for r in radii])
    assert (c[1:] > c[:-1]).all()
    u = on_box[:, None, :] * radii[None, :, None]
    assert torch.allclose(uncontract(contract(u.reshape(-1, 3))), u.reshape(-1, 3), rtol=1e-9)
    # The model's normalised coordinates stay in [0, 1] for any finite point.
    m = NerfModel(NerfConfig(contraction="linf", aabb=[-1, -2, -1, 3, 2, 1], **SMALL))
    x = m.normalize(torch.cat([torch.randn(1000, 3) * 1e6, torch.tensor([[1e38, -1e38, 0.0]])]))
    assert ((x >= 0) & (x <= 1)).all()


def test_background_grid_round_trips_cells_and_never_holds_the_inner_box():
    grid = ContractedGrid(torch.tensor([[-1.5, -1.0, -2.0], [1.5, 2.0, 2.0]]), 32)
    idx = torch.arange(32**3)
    centres = grid.cell_centers(idx, jitter=False)
    back, inside = grid.cell_index(centres)
    shell = grid._shell
    assert inside[shell].all() and torch.equal(back[shell], idx[shell])
    # The shell is exactly the cells whose centre lies outside the inner box: all but the middle 16^3.
    outside = ~((centres >= grid.inner[0]) & (centres <= grid.inner[1])).all(dim=-1)
    assert torch.equal(shell, outside) and int(shell.sum()) == 32**3 - 16**3
    grid.update(lambda p: torch.full((p.shape[0],), 100.0), 0.01)  # dense everywhere
    assert grid.mask.sum() == shell.sum() and not grid.occupied(torch.zeros(1, 3)).any()
    assert grid.occupied(torch.tensor([[0.0, 0.5, 30.0]])).all()


def _unbounded_model(seed=0):
    torch.manual_seed(seed)
    m = NerfModel(NerfConfig(contraction="linf", **SMALL))
    with torch.no_grad():
        m.encoding.table.uniform_(-1, 1)
    m.occupancy.update(m.density, m.config.render_step, 0.0)
    m.background.update(m.density, m.config.render_step, 0.0)
    return m.eval()


def test_marching_reaches_the_background_and_the_torch_path_finds_the_same_samples(monkeypatch):
    m = _unbounded_model()
    o = torch.tensor([[0.0, -2.5, 0.3]]).repeat(64, 1)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    results = {}
    for path in ("auto", "torch") if backend.HAVE_NUMBA else ("torch",):
        monkeypatch.setattr(backend, "_path", path)
        results[path] = renderer.march(o, d, m.occupancy, m.config.render_step, model=m)
    rays, t = results["torch"]
    p = o[rays] + d[rays] * t[:, None]
    r = (p.abs() / 1.5).amax(dim=1)
    assert (r > 20).any() and (r < 1).any()  # samples far out and in the inner box
    assert r.max() <= FAR_RADIUS * 1.01
    assert (torch.diff(t)[torch.diff(rays) == 0] > 0).all()  # sorted along each ray
    if "auto" in results:
        assert torch.equal(results["auto"][0], rays) and torch.allclose(results["auto"][1], t, rtol=1e-6)


def test_rounds_with_early_termination_give_the_full_composite():
    """Marching in rounds and retiring rays whose transmittance is spent changes the image by less than
    what the retired rays could still add."""
    m = _unbounded_model()
    cam_o = torch.tensor([[0.3, -2.6, 0.4]]).repeat(300, 1)
    d = torch.nn.functional.normalize(
        torch.randn(300, 3, generator=torch.Generator().manual_seed(2)) * 0.4 + torch.tensor([0.0, 1.0, 0.0]), dim=1
    )
    with torch.no_grad():
        fast = renderer.render_rays(m, cam_o, d, background=(0.0, 0.0, 0.0), near=0.0)
        rays, t = renderer.march(cam_o, d, m.occupancy, m.config.render_step, model=m)
        # Reference: every sample, its own step length, composited in order.
        grids = renderer._grids(m, m.occupancy, m.config.render_step, True)
        state = renderer.march_setup(cam_o, d, m.occupancy, grids)
        alive = torch.arange(300)
        parts = []
        while alive.numel():
            parts.append(renderer._round_samples(cam_o, d, alive, state, 1 << 14, grids))
            alive = alive[state.phase[alive] < 3]
        ray_idx, ts, dts = (torch.cat(x) for x in zip(*parts))
        order = torch.sort(ray_idx, stable=True).indices
        ray_idx, ts, dts = ray_idx[order], ts[order], dts[order]
        assert torch.equal(ray_idx, rays) and torch.equal(ts, t)
        sigma, rgb = m.query(cam_o[ray_idx] + d[ray_idx] * ts[:, None], d[ray_idx])
        tau = (sigma * dts).double()
        trans = renderer._exclusive_transmittance(tau, ray_idx, 300)
        w = (trans * (1 - torch.exp(-tau))).float()
        colour = torch.zeros(300, 3).index_add_(0, ray_idx, w[:, None] * rgb)
    assert fast["alpha"].min() > 0.5  # the random field fills the room: every ray ends somewhere
    assert fast["n_density_samples"] < 0.8 * len(ray_idx)  # termination skipped samples
    assert torch.allclose(fast["color"], colour, atol=2e-3)


@pytest.mark.slow
def test_an_unbounded_nerf_learns_a_room_that_a_bounded_one_cannot(tmp_path):
    train = load_dataset(write_room_dataset(tmp_path / "room", n_views=24, size=32))
    test = load_dataset(write_room_dataset(tmp_path / "room_test", n_views=4, size=32, seed=7))
    assert not train.has_alpha
    scores = {}
    for scene in ("bounded", "unbounded"):
        cfg = config_for(train, scene)
        assert (cfg.contraction == "linf") == (scene == "unbounded")
        for k, v in dict(log2_table_size=14, occ_resolution=64).items():
            setattr(cfg, k, v)
        torch.manual_seed(0)
        model = NerfModel(cfg)
        Trainer(model, train, TrainOptions(steps=400, target_samples=1 << 13, occ_warmup_steps=64)).train(
            progress=False
        )
        model.eval()
        if scene == "unbounded":
            # The unbounded threshold prunes the thin fog a room leaves in the grid (0.01: 52 % of the
            # inner cells kept, 150 samples per ray; 0.1: 22 %, 79), so rays march where surfaces are.
            assert model.occupancy.mask.float().mean() < 0.35
        scores[scene] = (
            float(np.mean(evaluate(model, train.subset(range(0, 24, 4))))),
            float(np.mean(evaluate(model, test))),
        )
    # The walls lie outside the bounded box: the bounded NeRF can only paint them on its faces, which
    # fits neither its own views nor new ones.
    (fit_b, new_b), (fit_u, new_u) = scores["bounded"], scores["unbounded"]
    assert fit_u > fit_b + 3.0 and new_u > new_b + 1.0, scores
    assert config_for(train, "auto").contraction == "linf"


def test_auto_scene_model_is_bounded_for_rgba_objects(tmp_path):
    from fixtures.sphere_data import write_sphere_dataset

    ds = load_dataset(write_sphere_dataset(tmp_path / "s", n_views=2, size=8))
    assert ds.has_alpha and config_for(ds, "auto").contraction == "none"


def test_a_camera_inside_an_unbounded_nerf_sees_everything_around_it():
    m = _unbounded_model()
    from blender_nerf_deform.engine.nerf.camera import Camera

    out = renderer.render_image(m, Camera.from_fov(look_at((0.0, -2.0, 0.0)), 8, 8, 1.2))
    assert out["rgba"][..., 3].min() > 0.5


def test_fused_compositing_kernels_match_their_torch_reference():
    """SH encoding, contraction and per-ray transmittance: the numba kernels rendering uses give the torch
    code's values (the torch code is what CUDA and training's gradients run)."""
    if not backend.HAVE_NUMBA:
        pytest.skip("numba is not installed: the torch path is the only one")
    from blender_nerf_deform.engine.nerf.encoding import sh_encode

    g = torch.Generator().manual_seed(3)
    d = torch.nn.functional.normalize(torch.randn(20000, 3, generator=g), dim=1)
    m = NerfModel(NerfConfig(contraction="linf", aabb=[-1, -2, -1, 2, 2, 3], **SMALL))
    p = torch.randn(20000, 3, generator=g) * 5
    tau = torch.rand(20000, generator=g) * 0.3
    rays = torch.sort(torch.randint(0, 900, (20000,), generator=g)).values
    fast = (sh_encode(d), m.normalize(p), renderer._exclusive_transmittance(tau, rays, 900))
    with backend.forced("torch"):
        slow = (sh_encode(d), m.normalize(p), renderer._exclusive_transmittance(tau, rays, 900))
    for a, b in zip(fast, slow):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-6)


def test_appearance_codes_learn_each_photo_s_exposure_and_frames_render_with_their_mean(tmp_path):
    """Photos of one room at two exposures: with per-image codes the NeRF fits both; its frames use the mean code,
    and the codes survive the checkpoint."""
    from PIL import Image

    from blender_nerf_deform.engine.nerf.checkpoint import load_nerf, save_nerf

    folder = write_room_dataset(tmp_path / "room", n_views=12, size=16)
    for k, path in enumerate(sorted((folder / "images").iterdir())):
        if k % 2:  # every other photo one stop darker
            img = np.asarray(Image.open(path), np.float32) * 0.5
            Image.fromarray(img.astype(np.uint8)).save(path)
    train = load_dataset(folder)
    cfg = config_for(train, "unbounded")
    for k, v in dict(SMALL, appearance_dim=4, appearance_count=len(train)).items():
        setattr(cfg, k, v)
    torch.manual_seed(0)
    model = NerfModel(cfg)
    Trainer(model, train, TrainOptions(steps=150, target_samples=1 << 12, occ_warmup_steps=32)).train(progress=False)
    codes = model.appearance.weight.detach()
    assert (codes[0::2].mean(0) - codes[1::2].mean(0)).norm() > 1e-3  # the two exposures got different codes
    save_nerf(model, tmp_path / "nerf.ckpt")
    again = load_nerf(tmp_path / "nerf.ckpt", device="cpu")
    assert torch.equal(again.appearance.weight, model.appearance.weight)
    from blender_nerf_deform.engine.nerf.renderer import render_image

    a = render_image(model.eval(), train.cameras[0])["rgb"]
    b = render_image(again, train.cameras[0])["rgb"]
    assert np.allclose(a, b, atol=1e-6)


def test_occupancy_updates_cost_an_unbounded_model_what_they_cost_a_bounded_one(tmp_path):
    """Two grids, each updated half as often: 16 steps per grid between updates unless asked otherwise."""
    train = load_dataset(write_room_dataset(tmp_path / "room", n_views=2, size=8))
    updated = []
    for scene, every, expected in (
        ("bounded", None, [0, 16, 32]),
        ("unbounded", None, [0, 32]),
        ("unbounded", 8, [0, 8, 16, 24, 32, 40]),
    ):
        cfg = config_for(train, scene)
        for k, v in SMALL.items():
            setattr(cfg, k, v)
        torch.manual_seed(0)
        trainer = Trainer(
            NerfModel(cfg),
            train,
            TrainOptions(steps=48, target_samples=1 << 8, occ_warmup_steps=0, occ_update_every=every),
        )
        steps = []

        def recorded(grid):  # the real update, and the step it ran at
            def update(*args, **kwargs):
                steps.append(trainer.step_count)  # noqa: B023 -- called only by trainer.train() in this iteration
                return type(grid).update(grid, *args, **kwargs)

            return update

        for grid in trainer.grids:
            grid.update = recorded(grid)
        trainer.train(progress=False)
        updated.append((scene, every, sorted(set(steps)), expected))
        assert len(steps) == len(trainer.grids) * len(expected)
    assert all(got == expected for *_, got, expected in updated), updated


def test_pose_refinement_s_gradient_turns_a_wrong_pose_back_and_resumes(tmp_path):
    """A room NeRF trained on true poses; one photo then given a pose 3 degrees off. The gradient of that
    photo's error in its pose correction (through the rays, the reused encoding's position gradient and
    the contraction) points back towards the true pose, and followed downhill it undoes at least a third
    of the error (the 500-step NeRF's error is lowest 0.7-1.6 degrees from the true pose: the trainer's
    threads make each run's NeRF a little different; a missing or reversed gradient leaves 3 or more);
    the corrections round-trip through the trainer state; before `pose_start` the poses stay as given."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from blender_nerf_deform.engine.errors import EngineError

    train = load_dataset(write_room_dataset(tmp_path / "room", n_views=24, size=64))
    cfg = config_for(train, "unbounded")
    for k, v in dict(log2_table_size=14, occ_resolution=64).items():
        setattr(cfg, k, v)
    torch.manual_seed(0)
    model = NerfModel(cfg)
    Trainer(model, train, TrainOptions(steps=500, target_samples=1 << 13, occ_warmup_steps=64)).train(progress=False)
    k, axis = 5, np.array([0.3, 1.0, -0.5]) / np.linalg.norm([0.3, 1.0, -0.5])
    wrong = Rotation.from_rotvec(np.deg2rad(3.0) * axis).as_matrix()
    c2w = np.array(train.cameras[k].c2w, dtype=np.float64)
    c2w[:3, :3] = wrong @ c2w[:3, :3]
    train.cameras[k] = dataclasses.replace(train.cameras[k], c2w=c2w)
    opts = TrainOptions(steps=10, refine_poses=True, pose_start=0.0, pixel_jitter=False, random_background=False)
    trainer = Trainer(model, train, opts)
    pixels = torch.arange(k * 64 * 64, (k + 1) * 64 * 64)
    o, d, target, _ = trainer.sample_rays(pixels.numel(), pixels)
    assert o.requires_grad and d.requires_grad
    out = renderer.render_rays(model, o, d, chunk=1 << 20)
    ((out["rgb"] - target[:, :3]) ** 2).mean().backward()
    g = trainer.pose_delta.grad
    assert torch.count_nonzero(g[:k]) == 0 and torch.count_nonzero(g[k + 1 :]) == 0  # only photo k's rays ran
    assert (-g[k, :3].double().numpy()) @ -axis > 0  # downhill is towards the true pose
    # Followed downhill (the field fixed, every pixel of the photo), the correction undoes most of the error.
    steps = torch.optim.Adam([trainer.pose_delta], lr=4e-3)
    for _ in range(40):
        steps.zero_grad()
        o, d, target, _ = trainer.sample_rays(pixels.numel(), pixels)
        ((renderer.render_rays(model, o, d, chunk=1 << 20)["rgb"] - target[:, :3]) ** 2).mean().backward()
        steps.step()
    rot, _ = trainer.pose_corrections()
    residual = np.rad2deg(Rotation.from_matrix(rot[k].detach().double().numpy() @ wrong).magnitude())
    assert residual < 2.0, residual
    # The corrections are part of the trainer state; a state for another number of photos is refused.
    with torch.no_grad():
        trainer.pose_delta.zero_()
        trainer.pose_delta[k, :3] = torch.from_numpy(-np.deg2rad(3.0) * axis).float()
    state = trainer.state_dict()
    again = Trainer(model, train, opts)
    again.load_state_dict(state)
    assert torch.equal(again.pose_delta, trainer.pose_delta)
    rot, _ = again.pose_corrections()
    assert np.allclose(rot[k].detach().double().numpy() @ wrong, np.eye(3), atol=1e-5)
    state["pose_delta"] = state["pose_delta"][:4]
    with pytest.raises(EngineError, match="pose corrections"):
        again.load_state_dict(state)
    # Before pose_start the rays are the photos' own and carry no gradient.
    late = Trainer(model, train, TrainOptions(steps=10, refine_poses=True, pose_start=0.5))
    o, d, _, _ = late.sample_rays(64)
    assert not o.requires_grad and not late.poses_move()
