# Two commands set up a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-dev
BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: demo test test-fast bench colcon-build clean

$(STAMP): requirements.txt requirements-dev.txt setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements-dev.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $@

$(BENCH_STAMP): $(STAMP) requirements-bench.txt
	$(BIN)/python -m pip install --quiet -r requirements-bench.txt
	@# open3d's wheel links libusb-1.0 (Debian libusb-1.0-0); without it its anchor is skipped
	@ldconfig -p | grep -q libusb-1.0 || { [ "$$(id -u)" = 0 ] && apt-get install -y -q libusb-1.0-0; } \
		|| echo "note: install libusb-1.0-0 for the open3d RANSAC anchor"
	touch $@

demo: $(STAMP)  ## simulate a UAV flight and run the whole job on it
	$(BIN)/lidar-obstacles demo

test: $(STAMP)  ## the whole test suite (live DDS tests and the colcon build included)
	$(BIN)/python -m pytest -q test

test-fast: $(STAMP)  ## unit tests only
	$(BIN)/python -m pytest -q -m "not slow" test

bench: $(BENCH_STAMP)  ## accuracy and speed against the anchors; writes benchmarks/results/
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) build install log out *.egg-info
