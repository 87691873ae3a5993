"""The requests the engine serves, as types: the protocol between Blender (the add-on) and the worker.

Standard library and numpy only (no torch), so the add-on, in Blender's Python, builds these
objects and sends `to_wire()`; the worker's handlers (ops.py) build them with `from_wire` and hand
each to one stage function; the command line (cli/) builds the same objects from its options.
Every request is checked once, where it is built from the wire: anything wrong is one
`EngineError` that names the request and the field, for instance

    render request: pose.deformed_vertices: expected a float array of shape (N, 3), got int64 (4, 2)

The readers below are written here rather than taken from pydantic or cattrs: Blender's Python
carries numpy and nothing else, and an extension must not install packages into it.

`from_wire(to_wire(x)) == x` for every request, and `to_wire` gives the params and arrays the
wire has always carried (protocol.py frames them: a JSON header, then raw arrays).

How a request travels
---------------------
A message is `{"type": "request", "id", "op", "params"}` plus named arrays; `params` holds JSON
values, `arrays` numpy arrays. The worker answers `result` (plain data and arrays), `progress`
(fraction, message) or `error` (kind: `input` for an EngineError, `missing`, `cancelled`, ...).

Session content (session.py): the worker keeps what Blender gave it under content keys chosen by
the client (`protocol.content_key`: a hash of each array's dtype, shape and bytes), so a frame
sends only what changed. A request names its content in `params["shared"] = {slot: key}` and
carries a slot's arrays (named `"<slot>.<name>"`) only when this worker has not had them:

    cage       vertices (N, 3), tets (M, 4): a rest cage
    embedding  tet_ids (P,), weights (P, 4): the extracted mesh in that cage
    regions    handle_index, handle_counts, pin_index [, cage_pin_index]: the handles' regions
               (surface vertices) and the pinned vertices

When the worker does not hold a key it answers error kind `missing` and the client resends once
with the arrays. The session checks those arrays when they arrive; `shared` is the client's
(addon/worker/client.py) and is no field of the types below.

The ops
-------
    info           -                              the worker's Python, torch and devices
    load           LoadRequest                    a NeRF's bounds and configuration
    extract        ExtractRequest                 the surface mesh (vertices, faces, colors, cut,
                                                  part: the edit region of each vertex)
    cage           CageRequest                    the rest cage (one per part, in one), the surface's
                                                  embedding in it, the cage vertices pinned at the cut
    train          TrainRequest                   a NeRF trained into out/nerf.ckpt, with progress
    training_preview  TrainingPreviewRequest      a small frame of a run (a side op, answered between
                                                  the training's steps while it runs)
    prepare        PrepareRequest                 photos -> a transforms.json dataset (structure from
                                                  motion), with progress
    first_surface  FirstSurfaceRequest            where a ray first meets the density (a click's pick)
    solve          SolveRequest                   a pose of the handles: the deformed cage vertices, or
                                                  (answer "surface") the deformed surface, for the preview
    render         RenderRequest                  one frame, its pose solved and rendered in one go
    warm           WarmRequest                    NeRFs loaded, and their frame kernels run once, ahead
                                                  of a file's first frame
    bake_volume    BakeVolumeRequest              the NeRF at a pose sampled on a voxel grid

A frame's pose (`Pose`): `RestPose` (`{"kind": "rest"}`: no cage, or nothing moved);
`CagePose` (`{"kind": "cage"}` and the array `deformed_vertices`: the cage's vertices after
Blender's modifiers, with the shared `cage`); `HandlesPose` (`{"kind": "handles", "mode",
"transforms", "handle_names"}`: one 4x4 per handle in the NeRF's frame, with the shared `cage`,
`embedding` and `regions`; the worker solves ARAP or affine regions and renders in the same request).

A camera (`WireCamera`) is a pinhole in the NeRF's frame: `fx`, `fy`, `cx`, `cy` in pixels,
`width`, `height`, `camera_to_world` (4x4 rows, Blender's convention: the camera looks down -Z).
A render answers `rgba` (H, W, 4) and `depth` (H, W) as float32, straight alpha, rows top-down.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from ..bend.baked_volume import check_resolution
from ..errors import EngineError
from ..geometry.poses import check_coordinates
from ..geometry.region import EditRegion, region_from_dict
from ..nerf.camera import Camera
from ..nerf.substeps import check_substeps


class Op(enum.StrEnum):
    INFO = "info"
    LOAD = "load"
    EXTRACT = "extract"
    CAGE = "cage"
    TRAIN = "train"
    TRAINING_PREVIEW = "training_preview"
    PREPARE = "prepare"
    FIRST_SURFACE = "first_surface"
    SOLVE = "solve"
    RENDER = "render"
    WARM = "warm"
    BAKE_VOLUME = "bake_volume"


class PoseKind(enum.StrEnum):
    REST = "rest"
    CAGE = "cage"
    HANDLES = "handles"


class DeformMode(enum.StrEnum):
    """How handles pose the cage: ARAP (as rigid as possible) or Affine Regions."""

    ARAP = "ARAP"
    AFFINE = "AFFINE"


class SolveAnswer(enum.StrEnum):
    CAGE = "cage"  # the deformed cage vertices
    SURFACE = "surface"  # the deformed extracted mesh, all the live preview draws


class Matcher(enum.StrEnum):
    EXHAUSTIVE = "exhaustive"
    SEQUENTIAL = "sequential"


class SceneModel(enum.StrEnum):
    AUTO = "auto"
    BOUNDED = "bounded"
    UNBOUNDED = "unbounded"


class MaskMeaning(enum.StrEnum):
    """What a dataset's masks mean (nerf/silhouettes.py: MASK_MEANINGS)."""

    AUTO = "auto"
    OBJECT = "object"  # the object alone is real: outside is empty
    IGNORE = "ignore"  # the masked-out pixels are not trained


