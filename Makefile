# Quick start: `make demo` (set up, then run the main job) and `make test`
# (set up, then run the whole test suite).  Set-up happens on first use.
.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	.venv/bin/python -m training.demo_geometry --out out/demo

test: setup
	.venv/bin/python -m pytest

bench: setup
	.venv/bin/genre bench geometry

clean:
	rm -rf out .pytest_cache build dist
