# The two commands of the README: `make demo` and `make test`. Both set everything up first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup demo test bench clean system-deps

setup: $(STAMP)

# open3d links against libusb-1.0 at import time; install it when missing (root only).
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

$(STAMP): pyproject.toml | system-deps
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "olsplat needs Python >= 3.11, got " + sys.version.split()[0])'
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# torch first and pinned: 2.13.0 is the local CPU build, anything else drags in CUDA.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	# open_clip's files only (never imported: it needs torchvision): its BPE vocabulary and its
	# tokenizer are the reference the tokenizer tests compare with.
	$(PY) -m pip install -q --no-deps open_clip_torch==3.3.0
	touch $(STAMP)

demo: setup
	$(VENV)/bin/olsplat demo --out out

test: setup
	$(PY) -m pytest

bench: setup
	$(VENV)/bin/olsplat bench raster

clean:
	rm -rf out build *.egg-info