class Extent(enum.StrEnum):
    NERF = "nerf"  # the NeRF's box
    CAGE = "cage"  # the box of the cage as posed


PREVIEW_MAX_SIDE = 1024  # a training preview is small: the training waits while it renders
FIRST_SURFACE_THRESHOLD = 10.0


# Reading the wire: each reader raises one EngineError naming the request and the field.


def _shown(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} {tuple(value.shape)}"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class _Reader:
    def __init__(self, where: str, params: Any, arrays: Any = None):
        if not isinstance(params, dict):
            raise EngineError(f"{where}: params: expected a JSON object, got {type(params).__name__}")
        if arrays is not None and not isinstance(arrays, dict):
            raise EngineError(f"{where}: arrays: expected named arrays, got {type(arrays).__name__}")
        self.where, self.params, self.arrays = where, params, arrays or {}

    def error(self, name: str, problem: str) -> EngineError:
        return EngineError(f"{self.where}: {name}: {problem}")

    def expected(self, name: str, what: str, value: Any) -> EngineError:
        return self.error(name, f"expected {what}, got {_shown(value)}")

    def missing(self, name: str, what: str) -> EngineError:
        return self.error(name, f"missing ({what})")

    def path(self, name: str, what: str = "a path", optional: bool = False) -> str | None:
        if name not in self.params:
            if optional:
                return None
            raise self.missing(name, what)
        value = self.params[name]
        if not isinstance(value, str) or not value:
            raise self.expected(name, what, value)
        return value

    def choice(self, name: str, enum_type: type[enum.StrEnum], default: Any = None):
        value = self.params.get(name, default)
        try:
            return enum_type(value)
        except ValueError:
            raise self.expected(name, f"one of {', '.join(m.value for m in enum_type)}", value) from None

    def device(self) -> str | None:
        value = self.params.get("device")
        if value is not None and (not isinstance(value, str) or not value):
            raise self.expected("device", "auto, cpu or cuda", value)
        return value

    def flag(self, name: str, default: bool) -> bool:
        value = self.params.get(name, default)
        if not isinstance(value, bool):
            raise self.expected(name, "true or false", value)
        return value

    def integer(self, name: str, default: Any = None, minimum: int | None = None, what: str = "") -> Any:
        value = self.params.get(name, default)
        if value is None and default is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
            raise self.expected(
                name, what or (f"an integer >= {minimum}" if minimum is not None else "an integer"), value
            )
        return value

    def number(self, name: str, default: Any = None, positive: bool = False, what: str = "") -> Any:
        """A finite number (int or float, as sent: its type is kept); None when absent and no default."""
        value = self.params.get(name, default)
        if value is None and default is None:
            return None
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or (positive and not value > 0):
            raise self.expected(name, what or ("a positive finite number" if positive else "a finite number"), value)
        return value

    def array(self, name: str, field: str, columns: int | None, kind: str, length: int | None = None) -> np.ndarray:
        """arrays[name]: `kind` "f" floats (finite), "i" integers, "flag" booleans or integers; shape (N,)
        or (N, columns); `length` N when it must match."""
        if name not in self.arrays:
            raise self.missing(field, "an array")
        a = self.arrays[name]
        return _checked_array(self, field, a, columns, kind, length)


