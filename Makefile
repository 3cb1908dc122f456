# The README's commands. Every target bootstraps .venv first (scripts/bootstrap).
VENV ?= .venv
PY := $(VENV)/bin/python
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: all venv test lint demo bench bench-dense soak clean help

help:  ## list the targets
	@grep -E '^[a-z]+:.*##' $(MAKEFILE_LIST) | sed 's/:.*## /\t/'

venv:  ## create/refresh .venv (ROS 2 Jazzy wheels unless rclpy is already importable)
	@VENV=$(VENV) bash scripts/bootstrap

lint: venv  ## ruff (lint + format check) and mypy --strict on owl_core and msg_adapters
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

test: lint  ## lint, then the whole test suite (unit, bags, DDS integration, colcon build)
	$(PY) -m pytest

demo: venv  ## render a scenario, run the pipeline, evaluate, plot; writes results/
	$(PY) -m owl_ros.tools.demo

bench: venv  ## full benchmark: OWL vs the OpenCV baseline, timings and accuracy
	$(PY) -m owl_ros.tools.bench

bench-dense: venv  ## dense stage: r/|t|, confidence, time to contact, CPU per frame
	$(PY) -m owl_ros.tools.dense_bench --walk ../shared/data/realsense_walk

soak: venv  ## 10-minute looped replay through the live node: RSS and per-frame time
	$(PY) -m owl_ros.tools.soak

clean:  ## remove build products, results and the venv
	rm -rf $(VENV) build install log results .pytest_cache .ruff_cache .mypy_cache
	find . -name __pycache__ -prune -exec rm -rf {} +
