# The project's entry points. Every target creates or reuses the virtual environment .venv
# from environment-requirements.txt, so a fresh machine needs only Python 3.11 and make.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export MPLBACKEND ?= Agg

.PHONY: setup report test test-fast lab bench clean student

$(STAMP): environment-requirements.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r environment-requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	$(BIN)/python -m ipykernel install --sys-prefix --name python3 --display-name "Python 3 (mpcrl_lite)" >/dev/null
	touch $(STAMP)

setup: $(STAMP)

## main job: execute every notebook into reports/ (executed .ipynb + HTML + summary.json)
report: $(STAMP)
	$(BIN)/python -m mpcrl_lite report --out reports

## the whole test suite (unit tests + notebook tests)
test: $(STAMP)
	$(BIN)/python -m pytest

## unit tests only (skips the notebook executions)
test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not notebook"

lab: $(STAMP)
	$(BIN)/jupyter lab notebooks/

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

## student version of the notebooks (solution cells removed) into student/
student: $(STAMP)
	$(BIN)/python tools/make_student_version.py --out student

clean:
	rm -rf reports .pytest_cache
