# Quick start: `make demo` (set up, then run the main job) and `make test`
# (set up, then run the whole test suite).  Set-up happens on first use.
# `make test-fast`: every test not marked slow (pyproject.toml), the loop while working.
# Both run `ruff check` first (its rules: pyproject.toml), then two pytest-xdist workers, a test file each at a
# time (docs/testing.md).
PYTEST = .venv/bin/python -m pytest -n 2 --dist loadfile
RUFF = .venv/bin/python -m ruff check --no-cache .
.PHONY: setup demo demo-geometry test test-fast lint bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@mkdir -p out/demo
	.venv/bin/genre reconstruct examples/sofa.png -o out/demo/sofa.obj --preview --save-intermediates out/demo/sofa --weights default
	@echo "make demo: mesh out/demo/sofa.obj, preview out/demo/sofa_preview.png, intermediates out/demo/sofa/"

# The deterministic geometry alone on a Cycles render of Suzanne (the true full
# spherical map stands in for the inpainting net): out/demo-geometry/preview.png
demo-geometry: setup
	.venv/bin/python -m training.demo_geometry --out out/demo-geometry

test:
	@bash scripts/setup.sh --test
	$(RUFF)
	$(PYTEST)

test-fast:
	@bash scripts/setup.sh --test
	$(RUFF)
	$(PYTEST) -m "not slow"

lint:
	$(RUFF)

bench: setup
	.venv/bin/genre bench geometry
	.venv/bin/genre bench inference
	.venv/bin/genre bench reconstruct

clean:
	rm -rf out .pytest_cache build dist

# The Blender add-on in a real GUI Blender (system `blender` + `xvfb-run`; Debian:
# apt-get install blender xvfb xauth): builds dist/, presses Reconstruct on
# examples/sofa.png with the shipped default (product) weights, saves screenshots to out/e2e/;
# then annotates examples/photos/squirrel.jpg (and a copy turned by EXIF) in an Image Editor, presses
# Reconstruct and checks the mask against the hand mask: out/e2e/annotate/, out/e2e/annotate_exif6/.
.PHONY: e2e
e2e: setup
	.venv/bin/python tests/addon/e2e/run_gui_e2e.py
