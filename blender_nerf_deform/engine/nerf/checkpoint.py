"""NeRF checkpoints: one file, tensors and plain data only, loaded without executing code.

Format (a dict written by `torch.save`, read by `torch.load(weights_only=True)`):

    {"format": "blender_nerf_deform.nerf", "version": 1,
     "config": NerfConfig as a plain dict,
     "state": the model's state_dict (tensors),
     "occupancy": {"density": tensor, "mask": tensor[, "allowed": tensor: the cells training ruled in]},
     "background": {"density": tensor, "mask": tensor}   (unbounded NeRFs only: the contracted grid),
     "trainer": optional plain dict + tensors to resume training}

`save_nerf` writes to a temporary file in the same folder and renames it over the
target, so an interrupted run never leaves a broken checkpoint.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from ..errors import EngineError
from ..files import atomic_write
from .model import NerfConfig, NerfModel, resolve_device

FORMAT = "blender_nerf_deform.nerf"
VERSION = 1


def save_nerf(model: NerfModel, path, trainer_state: dict | None = None) -> None:
    """Write the model (config, weights, occupancy grid[, trainer state]) atomically to `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": model.config.to_dict(),
        "state": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "occupancy": {
            "density": model.occupancy.density.cpu(),
            "mask": model.occupancy.mask.cpu(),
            "resolution": model.occupancy.resolution,
        },
    }
    if model.occupancy.allowed is not None:
        payload["occupancy"]["allowed"] = model.occupancy.allowed.cpu()
    if model.background is not None:
        payload["background"] = {
            "density": model.background.density.cpu(),
            "mask": model.background.mask.cpu(),
            "resolution": model.background.resolution,
        }
    if trainer_state is not None:
        payload["trainer"] = trainer_state
    atomic_write(path, lambda f: torch.save(payload, f))


def read_checkpoint(path) -> dict:
    """The raw checkpoint dict, validated (format, version, keys). EngineError on any problem."""
    path = Path(path)
    if not path.is_file():
        raise EngineError(f"{path}: checkpoint not found")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (
        RuntimeError,
        pickle.UnpicklingError,
        zipfile.BadZipFile,
        EOFError,
        ValueError,
        OSError,
        AttributeError,
        IndexError,
        KeyError,
        TypeError,
    ) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise EngineError(
            f"{path}: not a readable NeRF checkpoint (corrupt, truncated or foreign file: {first[:160]})"
        ) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise EngineError(f"{path}: not a blender_nerf_deform NeRF checkpoint (no format marker {FORMAT!r})")
    if data.get("version") != VERSION:
        raise EngineError(
            f"{path}: checkpoint format version {data.get('version')!r}, this engine reads version {VERSION}"
        )
    for key in ("config", "state", "occupancy"):
        if key not in data:
            raise EngineError(f"{path}: checkpoint lacks `{key}`")
    return data


def _tensor(container: dict, key: str, path, where: str) -> torch.Tensor:
    value = container.get(key) if isinstance(container, dict) else None
    if not isinstance(value, torch.Tensor):
        raise EngineError(f"{path}: checkpoint `{where}` has no tensor `{key}`")
    return value


def _check_arrays(data: dict, path) -> None:
    """Every array a kernel will index or a render will sum: a NaN box turns into out-of-bounds
    indices in the hash kernel, NaN weights into fully transparent frames."""
    if not isinstance(data["state"], dict) or not isinstance(data["occupancy"], dict):
        raise EngineError(f"{path}: checkpoint `state` and `occupancy` must be dicts of tensors")
    aabb = _tensor(data["state"], "aabb", path, "state")
    if aabb.numel() != 6 or not aabb.is_floating_point():
        raise EngineError(f"{path}: checkpoint `aabb` has {aabb.numel()} values of {aabb.dtype}, expected 6 floats")
    box = aabb.detach().double().reshape(2, 3)
    if not torch.isfinite(box).all() or not (box[1] > box[0]).all():
        raise EngineError(f"{path}: checkpoint `aabb` {box.tolist()} is not a finite box (max > min on every axis)")
    for name, value in data["state"].items():
        if not isinstance(value, torch.Tensor):
            raise EngineError(f"{path}: checkpoint `state.{name}` is not a tensor")
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise EngineError(
                f"checkpoint {path} has non-finite weights (a diverged training run?): `{name}` holds NaN or inf"
            )
    density = _tensor(data["occupancy"], "density", path, "occupancy")
    if not density.is_floating_point() or not bool(torch.isfinite(density).all()):
        raise EngineError(f"{path}: checkpoint `occupancy.density` holds NaN or inf (a diverged training run?)")
    _tensor(data["occupancy"], "mask", path, "occupancy")
    if "background" in data:
        density = _tensor(data["background"], "density", path, "background")
        if not density.is_floating_point() or not bool(torch.isfinite(density).all()):
            raise EngineError(f"{path}: checkpoint `background.density` holds NaN or inf (a diverged training run?)")
        _tensor(data["background"], "mask", path, "background")


def load_nerf(path, device="auto") -> NerfModel:
    """Rebuild the NerfModel stored at `path` on `device` ("auto", "cpu", "cuda" or a torch.device).

    Everything read from the file is checked (config ranges, finite box and weights, the
    occupancy grid's size) before any kernel sees it; EngineError naming the file otherwise."""
    data = read_checkpoint(path)
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    if not isinstance(data["config"], dict):
        raise EngineError(f"{path}: checkpoint `config` is not a dict")
    _check_arrays(data, path)
    try:
        config = NerfConfig.from_dict(dict(data["config"]))
        model = NerfModel(config)
        model.load_state_dict(data["state"])
        occ = data["occupancy"]
        model.occupancy.density = occ["density"].float().reshape(-1)
        model.occupancy.mask = occ["mask"].bool().reshape(-1)
        n_cells = model.occupancy.resolution**3
        if model.occupancy.mask.numel() != n_cells or model.occupancy.density.numel() != n_cells:
            raise ValueError(
                f"occupancy grid of {model.occupancy.mask.numel()} cells, the config's "
                f"occ_resolution {config.occ_resolution} needs {n_cells}"
            )
        if occ.get("allowed") is not None:
            allowed = occ["allowed"]
            if not isinstance(allowed, torch.Tensor) or allowed.numel() != n_cells:
                raise ValueError(f"occupancy `allowed` must be a tensor of {n_cells} cells")
            model.occupancy.restrict(allowed.bool())
        if model.background is not None:
            if not isinstance(data.get("background"), dict):
                raise ValueError("an unbounded NeRF's checkpoint lacks its background occupancy grid")
            bg = data["background"]
            model.background.density = bg["density"].float().reshape(-1)
            model.background.mask = bg["mask"].bool().reshape(-1) & model.background._shell
            if model.background.density.numel() != n_cells:
                raise ValueError(
                    f"background grid of {model.background.density.numel()} cells, the config's "
                    f"occ_resolution {config.occ_resolution} needs {n_cells}"
                )
    except EngineError as exc:
        raise EngineError(f"{path}: {exc}") from None
    except (RuntimeError, TypeError, ValueError, KeyError) as exc:
        raise EngineError(
            f"{path}: checkpoint does not match this engine's model ({str(exc).splitlines()[0][:160]})"
        ) from None
    return model.to(dev).eval()
