# thermognn — one command for the whole pipeline (`make demo`), one for the tests (`make test`).
# Both run `setup` first, which is idempotent.

SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
SUDO  := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
DEB_PKGS := python3-dolfinx python3-gmsh python3-meshio python3-h5py python3-venv
STAMP := $(VENV)/.thermognn-installed
DEMO_DIR ?= runs/demo

.PHONY: setup demo test test-fast bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@missing=""; for p in $(DEB_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing; \
	fi
	@[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --upgrade "pip>=23"
	@# numpy pinned to Debian's own build (dolfinx and h5py are compiled against it; never numpy 2)
	$(PY) -m pip install -q "numpy==$$(/usr/bin/python3 -c 'import numpy; print(numpy.__version__)')" \
	  "torch==2.13.0" torch-geometric typer "hydra-core>=1.3" rich pytest pytest-xdist matplotlib tensorboard
	$(PY) -m pip install -q --no-deps -e .
	@$(PY) -c "import numpy, dolfinx, torch, torch_geometric, h5py, meshio; assert numpy.__version__ < '2', numpy.__version__"
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/thermognn demo --out $(DEMO_DIR)

# one pytest worker a CPU core (pytest-xdist); a worker free takes tests queued on a busy one, so
# the few long pipeline tests run beside the many short ones. PYTEST_WORKERS=0 runs in one process.
# The 15 slowest tests are listed at the end.
PYTEST_WORKERS ?= auto
test: setup
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist worksteal --durations=15

test-fast: setup
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist worksteal -m "not slow"

# Speed-and-accuracy figures (printed, never asserted). Each script's docstring says what it measures.
bench: setup
	$(PY) benchmarks/fe_cost.py
	$(PY) benchmarks/fe_convergence.py
	$(PY) benchmarks/train_step_speed.py
	$(PY) benchmarks/serve_bench.py --seconds 60

clean:
	rm -rf runs outputs .pytest_cache
