# Developer entry points. `make test` is what CI runs (.ci/run).

PY ?= python3
VENV = .venv
BIN = $(VENV)/bin
STAMP = $(VENV)/.installed
# `make run` needs only the drivers of its robot (the [robot] extra), not [dev]'s test and lint
# tools; [dev] includes [robot], so the [dev] install satisfies this stamp too.
RUN_STAMP = $(VENV)/.installed-run
BUILD_INPUTS = pyproject.toml setup.py $(wildcard temoto/core/_fast/*.py temoto/core/_fast/*.pxd)

# The main job: the simulated mobile manipulator (ODrive base + Dynamixel arm, simulators
# in-process) runs a mission: drive to a shelf, reach, drive back, arm home.
RUN_CMD = $(BIN)/python -m temoto.managers.robot --profile hw_profiles/sim_mobile_manipulator.yaml \
	--mission examples/missions/mobile_manipulation.graph.json --local
PYTEST_ARGS ?=

.PHONY: install sysdeps run lint test test-ros2 bench clean

# ROS 2 (docs/ros2.md): the temoto[ros2] wheels go into a venv of their own, whose python runs
# the bridge process and the tests' rclpy peers (TEMOTO_ROS2_PYTHON): the wheels' start-up hook
# re-executes every interpreter of the venv they are in, which $(VENV) is spared.
ROS2_VENV = .venv-ros2
ROS2_STAMP = $(ROS2_VENV)/.installed
ROS2_PYTHON = $(CURDIR)/$(ROS2_VENV)/bin/python

install: $(STAMP)

# Reinstall (editable, rebuilding the Cython extensions) whenever the build inputs change.
$(STAMP): $(BUILD_INPUTS)
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install -e '.[dev]'
	touch $@ $(RUN_STAMP)

$(RUN_STAMP): $(BUILD_INPUTS)
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	@echo "make run: installing TeMoto with the [robot] extra into $(VENV) (make test adds [dev])"
	$(BIN)/python -m pip install --quiet -e '.[robot]'
	touch $@

# System tools of the network tests (tests/fleet/test_netns_fleet.py), of the live view's
# browser test (tests/web), of the Graphviz renderings (tests/core/test_dot.py) and of the
# simulators as a TCP serial port (socat, tests/test_cli_sim.py), as
# command:package.
# Installed with apt-get only when running as root and one is missing; otherwise the missing
# ones are just reported (the tests then skip, or fail under CI).
SYSDEPS = ip:iproute2 nft:nftables chromium:chromium dot:graphviz socat:socat

sysdeps:
	@missing=""; \
	for dep in $(SYSDEPS); do \
		PATH="$$PATH:/usr/sbin:/sbin" command -v $${dep%%:*} >/dev/null || missing="$$missing $${dep#*:}"; \
	done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" -eq 0 ] && command -v apt-get >/dev/null; then \
		echo "sysdeps: installing$$missing"; \
		export DEBIAN_FRONTEND=noninteractive; \
		apt-get install -y -q $$missing || { apt-get update -q && apt-get install -y -q $$missing; }; \
	else \
		echo "sysdeps: missing$$missing (as root: apt-get install$$missing); the network tests skip (fail under CI)"; \
	fi

run: $(RUN_STAMP)
	@$(BIN)/python -m temoto --version
	$(RUN_CMD)

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python tools/gen_lcm_types.py --check

# The whole suite on the compiled kernels (which must have been built), then on the pure-Python
# kernels the tests that reach them (tests/core/ and tests/kernel_tests.txt, measured by
# tools/kernel_tests.py); TEMOTO_KERNEL_TESTS_ONLY=0 runs the whole suite in both passes.
# The ROS 2 tests run against rclpy peers from $(ROS2_VENV) (about a minute to install, once).
TEMOTO_KERNEL_TESTS_ONLY ?= 1
test: install lint sysdeps $(ROS2_STAMP)
	TEMOTO_REQUIRE_EXTENSIONS=1 TEMOTO_ROS2_PYTHON=$(ROS2_PYTHON) $(BIN)/python -m pytest $(PYTEST_ARGS)
	TEMOTO_NO_EXTENSIONS=1 TEMOTO_KERNEL_TESTS_ONLY=$(TEMOTO_KERNEL_TESTS_ONLY) \
		TEMOTO_ROS2_PYTHON=$(ROS2_PYTHON) $(BIN)/python -m pytest $(PYTEST_ARGS)

$(ROS2_STAMP): pyproject.toml
	test -x $(ROS2_VENV)/bin/python || $(PY) -m venv $(ROS2_VENV)
	$(PY) -c 'import tomllib; print("\n".join(tomllib.load(open("pyproject.toml", "rb"))["project"]["optional-dependencies"]["ros2"]))' \
		| $(ROS2_VENV)/bin/python -m pip install --quiet -r /dev/stdin
	touch $@

# Only the ROS 2 tests against rclpy peers (make test runs them too).
test-ros2: install $(ROS2_STAMP)
	TEMOTO_ROS2_PYTHON=$(ROS2_PYTHON) $(BIN)/python -m pytest tests/ros2 $(PYTEST_ARGS)

bench: install
	$(BIN)/python -m bench --quick --json bench-results.json

clean:
	rm -rf $(VENV) $(ROS2_VENV) build dist *.egg-info .pytest_cache .mypy_cache .ruff_cache .hypothesis \
		.coverage .coverage.* htmlcov
	find . -path ./.git -prune -o -type d -name __pycache__ -prune -exec rm -rf {} +
	find temoto -name '*.so' -delete 2>/dev/null || true
	rm -f temoto/core/_fast/*.c