def _checked_array(reader: _Reader, field: str, a: Any, columns: int | None, kind: str, length: int | None):
    shape = "(N,)" if columns is None else f"(N, {columns})"
    what = {"f": "a float array", "i": "an integer array", "flag": "a flag array (bool or integer)"}[kind]
    if not isinstance(a, np.ndarray):
        raise reader.expected(field, f"{what} of shape {shape}", a)
    dtype_ok = {
        "f": np.issubdtype(a.dtype, np.floating),
        "i": np.issubdtype(a.dtype, np.integer),
        "flag": np.issubdtype(a.dtype, np.integer) or a.dtype == np.bool_,
    }[kind]
    shape_ok = a.ndim == 1 if columns is None else (a.ndim == 2 and a.shape[1] == columns)
    if not dtype_ok or not shape_ok:
        raise reader.expected(field, f"{what} of shape {shape}", a)
    if length is not None and len(a) != length:
        raise reader.error(field, f"{len(a)} rows for a mesh of {length} vertices")
    if kind == "f" and a.size and not np.isfinite(a).all():
        row = int(np.flatnonzero(~np.isfinite(a.reshape(len(a), -1)).all(axis=1))[0])
        raise reader.error(field, f"row {row} is not finite")
    return a


def _equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and np.array_equal(a, b)
        )
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


class _Wire:
    """Equality field by field, numpy arrays by dtype, shape and values."""

    op: ClassVar[str] = ""

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and all(
            _equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self)
        )

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def _where(cls, where: str | None) -> str:
        return where or f"{cls.op} request"


# The camera


