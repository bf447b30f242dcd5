# VisiBake: bootstrap, build, test.
#
#   make venv     .venv with Python 3.11, bpy 5.0.1 + requirements.txt (reinstalls only when they change)
#                 BPY=X.Y.Z: .venv-bpyX.Y.Z with that bpy and its Python (3.11 up to 5.0, 3.13 from 5.1)
#   make wheels   registry wheels bundled in the extension -> ./wheels/
#   make build    dist/<id>-<version>.zip with Blender's own extension tool, then validate it
#   make test     pytest (tests/core, tests/blender, tests/gpu); BPY=X.Y.Z against that Blender
#   make test-all the tests against every Blender of BPY_VERSIONS (what CI runs); test-others: all but the default
#   make test-core  tests/core only (no bpy, no extension build): seconds
#   make lint     ruff (pinned in requirements.txt; config in ruff.toml)
#   make demo     tools/visibake.py demo --out out/demo
#   make bench    benchmarks/run.py (BENCH_PROFILE=smoke|quick|outside|targets|standard|bounces|full), or accuracy.py (=accuracy), volume_*.py (=volume),
#                 brdf_vs_cycles.py (=appearance)
#   make clean    build/test outputs;  make distclean  also .venv and wheels

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test
.DELETE_ON_ERROR:

# The Blender the tests run against, as the bpy module: `make test BPY=5.3.0`. Each version
# gets a venv of its own; its Python follows from it (bpy 5.1 and later are built for
# Python 3.13, earlier ones for 3.11), and each Python has its own pinned requirements.
BPY_DEFAULT  := 5.0.1
BPY          ?= $(BPY_DEFAULT)
# What CI tests: the LTS lines, the default, and the newest bpy on the registry (raised deliberately).
BPY_VERSIONS := 4.2.23 4.5.15 5.0.1 5.3.0
python_of    = $(shell echo '$(1)' | awk -F. '{ print ($$1 > 5 || ($$1 == 5 && $$2 >= 1)) ? "3.13" : "3.11" }')
PYVER        := $(call python_of,$(BPY))
# pythonX.Y on the PATH, else pyenv's X.Y (installed but not selected on these machines).
PYTHON       ?= $(shell tools/find_python.sh $(PYVER))
VENV         := $(if $(filter $(BPY_DEFAULT),$(BPY)),.venv,.venv-bpy$(BPY))
REQUIREMENTS := $(if $(filter 3.11,$(PYVER)),requirements.txt,requirements-py$(subst .,,$(PYVER)).txt)
SITE         := $(VENV)/lib/python$(PYVER)/site-packages
PY        := $(VENV)/bin/python
PIP       := $(PY) -m pip --disable-pip-version-check --no-input
PIP_PROGRESS := $(if $(CI),--progress-bar off,)
PYTEST_FLAGS ?= -q -ra
# What `make test` runs: every test folder, or some of them (test-others narrows it).
TEST_PATHS   ?= tests

# Reinstall only when the *content* of the requirements or the bpy version changes (not an mtime).
REQ_KEY    := $(firstword $(shell cksum $(REQUIREMENTS) 2>/dev/null))
VENV_STAMP := $(VENV)/.installed-$(REQ_KEY)-bpy$(BPY)

# Single source of truth for the extension: blender_manifest.toml.
EXT_ID      := $(shell sed -n 's/^id *= *"\([^"]*\)".*/\1/p' blender_manifest.toml)
EXT_VERSION := $(shell sed -n 's/^version *= *"\([^"]*\)".*/\1/p' blender_manifest.toml)
ZIP         := dist/$(EXT_ID)-$(EXT_VERSION).zip
WHEEL_FILES := $(shell sed -n 's|^ *"\./\(wheels/[^"]*\.whl\)".*|\1|p' blender_manifest.toml)

# pip's --platform takes exact tags (no manylinux expansion), and one pip call picks a
# single file per package, so download once per Blender platform with its tag set.
WHEEL_PLATFORMS := linux-x64 windows-x64 macos-arm64
TAGS_linux-x64   := manylinux_2_28_x86_64 manylinux2014_x86_64
TAGS_windows-x64 := win_amd64
TAGS_macos-arm64 := macosx_13_0_arm64

