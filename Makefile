# Two commands do all the set-up on a fresh machine:
#   make demo   creates .venv, installs submapslam, generates a synthetic loop world, runs it
#   make test   creates .venv, installs submapslam with test tools, runs the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo test lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/submapslam demo --out demo_out

test: $(STAMP)
	$(VENV)/bin/ruff check submapslam datasets_synth tools tests
	$(VENV)/bin/pytest -n auto --dist loadfile --durations=15

bench: $(STAMP)
	$(PY) tools/bench_pipeline.py

clean:
	rm -rf demo_out .pytest_cache build *.egg-info
