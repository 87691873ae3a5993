"""Density only where enough photos pay for it: a cell that many samples of one photo looked through is never
occupied again (the floater in front of a camera), a cell many photos see stays, and what training ruled out
holds no density for extraction either, also after a checkpoint round trip."""

import torch

from blender_nerf_deform.engine.nerf.checkpoint import load_nerf, save_nerf
from blender_nerf_deform.engine.nerf.model import NerfConfig, NerfModel
from blender_nerf_deform.engine.nerf.occupancy import OccupancyGrid
from blender_nerf_deform.engine.nerf.visibility import MIN_SAMPLES, ViewCounts, exclusive_weight, record_seen


def _centre(grid: OccupancyGrid, cell: int) -> torch.Tensor:
    return grid.cell_centers(torch.tensor([cell]), jitter=False)[0]


def test_cells_looked_through_by_too_few_photos_are_ruled_out():
    grid = OccupancyGrid(torch.tensor([[-1.0] * 3, [1.0] * 3]), 8)
    counts = ViewCounts(grid)
    lone, shared, rare = 10, 200, 300
    n = MIN_SAMPLES + 8
    counts.record(_centre(grid, lone).expand(n, 3), torch.full((n,), 3))  # one photo's many rays
    counts.record(_centre(grid, shared).expand(n, 3), torch.arange(n) % 10)  # ten photos
    counts.record(_centre(grid, rare).expand(5, 3), torch.full((5,), 1))  # too few samples to judge
    counts.record(_centre(grid, 400).expand(2, 3), torch.tensor([6, 70]))  # photos 64 apart share a bit
    views = counts.views()
    assert views[lone] == 1 and views[shared] == 10 and views[rare] == 1 and views[400] == 1
    assert int(counts.samples[lone]) == n and int(counts.samples.sum()) == 2 * n + 5 + 2
    paid = counts.paid_for(2)
    assert not paid[lone] and paid[shared] and paid[rare] and paid[0]  # a cell no sample reached stays as it is
    grid.restrict(paid)
    assert not grid.mask[lone] and grid.mask[shared] and int((~grid.mask).sum()) == 1
    grid.restrict(torch.ones_like(paid))  # restrictions add up: the ruled-out cell stays out
    assert not grid.mask[lone] and not grid.permitted(_centre(grid, lone)[None])[0]
    grid.update(lambda p: torch.full((p.shape[0],), 100.0), 0.1)  # dense everywhere: still not occupied
    assert not grid.mask[lone] and bool(grid.mask[shared])


def test_only_samples_the_photo_still_sees_through_are_counted():
    w = torch.tensor([0.1, 0.3, 0.4, 0.2, 0.6, 0.3])
    ray = torch.tensor([0, 0, 0, 0, 1, 1])
    torch.testing.assert_close(exclusive_weight(w, ray), torch.tensor([0.0, 0.1, 0.4, 0.8, 0.0, 0.6]))
    grid = OccupancyGrid(torch.tensor([[-1.0] * 3, [1.0] * 3]), 4)
    counts = ViewCounts(grid)
    origins, dirs = torch.tensor([[-0.99, 0.1, 0.1], [0.1, -0.99, 0.1]]), torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    t = torch.tensor([0.2, 0.7, 1.2, 1.7, 0.2, 1.2])
    record_seen([counts], (ray, t, torch.full_like(t, 0.5), w), origins, dirs, torch.tensor([4, 9]))
    # Ray 0 (photo 4) sees through its first three samples (weight before them < 1/2), ray 1 (photo 9) its first.
    assert int(counts.samples.sum()) == 4
    assert int(counts.views().max()) == 1 and int((counts.views() > 0).sum()) == 4


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
    save_nerf(model, tmp_path / "n.ckpt")
    loaded = load_nerf(tmp_path / "n.ckpt", device="cpu")
    assert torch.equal(loaded.occupancy.allowed, allowed)
    with torch.no_grad():
        assert float(loaded.density(low)) == 0.0 and float(loaded.density(high)) > 0.0
        assert float(loaded.density(torch.tensor([[0.1, 0.2, -3.0]]))) == 0.0  # outside the box, as before
