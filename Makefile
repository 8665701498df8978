# Two commands do all the set-up on a fresh machine (Python 3.11): `make demo`, `make test`.
# `make demo` installs the runtime dependencies only; `make test` adds the dev extra
# (pytest, ruff, mypy, the HTTP, browser and container test tools) to the same .venv.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
RUNTIME := $(VENV)/.installed-runtime
DEV := $(VENV)/.installed-dev
# setuptools' note that an editable install's folders shadow same-named ones is about this
# very checkout; nothing to act on
PIP := PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip
# pytest processes of `make test` (one per core of the 2-core machine it is measured on)
TEST_PROCESSES ?= 2

.PHONY: demo test browser bench bench-peers clean

# the venv with this checkout installed (editable) and the extra $(1); bytecode compiled on every
# core after pip (which compiles one file at a time: ~20 s of its ~34 s on 2 cores), as every
# process of the suite would otherwise compile its imports again where PYTHONDONTWRITEBYTECODE is
# set; the packages' own test folders left out (30 % of the files, none imported: 12.8 -> 8.0 s)
define INSTALL
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (or: make PYTHON=python3)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet --no-compile -e '.$(1)'
	$(BIN)/python -c "$$COMPILE"
endef
export COMPILE := import compileall, re, sysconfig; p = sysconfig.get_paths()['purelib']; \
  raise SystemExit(not compileall.compile_dir(p, quiet=1, workers=0, rx=re.compile(re.escape(p) + r'/(.*/)?tests?/')))

$(RUNTIME): pyproject.toml
	$(call INSTALL,)
	touch $(RUNTIME)

# on a fresh clone one install of both (one resolution, not two: ~6 s less)
$(DEV): pyproject.toml
	$(call INSTALL,[dev])
	touch $(RUNTIME) $(DEV)

# the authors' run as published (variant: paper), then the same data with the default
# sampler (variant: evidence: model probabilities with their standard errors), then what next
demo: $(RUNTIME)
	rm -rf out/authors-demo.zarr out/authors-demo-evidence.zarr
	@echo "== The authors' run (examples/authors_demo/spec.yaml: variant paper, as published)"
	$(BIN)/abcns run examples/authors_demo/spec.yaml --out out/authors-demo.zarr
	@echo ""
	@echo "== The same data with the default sampler (examples/authors_demo/evidence.yaml: variant evidence;"
	@echo "   its model probabilities come with their standard errors)"
	$(BIN)/abcns run examples/authors_demo/evidence.yaml --out out/authors-demo-evidence.zarr --quiet
	@echo ""
	@echo "Next: the figures:   $(BIN)/abcns plot out/authors-demo-evidence.zarr --out out/figures --spec examples/authors_demo/evidence.yaml"
	@echo "      the live page: $(BIN)/abcns serve   (then open http://127.0.0.1:8000/ and send a job: $(BIN)/abcns submit SPEC)"
	@echo "      your own data: README.md, \"Your own data in 10 minutes\""

test: $(DEV) browser
	$(BIN)/ruff check abcns worker service tests benchmarks examples
	@# mypy (one core) beside the numba step (the other): numba's cache compiled once, before the workers that read it start
	$(BIN)/mypy abcns worker service & mypy=$$!; $(BIN)/python -m tests.numba_warm && wait $$mypy
	@# a file's tests in one process (its module fixtures shared); the files longest first (tests/conftest.py), so the
	@# two processes end together
	$(BIN)/python -m pytest -n $(TEST_PROCESSES) --dist loadfile --no-loadscope-reorder

# Debian's chromium for the live-page test (as root, e.g. in CI); nothing downloaded from elsewhere
browser:
	@command -v chromium >/dev/null 2>&1 || { if [ "$$(id -u)" = 0 ]; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "chromium is missing and this is not root: the browser test will be skipped"; fi; }

bench: $(RUNTIME)
	$(BIN)/python -m benchmarks.engine
	$(BIN)/python -m benchmarks.simulators
	$(BIN)/python -m benchmarks.runner

# abcns side by side with pyABC (the optional extra .[bench]): writes benchmarks/peers/RESULTS.md (~30-45 min on 2 cores)
bench-peers: $(DEV)
	$(PIP) install --quiet -e '.[dev,bench]'
	$(BIN)/python -m pytest -m peers tests/test_bench_peers.py tests/test_exact_bayes_benchmark.py
	$(BIN)/python -m benchmarks.peers --seeds 3
	$(BIN)/python -m benchmarks.exact_bayes --seeds 1-5

clean:
	rm -rf $(VENV)
