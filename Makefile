# Two commands on a fresh machine: `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
XVFB_PACKAGES := xvfb xauth libxcb-icccm4 libxcb-image0 libxcb-keysyms1 libxcb-randr0 \
	libxcb-render-util0 libxcb-xinerama0 libxcb-xinput0 libxcb-xfixes0 libxcb-shape0 \
	libxcb-cursor0 libxkbcommon-x11-0 libgl1-mesa-dri libegl1 libglx-mesa0 libgomp1

.PHONY: run test venv system-deps lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[testing]"
	touch $(STAMP)

venv: $(STAMP)

# Debian packages for headless Qt (Xvfb); installed only when missing and when we can (root or sudo).
system-deps:
	@if ! command -v Xvfb >/dev/null 2>&1 || ! ldconfig -p | grep -q libxcb-cursor; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else \
	    echo "Xvfb and Qt's xcb libraries are missing; install: $(XVFB_PACKAGES)"; exit 1; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $(XVFB_PACKAGES) >/dev/null; \
	fi

test: $(STAMP) system-deps
	$(BIN)/python -m pytest -q

run: $(STAMP)
	$(BIN)/python -m napari_dvc_correct.demo

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_correlate.py

clean:
	rm -rf $(VENV) build dist .pytest_cache
