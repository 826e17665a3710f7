# heartcv — the two commands: `make test` and `make demo` (both create .venv on first use).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The torch that the `kornia` extra (`heartcv measure --backend kornia`) runs on, installed before the project so
# that the extra finds it. Here pip's find-links hold a CPU wheel of this version; from PyPI on Linux the same spec
# is the multi-gigabyte CUDA build. Point it at the build you want: a wheel file, or e.g.
# `make test TORCH='torch --index-url https://download.pytorch.org/whl/cpu'`.
TORCH ?= torch==2.13.0

.PHONY: test test-slow test-gpu demo demo-invivo phantom-blind phantom95 heart-ramp bench clean-venv fuzz calibrate-real measure-real

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(TORCH)
	$(PY) -m pip install -q -e '.[dev,kornia]'
	# the imports of the editable install must resolve (heartcv.tracker, heartcv.cli are mapped folders)
	cd /tmp && $(abspath $(PY)) -c "import heartcv.tracker.files, heartcv.cli.main"
	touch $(STAMP)

# The tests run in TEST_JOBS processes (pytest-xdist), one test file per process at a time so that a file's shared
# fixtures are built once: by default one per core, at most 4 (each process holds up to ~1.4 GB); TEST_JOBS=1 runs
# them in this process, in file order.
TEST_JOBS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; echo $$n)
XDIST = $(if $(filter-out 0 1,$(TEST_JOBS)),-n $(TEST_JOBS) --dist loadfile,-p no:xdist)

# lint first (ruff: pycodestyle, pyflakes, bugbear, import order; pyproject.toml [tool.ruff]), then the fast tests
test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q $(XDIST)

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow $(XDIST) || [ $$? -eq 5 ]  # exit 5: no slow test collected yet

# the kornia backend on a CUDA device (skipped, with the reason, where torch sees none)
test-gpu: $(STAMP)
	$(PY) -m pytest -q -rs -m cuda

demo: $(STAMP)
	$(MAKE) -C sample_sequences demo PY=$(abspath $(PY))

# the second rendered scene of issue 15 (95 bpm, another patch, E 2.5x, respiration, an instrument; reuses the
# demo's calibration): sample_sequences/work/phantom95_scene/report/
phantom95: $(STAMP)
	$(MAKE) -C sample_sequences phantom95 PY=$(abspath $(PY))

# the demo's phantom with its recorded pressure ignored (issue 16): GE with the estimated input against the GE with
# the pressure, sample_sequences/work/phantom_blind/report/
phantom-blind: $(STAMP)
	$(MAKE) -C sample_sequences phantom-blind PY=$(abspath $(PY))

# a heart that speeds up from 72 to 96 bpm, its pressure ignored (issue 16): the GE's sampled heart rate against the
# KF's held one, sample_sequences/work/heart_ramp/report/
heart-ramp: $(STAMP)
	$(MAKE) -C sample_sequences heart-ramp PY=$(abspath $(PY))

# the real beating heart without calibration or pressure (issue 16): sample_sequences/work/invivo/report/; another
# recording of rectified stereo pairs with `make demo-invivo INVIVO=DIR` (see sample_sequences/Makefile for its
# geometry and frame rate variables)
demo-invivo: $(STAMP)
	$(MAKE) -C sample_sequences demo-invivo PY=$(abspath $(PY)) $(if $(INVIVO),INVIVO=$(abspath $(INVIVO))) \
		$(if $(WORK),WORK=$(abspath $(WORK))) $(if $(IV_RIG),IV_RIG=$(abspath $(IV_RIG)))

bench: $(STAMP)
	$(PY) -m benchmarks all

fuzz: $(STAMP)
	HEARTCV_FUZZ_REPORT=fuzz-report.json $(PY) -m pytest -q -m slow tests/test_fuzz_readers.py

# a real rig nobody here made: caliscope's 4 unsynchronised webcams and its inverted ChArUco board
# (../shared/data/caliscope_4cam_charuco); rig file, COLMAP/Kalibr exports and a report under sample_sequences/work
CALISCOPE := ../shared/data/caliscope_4cam_charuco
CS_OUT := sample_sequences/work/caliscope
calibrate-real: $(STAMP)
	mkdir -p $(CS_OUT)
	$(PY) -m heartcv.cli.main target --type charuco --squares 4x5 --square-mm 54 --marker-mm 40.5 \
		--dict DICT_4X4_1000 --inverted -o $(CS_OUT)/board.yaml
	$(PY) -m heartcv.cli.main calibrate $(CALISCOPE)/calibration/extrinsic --target $(CS_OUT)/board.yaml \
		-o $(CS_OUT)/rig.yaml --report $(CS_OUT)/report --json > $(CS_OUT)/calibrate.json
	$(PY) -m heartcv.cli.main rig import $(CALISCOPE)/camera_array.toml -o $(CS_OUT)/caliscope.yaml
	$(PY) -m heartcv.cli.main calibrate $(CALISCOPE)/calibration/extrinsic --target $(CS_OUT)/board.yaml \
		-o $(CS_OUT)/rig_held.yaml --intrinsics $(CS_OUT)/caliscope.yaml --hold all

clean-venv:
	rm -rf $(VENV)

# the real in-vivo beating heart (../shared/data/hamlyn_invivo_heart, 300 rectified 360x288 stereo pairs, no
# calibration): rig from the rectified geometry, the sparse and dense measurement with an overlay, and the
# acceptance tests of issue 14 (sample_sequences/work/measure_real; demo-invivo keeps its own folder)
IV := ../shared/data/hamlyn_invivo_heart
IV_OUT := sample_sequences/work/measure_real
measure-real: $(STAMP)
	mkdir -p $(IV_OUT)
	$(PY) -m heartcv.cli.main rig rectified --image-size 360x288 --focal-px 390 --baseline-m 0.0055 -o $(IV_OUT)/rig.yaml
	$(PY) -m heartcv.cli.main measure $(IV) --rig $(IV_OUT)/rig.yaml -o $(IV_OUT)/measurements.npz --fps 25 \
		--overlay $(IV_OUT)/overlay --json
	$(PY) -m heartcv.cli.main measure $(IV) --rig $(IV_OUT)/rig.yaml -o $(IV_OUT)/dense.npz --fps 25 --dense --json
	$(PY) -m pytest -q -m slow tests/cli/test_measure_endoscope.py
