"""The launch and sync counter (engine/launch_count.py): what it calls a launch and a sync, on known ops."""

import torch

from blender_nerf_deform.engine.launch_count import LaunchCounter, kernel_launch, read_back


def test_views_and_allocations_launch_nothing_and_arithmetic_launches_once_per_op():
    x = torch.randn(6, 4)
    with LaunchCounter() as c:
        x.view(24), x[:, 1], x.t(), x.reshape(4, 6), torch.empty(3)
    assert c.launches == 0 and c.syncs == 0
    with LaunchCounter() as c:
        (x * 2 + 1).relu()
    assert c.launches == 3 and c.syncs == 0
    assert dict(c.by_op) == {"mul": 1, "add": 1, "relu": 1}


def test_scalar_reads_data_dependent_shapes_and_boolean_indexing_are_syncs():
    x = torch.randn(50)
    mask = x > 0
    counts = torch.tensor([1, 2, 3])
    with LaunchCounter() as c:
        float(x.sum())
    assert c.syncs == 1  # the read; the sum is a launch, not a sync
    for op in (
        lambda: torch.nonzero(mask),
        lambda: x[mask],
        lambda: torch.bincount(counts),
        lambda: torch.unique(counts),
        lambda: torch.repeat_interleave(counts),
        lambda: bool(mask.any()),
        lambda: x.masked_select(mask),
    ):
        with LaunchCounter() as c:
            op()
        assert c.syncs >= 1, op
    with LaunchCounter() as c:  # the host's reads through read_back: one sync for all of them
        values = read_back(x.sum(), mask.sum(), counts.max())
    assert c.syncs == 1 and values[1] == int(mask.sum()) and values[2] == 3
    with LaunchCounter() as c:  # the same work with static sizes: no sync
        torch.repeat_interleave(counts, output_size=6)
        torch.where(mask, x, torch.zeros_like(x))
        x.index_select(0, counts)
        torch.cumsum(mask.long(), 0)
    assert c.syncs == 0 and c.launches >= 4


def test_the_backward_pass_is_counted():
    w = torch.randn(4, 3, requires_grad=True)
    x = torch.randn(8, 4)
    with LaunchCounter() as forward_only:
        (x @ w).relu().sum()
    with LaunchCounter() as both:
        (x @ w).relu().sum().backward()
    assert both.launches >= forward_only.launches + 3  # the relu's, the mm's and the sum's backward


def test_a_hand_written_kernel_counts_once_and_hides_its_inner_ops():
    x = torch.randn(10)
    with LaunchCounter() as c:
        with kernel_launch("copy"):
            y = x.clone() * 2 + 1
            float(y[0])
        x + 1
    assert c.launches == 2 and c.syncs == 0
    assert c.by_op["kernel:copy"] == 1
