"""NeRF checkpoints: one file, tensors and plain data only, loaded without executing code.

Format (a dict written by `torch.save`, read by `torch.load(weights_only=True)`):

    {"format": "blender_nerf_deform.nerf", "version": 1,
     "config": NerfConfig as a plain dict,
     "state": the model's state_dict (tensors),
     "occupancy": {"density": tensor, "mask": tensor},
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
        "occupancy": {"density": model.occupancy.density.cpu(), "mask": model.occupancy.mask.cpu(),
                      "resolution": model.occupancy.resolution},
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
    except (RuntimeError, pickle.UnpicklingError, zipfile.BadZipFile, EOFError, ValueError, OSError,
            AttributeError, IndexError, KeyError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise EngineError(f"{path}: not a readable NeRF checkpoint (corrupt, truncated or foreign file: {first[:160]})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise EngineError(f"{path}: not a blender_nerf_deform NeRF checkpoint (no format marker {FORMAT!r})")
    if data.get("version") != VERSION:
        raise EngineError(f"{path}: checkpoint format version {data.get('version')!r}, this engine reads version {VERSION}")
    for key in ("config", "state", "occupancy"):
        if key not in data:
            raise EngineError(f"{path}: checkpoint lacks `{key}`")
    return data


def load_nerf(path, device="auto") -> NerfModel:
    """Rebuild the NerfModel stored at `path` on `device` ("auto", "cpu", "cuda" or a torch.device)."""
    data = read_checkpoint(path)
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    try:
        config = NerfConfig.from_dict(dict(data["config"]))
        model = NerfModel(config)
        model.load_state_dict(data["state"])
        occ = data["occupancy"]
        model.occupancy.density = occ["density"].float().reshape(-1)
        model.occupancy.mask = occ["mask"].bool().reshape(-1)
        if model.occupancy.mask.numel() != model.occupancy.resolution**3:
            raise ValueError("occupancy grid size does not match the config")
    except EngineError as exc:
        raise EngineError(f"{path}: {exc}") from None
    except (RuntimeError, TypeError, ValueError, KeyError) as exc:
        raise EngineError(f"{path}: checkpoint does not match this engine's model ({str(exc).splitlines()[0][:160]})") from None
    return model.to(dev).eval()
