# The two commands of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
VENV := .venv/bin
SPEC ?= examples/pick-and-place.yml
export ANSIBLE_CONFIG := $(CURDIR)/ansible.cfg
export PATH := $(CURDIR)/.venv/bin:$(PATH)

.PHONY: setup demo test lint unit schema bench clean

setup:
	@scripts/setup.sh

## Deploy the example application to the embedded default site (inventories/local).
demo: setup
	$(VENV)/ansible-playbook playbooks/deploy.yml -i inventories/local -e rosdeployment_file=$(SPEC)

## Lint and every test.
test: setup
	$(VENV)/python -m pytest

unit: setup
	$(VENV)/python -m pytest tests/unit

## Regenerate docs/rosdeployment.schema.json from the schema in the code.
schema: setup
	$(VENV)/python scripts/write_schema.py

## Scheduler benchmark; results go to bench/RESULTS.md by hand, with machine and date.
bench: setup
	$(VENV)/python bench/bench_scheduler.py

clean:
	rm -rf rendered bench/out .pytest_cache .hypothesis
