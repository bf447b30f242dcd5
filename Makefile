# VisiBake: bootstrap, build, test.
#
#   make venv     .venv with Python 3.11 + requirements.txt (reinstalls only when it changes)
#   make wheels   registry wheels bundled in the extension -> ./wheels/
#   make build    dist/<id>-<version>.zip with Blender's own extension tool, then validate it
#   make test     pytest (tests/core, tests/blender, tests/gpu)
#   make test-core  tests/core only (no bpy, no extension build): seconds
#   make lint     ruff (pinned in requirements.txt; config in ruff.toml)
#   make demo     tools/visibake.py demo --out out/demo
#   make bench    benchmarks/run.py (BENCH_PROFILE=smoke|quick|standard|bounces|full)
#   make clean    build/test outputs;  make distclean  also .venv and wheels

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test
.DELETE_ON_ERROR:

PYTHON311 ?= python3.11
VENV      := .venv
PY        := $(VENV)/bin/python
PIP       := $(PY) -m pip --disable-pip-version-check --no-input
PIP_PROGRESS := $(if $(CI),--progress-bar off,)
PYTEST_FLAGS ?= -q -ra

# Reinstall only when the *content* of requirements.txt changes (not its mtime).
REQ_KEY    := $(firstword $(shell cksum requirements.txt 2>/dev/null))
VENV_STAMP := $(VENV)/.installed-$(REQ_KEY)

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
BPY_DIR      = $(firstword $(wildcard $(VENV)/lib/python3.11/site-packages/bpy/[0-9]*.[0-9]*))
BLENDER_EXT  = $(BPY_DIR)/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS   = $(BPY_DIR)/scripts/modules/_bpy_internal/extensions/tags.py

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

.PHONY: venv wheels build test test-core lint demo bench clean distclean

venv: $(VENV_STAMP)

$(VENV_STAMP):
	@command -v $(PYTHON311) >/dev/null 2>&1 && $(PYTHON311) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null \
	  || { echo "Python 3.11 is required (bpy 5.0.1 is built for it): install python3.11 and re-run" >&2; exit 1; }
	@if ! $(PY) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then \
	  rm -rf $(VENV); echo "creating $(VENV) with $$(command -v $(PYTHON311))"; \
	  if ! $(PYTHON311) -m venv $(VENV); then \
	    rm -rf $(VENV); $(call apt_install,python3.11-venv); $(PYTHON311) -m venv $(VENV); \
	  fi; \
	fi
	rm -f $(VENV)/.installed-*
	$(PIP) install $(PIP_PROGRESS) -r requirements.txt
	@missing=$$(ldd $(VENV)/lib/python3.11/site-packages/bpy/__init__.so 2>/dev/null | grep 'not found' || true); \
	if [ -n "$$missing" ]; then echo "bpy needs:"; echo "$$missing"; $(call apt_install,$(BPY_APT_PACKAGES)); fi
	$(PY) -c 'import bpy; print("bpy", bpy.app.version_string, "OK")'
	@touch $@

wheels: venv
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
	    echo "pip download wheels for $$plat ($$tags)"; \
	    $(PIP) download -q --no-deps --only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 \
	      $$(printf -- '--platform %s ' $$tags) --require-hashes -r requirements-wheels.txt -d wheels; \
	  done; \
	fi
	@status=0; for f in $(WHEEL_FILES); do \
	  [ -f "$$f" ] || { echo "missing $$f: listed in blender_manifest.toml but not downloaded (check requirements-wheels.txt and the TAGS_* platforms)" >&2; status=1; }; \
	done; [ $$status = 0 ] && echo "wheels: $(words $(WHEEL_FILES)) files present"

build: venv wheels
	@test -f "$(BLENDER_EXT)" || { echo "blender_ext.py not found in the bpy wheel ($(BPY_DIR))" >&2; exit 1; }
	@mkdir -p dist
	@rm -f $(ZIP)
	$(PY) $(BLENDER_EXT) build --source-dir . --output-dir dist --valid-tags $(VALID_TAGS)
	$(PY) $(BLENDER_EXT) validate --valid-tags $(VALID_TAGS) $(ZIP)

test: venv build
	$(PY) -m pytest tests $(PYTEST_FLAGS)

# The core tests need no extension zip and never import bpy (tests/core/test_layering.py).
test-core: venv
	$(PY) -m pytest tests/core $(PYTEST_FLAGS)

lint: venv
	$(VENV)/bin/ruff check .

demo: venv build
	$(PY) tools/visibake.py demo --out out/demo

# BENCH_PROFILE=smoke|quick|standard|bounces|full (see benchmarks/run.py); results in benchmarks/results/.
BENCH_PROFILE ?= quick
bench: venv
	$(PY) benchmarks/run.py --profile $(BENCH_PROFILE)

clean:
	rm -rf dist out .pytest_cache .hypothesis
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV) wheels
