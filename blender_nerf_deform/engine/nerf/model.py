"""The NeRF field: hash encoding + tiny density MLP + view-dependent colour MLP (instant-ngp).

Public interface (other stages rely on these names):

- `NerfConfig`: the one config dataclass, stored in the checkpoint.
- `NerfModel(config)`: `.config`, `.aabb` (2x3 world bounds), `.device`,
  `.occupancy` (an `OccupancyGrid`), `.encoding` (the `HashEncoding`),
  `density(points[N,3] world) -> [N]`, `query(points, dirs) -> (density[N], rgb[N,3])`,
  and the split the renderer uses so that training encodes each sample once:
  `encode(points) -> (encoding, inside, normalized)`,
  `features_from_encoding(encoding, inside) -> (density, geo)` and `color(geo, dirs) -> rgb`.
- `resolve_device("auto"|"cpu"|"cuda")`, `device_summary()` (torch build, CUDA devices).

Bounded NeRFs (`contraction` "none", synthetic objects): the hash grid spans the aabb and
points outside it have density 0. Unbounded NeRFs (`contraction` "linf", real captures
with a room or sky around the object): `aabb` is the *inner box* (what extraction, cages
and Blender's box use), the hash grid spans the contracted cube (contraction.py) so
every point of space has a density, and `.background` is a second occupancy grid over
the contracted space outside the inner box. Directions need not be normalised.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from .. import backend
from ..errors import EngineError
from . import composite_kernels
from .contraction import contract, inner_units
from .encoding import HashEncoding, sh_encode
from .occupancy import ContractedGrid, OccupancyGrid

CONTRACTIONS = ("none", "linf")
MASK_RECORDS = ("none", "object", "ignore")


@dataclass
class NerfConfig:
    """Everything needed to rebuild the model (the checkpoint stores it as a plain dict)."""

    aabb: list = field(default_factory=lambda: [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5])  # xmin ymin zmin xmax ymax zmax
    n_levels: int = 8
    n_features: int = 4
    log2_table_size: int = 17
    base_resolution: int = 16
    finest_resolution: int = 512
    density_hidden: int = 64
    geo_feat_dim: int = 15  # the density MLP outputs 1 + geo_feat_dim values, all fed to the colour MLP
    color_hidden: int = 64
    color_layers: int = 2
    sh_degree: int = 4
    occ_resolution: int = 128
    occ_threshold: float = 0.01  # a cell is occupied when its opacity over one render step exceeds this
    steps_per_diagonal: int = 512  # render step = aabb diagonal / this
    background: list = field(default_factory=lambda: [1.0, 1.0, 1.0])  # default background (RGBA data: white)
    contraction: str = "none"  # "linf": aabb is the inner box and the field covers all space (contraction.py)
    near_plane: float = 0.0  # rays start this far from the camera (unbounded scenes: no floaters on the lens)
    appearance_dim: int = 0  # per-image appearance code fed to the colour MLP (exposure, white balance); 0: none
    appearance_count: int = 0  # training images with a code; frames render with their mean
    # How training read the dataset's masks: "none" (it had none), "object" (the object alone: empty around it),
    # "ignore" (the masked-out pixels were skipped). What Load NeRF reports; the model is the same either way.
    masks: str = "none"

    @classmethod
    def from_dict(cls, d: dict) -> NerfConfig:
        """The config of a plain dict (a checkpoint's), validated: EngineError naming the bad key."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise EngineError(f"unknown NeRF config keys {sorted(unknown)}")
        config = cls(**d)
        config.validate()
        return config

    def validate(self) -> None:
        """EngineError unless every field has a type and a value the model can be built from; a file's
        config must not reach the kernels as a NaN box, a zero step or a table of 2^40 rows."""
        for name, (lo, hi) in _INT_RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise EngineError(f"config `{name}` = {v!r} is invalid: it must be an integer from {lo} to {hi}")
        if self.finest_resolution < self.base_resolution:
            raise EngineError(
                f"config `finest_resolution` = {self.finest_resolution} is below `base_resolution` "
                f"= {self.base_resolution}"
            )
        for name, length in (("aabb", 6), ("background", 3)):
            v = getattr(self, name)
            if not isinstance(v, (list, tuple)) or len(v) != length or not all(_finite_number(x) for x in v):
                raise EngineError(f"config `{name}` = {v!r} is invalid: it must be {length} finite numbers")
        if not all(self.aabb[i + 3] > self.aabb[i] for i in range(3)):
            raise EngineError(f"config `aabb` = {self.aabb!r} is not a box (max > min on every axis)")
        if self.masks not in MASK_RECORDS:
            raise EngineError(f"config `masks` = {self.masks!r} is invalid: one of {', '.join(MASK_RECORDS)}")
        if self.contraction not in CONTRACTIONS:
            raise EngineError(
                f"config `contraction` = {self.contraction!r} is invalid: one of {', '.join(CONTRACTIONS)}"
            )
        if not _finite_number(self.near_plane) or self.near_plane < 0:
            raise EngineError(f"config `near_plane` = {self.near_plane!r} is invalid: it must be a finite number >= 0")
        if not _finite_number(self.occ_threshold) or self.occ_threshold < 0:
            raise EngineError(
                f"config `occ_threshold` = {self.occ_threshold!r} is invalid: it must be a finite number >= 0"
            )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def render_step(self) -> float:
        lo, hi = self.aabb[:3], self.aabb[3:]
        return math.sqrt(sum((b - a) ** 2 for a, b in zip(lo, hi))) / self.steps_per_diagonal


# Inclusive bounds of the integer fields: generous, but a model outside them cannot be built (memory)
# or evaluated (sh_encode has degrees 1..4; a render step needs steps_per_diagonal >= 1).
_INT_RANGES = {
    "n_levels": (1, 32),
    "n_features": (1, 64),
    "log2_table_size": (1, 28),
    "base_resolution": (1, 1 << 20),
    "finest_resolution": (1, 1 << 20),
    "density_hidden": (1, 4096),
    "geo_feat_dim": (0, 4096),
    "color_hidden": (1, 4096),
    "color_layers": (0, 64),
    "sh_degree": (1, 4),
    "occ_resolution": (1, 1024),
    "steps_per_diagonal": (1, 1 << 20),
    "appearance_dim": (0, 64),
    "appearance_count": (0, 1 << 20),
}


def _finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


class _TruncExp(torch.autograd.Function):
    """exp with a gradient clamped for stability (instant-ngp / torch-ngp's trunc_exp)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x)


def resolve_device(name: str = "auto") -> torch.device:
    """'auto' → cuda when available, else cpu; 'cuda' without CUDA is an EngineError."""
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise EngineError("--device cuda: this torch has no CUDA device (torch.cuda.is_available() is False)")
    if name not in ("cpu", "cuda"):
        raise EngineError(f"unknown device {name!r}: use auto, cpu or cuda")
    return torch.device(name)


def device_summary() -> dict:
    """The torch build and the devices it sees (the worker's hello and its `info` op)."""
    return {
        "torch": torch.__version__,
        "cuda": torch.cuda.is_available(),
        "devices": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())],
    }


