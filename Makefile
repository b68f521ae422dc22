# sceneforge — every target creates the virtual environment first when it is missing.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
DEMO   ?= demo
# where pip gets torch: empty = the default index; on a machine with no NVIDIA GPU where pip
# would take the CUDA build, TORCH_INDEX=https://download.pytorch.org/whl/cpu gets the CPU one.
# The index of the last install is remembered in $(TORCH_FILE): a later `make` keeps it, and a
# different TORCH_INDEX (`TORCH_INDEX=` for the default index) reinstalls torch from that one.
TORCH_FILE  := $(VENV)/.torch-index
TORCH_INDEX ?= $(shell cat $(TORCH_FILE) 2>/dev/null)

.DEFAULT_GOAL := help
.PHONY: help install demo test bench lint clean FORCE

help:  ## list the targets
	@grep -E '^[a-z]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-8s %s\n", $$1, $$2}'

# rewritten only when TORCH_INDEX differs from the last install's, so that it alone redoes the install
$(TORCH_FILE): FORCE
	@mkdir -p $(VENV)
	@if [ ! -f $@ ] || [ "$$(cat $@)" != "$(TORCH_INDEX)" ]; then printf '%s\n' "$(TORCH_INDEX)" > $@; fi

$(STAMP): pyproject.toml setup.py sceneforge/raytrace/_embree.cpp scripts/system-deps.sh $(TORCH_FILE)
	PYTHON=$(PYTHON) bash scripts/system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip setuptools wheel
	# torch first and pinned (README "Two commands": which build that is, and TORCH_INDEX); pip
	# keeps an installed torch==2.13.0 whatever the index, so a new index uninstalls it first
	$(if $(filter $(TORCH_FILE),$?),@echo "torch: installing from $(or $(TORCH_INDEX),the default index)"; \
	  $(PY) -m pip uninstall --quiet --yes torch 2>/dev/null || true)
	$(PY) -m pip install --quiet torch==2.13.0 $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(PY) -m pip install --quiet -e ".[all]"
	@$(PY) -c "from sceneforge.raytrace import default_backend as d; print('ray tracing engine:', d())"
	touch $(STAMP)

install: $(STAMP)  ## create .venv and install sceneforge with every extra

demo: $(STAMP)  ## the main job on the bundled toy houses (writes demo/)
	$(VENV)/bin/sceneforge houses inspect bundled:toy --preview $(DEMO)/previews
	$(VENV)/bin/sceneforge render bundled:toy $(DEMO)/toy.zarr --workers 2
	$(VENV)/bin/sceneforge validate $(DEMO)/toy.zarr
	$(VENV)/bin/sceneforge show $(DEMO)/toy.zarr --view 0 -o $(DEMO)/toy_view0.png --3d $(DEMO)/toy_view0.ply

test: $(STAMP)  ## run the test suite (no GPU, no network)
	$(PY) -m pytest -q -n 2

bench: $(STAMP)  ## run the benchmarks and print their figures
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

lint: $(STAMP)  ## static checks
	$(PY) -m pip install --quiet ruff
	$(VENV)/bin/ruff check sceneforge cli schemas tests benchmarks

clean:  ## remove the virtual environment and demo output
	rm -rf $(VENV) $(DEMO)
