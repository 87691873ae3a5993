"""Density only where enough photos pay for it: free space that too few photos see through is ruled out (the
floater in front of a camera), what many see and what none sees (an object's inside) stays, and what training
ruled out holds no density for extraction either, also after a checkpoint round trip."""

import math

import numpy as np
import torch
from fixtures.sphere_data import RADIUS, sphere_cameras, write_sphere_dataset

from blender_nerf_deform.engine.nerf.camera import Camera
from blender_nerf_deform.engine.nerf.checkpoint import load_nerf, save_nerf
from blender_nerf_deform.engine.nerf.dataset import load_dataset
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
from blender_nerf_deform.engine.nerf.occupancy import OccupancyGrid
from blender_nerf_deform.engine.nerf.trainer import Trainer, TrainOptions, config_for
from blender_nerf_deform.engine.nerf.visibility import paid_for, photos_seeing_through

SIZE, ANGLE = 48, 0.47  # a narrow lens, as gold_cape's: few photos see the space beside one camera


def _sphere_depth(camera: Camera) -> torch.Tensor:
    """Exact distance to the sphere of radius RADIUS at the origin along each pixel's ray (inf where it misses)."""
    j, i = np.meshgrid(np.arange(camera.height) + 0.5, np.arange(camera.width) + 0.5, indexing="ij")
    d = (
        np.stack([(i - camera.cx) / camera.fx, -(j - camera.cy) / camera.fy, -np.ones_like(i)], -1)
        @ camera.c2w[:3, :3].T
    )
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = camera.c2w[:3, 3]
    b = d @ o
    disc = b * b - (o @ o - RADIUS**2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    return torch.from_numpy(t.astype(np.float32))


def test_free_space_too_few_photos_see_through_is_ruled_out():
    f = 0.5 * SIZE / math.tan(0.5 * ANGLE)
    cameras = [Camera(c2w, f, f, SIZE / 2, SIZE / 2, SIZE, SIZE) for c2w in sphere_cameras(24)]
    grid = OccupancyGrid(torch.tensor([[-3.2] * 3, [3.2] * 3]), 32)
    counts = photos_seeing_through(grid, cameras, _sphere_depth, downscale=2)
    centres = grid.cell_centers(torch.arange(32**3), jitter=False)

    def count_at(p):
        return int(counts[(centres - torch.tensor(p, dtype=torch.float32)).norm(dim=-1).argmin()])

    eye = cameras[0].c2w[:3, 3]
    axis = -eye / np.linalg.norm(eye)
    in_front = eye + 0.4 * axis  # the free space right in front of one camera: hidden behind the sphere from afar
    surface = axis * -RADIUS  # the sphere's side facing that camera: many photos see it
    assert 1 <= count_at(in_front) <= 3, count_at(in_front)
    assert count_at(surface) >= 6, count_at(surface)
    assert count_at((0.0, 0.0, 0.0)) == 0  # inside: no photo sees through it
    kept = paid_for(counts, 4)
    index = lambda p: int((centres - torch.tensor(p, dtype=torch.float32)).norm(dim=-1).argmin())  # noqa: E731
    assert not kept[index(in_front)] and kept[index(surface)] and kept[index((0.0, 0.0, 0.0))]


def test_training_judges_free_space_by_the_photos_and_keeps_the_object(tmp_path):
    """A short run with the judgement on: the inner grid gets its restriction, the sphere stays occupied."""
    ds = load_dataset(write_sphere_dataset(tmp_path / "s", n_views=16, size=24))
    ds.images[..., :3] = ds.images[..., :3] * ds.images[..., 3:] + 0.3 * (1 - ds.images[..., 3:])  # opaque photos
    ds.images[..., 3] = 1.0
    ds.has_alpha = False
    cfg = config_for(ds)
    cfg.log2_table_size, cfg.finest_resolution, cfg.occ_resolution = 14, 128, 32
    torch.manual_seed(0)
    model = NerfModel(cfg)
    trainer = Trainer(model, ds, TrainOptions(steps=80, min_views=3))
    trainer.train(progress=False)
    grid = model.occupancy
    assert not trainer.visibility_marks and grid.allowed is not None and not grid.allowed.all()
    surface = grid.cell_index(torch.tensor([[RADIUS - 0.05, 0.0, 0.0], [0.0, 0.0, RADIUS - 0.05]]))[0]
    assert grid.allowed[surface].all()


def test_ruled_out_space_holds_no_density_and_survives_a_checkpoint(tmp_path):
    torch.manual_seed(0)
    model = NerfModel(NerfConfig(log2_table_size=12, finest_resolution=64, occ_resolution=8))
    with torch.no_grad():
        model.density_net[-1].weight[0].fill_(0.0)  # trunc_exp(-1) everywhere: a small positive density
    allowed = torch.ones(8**3, dtype=torch.bool)
    allowed[:256] = False  # the lower half along z
    model.occupancy.restrict(allowed)
    low, high = torch.tensor([[0.1, 0.2, -1.0]]), torch.tensor([[0.1, 0.2, 1.0]])
    with torch.no_grad():
        assert float(model.density(low)) == 0.0 and float(model.density(high)) > 0.0
    model.occupancy.restrict(torch.ones_like(allowed))  # restrictions add up: the lower half stays out
    assert torch.equal(model.occupancy.allowed, allowed)
    model.occupancy.update(lambda p: torch.full((p.shape[0],), 100.0), 0.1)  # dense everywhere: still not occupied
    assert not model.occupancy.mask[:256].any() and model.occupancy.mask[256:].all()
    save_nerf(model, tmp_path / "n.ckpt")
    loaded = load_nerf(tmp_path / "n.ckpt", device="cpu")
    assert torch.equal(loaded.occupancy.allowed, allowed)
    with torch.no_grad():
        assert float(loaded.density(low)) == 0.0 and float(loaded.density(high)) > 0.0
        assert float(loaded.density(torch.tensor([[0.1, 0.2, -3.0]]))) == 0.0  # outside the box, as before
