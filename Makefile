# Quick start: `make demo` (set up, run the demo mission through the daemon, print the summary, write the plot)
#              `make test` (set up, run the whole test suite)
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: demo test test-fast setup clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[plot,test]'
	$(BIN)/vflpcd compile
	touch $@

setup: $(BIN)/.installed

demo: $(BIN)/.installed
	$(BIN)/vflpcd run config/missions/vehicle_can.toml --with-sitl --log-dir results/demo --plot

# three workers on two cores: most of the integration tests wait on real time (missions, SITL)
test: $(BIN)/.installed
	$(BIN)/pytest -q -n 3 --dist worksteal

# the inner loop: the unit tests only (no real-time missions, SITL or benches)
test-fast: $(BIN)/.installed
	$(BIN)/pytest -q -n 3 --dist worksteal tests/unit

clean:
	rm -rf $(VENV) results .pytest_cache *.egg-info
