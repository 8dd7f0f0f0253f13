# Two commands from a fresh clone with only python3: `make scan` and `make test`.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: setup scan test lint clean

setup: $(STAMP)

# Re-install only when the pins or the package metadata change. Interface packages without a wheel
# (tf2_msgs, ur_dashboard_msgs, touchroller_interfaces) are built from interfaces/ only when the venv cannot
# import them (a ROS install or a built workspace can).
$(STAMP): requirements.txt setup.py setup.cfg package.xml $(wildcard interfaces/*/msg/*.msg interfaces/*/action/*.action)
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	@echo "Setting up $(VENV) (pinned versions from requirements.txt)..."
	@$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.txt
	@interfaces/build_missing.sh $(VENV)
	@$(VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	@touch $(STAMP)

scan: $(STAMP)
	$(VENV)/bin/touchroller scan

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

# Two workers (pytest-xdist), a file's tests on one worker so its module fixtures are made once; the longest
# test is handed out first (conftest.py). TEST_WORKERS=0 runs the suite in this process, one test at a time.
TEST_WORKERS ?= 2

test: $(STAMP) lint
	$(VENV)/bin/python -m pytest $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder)

clean:
	rm -rf $(VENV) build install log *.egg-info
