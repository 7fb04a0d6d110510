# One command each: `make demo` sets up and builds the bundled example; `make test` sets up and runs the tests.
.PHONY: setup demo test bench clean
VENV := .venv/bin

setup:
	bash scripts/setup.sh

demo: setup
	$(VENV)/usdrelight build examples/motorcycle/photo.png --depth examples/motorcycle/depth.exr \
		--intrinsics examples/motorcycle/intrinsics.json -o out/motorcycle
	$(VENV)/usdrelight validate out/motorcycle/scene.usda
	$(VENV)/usdrelight fit out/motorcycle/scene.usda --report out/motorcycle/fit_report
	$(VENV)/usdrelight relight out/motorcycle/scene.usda --with-fitted -o out/motorcycle/relit \
		--light spot:1.2,0.6,-1.0:-0.6,-0.3,-0.7:60,30,10:35:0.5
	$(VENV)/usdrelight relight out/motorcycle/scene.usda --fitted-scale 0.05 --contact-sheet -o out/motorcycle/relit_night \
		--light spot:-1.2,0.5,-1.0:0.8,-0.2,-0.6:30,18,8:40:0.4 --light dome:0.01,0.012,0.02

test: setup
	$(VENV)/python -m pytest -q

bench: setup
	$(VENV)/python benchmarks/bench_build.py

clean:
	rm -rf out .pytest_cache
