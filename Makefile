# The two commands a new user needs: `make demo` and `make test`. Both create .venv and install
# the project into it when that has not been done yet (or pyproject.toml changed since).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

CHROMIUM := /usr/bin/chromium

.PHONY: demo test test-fast test-extremes lint bench install clean browser

BENCH_STAMP := $(VENV)/.installed-bench

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

$(BENCH_STAMP): $(STAMP)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test,bench]'
	@touch $(BENCH_STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/operator-site demo

# The browser test needs Debian's chromium (and Mesa's llvmpipe, which draws its 3D view):
# installed here when we are root, else the test is skipped and says why.
browser:
	@if [ ! -x $(CHROMIUM) ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "make: installing Debian's chromium for the browser test"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	      chromium libgl1-mesa-dri >/dev/null) \
	      || echo "make: could not install chromium: the browser test will skip"; \
	  else echo "make: no $(CHROMIUM) and not root: the browser test will skip"; fi; \
	fi

# Test files are shared between TEST_WORKERS processes, each file's tests in one of them (their
# fixtures start work sites, namespaces and browsers per file). Most integration tests wait on
# real time, so two workers on two cores take about half the time of one.
TEST_WORKERS ?= 2

test: $(STAMP) browser
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile

# The unit tier: no processes, no network, no browser, nothing that takes seconds, and a tenth
# of each large property test's examples (tests/conftest.py: examples).
test-fast: $(STAMP)
	$(VENV)/bin/ruff check .
	TELEROBOT_TESTS=fast $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile \
	  -m "not integration and not browser and not slow"

# The nightly-sized property run: 25 times each property test's examples (5,000 for each of the
# simulator's and the deformation's extremes tests; tests/conftest.py: examples).
test-extremes: $(STAMP)
	TELEROBOT_TESTS=extremes $(PY) -m pytest -q tests/test_simulator_extremes.py tests/test_deform_extremes.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Every benchmark (`python -m bench NAME`, from the repository root); figures land in docs/bench/
# (JSON, CSV, PNG), then `python -m bench report` rewrites the summary at the top of
# docs/benchmarks.md from the JSON (the sections below it discuss them).
# e2e: E2E_SEEDS seeds per task, 100 by default (the work sites simulate 3× faster than real time
# where the machine keeps up; the 200 runs take over an hour); a quick look:
# `make bench E2E_SEEDS=10`.
E2E_SEEDS ?= 100
# trade: each user knob's values on each task, TRADE_SEEDS seeds a value (the defaults' runs
# shared).
TRADE_SEEDS ?= 5
# tasks: every shipped task file (examples/tasks/) on TASK_SEEDS seeded layouts.
TASK_SEEDS ?= 20
# latency: the corner task across an emulated link at 0, 500 and 1,000 ms round trips with 1 %
# loss, LATENCY_RUNS runs a point in real time (about a minute each).
LATENCY_RUNS ?= 20
bench: $(BENCH_STAMP)
	$(PY) -m bench sim --out docs/bench
	$(PY) -m bench step_gain --out docs/bench
	$(PY) -m bench deform --out docs/bench
	$(PY) -m bench control --out docs/bench
	$(PY) -m bench vision --out docs/bench
	$(PY) -m bench net --out docs/bench
	$(PY) -m bench safety --out docs/bench
	$(PY) -m bench linkcut --out docs/bench
	$(PY) -m bench fleet --out docs/bench
	$(PY) -m bench pacing --out docs/bench
	$(PY) -m bench latency --rtt-ms 0,500,1000 --loss 0.01 --runs $(LATENCY_RUNS) --out docs/bench
	$(PY) -m bench ui --out docs/bench
	$(PY) -m bench ui --dpr 0.5 --out docs/bench
	$(PY) -m bench lcp > docs/bench/lcp.json
	$(PY) -m bench program_sweeps --out docs/bench
	$(PY) -m bench e2e --seeds $(E2E_SEEDS) --time-scale 3 --out docs/bench
	$(PY) -m bench trade --seeds $(TRADE_SEEDS) --time-scale 3 --tasks corner --out docs/bench
	$(PY) -m bench trade --seeds $(TRADE_SEEDS) --time-scale 3 --tasks around-corner \
	  --out docs/bench/trade-around-corner
	$(PY) -m bench tasks --seeds $(TASK_SEEDS) --time-scale 3 --out docs/bench
	$(PY) -m bench report

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
