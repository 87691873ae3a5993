#!/usr/bin/env python3
"""Check the layering rule of docs/ARCHITECTURE.md by reading imports from the source.

- `engine/` never imports Blender's modules (bpy and friends).
- `addon/` never imports torch, neither directly nor through an engine module
  it imports (or the packages above it, which Python runs first); and the
  engine modules it imports reach nothing but the standard library and numpy
  (all that Blender's own Python has besides bpy).
- No import cycle among the engine's modules, nor among the add-on's.
- The add-on's layers (ADDON_LAYERS): a module imports only from its own layer or lower ones.
- The plumbing holds no stage logic (docs/ARCHITECTURE.md, section 2): `engine/cli/` and
  `engine/service/` import no numerical library but numpy (no torch, numba,
  scipy, scikit-image, trimesh, libigl, pytetwild, PIL): the numbers are
  computed by the stage packages they call. And the stages never import the
  plumbing (`cli/`, `service/`): the dependency runs one way.

Every `import` statement counts, including those inside functions, so a lazy
import cannot slip past. Exits 1 and lists the violations when any is found.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

BLENDER_MODULES = {
    "bpy",
    "bpy_extras",
    "bmesh",
    "mathutils",
    "gpu",
    "gpu_extras",
    "bgl",
    "blf",
    "aud",
    "addon_utils",
    "bl_math",
    "idprop",
    "imbuf",
    "freestyle",
}
TORCH_MODULES = {"torch", "torchvision", "torchaudio", "functorch", "tinycudann"}
# What engine modules used by the add-on may import: Blender's Python has numpy and the stdlib.
ADDON_SAFE = set(sys.stdlib_module_names) | {"numpy"}
# Libraries that do a stage's work: the command line and the worker call stages instead.
STAGE_LIBRARIES = TORCH_MODULES | {"numba", "llvmlite", "scipy", "skimage", "trimesh", "igl", "pytetwild", "PIL"}
PLUMBING = ("cli", "service")
# The add-on's layers, bottom up: one sub-package of addon/ each (docs/ARCHITECTURE.md, "The add-on
# in layers"). A module imports only from its own layer or lower ones, also inside functions; api.py
# (the scripting API) and versioning.py sit on top, addon/__init__.py (registration) above everything.
ADDON_LAYERS = ("data", "worker", "capture", "train", "edit", "deform", "render", "export", "ui")
ADDON_TOP = ("api", "versioning")  # versioning.py: the repairs of older .blend files


def _module_name(package_root: Path, path: Path) -> str:
    parts = list(path.relative_to(package_root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, absolute module name) for every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                base = node.module or ""
            else:
                anchor = module.split(".") if is_package else module.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            found.append((node.lineno, base))
            # `from . import x` may import submodule x (only project modules can be reached that way).
            if node.level:
                found.extend((node.lineno, f"{base}.{alias.name}") for alias in node.names)
    return found


def import_graph(package_root: Path) -> dict[str, tuple[Path, list[tuple[int, str]]]]:
    graph = {}
    for path in sorted(package_root.rglob("*.py")):
        module = _module_name(package_root, path)
        graph[module] = (path, _imports(path, module))
    return graph


def _top(name: str) -> str:
    return name.split(".")[0]


def _with_parents(name: str, pkg: str) -> list[str]:
    """`pkg.a.b` and the packages Python imports first to get it: pkg.a, pkg (their __init__)."""
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(len(parts), 1, -1)] if name.startswith(pkg + ".") else [name]


def import_cycle(graph: dict, prefix: str) -> list[str] | None:
    """One cycle among the modules under `prefix` (each import also runs its parent packages), or None."""
    edges = {}
    for module, (_path, imports) in graph.items():
        if not module.startswith(prefix):
            continue
        targets = set()
        for _line, name in imports:
            for target in _with_parents(name, prefix.split(".")[0]):
                # A package's own __init__ running its parents is not a cycle back to itself.
                if (
                    target in graph
                    and target.startswith(prefix)
                    and target != module
                    and not module.startswith(target + ".")
                ):
                    targets.add(target)
        edges[module] = sorted(targets)
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in edges.get(m, ()):
            if state.get(n) == 1:
                return stack[stack.index(n) :] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (found := visit(m)):
            return found
    return None


def _addon_layer(module: str, addon: str, addon_layers) -> tuple[int, str] | None:
    """(rank, name) of the layer an add-on module belongs to, by its path: addon/<layer>/..., api.py
    on top; None for a module outside every layer."""
    parts = module[len(addon) + 1 :].split(".")
    if parts[0] in addon_layers:
        return addon_layers.index(parts[0]), parts[0]
    if len(parts) == 1 and parts[0] in ADDON_TOP:
        return len(addon_layers), parts[0]
    return None


def violations(package_root: Path, addon_layers=ADDON_LAYERS) -> list[str]:
    """Every breach of the rules above, one line each. `addon_layers` None: no layer order (a made-up
    package whose add-on modules are not laid out in layers, as in the checker's own tests)."""
    pkg = package_root.name
    graph = import_graph(package_root)
    problems = []

    for module, (path, imports) in graph.items():
        if module.startswith(f"{pkg}.engine"):
            for line, name in imports:
                if _top(name) in BLENDER_MODULES:
                    problems.append(f"{path}:{line}: engine imports {name} (engine/ must not import Blender modules)")

    engine = f"{pkg}.engine"
    cycle = import_cycle(graph, engine)
    if cycle:
        problems.append(f"{graph[cycle[0]][0]}: import cycle in engine/: {' -> '.join(cycle)}")
    reported = set()
    for module, (path, imports) in graph.items():
        part = module[len(engine) + 1 :].split(".")[0] if module.startswith(engine + ".") else ""
        for line, name in imports:
            if part in PLUMBING and _top(name) in STAGE_LIBRARIES:
                problems.append(
                    f"{path}:{line}: engine/{part}/ imports {name}: the command line and the worker "
                    "hold no stage logic (call a stage function of nerf/, geometry/ or bend/)"
                )
            target = name[len(engine) + 1 :].split(".")[0] if name.startswith(engine + ".") else ""
            if part and part not in PLUMBING + ("__main__",) and target in PLUMBING and (path, line) not in reported:
                reported.add((path, line))
                problems.append(
                    f"{path}:{line}: stage module {module} imports {name} "
                    "(stages never import engine/cli or engine/service)"
                )

    addon = f"{pkg}.addon"
    cycle = import_cycle(graph, addon)
    if cycle:
        problems.append(f"{graph[cycle[0]][0]}: import cycle in addon/: {' -> '.join(cycle)}")
    for module, (path, imports) in graph.items():
        if addon_layers is None or not module.startswith(addon + "."):
            continue
        here = _addon_layer(module, addon, addon_layers)
        if here is None:
            problems.append(
                f"{path}: {module} is in no layer: put it in one of addon/{{{','.join(addon_layers)}}}/ "
                "(tools/check_layering.py, ADDON_LAYERS)"
            )
            continue
        for line, name in imports:
            target = next((t for t in _with_parents(name, pkg) if t.startswith(addon + ".")), None)
            there = _addon_layer(target, addon, addon_layers) if target else None
            if there is not None and there[0] > here[0] and (path, line) not in reported:
                reported.add((path, line))
                problems.append(
                    f"{path}:{line}: {module} ({here[1]}) imports {target} ({there[1]}): "
                    "imports run from higher layers to lower ones only"
                )

    # A module Blender's Python lacks, reachable from addon/ through any chain of engine modules.
    def reaches_unsafe(module: str, seen: set[str]) -> list[str] | None:
        if module in seen or module not in graph:
            return None
        seen.add(module)
        for _line, imported in graph[module][1]:
            for name in _with_parents(imported, pkg):
                if name.startswith(pkg + ".") or name == pkg:
                    if not name.startswith(f"{pkg}.addon"):
                        chain = reaches_unsafe(name, seen)
                        if chain:
                            return [module] + chain
                elif _top(name) not in ADDON_SAFE:
                    return [module, name]
        return None

    for module, (path, imports) in graph.items():
        if not module.startswith(f"{pkg}.addon"):
            continue
        for line, name in imports:
            if _top(name) in TORCH_MODULES:
                problems.append(f"{path}:{line}: addon imports {name} (addon/ must not import torch)")
            elif not (name == pkg or name.startswith(pkg + ".")) and _top(name) not in ADDON_SAFE | BLENDER_MODULES:
                problems.append(f"{path}:{line}: addon imports {name}, which Blender's Python does not have")
            elif name.startswith(f"{pkg}.engine"):
                chain = next((c for n in _with_parents(name, pkg) if (c := reaches_unsafe(n, set()))), None)
                if chain and (path, line) not in reported:
                    reported.add((path, line))
                    problems.append(
                        f"{path}:{line}: addon imports {name}, which reaches {chain[-1]} "
                        f"(not in Blender's Python): {' -> '.join(chain)}"
                    )
    return problems


def main() -> int:
    root = Path(__file__).resolve().parent.parent / "blender_nerf_deform"
    problems = violations(root)
    for problem in problems:
        print(problem)
    print("layering: ok" if not problems else f"layering: {len(problems)} violation(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
