"""The worker session: what Blender gave this worker, kept under content keys, and what is built from it.

Blender sends a rest cage, a surface embedding or a set of handle regions once
(docs/ARCHITECTURE.md, "The worker session"); later requests name them by key. Each slot
keeps its few newest entries (a scene with several NeRFs, or an edit going back
and forth, reuses them); what is derived from them (the cage's ray bender, the
ARAP factorization of a set of regions) is cached by the same keys, so a frame
that changes only the pose pays for nothing else. Content is validated here,
once, before any stage (or numba kernel) sees it.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..errors import EngineError
from ..geometry.poses import check_coordinates
from .registry import Job, Missing

# slot → {array name: (dims, kind)}: dims -1 = any length; kind "f" finite float, "i" integer.
SLOTS = {
    "cage": {"vertices": ((-1, 3), "f"), "tets": ((-1, 4), "i")},
    "embedding": {"tet_ids": ((-1,), "i"), "weights": ((-1, 4), "f")},
    "regions": {
        "handle_index": ((-1,), "i"),
        "handle_counts": ((-1,), "i"),
        "pin_index": ((-1,), "i"),
        "cage_pin_index": ((-1,), "i"),
    },
}
# Arrays a slot may go without: cage vertices pinned at an edit region's cut (none without a cut).
OPTIONAL = {"regions": {"cage_pin_index"}}
KEEP = 4  # entries per slot, and per kind of derived object


def _checked(slot: str, name: str, array: np.ndarray) -> np.ndarray:
    dims, kind = SLOTS[slot][name]
    a = np.asarray(array)
    if a.ndim != len(dims) or any(d not in (-1, n) for d, n in zip(dims, a.shape)):
        raise EngineError(f"{slot} {name} must have shape {tuple('N' if d == -1 else d for d in dims)}, got {a.shape}")
    if kind == "f":
        if not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
            raise EngineError(f"{slot} {name} must be finite floats ({a.dtype} given, or NaN/inf inside)")
        return np.ascontiguousarray(a, dtype=np.float64)
    if not np.issubdtype(a.dtype, np.integer) or (a.size and a.min() < 0):
        raise EngineError(f"{slot} {name} must be non-negative integers, got {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.int64)


def _validate(slot: str, arrays: dict) -> dict:
    out = {name: _checked(slot, name, arrays[name]) for name in SLOTS[slot] if name in arrays}
    missing = sorted(set(SLOTS[slot]) - set(out) - OPTIONAL.get(slot, set()))
    if missing:
        raise EngineError(f"{slot} sent without {', '.join(missing)}")
    if slot == "cage":
        check_coordinates(out["vertices"], "the rest cage")
        if len(out["tets"]) == 0:
            raise EngineError("the cage has no tets")
        if out["tets"].max() >= len(out["vertices"]):
            raise EngineError(f"cage tets index vertices outside 0..{len(out['vertices']) - 1}")
    return out


class Session:
    def __init__(self):
        self._content: dict[str, OrderedDict[str, dict]] = {slot: OrderedDict() for slot in SLOTS}
        self._derived: dict[str, OrderedDict[tuple, object]] = {}

    def shared(self, job: Job, *slots: str) -> dict[str, tuple[str, dict]]:
        """{slot: (key, arrays)} for the slots a request names, stored first when it carries them."""
        keys = job.params.get("shared") or {}
        found, missing = {}, []
        for slot in slots:
            key = keys.get(slot)
            if not isinstance(key, str) or not key:
                raise EngineError(f"request {job.op!r} names no {slot} (params['shared'][{slot!r}])")
            prefix = f"{slot}."
            sent = {name[len(prefix) :]: a for name, a in job.arrays.items() if name.startswith(prefix)}
            store = self._content[slot]
            if sent:
                store[key] = _validate(slot, sent)
                while len(store) > KEEP:
                    store.popitem(last=False)
            if key not in store:
                missing.append(slot)
                continue
            store.move_to_end(key)
            found[slot] = (key, store[key])
        if missing:
            raise Missing(missing)
        return found

    def derived(self, kind: str, key: tuple, build, keep: int = KEEP):
        """The object `build()` made for `key` (content keys and whatever else it depends on), made once;
        the `keep` newest of a kind are kept."""
        cache = self._derived.setdefault(kind, OrderedDict())
        if key not in cache:
            cache[key] = build()
            while len(cache) > keep:
                cache.popitem(last=False)
        cache.move_to_end(key)
        return cache[key]

    def has(self, kind: str, key: tuple) -> bool:
        return key in self._derived.get(kind, ())

    def drop(self, kind: str) -> None:
        """Forget every derived object of a kind (e.g. ray benders of a checkpoint that changed)."""
        self._derived.pop(kind, None)


SESSION = Session()
