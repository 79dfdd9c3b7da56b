# Two commands do all the set-up on a fresh machine (see README):
#   make run    -> the paper's ring scenario end to end
#   make test   -> the test suite (CI runs `make lint` first)
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
SCENARIO ?= scenarios/ring_paper.toml
OUT    ?= runs/ring_paper

.PHONY: setup run test test-slow lint format bench clean

# setup.py, road/kernels.c, sumo/calls.c and sumo/libsumo_cxx.cpp: the optional compiled parts, built in place by the install.
$(VENV)/.installed: pyproject.toml constraints-cpu.txt setup.py macromicro_sumo/road/kernels.c macromicro_sumo/sumo/calls.c macromicro_sumo/sumo/libsumo_cxx.cpp
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# CPU torch first: a plain torch requirement would pull the CUDA build.
	$(PY) -m pip install --quiet -c constraints-cpu.txt "torch==2.13.0"
	# The optional extras too, so that the tests cover the Ray backend and Parquet export.
	$(PY) -m pip install --quiet -c constraints-cpu.txt -e ".[dev,ray,parquet]"
	touch $@

setup: $(VENV)/.installed

run: setup
	$(VENV)/bin/macromicro run $(SCENARIO) --out $(OUT)

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

test: setup
	$(VENV)/bin/pytest -q

test-slow: setup
	$(VENV)/bin/pytest -q -m slow

clean:
	rm -rf $(VENV) runs .pytest_cache
