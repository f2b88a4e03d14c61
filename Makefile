# Quick start: `make demo` (set up, then run the main job) and `make test`
# (set up, then run the whole test suite).  Set-up happens on first use.
.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	.venv/bin/python -m training.demo_geometry --out out/demo
	@if [ -f genre_backend/weights/default.safetensors ] && [ -f examples/photo.png ]; then \
		.venv/bin/genre reconstruct examples/photo.png -o out/demo/photo.obj --save-intermediates out/demo/photo; \
	else \
		echo "make demo: photo -> mesh needs genre_backend/weights/default.safetensors and examples/photo.png (not shipped yet)"; \
	fi

test:
	@bash scripts/setup.sh --test
	.venv/bin/python -m pytest

bench: setup
	.venv/bin/genre bench geometry

clean:
	rm -rf out .pytest_cache build dist

# The Blender add-on in a real GUI Blender (system `blender` + `xvfb-run`; Debian:
# apt-get install blender xvfb xauth): builds dist/, trains tiny test weights once
# (cached in out/e2e/weights), presses Reconstruct, saves screenshots to out/e2e/.
.PHONY: e2e
e2e: setup
	.venv/bin/python tests/e2e/run_gui_e2e.py
