# The two commands of the README: `make demo` and `make test`. Both set everything up first.
# `make lint` (ruff + mypy) runs in CI before the tests.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup demo test lint bench fuzz clean system-deps

setup: $(STAMP)

# open3d links against libusb-1.0 at import time; install it when missing (root only).
# Debian's chromium runs the ground page's browser tests; without root and without it they skip.
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then :; \
	elif [ "$$(id -u)" = "0" ]; then \
		echo "installing the system library libusb-1.0-0 (needed by open3d)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	else \
		echo "error: the system library libusb-1.0-0 is missing and we are not root."; \
		echo "       ask an administrator to run: sudo apt-get install libusb-1.0-0"; \
		exit 1; \
	fi
	@if command -v chromium >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = "0" ]; then \
		echo "installing Debian's chromium (the browser tests of olsplat ground web)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	else \
		echo "note: chromium is missing and we are not root: the browser tests will be skipped"; \
		echo "      (sudo apt-get install chromium runs them)"; \
	fi

$(STAMP): pyproject.toml setup.py $(wildcard olsplat_nodes/native/*.[ch]) | system-deps
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "olsplat needs Python >= 3.11, got " + sys.version.split()[0])'
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch first and pinned: 2.13.0 is the local CPU build, anything else drags in CUDA.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[all]'
	# Two files of open_clip (not installed: it needs torchvision): CLIP's BPE vocabulary and
	# open_clip's tokenizer, the reference the tokenizer tests compare with.
	$(PY) -m pip download -q --no-deps open_clip_torch==3.3.0 -d $(VENV)/reference
	$(PY) -c "import glob, zipfile; z = zipfile.ZipFile(glob.glob('$(VENV)/reference/open_clip_torch-*.whl')[0]); \
		[z.extract(n, '$(VENV)/reference') for n in ('open_clip/tokenizer.py', 'open_clip/bpe_simple_vocab_16e6.txt.gz')]"
	# numba compiles on first use (~75 s for every node's kernels here): once now, not in a flight's first minute
	$(VENV)/bin/olsplat warm-up
	touch $(STAMP)

# the pre-flight check first: a blocker (a cold numba cache, a broken model file) stops the demo with its fix
demo: setup
	$(VENV)/bin/olsplat doctor
	$(VENV)/bin/olsplat demo --out out

# Two passes: the tests that need no process of their own on two workers, then the serial ones
# (graphs, servers, a browser, timing; marked in tests/conftest.py) one at a time. Both always
# run; the target fails if either failed. The session's simulated flights are made once for both
# passes, in a folder removed at the end ($OLSPLAT_TEST_SHARED: tests/conftest.py, made_once).
test: setup
	shared=$$(mktemp -d); export OLSPLAT_TEST_SHARED=$$shared; \
	$(PY) -m pytest -n 2 -m "not serial"; first=$$?; \
	$(PY) -m pytest -m serial; second=$$?; \
	rm -rf "$$shared"; exit $$(( first || second ))

# ruff (lint rules and formatting) and mypy, configured in pyproject.toml. mypy sees msgs/ and
# sim/ by their import names (olsplat_msgs, olsplat_sim) through links under build/mypy.
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	@mkdir -p build/mypy && ln -sfn ../../msgs build/mypy/olsplat_msgs && ln -sfn ../../sim build/mypy/olsplat_sim
	$(VENV)/bin/mypy

bench: setup
	$(VENV)/bin/olsplat bench raster

# The live-graph fuzzer ten times longer than in `make test` (100,000 mutants per socket), with a
# fresh seed each run (printed; OLSPLAT_FUZZ_SEED=N repeats one). About 5 minutes here.
FUZZ_PER_SOCKET ?= 100000
fuzz: setup
	OLSPLAT_FUZZ_PER_SOCKET=$(FUZZ_PER_SOCKET) OLSPLAT_FUZZ_SEED=$${OLSPLAT_FUZZ_SEED:-$$(date +%s)} \
		$(PY) -m pytest -s tests/nodes/test_live_fuzz.py

clean:
	rm -rf out build *.egg-info