def _mlp(n_in: int, n_hidden: int, n_layers: int, n_out: int) -> torch.nn.Sequential:
    layers, d = [], n_in
    for _ in range(n_layers):
        layers += [torch.nn.Linear(d, n_hidden, bias=False), torch.nn.ReLU(inplace=True)]
        d = n_hidden
    layers.append(torch.nn.Linear(d, n_out, bias=False))
    return torch.nn.Sequential(*layers)


class NerfModel(torch.nn.Module):
    def __init__(self, config: NerfConfig | None = None):
        super().__init__()
        self.config = config = config or NerfConfig()
        self.register_buffer("aabb", torch.tensor(config.aabb, dtype=torch.float32).reshape(2, 3))
        self.encoding = HashEncoding(
            config.n_levels, config.n_features, config.log2_table_size, config.base_resolution, config.finest_resolution
        )
        self.density_net = _mlp(self.encoding.out_dim, config.density_hidden, 1, 1 + config.geo_feat_dim)
        self.color_net = _mlp(
            1 + config.geo_feat_dim + config.sh_degree**2 + config.appearance_dim,
            config.color_hidden,
            config.color_layers,
            3,
        )
        # nerfacto / NeRF-W's appearance embedding: one learnt code per training image, zero to start.
        self.appearance = None
        if config.appearance_dim:
            self.appearance = torch.nn.Embedding(max(1, config.appearance_count), config.appearance_dim)
            torch.nn.init.zeros_(self.appearance.weight)
        self.occupancy = OccupancyGrid(self.aabb, config.occ_resolution)
        self.background = ContractedGrid(self.aabb, config.occ_resolution) if self.unbounded else None

    @property
    def unbounded(self) -> bool:
        return self.config.contraction != "none"

    @property
    def device(self) -> torch.device:
        return self.aabb.device

    def _apply(self, fn, *args, **kwargs):
        # .to(), .cuda(), .cpu() all come here: the occupancy grid (not a Module) follows the weights.
        out = super()._apply(fn, *args, **kwargs)
        if "occupancy" in self.__dict__:
            self.occupancy.to(self.aabb.device)
            if self.background is not None:
                self.background.to(self.aabb.device)
        return out

    def normalize(self, points: torch.Tensor) -> torch.Tensor:
        """World points → the hash grid's [0, 1]^3 (through the contraction for unbounded NeRFs)."""
        if self.unbounded:
            center, half = 0.5 * (self.aabb[0] + self.aabb[1]), 0.5 * (self.aabb[1] - self.aabb[0])
            if (
                points.device.type == "cpu"
                and points.dtype == torch.float32
                and not points.requires_grad
                and backend.use_kernels(points.device)
            ):
                return composite_kernels.contract_normalize(points, center, half)
            return (contract(inner_units(points, center, half)) + 2.0) * 0.25
        return (points - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def encode(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Hash encoding (N, L*F) of world points, whether each is inside the field's domain (the aabb, or all
        of space when unbounded), and the normalised points."""
        x = self.normalize(points)
        inside = ((x >= 0) & (x <= 1)).all(dim=-1)
        return self.encoding(x), inside, x

    def features_from_encoding(self, encoded: torch.Tensor, inside: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.density_net(encoded)
        sigma = trunc_exp(h[:, 0] - 1.0) * inside
        return sigma, h

    def density_and_features(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density (N,) >= 0 and the geometry features (N, 1+geo_feat_dim) the colour MLP reads."""
        encoded, inside, _ = self.encode(points)
        return self.features_from_encoding(encoded, inside)

    def color(self, geo: torch.Tensor, dirs: torch.Tensor, codes: torch.Tensor | None = None) -> torch.Tensor:
        """RGB of samples; `codes` (N, appearance_dim) are their images' appearance codes (default: the mean
        code, which is how frames render)."""
        d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        parts = [geo, sh_encode(d, self.config.sh_degree)]
        if self.appearance is not None:
            if codes is None:
                codes = self.appearance.weight.mean(dim=0, keepdim=True).expand(geo.shape[0], -1)
            parts.append(codes)
        return torch.sigmoid(self.color_net(torch.cat(parts, dim=-1)))

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """Volume density (N,) >= 0 at world points (N, 3); 0 outside the aabb, and in the cells training ruled out
        (`OccupancyGrid.restrict`: outside an object's silhouettes, or paid for by too few photos), which frames
        skip too, so that extraction and the occupancy updates see what renders."""
        sigma = self.density_and_features(points)[0]
        if self.occupancy.allowed is not None:
            sigma = sigma * self.occupancy.permitted(points)
        return sigma

    def query(self, points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(density (N,), rgb (N, 3) in [0, 1]) at world points seen along directions dirs."""
        sigma, geo = self.density_and_features(points)
        return sigma, self.color(geo, dirs)

    def forward(self, points, dirs):
        return self.query(points, dirs)
