# The two commands of the README: `make demo` and `make test`. Both set up .venv when missing.
SHELL := /bin/bash
PY := .venv/bin/python
export PYTHONPATH := $(CURDIR)
export ROS_LOG_DIR ?= $(CURDIR)/log/ros
BAG ?=
OUT ?= out/demo
# `make demo BAG=run.mcap GT=seq_folder PARAMS="T_base_camera=[0,0,0,0,0,0,1]"` runs the demo on your own bag (see
# tools/demo.py); the image, camera_info and odometry topics are found by message type. IMAGE_TOPIC=,
# CAMERA_INFO_TOPIC= and ODOM_TOPIC= choose among several topics of one type.
IMAGE_TOPIC ?=
CAMERA_INFO_TOPIC ?=
ODOM_TOPIC ?=
GT ?=
PARAMS ?=
DEMO_ARGS ?=
BENCH_OUT ?= out/bench
BENCH_ARGS ?=
# make test runs the suite in this many pytest-xdist workers (a test file stays on one worker; 1 = no workers). Three
# on a 2-core machine: the node tests wait on DDS and on ticks for much of their time, and a third worker fills it
TEST_WORKERS ?= 3
# more pytest options for make test, e.g. PYTEST_ARGS=--durations=25
PYTEST_ARGS ?=

.PHONY: venv demo test bench clean

venv:
	@scripts/ensure_venv.sh

demo: venv
	$(PY) -m dpv_sensor.tools.demo --out $(OUT) $(if $(BAG),--bag $(BAG)) \
	  $(if $(IMAGE_TOPIC),--image-topic $(IMAGE_TOPIC)) $(if $(CAMERA_INFO_TOPIC),--camera-info-topic $(CAMERA_INFO_TOPIC)) \
	  $(if $(ODOM_TOPIC),--odom-topic $(ODOM_TOPIC)) $(if $(GT),--gt $(GT)) $(if $(PARAMS),--params $(PARAMS)) $(DEMO_ARGS)

test: venv
	$(PY) -m pytest -q -ra $(if $(filter-out 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile) $(PYTEST_ARGS) test

bench: venv
	$(PY) -m dpv_sensor.tools.bench --out $(BENCH_OUT) $(BENCH_ARGS)

clean:
	rm -rf build install log out .pytest_cache
