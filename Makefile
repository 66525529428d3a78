# Two commands on a fresh machine:
#   make demo   simulate a wide bead field, estimate its PSF operator, print the errors,
#               write figures and TIFFs into demo-output/
#   make test   run the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test check install lint bench fuzz

$(BIN)/psfspace: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[testing]"
	touch $@

install: $(BIN)/psfspace

demo: install
	$(BIN)/psfspace demo --out demo-output

# one worker per core (pytest-xdist; a file runs on one worker, its module fixtures once), the
# files with the longest tests first (tests/conftest.py)
test: install
	$(BIN)/python -m pytest -n auto --dist loadfile

# the inner loop: the tests that take under a second (tests/slow_tests.txt lists the others)
check: install
	$(BIN)/python -m pytest -m "not slow" -q

# the doors under a longer, random property-based run (hypothesis: tests/test_fuzz.py, and
# damaged model and family files through every door that reads them)
fuzz: install
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest tests/test_fuzz.py tests/test_one_validator.py \
		-q -p no:randomly \
		--hypothesis-show-statistics

lint: install
	$(BIN)/ruff check src tests bench benchmarks docs

bench: install
	$(BIN)/python bench/run.py accuracy
	$(BIN)/python bench/run.py speed
	$(BIN)/python bench/run.py apply
