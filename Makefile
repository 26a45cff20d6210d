# Two entry points that work on a fresh machine with only Python 3:
#   make run   - create .venv on first use, install, run the demo (ngnav demo: Table 1,
#                a simulated flight through the filter beside its bound, its report)
#   make test  - create .venv on first use, install, lint and run all tests
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test bench lint clean

# PYTHONWARNINGS: setuptools announces every editable install on stderr (a notice about
# folders named like the package: here the package is this folder); the notice is all it hides
$(STAMP): pyproject.toml requirements.lock
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade "pip>=23.2"
	PYTHONWARNINGS="ignore:Editable installation" \
		$(BIN)/python -m pip install -q -c requirements.lock -e ".[test]"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/ngnav demo --out demo

test: $(STAMP)
	$(BIN)/ruff check ngnav filters telemetry studies tests
	$(BIN)/ruff format --check ngnav filters telemetry studies tests
	$(BIN)/python -m pytest -n 2 --dist loadfile

bench: $(STAMP)
	$(BIN)/ngnav bench

clean:
	rm -rf $(VENV) build *.egg-info