# Blender's extension tool ships inside the bpy wheel (recursive: resolved after `venv`).
# The zip is built with the default Blender's tool and validated by each tested Blender's.
bpy_dir      = $(firstword $(wildcard $(1)/bpy/[0-9]*.[0-9]*))
BUILD_DIR    = $(call bpy_dir,.venv/lib/python3.11/site-packages)
BLENDER_EXT  = $(BUILD_DIR)/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS   = $(BUILD_DIR)/scripts/modules/_bpy_internal/extensions/tags.py
TEST_DIR     = $(call bpy_dir,$(SITE))

# Shared libraries bpy links against, and the Debian packages providing them
# (only installed when something is missing; a stock desktop/CI image has them).
BPY_APT_PACKAGES := libx11-6 libxrender1 libxfixes3 libxi6 libxxf86vm1 libxkbcommon0 \
                    libsm6 libice6 libgl1 libegl1 libgl1-mesa-dri

define apt_install
if command -v apt-get >/dev/null 2>&1; then \
  if [ "$$(id -u)" = 0 ]; then SUDO=; elif command -v sudo >/dev/null 2>&1; then SUDO="sudo -n"; \
  else echo "need root to apt-get install $(1)" >&2; exit 1; fi; \
  echo "apt-get install $(1)"; \
  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(1); \
else echo "missing system packages ($(1)) and no apt-get to install them" >&2; exit 1; fi
endef

.PHONY: venv default-venv wheels build build-platforms test test-built test-others test-all test-core lint demo bench clean distclean

venv: $(VENV_STAMP)

PYVER_CHECK := import sys; sys.exit(sys.version_info[:2] != tuple(map(int, "$(PYVER)".split("."))))

$(VENV_STAMP):
	@[ -n "$(PYTHON)" ] || { echo "Python $(PYVER) is required (bpy $(BPY) is built for it): install python$(PYVER) and re-run" >&2; exit 1; }
	@if ! $(PY) -c '$(PYVER_CHECK)' 2>/dev/null; then \
	  rm -rf $(VENV); echo "creating $(VENV) with $(PYTHON)"; \
	  if ! $(PYTHON) -m venv $(VENV); then \
	    rm -rf $(VENV); $(call apt_install,python$(PYVER)-venv); $(PYTHON) -m venv $(VENV); \
	  fi; \
	fi
	rm -f $(VENV)/.installed-*
	$(PIP) install $(PIP_PROGRESS) -r $(REQUIREMENTS) bpy==$(BPY)
	@missing=$$(ldd $(SITE)/bpy/__init__.so 2>/dev/null | grep 'not found' || true); \
	if [ -n "$$missing" ]; then echo "bpy needs:"; echo "$$missing"; $(call apt_install,$(BPY_APT_PACKAGES)); fi
	$(PY) -c 'import bpy; print("bpy", bpy.app.version_string, "OK")'
	@touch $@

# The Pythons of the supported Blenders: 3.11 (4.2 to 5.0) and 3.13 (5.1 and later).
WHEEL_PYTHONS := 3.11 3.13

