# heartcv — the two commands: `make test` and `make demo` (both create .venv on first use).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test test-slow demo bench clean-venv

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow || [ $$? -eq 5 ]  # exit 5: no slow test collected yet

demo: $(STAMP)
	$(MAKE) -C sample_sequences demo PY=$(abspath $(PY))

bench: $(STAMP)
	$(PY) -m benchmarks all

clean-venv:
	rm -rf $(VENV)
