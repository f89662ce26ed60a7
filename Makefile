# Two commands do all set-up on a fresh machine:
#   make demo   the whole stack on this machine: the frozen policy on a LIBERO-PRO task bare, under a
#               shipped harness, and that harness around a do-nothing policy, on the same seeds
#   make test   the default test suite (what CI runs)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.zetta-installed

.PHONY: setup proto demo demo-throughput up test test-slow test-all bench bench-sweep bench-harness bench-policy bench-sim results lint clean

setup: $(STAMP) proto $(VENV)/.zetta-validators $(VENV)/.zetta-interop

# One venv with everything; the stamp re-runs the install when pyproject.toml changes.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	$(PY) -m pip uninstall -q -y opencv-python-headless 2>/dev/null || true
	@command -v redis-server >/dev/null || { [ "$$(id -u)" = 0 ] && apt-get update -qq && apt-get install -y -qq redis-server; } || true
	touch $(STAMP)

# promtool, prometheus and docker-compose from Debian for tests/deploy (skipped there when missing).
$(VENV)/.zetta-validators: $(STAMP) deploy/tools/install-validators.sh
	bash deploy/tools/install-validators.sh $(VENV)
	touch $@

# LeRobot, openpi and Node.js libraries the interop tests drive (skipped there when missing).
$(VENV)/.zetta-interop: $(STAMP) scripts/install-interop.sh
	bash scripts/install-interop.sh $(VENV)
	touch $@

proto: $(STAMP)
	$(PY) scripts/gen_proto.py

demo: setup
	$(VENV)/bin/zetta up --demo

# The infrastructure demo: 16 concurrent LIBERO-Goal episodes, success, episodes/min, per-hop latency.
demo-throughput: setup
	$(VENV)/bin/zetta up --demo throughput

up: setup
	$(VENV)/bin/zetta up

# CI runs this (.ci/run): lint first, then the default suite.
test: setup lint
	$(PY) -m pytest -m "not slow and not gpu" -q

test-slow: setup
	$(PY) -m pytest -m "slow" -q

test-all: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) bench/bench_rollout.py

# The Zetta VLA: batch throughput, split vs monolithic under a 200 ms SLO, W8A8 vs float.
bench-sweep: setup
	$(VENV)/bin/zetta bench rollout

bench-harness: setup
	$(PY) bench/bench_harness.py

bench-policy: setup
	$(PY) bench/bench_policy.py

# docs/results/*.md from their results files (docs/results/README.md lists the commands that write those).
results: setup
	$(PY) scripts/gen_results.py

# Simulation: fast step vs env.step vs raw mj_step, slot create/reset, threads vs processes.
bench-sim: setup
	$(PY) bench/bench_sim.py

# The API (buf), errors and unused suppressions (ruff), types (mypy; scope in pyproject.toml).
lint: setup
	$(VENV)/bin/buf lint
	$(VENV)/bin/ruff check services clients bench scripts tests deploy
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) clients/python/zetta_wire/v1
