# The README's two commands: `make test` and `make demo`. Each creates .venv
# on first use and installs the pinned dependencies (constraints.txt).
# `make test-jazzy` does the same in .venv-jazzy with ROS 2 Jazzy's wheels.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

# Network safety: ROS 2 discovery stays on this machine, in a domain of its
# own. Tests give every test its own ROS_DOMAIN_ID on top of this.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 73
# Ray (the [cluster] extra, `selfcontra batch`) reports usage statistics to the internet unless told not to.
export RAY_USAGE_STATS_ENABLED := 0

.PHONY: all venv venv-jazzy test test-jazzy lint typecheck unit demo bags clean

all: test

# opencv-contrib-python-headless and plain opencv-python(-headless) write the same
# cv2 package, so a venv made before the switch to contrib loses the plain one,
# and the contrib one with it (uninstalling the plain one deleted its cv2 files);
# the install below puts contrib back whole. A fresh venv never had either.
drop_plain_opencv = @if $(1)/python -m pip show --quiet opencv-python-headless opencv-python >/dev/null 2>&1; then \
	$(1)/python -m pip uninstall --quiet --yes opencv-python-headless opencv-python opencv-contrib-python-headless; fi

# --no-compile: Python writes each .pyc on first import; compiling all of SciPy & co.
# up front is a third of the install time.
$(STAMP): setup.py setup.cfg constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(call drop_plain_opencv,$(BIN))
	$(BIN)/python -m pip install --quiet --no-compile -c constraints.txt -e ".[ros,dev,cluster]"
	$(BIN)/python -m pip check
	@touch $(STAMP)

venv: $(STAMP)

# ROS 2 Jazzy (Fast DDS 2.14) in a venv of its own. Kilted's and Jazzy's wheels
# share names (ros-rclpy 9.x / 7.x, ros-rcl, ...), so one venv never holds both:
# constraints.txt comes without its ros- lines (Kilted's pins), and `pip check`
# fails an install that mixed them.
JAZZY_VENV := .venv-jazzy
JAZZY_BIN := $(JAZZY_VENV)/bin
JAZZY_STAMP := $(JAZZY_VENV)/.installed

$(JAZZY_STAMP): setup.py setup.cfg constraints.txt constraints-jazzy.txt
	@test -x $(JAZZY_BIN)/python || $(PYTHON) -m venv $(JAZZY_VENV)
	$(JAZZY_BIN)/python -m pip install --quiet --upgrade pip
	$(call drop_plain_opencv,$(JAZZY_BIN))
	sed '/^ros-/d' constraints.txt > $(JAZZY_VENV)/constraints-without-ros.txt
	$(JAZZY_BIN)/python -m pip install --quiet --no-compile -c $(JAZZY_VENV)/constraints-without-ros.txt \
		-c constraints-jazzy.txt -e ".[ros-jazzy,dev]"
	$(JAZZY_BIN)/python -m pip check
	@touch $(JAZZY_STAMP)

venv-jazzy: $(JAZZY_STAMP)

# Only what depends on the distribution runs twice: mypy against Jazzy's rclpy and the ROS tests.
test-jazzy: $(JAZZY_STAMP)
	$(JAZZY_BIN)/mypy --cache-dir .mypy_cache-jazzy selfcontra_ros
	$(JAZZY_BIN)/python -m pytest -q -p no:cacheprovider test/ros

lint: $(STAMP)
	$(BIN)/ruff check selfcontra_ros test bench docs bags launch
	$(BIN)/ruff format --check selfcontra_ros test bench docs bags launch

typecheck: $(STAMP)
	$(BIN)/mypy selfcontra_ros

unit: $(STAMP)
	$(BIN)/python -m pytest -q

# On a fresh checkout numba compiles the package's kernels (those of every feature set) for about a minute
# (selfcontra_ros/warmup.py); it does so on the second core while ruff and mypy run, and the tests load the
# kernels from numba's on-disk cache. A failing lint, type check or warm-up still fails the target, after the other has ended.
test: $(STAMP)
	@$(BIN)/python -c "from selfcontra_ros.confidence.constants import FEATURE_SETS; from selfcontra_ros.warmup import warm_up; warm_up(tuple(FEATURE_SETS))" & \
	warm=$$!; $(MAKE) --no-print-directory lint typecheck; checks=$$?; \
	wait $$warm || { echo "make test: the numba warm-up failed"; exit 1; }; exit $$checks
	$(MAKE) --no-print-directory unit

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
	rm -rf $(VENV) $(JAZZY_VENV) build install log .pytest_cache .mypy_cache .mypy_cache-jazzy .ruff_cache $(DEMO_OUT)
