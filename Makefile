# The project's entry points. Every target creates or reuses the virtual environment .venv
# from environment-requirements.txt, so a fresh machine needs only Python 3.11 and make.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
export MPLBACKEND ?= Agg

.PHONY: setup bytecode report test test-fast lab bench clean student site study

$(STAMP): environment-requirements.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r environment-requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	$(BIN)/python -m ipykernel install --sys-prefix --name python3 --display-name "Python 3 (mpcrl_lite)" >/dev/null
	$(BIN)/python -m mpcrl_lite.cli.warm
	$(BIN)/python -m compileall -q mpcrl_lite >/dev/null
	touch $(STAMP)

setup: $(STAMP)

## the package's bytecode (__pycache__), brought up to date in 0.04 s: Python writes it on
## import by itself, except where the environment says not to (PYTHONDONTWRITEBYTECODE, set
## in many container images), and then every command would compile the package's modules
## again, 0.08 s of each start. The targets below that start many processes run it first.
bytecode: $(STAMP)
	$(BIN)/python -m compileall -q mpcrl_lite >/dev/null

## main job: execute every notebook into reports/ (executed .ipynb + offline HTML + summary.json)
## REPORT_PROFILE=classroom (or ci) runs the smaller parameter profiles. The prose's claims
## (notebooks/claims.yaml) are checked against the run; the run times go into the table that
## README.md, notebooks/README.md and notebooks/TEACHING.md share (tools/update_run_times.py).
REPORT_PROFILE ?= full
report: bytecode
	$(BIN)/python -m mpcrl_lite report --out reports --profile $(REPORT_PROFILE)
	$(BIN)/python tools/update_run_times.py reports/summary.json

## the whole test suite: lint (ruff), unit tests and notebook tests, on every core
## (pytest-xdist; TEST_WORKERS=0 runs it in one process). --dist loadfile keeps each test
## file on one worker, so the notebook tests' session fixture executes each notebook once.
TEST_WORKERS ?= auto
test: bytecode
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

## unit tests only (skips the notebook executions)
test-fast: $(STAMP)
	$(BIN)/python -m pytest -m "not notebook"

## JupyterLab on the repository root (notebooks/ and student/ alike), opened at notebooks/.
## Extra options go in LAB_ARGS, e.g. make lab LAB_ARGS="--no-browser --port 8890";
## as root (containers) --allow-root is added.
LAB_ARGS ?=
LAB_ROOT_ARG := $(if $(filter 0,$(shell id -u 2>/dev/null)),--allow-root)
lab: $(STAMP)
	$(BIN)/jupyter lab --ServerApp.root_dir=. --LabApp.default_url=/lab/tree/notebooks \
		$(LAB_ROOT_ARG) $(LAB_ARGS)

bench: bytecode
	$(BIN)/python benchmarks/run_all.py --out benchmarks/results/bench-$$(date +%Y%m%d-%H%M%S).json

## student version of the notebooks (solution cells removed) into student/
student: $(STAMP)
	$(BIN)/python tools/make_student_version.py --out student

## static site: site/index.html with the notebook tour, every executed notebook, the paper's
## figures, the parameter study and summary.json; opens from disk, no server needed.
## SITE_PROFILE=full|classroom|ci; SITE_FROM=reports reuses the notebooks that `make report` ran.
SITE_PROFILE ?= classroom
SITE_FROM ?=
site: $(STAMP)
	$(BIN)/python -m mpcrl_lite.publish.site --out site --profile $(SITE_PROFILE) $(if $(SITE_FROM),--report $(SITE_FROM))

## multi-seed study: SEEDS runs of MONTHS months (seeds from SEED_START) into STUDY_OUT
## (study.csv, study.json, study_curves.png; resumes an interrupted study). Each of the 2
## workers steps its share of the seeds in lockstep; LOCKSTEP=K sets the runs per task.
## FORECAST=until_midnight studies the day-end MPC (an extension beyond the paper's class).
SEEDS ?= 20
MONTHS ?= 100
SEED_START ?= 0
STUDY_OUT ?= study
LOCKSTEP ?=
FORECAST ?= paper
study: $(STAMP)
	$(BIN)/python -m mpcrl_lite study --seeds $(SEEDS) --months $(MONTHS) \
		--seed-start $(SEED_START) --out $(STUDY_OUT) --forecast $(FORECAST) \
		$(if $(LOCKSTEP),--lockstep $(LOCKSTEP))

clean:
	rm -rf reports site .pytest_cache
