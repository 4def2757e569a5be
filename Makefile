# Two entry points on a fresh machine with Python 3.11:  `make run`  and  `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
STAMP  := $(VENV)/.installed

.PHONY: run test test-slow check bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e '.[gateway,test]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/skinmap demo

# The default suite (3-4 minutes on a 2-core machine); the longer tests are marked slow.
test: $(STAMP)
	$(VENV)/bin/python -m pytest -m "not slow"

test-slow: $(STAMP)
	$(VENV)/bin/python -m pytest -m slow

# Static checks: mypy on the whole installed package (.ci/typecheck.py), dead code (vulture).
check: $(STAMP)
	$(VENV)/bin/python .ci/typecheck.py
	$(VENV)/bin/vulture --min-confidence 80 skinmap protocol firmware-host reconstruction daemon wire client ports strains elements tests bench

bench: $(STAMP)
	$(VENV)/bin/python bench/run_all.py

clean:
	rm -rf $(VENV) build *.egg-info
