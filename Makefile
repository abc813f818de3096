# Two commands for a fresh machine: `make demo` and `make test`.
# Each creates .venv on first use and installs the pinned dependencies (constraints.txt).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LINTED := $(wildcard src tests bench)

.PHONY: demo test test-all quick lint typecheck unit bench clean chromium netns-deps

# pip is upgraded only when older than 23 (asking the index costs 20-30 s on a loaded machine);
# --no-compile: a package's modules are compiled when first imported, not all of them at install
# (a quarter of the install's CPU)
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -c 'import sys, pip; sys.exit(int(pip.__version__.split(".")[0]) < 23)' || \
	  $(BIN)/python -m pip install --quiet --disable-pip-version-check --upgrade "pip>=23"
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-compile \
	  -c constraints.txt -e '.[dev,ros2]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/mso demo --dashboard

lint: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)

typecheck: $(STAMP)
	$(BIN)/mypy

# the dashboard's browser test drives Debian's chromium (never a browser a tool downloads);
# installed here when missing and we are root (CI is), else that one test is skipped
chromium:
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { apt-get install -y -q chromium >/dev/null 2>&1 || \
	    { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; }; } ; } || \
	  echo "note: no chromium (apt-get install chromium): the browser test will be skipped"

# the suite in parallel (pytest-xdist): one worker per core (TEST_JOBS=1 for one process); a
# worker that finishes its share takes tests from the other's (worksteal: the long end-to-end
# tests do not leave one core idle at the end)
TEST_JOBS ?= auto
XDIST = -n $(TEST_JOBS) --dist worksteal

# `make test` runs every test but the end-to-end ones (marked slow: node processes, netns, a
# browser; each behaviour they show is also tested in one process or the simulator) and says at
# the end how many it left out. SLOW=1, CI=true (CI runs .ci/run) or `make test-all` run them too.
WITH_SLOW := $(filter 1 true yes,$(SLOW) $(CI))

unit: $(STAMP) $(if $(WITH_SLOW),chromium)
	$(BIN)/pytest $(XDIST) $(if $(WITH_SLOW),,-m "not slow")

test: lint typecheck unit

test-all:
	$(MAKE) test SLOW=1

# while working: the fast set alone, stopping at the first failure
quick: $(STAMP)
	$(BIN)/pytest $(XDIST) -m "not slow" -x

bench: $(STAMP)
	$(BIN)/python bench/chains.py

# the netns backend (`mso emulate --backend netns`) needs babeld and nftables (Debian's packages;
# root). The netns tests install them themselves in CI (CI=true, root).
netns-deps:
	command -v babeld >/dev/null && command -v batmand >/dev/null && command -v nft >/dev/null || \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq babeld batmand nftables)

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache .mypy_cache .ruff_cache
