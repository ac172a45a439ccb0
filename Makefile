# Two commands for a fresh machine with only Python 3.11:  make demo   and   make test
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast venv clean colcon

venv: $(STAMP)

$(STAMP): requirements/runtime.txt requirements/train.txt requirements/test.txt
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) (set PYTHON=/path/to/python3.11)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements/runtime.txt -r requirements/train.txt -r requirements/test.txt
	# the package itself, editable and without downloads: .venv/bin/fpcc and .venv/bin/segmenter
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

## Start the node, replay the demo bag into it over DDS, record outputs, print a summary, write a PNG.
demo: $(STAMP)
	$(PY) -m fpcc_ros.cli demo --out demo_output

## The full test suite (what CI runs).
test: $(STAMP)
	$(PY) -m pytest -q

## Without the ROS integration tests (seconds).
test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not ros and not slow"

clean:
	rm -rf $(VENV) build install log demo_output .pytest_cache
