# The two commands of the README: `make demo` and `make test`. Both set everything up first.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.osteonav-installed
# test workers (pytest-xdist): one per CPU; each test file runs whole on one worker, so a module's
# fixtures (simulated trials, replays) are made once
TEST_WORKERS ?= auto

.PHONY: demo test bench bench-rate bench-marker setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/osteonav demo

test: $(STAMP)
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

bench: $(STAMP)
	$(VENV)/bin/osteonav bench --quick

bench-rate: $(STAMP)
	$(VENV)/bin/osteonav bench-rate

bench-marker: $(STAMP)
	$(VENV)/bin/osteonav bench-marker

clean:
	rm -rf $(VENV) recordings/demo
