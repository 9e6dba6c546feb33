# The two commands (see README): `make demo` runs the main job, `make test` runs the tests.
# Both do the setup first when it is missing or stale; `make setup` does only the setup.
SHELL := /bin/bash
ENV := source scripts/env.sh >/dev/null &&
# 3 workers on CI's 2 cores: the real-process tests spend much of their time waiting on the simulated robot
# (5 min -> 4 min; at -n 2 the cores were busy 56 % of the time). GOMP_SPINCOUNT=0: torch's idle OpenMP
# workers sleep at once instead of spinning on cores the other workers need (a SLAM test beside a busy core:
# 22.7 -> 10.0 s)
PYTEST_ARGS ?= -n 3 --dist loadgroup

.PHONY: setup demo demo-explore test lint clean bench bench-object-query bench-decision-maker bench-voice bench-voice-stop bench-slam bench-web-stop \
	bench-slam-streaming setup-gpu bench-gpu gpu-wheels

setup:
	@bash scripts/setup.sh

demo: setup
	@$(ENV) ros_run home_robot_bringup demo

demo-explore: setup
	@$(ENV) ros_run home_robot_exploration demo_explore

test: setup
	@$(ENV) GOMP_SPINCOUNT=0 python -m pytest $(PYTEST_ARGS)

lint: setup
	@$(ENV) ruff check .

# Benchmarks print figures (and the ratio to the seed's method where there is one); minutes each.
# bench-voice-stop last: it exits 1 when a spoken stop was missed (a finding, reported after the others ran).
bench: bench-object-query bench-decision-maker bench-web-stop bench-voice bench-slam bench-slam-streaming bench-voice-stop

bench-object-query: setup
	@$(ENV) python bench/object_query_bench.py

bench-decision-maker: setup
	@$(ENV) python bench/decision_maker_cancel.py --trials 200

bench-web-stop: setup
	@$(ENV) python bench/web_stop.py --trials 100

bench-voice: setup
	@$(ENV) python bench/voice_latency.py

bench-voice-stop: setup
	@$(ENV) python bench/voice_stop_latency.py

bench-slam: setup
	@$(ENV) python bench/slam_synthetic.py

bench-slam-streaming: setup
	@$(ENV) python bench/slam_streaming.py

# CUDA machine (docs/slam.md "On a GPU"): no venv needed, the machine's CUDA torch is used (PYTHON=...).
# gpu-wheels runs where a package index is reachable and fills .whl/ for a machine without network.
gpu-wheels:
	@bash bench/gpu.sh --download

setup-gpu:
	@bash bench/gpu.sh --setup-only

bench-gpu:
	@bash bench/gpu.sh

clean:
	rm -rf build install log
