# The two commands of the README: `make demo` and `make test`. Both set up .venv when missing.
SHELL := /bin/bash
PY := .venv/bin/python
export PYTHONPATH := $(CURDIR)
export ROS_LOG_DIR ?= $(CURDIR)/log/ros
BAG ?=
OUT ?= out/demo

.PHONY: venv demo test bench clean

venv:
	@scripts/ensure_venv.sh

demo: venv
	$(PY) -m dpv_sensor.tools.demo --out $(OUT) $(if $(BAG),--bag $(BAG))

test: venv
	$(PY) -m pytest -q -ra test

bench: venv
	$(PY) -m dpv_sensor.tools.bench

clean:
	rm -rf build install log out .pytest_cache
