"""Shared by both halves of the suite: the repository on sys.path, Blender's user folders kept
private, and the session fixtures both use (imported by name, not with a star).

    engine/   the engine without Blender: no test there imports bpy
    addon/    the add-on in real headless Blender (the `bpy` module), factory settings reset
              around every test (addon/conftest.py)

Blender's user folders are pointed at a temporary directory before bpy is ever imported, so the
suite never reads or writes the developer's own Blender preferences or extensions.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

# Under pytest-xdist (`make test`: two workers on CI's two cores) every process the suite starts runs
# one compute thread (torch, numba, OpenMP; inherited by the workers, CLIs and Blender children):
# two workers each running torch's and numba's thread pools on two cores spin against each other,
# which made each test ~2.5x slower than alone (measured 2026-12-03). Set before torch is imported.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    for _name in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

# One numba kernel cache for every process of the suite (engine commands, workers, Blender's children,
# both xdist workers). Left to themselves the workers cache under each Blender user folder, so every
# fresh user folder (one per xdist worker, the demo's, ...) compiled the kernels again: ~30 s each.
# Kept in build/ between runs, as numba keeps its own cache beside the sources; a test of where a
# worker caches on its own (a farm node) drops the variable for its processes.
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parent.parent / "build" / "numba_cache"))

_user_resources = tempfile.mkdtemp(prefix="nerf_deform_blender_user_")
os.environ["BLENDER_USER_RESOURCES"] = _user_resources

from fixtures import REPO  # noqa: E402

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fixtures.floor_data import floor_nerf  # noqa: E402,F401  (a statue on a floor, rendered by Blender, trained)
from fixtures.trained import sphere_nerf  # noqa: E402,F401  (a small trained NeRF, session-scoped)

# The modules that take minutes, heaviest first (measured: a clean-clone `make test`,
# docs/benchmarks-history.md, "Test suite"): started first, so that the two xdist workers do not end
# with one of them running a long module alone. The Makefile passes --no-loadscope-reorder: by
# default xdist queues the modules with the most tests first, which put the floor NeRF's few tests
# (a 3-minute fixture) last.
SLOW_FIRST = (
    "engine/test_stretch_fidelity.py",
    "engine/test_region_floor.py",
    "addon/test_demo.py",
    "addon/test_bake_volume.py",
    "engine/test_worker_side_requests.py",
    "addon/test_worker_setup.py",
    "engine/test_geometry_cli.py",
    "engine/test_unbounded.py",
    "engine/test_hostile_input.py",
    "engine/test_nerf_train.py",
    "addon/test_train_nerf.py",
    "addon/test_animation_cli.py",
    "addon/test_training_preview.py",
    "addon/test_hostile_addon.py",
    "addon/test_worker.py",
    "addon/test_edit_region.py",
    "addon/test_build_cage.py",
)


def pytest_collection_modifyitems(session, config, items):
    def rank(item):
        path = item.path.as_posix()
        return next((i for i, name in enumerate(SLOW_FIRST) if path.endswith(name)), len(SLOW_FIRST))

    items.sort(key=rank)  # stable: within a module and among the rest, the collection order stays
