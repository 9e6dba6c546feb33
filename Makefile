# The two commands (see README): `make demo` runs the main job, `make test` runs the tests.
# Both do the setup first when it is missing or stale; `make setup` does only the setup.
SHELL := /bin/bash
ENV := source scripts/env.sh >/dev/null &&
PYTEST_ARGS ?= -n 2

.PHONY: setup demo test lint bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@$(ENV) ros_run home_robot_bringup demo

test: setup
	@$(ENV) python -m pytest $(PYTEST_ARGS)

lint: setup
	@$(ENV) ruff check .

clean:
	rm -rf build install log
