# The README's two commands: `make test` and `make demo`. Each creates .venv
# on first use and installs the pinned dependencies (constraints.txt).

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

# Network safety: ROS 2 discovery stays on this machine, in a domain of its
# own. Tests give every test its own ROS_DOMAIN_ID on top of this.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 73

.PHONY: all venv test lint typecheck unit demo bags clean

all: test

$(STAMP): setup.py setup.cfg constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[ros,dev]"
	@touch $(STAMP)

venv: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check selfcontra_ros test bench docs bags launch
	$(BIN)/ruff format --check selfcontra_ros test bench docs bags launch

typecheck: $(STAMP)
	$(BIN)/mypy selfcontra_ros

unit: $(STAMP)
	$(BIN)/python -m pytest -q

test: lint typecheck unit

# Sample bags from synthetic scenes (and from KITTI: make bags KITTI=path/to/kitti_odometry).
bags: $(STAMP)
	$(BIN)/python bags/make_bags.py --out bags $(if $(KITTI),--kitti $(KITTI))

DEMO_OUT ?= demo_out
demo: $(STAMP)
	$(BIN)/python -m selfcontra_ros.demo --out $(DEMO_OUT)

# Where the labeler's time goes per stage at KITTI size, windows 10 and 20 (bench/profile_labeler.py).
.PHONY: profile
profile: $(STAMP)
	$(BIN)/python bench/profile_labeler.py

clean:
	rm -rf $(VENV) build install log .pytest_cache .mypy_cache .ruff_cache $(DEMO_OUT)
