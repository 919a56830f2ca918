# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
# Both create .venv from pyproject.toml when it is missing or older than pyproject.toml.

SHELL  := /bin/bash
.SHELLFLAGS := -o pipefail -c
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DOCS_STAMP := $(VENV)/.installed-docs

.PHONY: demo test test-slow bench bench-report figs docs lint clean system-libs

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,peers,figs]'
	@touch $@

# Open3D (a peer in the tests) loads libusb-1.0, and tests/test_view.py screenshots the 3D
# view with headless Chromium: install what is missing when we can (one apt-get update).
system-libs:
	@missing=""; \
	ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing=" libusb-1.0-0"; \
	command -v chromium >/dev/null || missing="$$missing chromium"; \
	if [ -z "$$missing" ]; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing$$missing (libusb for Open3D, chromium for the 3D view's browser test)"; \
		apt-get update -qq && apt-get install -y -qq $$missing >/dev/null; \
	else echo "not root or no apt-get, so not installed:$$missing; Open3D's cross-checks" \
		"(libusb) and the 3D view's browser test (chromium) will skip"; fi

demo: $(STAMP)
	$(PY) -m jaxreg demo

test: $(STAMP) system-libs
	$(PY) -m ruff check jaxreg tests benchmarks examples paper_figs
	$(PY) -m pytest -q -n 2 --dist loadfile

# The long studies and numerical cross-checks marked slow (about 15 minutes more on 2 cores).
test-slow: $(STAMP) system-libs
	$(PY) -m pytest -q -n 2 --dist loadfile -m slow

# Every benchmark table, peers in the same run. The whole output (the date, the machine, the
# CPU and the peers' versions first, the load average before each script) is kept in
# benchmarks/results/make_bench.txt, and benchmarks/_report.py writes benchmarks/README.md and
# README.md's summary of the goals from it.
bench: $(STAMP) system-libs
	cd benchmarks && { \
		../$(PY) _report.py --header; \
		for f in bench_*.py; do \
			echo "== $$f (load average $$(cut -d' ' -f1-3 /proc/loadavg), $$(date -u +%H:%M) UTC)"; \
			PYTHONUNBUFFERED=1 ../$(PY) $$f || exit 1; \
		done; } 2>&1 | tee results/make_bench.txt
	$(PY) benchmarks/_report.py benchmarks/results/make_bench.txt

# benchmarks/README.md and README.md's summary again from the kept log, without running anything.
bench-report: $(STAMP)
	$(PY) benchmarks/_report.py benchmarks/results/make_bench.txt

# Every paper figure: PNG, its numbers (CSV) and its caption (TXT) in paper_figs/out/.
figs: $(STAMP)
	cd paper_figs && for f in fig_*.py; do echo "== $$f"; MPLBACKEND=Agg ../$(PY) $$f || exit 1; done
	@ls paper_figs/out/*.png

# The API reference as HTML in site/ (open site/index.html): the README as its first page,
# docs/reference.md, a page per package from the docstrings. --strict: a broken link or
# cross-reference fails the build.
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[docs]'
	@touch $@

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

lint: $(STAMP)
	$(PY) -m ruff check jaxreg tests benchmarks examples paper_figs

clean:
	rm -rf $(VENV) build site *.egg-info .pytest_cache .hypothesis
