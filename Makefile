# Two commands (docs/INTERFACES.md section 7): `make demo` and `make test`; `make check` for
# the edit loop. Each creates .venv if missing and installs everything into it.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv test check demo bench figures clean

venv: $(STAMP)

# The robot package (setup.py: egovib_ros, what `pip install .` or colcon installs) and,
# beside it, the repository's research tools (research/: experiments, benchmarks, the demo;
# their commands join `egovib`).
$(STAMP): requirements-ros.txt requirements-dev.txt setup.py research/pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements-ros.txt -r requirements-dev.txt
	$(PY) -m pip install -q -e ".[cluster]" -e research/
	touch $(STAMP)

# Three suites. The node tests (ROS 2 processes on real-time streams: about one core over
# their 4 minutes, mostly waiting) run on two workers beside the tests without ROS 2
# processes (two workers, CPU-bound), each worker's DDS domains apart (test/conftest.py
# `ros_domain`); they pass beside `stress-ng --cpu 2`, and side by side the two suites take
# about as long as the other suite alone (2026-11-30, idle: the other suite 624 s beside the
# node suite, 636 s alone on a cold cache; the node suite alone 238 s). Their report follows
# the other suite's. Then the node tests marked `alone`,
# one at a time (a live calibrator needs a core of its own).
# The slowest of each are listed (--durations): where a faster suite starts. `--dist
# loadscope` keeps a module's tests on one worker: its module fixtures (a calibrated corpus,
# a gap table) are built once. One BLAS thread per worker: the workers already fill the
# two cores, and the gap baseline's many small per-bin solves run ~20x slower when OpenBLAS
# threads contend for them.
test: $(STAMP)
	export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1; nodes_log=$$(mktemp); \
	$(PY) -m pytest -q -p no:cacheprovider --durations=10 -n 2 -m "nodes and not alone" test \
		> $$nodes_log 2>&1 & nodes=$$!; \
	$(PY) -m pytest -q -p no:cacheprovider --durations=15 -n 2 --dist loadscope -m "not nodes" test; a=$$?; \
	wait $$nodes; b=$$?; cat $$nodes_log; rm -f $$nodes_log; \
	$(PY) -m pytest -q -p no:cacheprovider -m alone test; c=$$?; \
	test $$a -eq 0 && test $$b -eq 0 && test $$c -eq 0

# The edit loop: the fast tests (no node test, no test file marked `slow` in
# test/conftest.py; ruff among them, test/test_lint.py) on two workers.
check: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 \
	$(PY) -m pytest -q -p no:cacheprovider -n 2 -m "not nodes and not slow" test

demo: $(STAMP)
	$(VENV)/bin/egovib demo

bench: $(STAMP)
	$(VENV)/bin/egovib bench --json docs/bench.json --force

figures: $(STAMP)
	$(VENV)/bin/egovib figures --out docs --force

clean:
	rm -rf build install log .pytest_cache
