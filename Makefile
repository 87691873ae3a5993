# blender_nerf_deform: the two commands of the README, and their helpers.
#   make demo   set up .venv, then run the main job on the embedded default scene
#   make test   set up .venv, then run the whole test suite

PYTHON ?= python3.11
VENV   := .venv
VPY    := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Extra arguments for pytest, e.g. `make test PYTEST_ARGS="-k engine -x"`.
PYTEST_ARGS ?=
# pytest-xdist workers (0: one process); a module's tests stay together in one worker.
TEST_WORKERS ?= 2

.PHONY: setup test demo extension clean

setup: $(STAMP)

# Re-installs only when requirements.txt changed since the last install, so a
# second `make setup` with nothing changed is a no-op.
$(STAMP): requirements.txt blender_nerf_deform/engine/requirements.txt
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found; Python 3.11 is required (Blender 4.2-5.0 ship 3.11)" >&2; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || { echo "error: $(PYTHON) is not Python 3.11" >&2; exit 1; }
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install --disable-pip-version-check -q -r requirements.txt
	@touch $(STAMP)

test: setup
	$(VPY) -m pytest addon_tests -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

demo: setup
	$(VPY) tools/demo.py

extension: setup
	$(VPY) tools/build_extension.py

clean:
	rm -rf build dist .pytest_cache
