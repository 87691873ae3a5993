"""Count what a piece of torch code would cost on a GPU, on any device: kernel launches and host-device syncs.

On CUDA the cost of the engine's small kernels is launching them and every point where the host waits
for the device (a scalar read, an output whose size depends on the data), before it is arithmetic. Both
can be counted on the CPU by running the CUDA code path there (`backend.forced("torch")`) inside a
`LaunchCounter`, a `TorchDispatchMode` that sees every aten op, the backward's included:

- a *launch* is every op that runs a kernel: views, aliases and uninitialised allocations are not;
- a *sync* is an op whose result the host must wait for on CUDA: scalar reads (`.item()`, `float()`,
  `bool()`, `int()`, `.tolist()`), and ops whose output size depends on the data (`nonzero`, boolean
  indexing, `masked_select`, `unique`, `bincount`, `repeat_interleave` without `output_size`);
- a read of device values by the host goes through `read_back(*values)`: one copy, one sync (on the CPU
  `.tolist()` and `.cpu()` dispatch nothing, so the counter could not see them otherwise);
- a hand-written kernel (a Triton kernel, which the dispatcher does not see as one op) says so with
  `kernel_launch(name)`: it counts as one launch, and the torch ops it runs inside (the Triton
  interpreter's copies on the CPU) are not counted.

    with LaunchCounter() as counter:
        trainer.step()
    counter.launches, counter.syncs, counter.by_op
"""

from __future__ import annotations

import collections
import contextlib

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten

# Ops that allocate without writing or only read metadata: no kernel runs.
_NO_KERNEL = {
    "empty",
    "empty_like",
    "empty_strided",
    "new_empty",
    "new_empty_strided",
    "detach",
    "alias",
    "lift_fresh",
    "sym_size",
    "sym_stride",
    "sym_numel",
    "sym_storage_offset",
    "is_same_size",
    "_reshape_alias",
    "set_",
    "resize_",
    "_unsafe_view",
    "view",
    "_to_copy_noop",
}
# Ops that make the host wait for the device on CUDA, whatever their arguments.
_ALWAYS_SYNC = {
    "_local_scalar_dense",
    "nonzero",
    "masked_select",
    "_unique",
    "_unique2",
    "unique_dim",
    "unique_consecutive",
    "bincount",
    "masked_scatter",
    "masked_scatter_",
    "equal",
    "is_nonzero",
    "argwhere",
    "nonzero_numpy",
}


def _is_bool_index(indices) -> bool:
    return any(isinstance(i, torch.Tensor) and i.dtype in (torch.bool, torch.uint8) for i in indices or ())


def is_sync(func, args, kwargs) -> bool:
    """Whether the aten op `func` called with these arguments waits for the device on CUDA."""
    name = func.overloadpacket.__name__
    if name in _ALWAYS_SYNC:
        return True
    if name == "repeat_interleave":  # repeats given as a tensor: the output's size is their sum
        return func is not aten.repeat_interleave.self_int and kwargs.get("output_size") is None
    if name in ("index", "_index_put_impl_", "index_put", "index_put_", "_unsafe_index", "_unsafe_index_put"):
        return _is_bool_index(args[1] if len(args) > 1 else kwargs.get("indices"))
    return False


def launches_kernel(func) -> bool:
    """Whether the aten op `func` runs a kernel (views, aliases and bare allocations do not)."""
    if func.is_view:
        return False
    return func.overloadpacket.__name__ not in _NO_KERNEL


_active: list[LaunchCounter] = []


class LaunchCounter(TorchDispatchMode):
    """Counts launches and syncs of the ops run inside it (see the module docstring)."""

    def __init__(self):
        super().__init__()
        self.launches = 0
        self.syncs = 0
        self.by_op: collections.Counter = collections.Counter()  # launches per op name (kernels as "kernel:NAME")
        self.syncs_by_op: collections.Counter = collections.Counter()
        self._inside_kernel = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if not self._inside_kernel:
            name = func.overloadpacket.__name__
            if is_sync(func, args, kwargs):
                self.syncs += 1
                self.syncs_by_op[name] += 1
            if launches_kernel(func):
                self.launches += 1
                self.by_op[name] += 1
        return func(*args, **kwargs)

    def __enter__(self):
        _active.append(self)
        return super().__enter__()

    def __exit__(self, *exc):
        _active.remove(self)
        return super().__exit__(*exc)

    def reset(self) -> None:
        self.launches = self.syncs = 0
        self.by_op.clear()
        self.syncs_by_op.clear()

    def summary(self, top: int = 12) -> dict:
        return {
            "launches": self.launches,
            "syncs": self.syncs,
            "top_launches": dict(self.by_op.most_common(top)),
            "syncs_by_op": dict(self.syncs_by_op),
        }


@contextlib.contextmanager
def kernel_launch(name: str):
    """Mark one hand-written kernel launch: it counts once in every active counter, its inner ops not at all."""
    for counter in _active:
        counter.launches += 1
        counter.by_op["kernel:" + name] += 1
        counter._inside_kernel += 1
    try:
        yield
    finally:
        for counter in _active:
            counter._inside_kernel -= 1


def read_back(*values) -> list[float]:
    """The host's read of several device scalars in one copy (on CUDA, one sync): their values as floats
    (exact for integers below 2^53)."""
    for counter in _active:
        counter.syncs += 1
        counter.syncs_by_op["read_back"] += 1
    packed = torch.stack([torch.as_tensor(v).detach().reshape(()).to(torch.float64) for v in values])
    return packed.tolist()


def to_host(tensor: torch.Tensor) -> torch.Tensor:
    """A copy of a device tensor in host memory (on CUDA, one sync; counted as one here on any device)."""
    for counter in _active:
        counter.syncs += 1
        counter.syncs_by_op["to_host"] += 1
    return tensor.detach().cpu()