@dataclass(eq=False)
class WireCamera(_Wire):
    """A pinhole in the NeRF's frame, as the wire carries it (`clip_start`/`clip_end`: what the add-on's
    camera also sends; unused by the engine)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_to_world: np.ndarray  # (4, 4) float64
    clip_start: float | None = None
    clip_end: float | None = None

    @classmethod
    def from_pinhole(cls, pinhole: Any, camera_to_world: np.ndarray) -> WireCamera:
        """The camera of a pinhole (an object with its attributes: the add-on's `data.camera.Pinhole`)
        placed at `camera_to_world` (the NeRF's frame)."""
        return cls(
            width=pinhole.width,
            height=pinhole.height,
            fx=pinhole.fx,
            fy=pinhole.fy,
            cx=pinhole.cx,
            cy=pinhole.cy,
            camera_to_world=camera_to_world,
            clip_start=pinhole.clip_start,
            clip_end=pinhole.clip_end,
        )

    @classmethod
    def from_wire(cls, value: Any, reader: _Reader | None = None, name: str = "camera") -> WireCamera:
        """The camera of a request's `camera` param (`reader`: the request's, which names it in errors)."""
        reader = reader if reader is not None else _Reader("camera", {})
        if not isinstance(value, dict):
            raise reader.expected(name, "a camera (a JSON object)", value)
        sub = _Reader(reader.where, value)

        def number(key: str, nonzero: bool = False):
            if key not in value:
                raise reader.missing(f"{name}.{key}", "a number")
            v = value[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (nonzero and v == 0):
                raise reader.expected(f"{name}.{key}", "a finite non-zero number" if nonzero else "a finite number", v)
            return float(v)

        def pixels(key: str) -> int:
            if key not in value:
                raise reader.missing(f"{name}.{key}", "a whole number of pixels")
            v = value[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v or v < 1 or int(v) != v:
                raise reader.expected(f"{name}.{key}", "a whole number of pixels >= 1", v)
            return int(v)

        if "camera_to_world" not in value:
            raise reader.missing(f"{name}.camera_to_world", "a 4x4 matrix")
        try:
            c2w = np.asarray(value["camera_to_world"], dtype=np.float64)
        except (TypeError, ValueError):
            c2w = None
        if c2w is None or c2w.size != 16 or not np.isfinite(c2w).all():
            raise reader.expected(f"{name}.camera_to_world", "a 4x4 matrix of finite numbers", value["camera_to_world"])
        clip = {}
        for key in ("clip_start", "clip_end"):
            if key in value:
                clip[key] = sub.number(key)
        return cls(
            width=pixels("width"),
            height=pixels("height"),
            fx=number("fx", nonzero=True),
            fy=number("fy", nonzero=True),
            cx=number("cx"),
            cy=number("cy"),
            camera_to_world=c2w.reshape(4, 4),
            **clip,
        )

    def to_wire(self) -> dict:
        out = {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "camera_to_world": np.asarray(self.camera_to_world, dtype=np.float64).tolist(),
        }
        for key in ("clip_start", "clip_end"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    def camera(self) -> Camera:
        """The engine's camera."""
        return Camera(
            c2w=np.asarray(self.camera_to_world, dtype=np.float64).reshape(4, 4),
            fx=float(self.fx),
            fy=float(self.fy),
            cx=float(self.cx),
            cy=float(self.cy),
            width=int(self.width),
            height=int(self.height),
        )


# Poses


@dataclass(eq=False)
class RestPose(_Wire):
    """No cage, or nothing moved."""

    kind: ClassVar[PoseKind] = PoseKind.REST

    def to_wire(self) -> tuple[dict, dict]:
        return {"kind": "rest"}, {}


@dataclass(eq=False)
class CagePose(_Wire):
    """The cage's vertices as Blender's modifiers deform them (NeRF frame; the shared `cage`'s order)."""

    deformed_vertices: np.ndarray  # (N, 3) float
    kind: ClassVar[PoseKind] = PoseKind.CAGE

    def to_wire(self) -> tuple[dict, dict]:
        return {"kind": "cage"}, {"deformed_vertices": self.deformed_vertices}

    def check_cage(self, rest_vertices: np.ndarray, where: str = "render request") -> None:
        """EngineError unless the pose has the shape of the rest cage it deforms."""
        if self.deformed_vertices.shape != rest_vertices.shape:
            raise EngineError(
                f"{where}: pose.deformed_vertices: {self.deformed_vertices.shape[0]} vertices for a cage of "
                f"{rest_vertices.shape[0]} (the deformed cage must have the rest cage's shape {rest_vertices.shape})"
            )


@dataclass(eq=False)
class HandlesPose(_Wire):
    """The handles' transforms (one 4x4 each, NeRF frame), solved in the worker with the shared cage,
    embedding and regions. Each transform's values are checked by the deformer, which names the handle."""

    mode: DeformMode = DeformMode.ARAP
    transforms: tuple = ()  # of (4, 4) (or (3, 4)) float64 arrays
    handle_names: tuple = ()  # of str
    kind: ClassVar[PoseKind] = PoseKind.HANDLES

    @classmethod
    def read(cls, r: _Reader, prefix: str = "") -> HandlesPose:
        mode = r.params.get("mode", "ARAP")
        if not isinstance(mode, str) or mode not in tuple(DeformMode):
            raise r.expected(prefix + "mode", "ARAP or AFFINE", mode)
        raw = r.params.get("transforms", [])
        if not isinstance(raw, list):
            raise r.expected(prefix + "transforms", "a list of 4x4 matrices, one per handle", raw)
        transforms = []
        for i, t in enumerate(raw):
            try:
                m = np.asarray(t, dtype=np.float64)
            except (TypeError, ValueError):
                m = None
            if m is None or m.shape not in ((4, 4), (3, 4)):
                raise r.expected(f"{prefix}transforms[{i}]", "a 4x4 matrix of numbers", t)
            transforms.append(m)
        names = r.params.get("handle_names") or []
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise r.expected(prefix + "handle_names", "a list of handle names", names)
        return cls(DeformMode(mode), tuple(transforms), tuple(names))

    def params(self) -> dict:
        return {
            "mode": self.mode.value if isinstance(self.mode, enum.Enum) else self.mode,
            "transforms": [np.asarray(t).tolist() for t in self.transforms],
            "handle_names": list(self.handle_names),
        }

    def to_wire(self) -> tuple[dict, dict]:
        return {"kind": "handles", **self.params()}, {}


Pose = RestPose | CagePose | HandlesPose


def pose_from_wire(value: Any, arrays: dict, reader: _Reader) -> Pose:
    """The pose of a render or bake request (absent or null: rest)."""
    if value is None:
        return RestPose()
    if not isinstance(value, dict):
        raise reader.expected("pose", "a pose (a JSON object with a `kind`)", value)
    kind = value.get("kind")
    if kind not in tuple(PoseKind):
        raise reader.expected("pose.kind", "rest, cage or handles", kind)
    if kind == PoseKind.REST:
        return RestPose()
    if kind == PoseKind.CAGE:
        v = (
            reader.array("deformed_vertices", "pose.deformed_vertices", 3, "f")
            if "deformed_vertices" in arrays
            else None
        )
        if v is None:
            raise reader.missing("pose.deformed_vertices", "the array of the deformed cage's vertices")
        check_coordinates(v, f"{reader.where}: pose.deformed_vertices (the cage as its modifiers deform it)")
        return CagePose(np.asarray(v, dtype=np.float64))
    return HandlesPose.read(_Reader(reader.where, value), prefix="pose.")


# The requests


@dataclass(eq=False)
class InfoRequest(_Wire):
    op: ClassVar[str] = Op.INFO

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> InfoRequest:
        _Reader(cls._where(where), params, arrays)
        return cls()

    def to_wire(self) -> tuple[dict, dict]:
        return {}, {}


@dataclass(eq=False)
class LoadRequest(_Wire):
    path: str
    device: str | None = None  # None: "auto"
    op: ClassVar[str] = Op.LOAD

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> LoadRequest:
        r = _Reader(cls._where(where), params, arrays)
        return cls(r.path("path", "the path of a NeRF checkpoint"), r.device())

    def to_wire(self) -> tuple[dict, dict]:
        return _with_device({"path": self.path}, self.device), {}


def _with_device(params: dict, device: str | None) -> dict:
    if device is not None:
        params["device"] = device
    return params


@dataclass(eq=False)
class ExtractRequest(_Wire):
    """The NeRF's surface: `regions` as the wire's dicts (checked: `edit_regions()` reads them)."""

    checkpoint: str
    threshold: float | None = None
    resolution: int | None = None
    min_volume: float | None = None
    regions: tuple = ()  # of edit-region dicts: {"center", "size", "rotation_euler"}
    pick: tuple | None = None  # a point on the object, NeRF frame
    device: str | None = None
    op: ClassVar[str] = Op.EXTRACT

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> ExtractRequest:
        r = _Reader(cls._where(where), params, arrays)
        checkpoint = r.path("checkpoint", "the path of a NeRF checkpoint")
        listed = params.get("regions") or ([params["region"]] if params.get("region") is not None else [])
        if not isinstance(listed, list):
            raise r.expected("regions", "a list of edit regions", listed)
        for i, region in enumerate(listed):
            region_from_dict(region, where=f"{r.where}: regions[{i}] (edit region {i + 1})")
        pick = params.get("pick")
        if pick is not None:
            try:
                point = np.asarray(pick, dtype=np.float64)
            except (TypeError, ValueError):
                point = None
            if point is None or point.shape != (3,) or not np.isfinite(point).all():
                raise r.expected("pick", "three finite numbers (a point on the object)", pick)
            pick = tuple(pick)
        return cls(
            checkpoint,
            r.number("threshold"),
            r.integer("resolution", minimum=1),
            r.number("min_volume"),
            tuple(listed),
            pick,
            r.device(),
        )

    def edit_regions(self) -> list[EditRegion]:
        return [region_from_dict(r, where=f"edit region {i + 1}") for i, r in enumerate(self.regions)]

    def pick_point(self) -> np.ndarray | None:
        return None if self.pick is None else np.asarray(self.pick, dtype=np.float64)

    def to_wire(self) -> tuple[dict, dict]:
        params: dict = {"checkpoint": self.checkpoint}
        for name in ("threshold", "resolution", "min_volume"):
            if getattr(self, name) is not None:
                params[name] = getattr(self, name)
        if self.regions:
            params["regions"] = list(self.regions)
        if self.pick is not None:
            params["pick"] = list(self.pick)
        return _with_device(params, self.device), {}


@dataclass(eq=False)
class CageRequest(_Wire):
    """A cage around a surface mesh: `cut` (flags: where an edit region closed the surface), `part`
    (the edit region of each vertex: one cage per part), `refine` (flags: the surface vertices around
    which the cage is made finer, to `refine_edge`, None: half the cage's median edge) or `refine_box`
    ((2, 3) lo/hi: refine the tets whose centroid lies inside, to `refine_edge`)."""

    vertices: np.ndarray  # (N, 3) float
    faces: np.ndarray  # (F, 3) integer
    cut: np.ndarray | None = None  # (N,) flags
    part: np.ndarray | None = None  # (N,) integers
    refine: np.ndarray | None = None  # (N,) flags
    checkpoint: str | None = None  # with it, the margin is widened where the NeRF's density is still soft
    threshold: float | None = None
    margin: float | None = None
    edge_length: float | None = None
    target_tets: int | None = None
    pin_cut: bool = True
    refine_edge: float | None = None
    refine_box: np.ndarray | None = None
    device: str | None = None
    op: ClassVar[str] = Op.CAGE

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> CageRequest:
        r = _Reader(cls._where(where), params, arrays)
        vertices = r.array("vertices", "vertices", 3, "f")
        faces = r.array("faces", "faces", 3, "i")
        n = len(vertices)
        if faces.size and (faces.min() < 0 or faces.max() >= n):
            raise r.error("faces", f"index vertices outside 0..{n - 1}")
        optional = {}
        for name, kind, what in (
            ("cut", "flag", "cut flags"),
            ("part", "i", "part labels"),
            ("refine", "flag", "refinement flags"),
        ):
            if name in r.arrays:
                a = r.array(name, name, None, kind)
                if len(a) != n:
                    raise r.error(name, f"{len(a)} {what} for a mesh of {n} vertices")
                optional[name] = a
        refine_edge = params.get("refine_edge")
        if refine_edge is None or (type(refine_edge) in (int, float) and refine_edge == 0):
            refine_edge = None  # absent or 0: half the cage's median edge
        else:
            refine_edge = r.number("refine_edge", positive=True, what="a positive length")
        box = params.get("refine_box")
        if box is not None:
            try:
                box = np.asarray(box, dtype=np.float64)
            except (TypeError, ValueError):
                box = None
            if box is None or box.size != 6 or not np.isfinite(box).all():
                raise r.expected("refine_box", "[xmin, ymin, zmin, xmax, ymax, zmax]", params.get("refine_box"))
            box = box.reshape(2, 3)
            if refine_edge is None:
                raise r.error("refine_box", "needs refine_edge (the edge length to refine to)")
            if "refine" in optional:
                raise r.error("refine_box", "give refine (flags) or refine_box, not both")
        return cls(
            vertices,
            faces,
            checkpoint=r.path("checkpoint", "the path of a NeRF checkpoint", optional=True),
            threshold=r.number("threshold", what="a finite density >= 0"),
            margin=r.number("margin", positive=True, what="a positive finite distance"),
            edge_length=r.number("edge_length", positive=True, what="a positive finite length"),
            target_tets=r.integer("target_tets", minimum=1, what="a positive number of tets"),
            pin_cut=r.flag("pin_cut", True),
            refine_edge=refine_edge,
            refine_box=box,
            device=r.device(),
            **optional,
        )

    def to_wire(self) -> tuple[dict, dict]:
        params: dict = {}
        for name in ("checkpoint", "threshold", "margin", "edge_length", "target_tets", "refine_edge"):
            if getattr(self, name) is not None:
                params[name] = getattr(self, name)
        params["pin_cut"] = self.pin_cut
        if self.refine_box is not None:
            params["refine_box"] = np.asarray(self.refine_box, dtype=np.float64).reshape(-1).tolist()
        arrays = {"vertices": self.vertices, "faces": self.faces}
        for name in ("cut", "part", "refine"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        return _with_device(params, self.device), arrays


@dataclass(eq=False)
class TrainRequest(_Wire):
    data: str
    out: str
    steps: int | None = None
    max_seconds: float | None = None
    device: str = "auto"
    downscale: int = 1
    resume: bool = False
    overwrite: bool = False
    scene: SceneModel = SceneModel.AUTO
    masks: MaskMeaning = MaskMeaning.AUTO
    op: ClassVar[str] = Op.TRAIN

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> TrainRequest:
        r = _Reader(cls._where(where), params, arrays)
        data, out = r.path("data", "a dataset folder"), r.path("out", "a run folder")
        return cls(
            data,
            out,
            steps=r.integer("steps", minimum=1, what="a positive number of steps"),
            max_seconds=r.number("max_seconds", positive=True, what="a positive number of seconds"),
            device=r.device() or "auto",
            downscale=r.integer("downscale", 1, minimum=1, what="a whole number >= 1"),
            resume=r.flag("resume", False),
            overwrite=r.flag("overwrite", False),
            scene=r.choice("scene", SceneModel, "auto"),
            masks=r.choice("masks", MaskMeaning, "auto"),
        )

    def to_wire(self) -> tuple[dict, dict]:
        params = {
            "data": self.data,
            "out": self.out,
            "device": self.device,
            "downscale": self.downscale,
            "resume": self.resume,
            "masks": str(self.masks),
        }
        if self.max_seconds is not None:
            params["max_seconds"] = self.max_seconds
        if self.steps is not None:
            params["steps"] = self.steps
        if self.overwrite:
            params["overwrite"] = True
        if self.scene != SceneModel.AUTO:
            params["scene"] = self.scene.value
        return params, {}


@dataclass(eq=False)
class TrainingPreviewRequest(_Wire):
    """A small frame of a run: `camera`, or None for a view of the NeRF's box of `size` (width, height)."""

    checkpoint: str
    camera: WireCamera | None = None
    size: tuple | None = None
    device: str | None = None
    op: ClassVar[str] = Op.TRAINING_PREVIEW

    @staticmethod
    def run_of(params: Any) -> str | None:
        """The checkpoint a preview asks for, when it names one (which training answers it)."""
        checkpoint = params.get("checkpoint") if isinstance(params, dict) else None
        return checkpoint if isinstance(checkpoint, str) else None

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> TrainingPreviewRequest:
        r = _Reader(cls._where(where), params, arrays)
        checkpoint = r.path("checkpoint", "the path of the run's nerf.ckpt")
        if "camera" not in params:
            raise r.missing("camera", "a camera, or null for a view of the NeRF's box")
        cam, size = params["camera"], None
        if cam is None:
            size = params.get("size")
            if not (
                isinstance(size, list)
                and len(size) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) for v in size)
            ):
                raise r.expected("size", "[width, height] in pixels (a preview without a camera)", size)
            width, height, name, size = size[0], size[1], "size", tuple(size)
        elif isinstance(cam, dict):
            cam = WireCamera.from_wire(cam, r)
            width, height, name = cam.width, cam.height, "camera"
        else:
            raise r.expected("camera", "a camera (a JSON object), or null for a view of the NeRF's box", cam)
        if not (1 <= width <= PREVIEW_MAX_SIDE and 1 <= height <= PREVIEW_MAX_SIDE):
            raise r.error(
                name,
                f"a training preview is at most {PREVIEW_MAX_SIDE}x{PREVIEW_MAX_SIDE} pixels, got {width}x{height}",
            )
        return cls(checkpoint, cam, size, r.device())

    def to_wire(self) -> tuple[dict, dict]:
        params: dict = {"checkpoint": self.checkpoint, "camera": None if self.camera is None else self.camera.to_wire()}
        if self.size is not None:
            params["size"] = list(self.size)
        return _with_device(params, self.device), {}


@dataclass(eq=False)
class PrepareRequest(_Wire):
    images: str
    out: str
    matcher: Matcher = Matcher.EXHAUSTIVE
    max_size: int = 1600
    seed: int = 0
    op: ClassVar[str] = Op.PREPARE

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> PrepareRequest:
        r = _Reader(cls._where(where), params, arrays)
        return cls(
            r.path("images", "a folder of photos"),
            r.path("out", "a dataset folder"),
            r.choice("matcher", Matcher, "exhaustive"),
            r.integer("max_size", 1600),
            r.integer("seed", 0),
        )

    def to_wire(self) -> tuple[dict, dict]:
        params = {"images": self.images, "out": self.out, "matcher": self.matcher.value}
        if self.max_size != 1600:
            params["max_size"] = self.max_size
        if self.seed != 0:
            params["seed"] = self.seed
        return params, {}


@dataclass(eq=False)
class FirstSurfaceRequest(_Wire):
    checkpoint: str
    origin: tuple
    direction: tuple
    threshold: float = FIRST_SURFACE_THRESHOLD
    device: str | None = None
    op: ClassVar[str] = Op.FIRST_SURFACE

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> FirstSurfaceRequest:
        r = _Reader(cls._where(where), params, arrays)
        checkpoint = r.path("checkpoint", "the path of a NeRF checkpoint")
        ray = []
        for name in ("origin", "direction"):
            value = params.get(name)
            try:
                v = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                v = None
            if v is None or v.shape != (3,) or not np.isfinite(v).all():
                raise r.expected(name, "three finite numbers", value)
            ray.append(tuple(value))
        return cls(checkpoint, ray[0], ray[1], float(r.number("threshold", FIRST_SURFACE_THRESHOLD)), r.device())

    def to_wire(self) -> tuple[dict, dict]:
        params = {
            "checkpoint": self.checkpoint,
            "origin": list(self.origin),
            "direction": list(self.direction),
            "threshold": self.threshold,
        }
        return _with_device(params, self.device), {}


@dataclass(eq=False)
class SolveRequest(_Wire):
    """The handles' pose (the shared cage, embedding and regions name the rest)."""

    pose: HandlesPose
    answer: SolveAnswer = SolveAnswer.CAGE
    op: ClassVar[str] = Op.SOLVE

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> SolveRequest:
        r = _Reader(cls._where(where), params, arrays)
        if params.get("kind", PoseKind.HANDLES) != PoseKind.HANDLES:
            raise r.expected("kind", "handles (a solve poses the handles), or none", params.get("kind"))
        answer = params.get("answer") or "cage"
        if not isinstance(answer, str) or answer not in tuple(SolveAnswer):
            raise r.expected("answer", "surface, or cage (the default)", answer)
        return cls(HandlesPose.read(r), SolveAnswer(answer))

    def to_wire(self) -> tuple[dict, dict]:
        params = self.pose.params()
        if self.answer == SolveAnswer.SURFACE:
            params["answer"] = "surface"
        return params, {}


@dataclass(eq=False)
class RenderRequest(_Wire):
    """One frame: `substeps` None is the wire's absent value (1: a preview's march)."""

    checkpoint: str
    camera: WireCamera
    pose: Pose = field(default_factory=RestPose)
    substeps: int | None = None
    device: str | None = None
    op: ClassVar[str] = Op.RENDER

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> RenderRequest:
        r = _Reader(cls._where(where), params, arrays)
        substeps = None
        if "substeps" in params:
            try:
                substeps = check_substeps(params["substeps"])
            except EngineError as error:
                raise r.error("substeps", str(error)) from None
        checkpoint = r.path("checkpoint", "the path of a NeRF checkpoint")
        if "camera" not in params:
            raise r.missing("camera", "a camera")
        camera = WireCamera.from_wire(params["camera"], r)
        return cls(checkpoint, camera, pose_from_wire(params.get("pose"), r.arrays, r), substeps, r.device())

    def to_wire(self) -> tuple[dict, dict]:
        pose, arrays = self.pose.to_wire()
        params = {"checkpoint": self.checkpoint, "pose": pose}
        if self.substeps is not None:
            params["substeps"] = self.substeps
        params["camera"] = self.camera.to_wire()
        return _with_device(params, self.device), arrays


@dataclass(eq=False)
class WarmRequest(_Wire):
    checkpoints: tuple  # of paths
    op: ClassVar[str] = Op.WARM

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> WarmRequest:
        r = _Reader(cls._where(where), params, arrays)
        paths = params.get("checkpoints")
        if not isinstance(paths, list) or not all(isinstance(p, str) for p in paths):
            raise r.expected("checkpoints", "a list of checkpoint paths", paths)
        return cls(tuple(paths))

    def to_wire(self) -> tuple[dict, dict]:
        return {"checkpoints": list(self.checkpoints)}, {}


@dataclass(eq=False)
class BakeVolumeRequest(_Wire):
    """The NeRF at a pose on a voxel grid over `extent`: "nerf", "cage" (the posed cage's box) or an
    edit region's dict."""

    checkpoint: str
    pose: Pose = field(default_factory=RestPose)
    extent: Any = Extent.NERF  # Extent or an edit-region dict
    resolution: int = 256
    supersample: int = 1
    device: str | None = None
    op: ClassVar[str] = Op.BAKE_VOLUME

    @classmethod
    def from_wire(cls, params: dict, arrays: dict | None = None, where: str | None = None) -> BakeVolumeRequest:
        r = _Reader(cls._where(where), params, arrays)
        checkpoint = r.path("checkpoint", "the path of a NeRF checkpoint")
        extent = params.get("extent", "nerf")
        if isinstance(extent, dict):
            region_from_dict(extent, where=f"{r.where}: extent (the box to bake)")
        else:
            extent = r.choice("extent", Extent, "nerf")
        pose = pose_from_wire(params.get("pose"), r.arrays, r)
        if extent == Extent.CAGE and isinstance(pose, RestPose):
            raise r.error("extent", "cage needs a cage pose or a handles pose (the cage as posed)")
        try:
            resolution = check_resolution(params.get("resolution", 256))
        except EngineError as error:
            raise r.error("resolution", str(error)) from None
        return cls(
            checkpoint,
            pose,
            extent,
            resolution,
            r.integer("supersample", 1, minimum=1, what="a whole number >= 1"),
            r.device(),
        )

    def extent_value(self) -> Any:
        """What bend.volume.bake_box takes: "nerf", "cage" or an EditRegion."""
        if isinstance(self.extent, dict):
            return region_from_dict(self.extent, where="the box to bake")
        return str(self.extent)

    def to_wire(self) -> tuple[dict, dict]:
        pose, arrays = self.pose.to_wire()
        params = {
            "checkpoint": self.checkpoint,
            "pose": pose,
            "extent": self.extent if isinstance(self.extent, dict) else str(self.extent),
            "resolution": self.resolution,
            "supersample": self.supersample,
        }
        return _with_device(params, self.device), arrays


REQUESTS: dict[str, type] = {
    t.op: t
    for t in (
        InfoRequest,
        LoadRequest,
        ExtractRequest,
        CageRequest,
        TrainRequest,
        TrainingPreviewRequest,
        PrepareRequest,
        FirstSurfaceRequest,
        SolveRequest,
        RenderRequest,
        WarmRequest,
        BakeVolumeRequest,
    )
}


def check_embedding(tets: np.ndarray, tet_ids: np.ndarray, weights: np.ndarray) -> None:
    """EngineError unless a shared embedding fits the shared cage it names (checked when both are known)."""
    if len(tet_ids) != len(weights):
        raise EngineError(f"the embedding has {len(tet_ids)} tets for {len(weights)} weight rows")
    if len(tet_ids) and tet_ids.max() >= len(tets):
        raise EngineError(f"the embedding names tets outside the cage's 0..{len(tets) - 1}: rebuild the cage")
