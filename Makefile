# psimap: `make demo` and `make test` set everything up on a fresh machine.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.psimap-installed
NATIVE_SRC := $(wildcard psimap/render/csrc/*) CMakeLists.txt pyproject.toml

.PHONY: install demo test bench mutate clean

install: $(STAMP)

$(STAMP): $(NATIVE_SRC)
	@dpkg -s libusb-1.0-0 >/dev/null 2>&1 || { \
	  echo "installing Debian's libusb-1.0-0 (open3d needs it)"; \
	  apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; }
	@# an export's preview.png: MuJoCo's offscreen OpenGL (EGL, OSMesa the fallback); report.html's
	@# test opens the page in headless Chromium
	@missing=$$(for p in libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 chromium; do \
	  dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then echo "installing Debian's" $$missing "(previews)"; \
	  apt-get update -qq && apt-get install -y -qq $$missing >/dev/null; fi
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch first, pinned: a looser spec pulls a multi-GB CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q "scikit-build-core>=0.10" "nanobind>=2.0"
	# The native kernels are built here; a compile error fails this step loudly.
	$(PY) -m pip install -q --no-build-isolation -e ".[dev,newton]"
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/psimap demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile tests

# Not part of CI: applies every mutation in tests/mutations.md to a copy of the tree and reports
# any the tests do not catch (tests/mutate.py; `$(PY) tests/mutate.py M07` runs one).
mutate: $(STAMP)
	$(PY) tests/mutate.py

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf build demo_out bench_out