wheels: default-venv
	@mkdir -p wheels
	@for f in wheels/*.whl; do [ -e "$$f" ] || continue; \
	  case " $(WHEEL_FILES) " in *" $$f "*) ;; *) echo "removing stale $$f (not in blender_manifest.toml)"; rm -f "$$f";; esac; \
	done
	@missing=; for f in $(WHEEL_FILES); do [ -f "$$f" ] || missing="$$missing $$f"; done; \
	if [ -n "$$missing" ]; then \
	  for plat in $(WHEEL_PLATFORMS); do \
	    case $$plat in \
	      linux-x64) tags="$(TAGS_linux-x64)";; windows-x64) tags="$(TAGS_windows-x64)";; macos-arm64) tags="$(TAGS_macos-arm64)";; \
	    esac; \
	    for py in $(WHEEL_PYTHONS); do \
	      echo "pip download wheels for $$plat, Python $$py ($$tags)"; \
	      $(BUILD_PIP) download -q --no-deps --only-binary=:all: --python-version $$py --implementation cp \
	        --abi cp$${py/./} $$(printf -- '--platform %s ' $$tags) --require-hashes -r requirements-wheels.txt -d wheels; \
	    done; \
	  done; \
	fi
	@status=0; for f in $(WHEEL_FILES); do \
	  [ -f "$$f" ] || { echo "missing $$f: listed in blender_manifest.toml but not downloaded (check requirements-wheels.txt and the TAGS_* platforms)" >&2; status=1; }; \
	done; [ $$status = 0 ] && echo "wheels: $(words $(WHEEL_FILES)) files present"

# The build always uses the default Blender's venv and extension tool.
BUILD_PY  := .venv/bin/python
BUILD_PIP := $(BUILD_PY) -m pip --disable-pip-version-check --no-input

default-venv:
	@$(MAKE) --no-print-directory venv BPY=$(BPY_DEFAULT)

build: default-venv wheels
	@test -f "$(BLENDER_EXT)" || { echo "blender_ext.py not found in the bpy wheel ($(BUILD_DIR))" >&2; exit 1; }
	@mkdir -p dist
	@rm -f $(ZIP)
	$(BUILD_PY) $(BLENDER_EXT) build --source-dir . --output-dir dist --valid-tags $(VALID_TAGS)
	$(BUILD_PY) $(BLENDER_EXT) validate --valid-tags $(VALID_TAGS) $(ZIP)

# One zip per platform (each with only its own wheels), for a smaller download.
build-platforms: build
	$(BUILD_PY) $(BLENDER_EXT) build --source-dir . --output-dir dist --valid-tags $(VALID_TAGS) --split-platforms
	@ls -l dist/*.zip

test: venv build
	@$(MAKE) --no-print-directory test-built

# The tests against the zip already built (test-others builds it once for every Blender).
# Then every skip of the run must be one tests/expected_skips.toml allows for this Blender
# (tools/check_skips.py; under CI=true, those allowed outside CI only fail too).
SKIP_REPORT := out/skips/bpy$(BPY).json
test-built: venv
	@test -f $(ZIP) || { echo "$(ZIP) is missing: run make build first" >&2; exit 1; }
	@if [ "$(VENV)" != .venv ]; then \
	  echo "validating $(ZIP) with bpy $(BPY)'s extension tool"; \
	  $(PY) $(TEST_DIR)/scripts/addons_core/bl_pkg/cli/blender_ext.py validate $(ZIP); \
	fi
	@rm -f $(SKIP_REPORT)
	$(PY) -m pytest $(TEST_PATHS) $(PYTEST_FLAGS) --skip-report=$(SKIP_REPORT)
	$(PY) tools/check_skips.py $(SKIP_REPORT)

# The other Blenders of BPY_VERSIONS (CI runs `make test` first, then these), each without
# what would repeat the default's run exactly:
# - tests/core never imports bpy (tests/core/test_layering.py): under a Blender with the
#   default's Python it runs the same code on the same pinned requirements, so it runs once
#   per Python line (3.11: the default; 3.13: 5.3.0), not once per Blender;
# - tests/blender/test_benchmark_smoke.py checks `make bench`, which runs the default Blender;
# - tests/blender/test_cli_cluster.py, under the default's Python: its Dask workers are plain
#   Python processes running core on the default's packages, and its Blender side is the CLI's
#   and the panel's bake, which the rest of tests/blender runs under every Blender.
# They run in two lanes at once, each line prefixed with its Blender: the Blenders with
# another Python than the default's (tests/core too: the longer runs), and those with the
# default's. A test run is mostly one busy thread (Blender's operators, Python), so on a
# 2-core CI machine two lanes take about the time of the longer one, not of both.
SAME_PYTHON_AS_DEFAULT := $(foreach v,$(BPY_VERSIONS),$(if $(filter $(call python_of,$(v)),$(call python_of,$(BPY_DEFAULT))),$(v)))
OTHERS_FLAGS := -p no:cacheprovider --ignore=tests/blender/test_benchmark_smoke.py
SAME_PYTHON_FLAGS := --ignore=tests/blender/test_cli_cluster.py

test-others: build
	@run_lane() { \
	  for version in "$$@"; do \
	    case " $(SAME_PYTHON_AS_DEFAULT) " in \
	      *" $$version "*) paths="tests/blender tests/gpu"; flags="$(SAME_PYTHON_FLAGS)"; \
	        why="the default's Python: tests/core and the cluster tests ran under the default";; \
	      *) paths=tests; flags=; why="its Python differs from the default's: tests/core runs too";; \
	    esac; \
	    echo "[bpy $$version] == $$paths ($$why; the benchmarks' smoke tests: default Blender only)"; \
	    started=$$(date +%s); \
	    $(MAKE) --no-print-directory test-built BPY=$$version TEST_PATHS="$$paths" \
	      PYTEST_FLAGS="$(PYTEST_FLAGS) $(OTHERS_FLAGS) $$flags" 2>&1 | sed -u "s/^/[bpy $$version] /" || return 1; \
	    echo "[bpy $$version] == passed in $$(( $$(date +%s) - started )) s"; \
	  done; \
	}; \
	other_python=; same_python=; \
	for version in $(filter-out $(BPY_DEFAULT),$(BPY_VERSIONS)); do \
	  case " $(SAME_PYTHON_AS_DEFAULT) " in *" $$version "*) same_python="$$same_python $$version";; \
	    *) other_python="$$other_python $$version";; esac; \
	done; \
	run_lane $$other_python & first=$$!; run_lane $$same_python & second=$$!; \
	status=0; wait $$first || status=1; wait $$second || status=1; \
	[ $$status = 0 ] && echo "== every other Blender passed" || { echo "== a Blender's tests failed (see its [bpy ...] lines)" >&2; exit 1; }

test-all: test test-others

# The core tests need no extension zip and never import bpy (tests/core/test_layering.py).
test-core: venv
	$(PY) -m pytest tests/core $(PYTEST_FLAGS)

lint: venv
	$(VENV)/bin/ruff check .

demo: venv build
	$(PY) tools/visibake.py demo --out out/demo

# BENCH_PROFILE=smoke|quick|outside|targets|standard|bounces|full (see benchmarks/run.py); results in benchmarks/results/.
# BENCH_PROFILE=accuracy: error against N per scene, one technique at a time (benchmarks/accuracy.py).
# BENCH_PROFILE=seams: seam stitching judged on renders of the baked lighting (benchmarks/seams.py).
# BENCH_PROFILE=volume: volume lighting against Monte Carlo and Cycles (benchmarks/volume_accuracy.py, volume_vs_cycles.py).
# BENCH_PROFILE=appearance: tile BRDFs against Cycles, and their speed (benchmarks/brdf_vs_cycles.py -> docs/appearance/).
# BENCH_PROFILE=lightfield: light fields of the baked demo, their speed and views against Cycles
#   (benchmarks/lightfield_vs_cycles.py -> docs/lightfield/).
# BENCH_PROFILE=scaleout: the demo baked by rows (traced, lit and gathered) on 1, 2 and 4 local Dask
#   workers against one process (benchmarks/scaleout.py; the workers import the checkout's core).
BENCH_PROFILE ?= quick
bench: venv
ifeq ($(BENCH_PROFILE),accuracy)
	$(PY) benchmarks/accuracy.py
else ifeq ($(BENCH_PROFILE),seams)
	$(PY) benchmarks/seams.py
else ifeq ($(BENCH_PROFILE),volume)
	$(PY) benchmarks/volume_accuracy.py
	$(PY) benchmarks/volume_vs_cycles.py
else ifeq ($(BENCH_PROFILE),appearance)
	$(PY) benchmarks/brdf_vs_cycles.py
else ifeq ($(BENCH_PROFILE),lightfield)
	$(PY) benchmarks/lightfield_vs_cycles.py
else ifeq ($(BENCH_PROFILE),scaleout)
	PYTHONPATH=$(CURDIR) $(PY) benchmarks/scaleout.py
else
	$(PY) benchmarks/run.py --profile $(BENCH_PROFILE)
endif

clean:
	rm -rf dist out .pytest_cache .hypothesis
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf .venv .venv-bpy* wheels
