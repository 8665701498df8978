# Two commands do all the set-up on a fresh machine (Python 3.11): `make demo`, `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test browser bench bench-peers clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or: make PYTHON=python3)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	rm -rf out/authors-demo.zarr
	$(BIN)/abcns run examples/authors_demo/spec.yaml --out out/authors-demo.zarr --quiet
	$(BIN)/abcns summary out/authors-demo.zarr

test: $(STAMP) browser
	$(BIN)/ruff check abcns worker service tests benchmarks examples
	$(BIN)/python -m pytest

# Debian's chromium for the live-page test (as root, e.g. in CI); nothing downloaded from elsewhere
browser:
	@command -v chromium >/dev/null 2>&1 || { if [ "$$(id -u)" = 0 ]; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "chromium is missing and this is not root: the browser test will be skipped"; fi; }

bench: $(STAMP)
	$(BIN)/python -m benchmarks.engine
	$(BIN)/python -m benchmarks.simulators
	$(BIN)/python -m benchmarks.runner

# abcns side by side with pyABC (the optional extra .[bench]): writes benchmarks/peers/RESULTS.md (~30-45 min on 2 cores)
bench-peers: $(STAMP)
	$(BIN)/pip install --quiet -e '.[dev,bench]'
	$(BIN)/python -m benchmarks.peers --seeds 3

clean:
	rm -rf $(VENV)
