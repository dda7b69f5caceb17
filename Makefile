# polspike: two commands set everything up on a fresh Debian 12 machine.
#   make demo  -> install (venv, pip, apt) then run the end-to-end demo
#   make test  -> install then run the test suite
#   make docs  -> install then build the documentation site (site/index.html)
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/demo
export DRJIT_LIBLLVM_PATH ?= /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
export MPLBACKEND := Agg
# the suite runs on min(cores, 4) pytest-xdist workers, one test file per worker at a time (--dist loadfile:
# a file's tests keep their order, e.g. the README tour); XDIST= runs it in one process
XDIST ?= -n $(shell n=$$(nproc); echo $$(( n < 4 ? n : 4 ))) --dist loadfile

.PHONY: install demo test test-quick test-all bench docs docs-serve clean system-deps

install: $(STAMP)

system-deps:
	@bash .ci/system-deps.sh

$(STAMP): pyproject.toml .ci/system-deps.sh
	@bash .ci/system-deps.sh
	@test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	@touch $(STAMP)

demo: install
	$(BIN)/polspike demo --out $(OUT)

test: install  # the whole suite, the tests marked slow included (what CI runs; budget 20 minutes on 2 cores)
	@bash .ci/system-deps.sh --test
	$(BIN)/python -m pytest -q -p no:cacheprovider --durations=30 $(XDIST) $(PYTEST_ARGS)

test-quick: install  # the suite without the tests marked slow (each > ~20 s), for a quick local check
	@bash .ci/system-deps.sh --test
	$(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider $(XDIST) $(PYTEST_ARGS)

test-all: test  # the same as test

bench: install  # every benchmark, JSON + table each under out/bench/ (tens of minutes on 2 cores)
	$(BIN)/polspike bench spike-sim --out out/bench/spike_sim
	$(BIN)/polspike bench render --out out/bench/render
	$(BIN)/polspike bench reconstruct --out out/bench/reconstruct
	$(BIN)/polspike bench reconstruct-net --threads 2 --json out/bench/reconstruct_net.json
	$(BIN)/polspike bench dataset --out out/bench/dataset
	$(BIN)/polspike bench tradeoff --out out/bench/tradeoff
	[ -f out/datasets/eval_paper_val/dataset.json ] || $(BIN)/polspike dataset build datasets/manifests/eval_paper_val.toml --out out/datasets/eval_paper_val
	$(BIN)/polspike bench ensemble out/datasets/eval_paper_val --split train --out out/bench/ensemble

docs: install  # the documentation site under site/ (strict: any warning fails the build)
	$(BIN)/pip install --quiet -e '.[docs]'
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(BIN)/mkdocs build --strict

docs-serve: docs  # the site at http://127.0.0.1:8000, rebuilt on every edit
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(BIN)/mkdocs serve

clean:
	rm -rf out build site *.egg-info
