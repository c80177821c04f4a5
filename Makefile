# xmetro_ros — two commands do everything on a fresh machine: `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.xmetro-setup-stamp
SETUP_INPUTS := pyproject.toml setup.py CMakeLists.txt package.xml $(wildcard msg/*.msg srv/*.srv action/*.action) \
                tools/setup.sh tools/constraints.txt tools/build-requirements.txt \
                $(wildcard vendor/tf2_msgs/CMakeLists.txt vendor/tf2_msgs/package.xml vendor/tf2_msgs/*.yaml \
                           vendor/tf2_msgs/msg/*.msg vendor/tf2_msgs/srv/*.srv vendor/tf2_msgs/action/*.action)
# Everything that starts a DDS participant runs in a private network namespace when root (tools/netns_run).
NETNS := tools/netns_run
PYTEST_ARGS ?=
# Small (N,3)@(3,3) products are ~100x slower with OpenBLAS's threads on a busy 2-core machine.
export OPENBLAS_NUM_THREADS := 1
# Localhost-only DDS is an opt-in of our tests, demo and benchmarks (the shipped node honours the caller's DDS
# environment): every process started from here, and its children, applies it (xmetro_ros/ros/dds_env.py).
export XMETRO_LOCALHOST_ONLY := 1

.PHONY: setup lint test demo bench clean

setup: $(STAMP)

$(STAMP): $(SETUP_INPUTS)
	bash tools/setup.sh
	@touch $(STAMP)

# ruff (style, likely bugs, docstrings of public API) and mypy (types: our code clean; pyproject.toml lists the
# third-party packages without type information).
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

# pytest's exit code 5 (nothing collected) means a broken suite: it fails like any other error.
test: setup lint
	@rc=0; $(NETNS) $(PY) -m pytest -q -p no:cacheprovider $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests"; fi; exit $$rc

demo: setup
	$(NETNS) $(VENV)/bin/xmetro demo

bench: setup
	$(NETNS) $(PY) bench/run_all.py

clean:
	rm -rf build out .pytest_cache .ruff_cache tf2_msgs xmetro_ros/msg xmetro_ros/srv xmetro_ros/action xmetro_ros/config xmetro_ros/*.so
