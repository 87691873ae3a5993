# blender_nerf_deform: the two commands of the README, and their helpers.
#   make demo   set up .venv, then run the main job on the embedded default scene
#   make test   set up .venv, then run the whole test suite
#   make smoke  the extension zip in the bpy module of every supported Blender (tools/smoke_blender.py)
#   make lint   ruff: the lint rules and the formatting of pyproject.toml, on the whole tree

PYTHON ?= python3.11
VENV   := .venv
VPY    := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Extra arguments for pytest, e.g. `make test PYTEST_ARGS="-k engine -x"`.
PYTEST_ARGS ?=
# pytest-xdist workers (0: one process); a module's tests stay together in one worker.
TEST_WORKERS ?= 2

# make smoke: one venv per Blender release under $(SMOKE) (pins: addon_tests/smoke/), 5.0 is .venv's
# own bpy. Wheels are kept in $(SMOKE_WHEELS) (outside the clone: a fresh clone, as CI's, reuses
# them); `make smoke SMOKE_RELEASES="4.2 5.3"` runs some; SMOKE_ARGS go to tools/smoke_blender.py.
SMOKE          := .smoke
SMOKE_RELEASES ?= 4.2 4.5 5.0 5.2 5.3
SMOKE_WHEELS   ?= $(HOME)/.cache/blender_nerf_deform/smoke-wheels
PYTHON313      ?= env PYENV_VERSION=3.13.0 python3.13
SMOKE_ARGS     ?=
smoke_python    = $(if $(filter 5.0,$(1)),$(VPY),$(SMOKE)/bpy-$(1)/bin/python)

.PHONY: setup test demo extension smoke lint clean

setup: $(STAMP)

# Re-installs only when requirements.txt changed since the last install, so a
# second `make setup` with nothing changed is a no-op.
$(STAMP): requirements.txt blender_nerf_deform/engine/requirements.txt blender_nerf_deform/engine/requirements-cuda.txt
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found; Python 3.11 is required (Blender 4.2-5.0 ship 3.11)" >&2; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || { echo "error: $(PYTHON) is not Python 3.11" >&2; exit 1; }
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install --disable-pip-version-check -q -r requirements.txt
	@touch $(STAMP)

test: setup
	$(VPY) -m pytest addon_tests -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder $(PYTEST_ARGS)

lint: setup
	$(VPY) -m ruff check .
	$(VPY) -m ruff format --check .

demo: setup
	$(VPY) tools/demo.py

extension: setup
	$(VPY) tools/build_extension.py

smoke: setup $(foreach r,$(filter-out 5.0,$(SMOKE_RELEASES)),$(SMOKE)/bpy-$(r)/.installed)
	$(VPY) tools/smoke_blender.py $(foreach r,$(SMOKE_RELEASES),--release $(r)=$(call smoke_python,$(r))) $(SMOKE_ARGS)

# Blender 4.x ship Python 3.11 ($(PYTHON)), 5.1+ Python 3.13 ($(PYTHON313)). Installs from the wheel
# folder alone when it has every pinned wheel; downloads what is missing into it otherwise.
$(SMOKE)/bpy-%/.installed: addon_tests/smoke/requirements-bpy-%.txt
	@test -x $(SMOKE)/bpy-$*/bin/python || $(if $(filter 4.%,$*),$(PYTHON),$(PYTHON313)) -m venv $(SMOKE)/bpy-$*
	@mkdir -p $(SMOKE_WHEELS)
	@$(SMOKE)/bpy-$*/bin/python -m pip install -q --no-index --find-links $(SMOKE_WHEELS) -r $< 2>/dev/null \
	  || { echo "smoke: downloading the wheels of bpy $* into $(SMOKE_WHEELS)"; \
	       $(SMOKE)/bpy-$*/bin/python -m pip download -q -d $(SMOKE_WHEELS) -r $< \
	       && $(SMOKE)/bpy-$*/bin/python -m pip install -q --no-index --find-links $(SMOKE_WHEELS) -r $<; }
	@touch $@

clean:
	rm -rf build dist .pytest_cache
