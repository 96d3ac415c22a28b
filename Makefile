# `make demo` and `make test` do all set-up on a fresh Debian bookworm machine (see .ci/setup),
# then compile the forms of the built-in scenes once (membranes.app.warmup: dolfinx keeps them
# in ~/.cache/fenics), so that no timed run pays for the compilation.
.PHONY: setup warmup demo demos lint test clean

setup:
	@bash .ci/setup

# A failed warm-up does not stop `make test`: the forms then compile on first use, and the
# tests say what is broken.
warmup: setup
	@.venv/bin/python -m membranes.app.warmup || \
		echo "warmup failed: the forms will compile on first use, inside timed runs" >&2

# The full disk comparison (theory §8, §9): J = 3 levels, finest h ≈ 0.025, ~10k vertices.
demo: warmup
	.venv/bin/membranes report --scene disk --h 0.16 --levels 3 --out out/report

# The literate demos of demos/, in full (pictures and outputs under out/demos).
demos: warmup
	.venv/bin/python demos/demo_disk.py --out out/demos/disk
	.venv/bin/python demos/demo_user_mesh.py --out out/demos/user_mesh
	.venv/bin/python demos/demo_sweep.py --out out/demos/sweep

lint: setup
	.venv/bin/ruff check .

# The suite on up to 4 pytest-xdist workers (one per core), a test file per worker: many
# tests wait on MPI start-up and subprocesses, which the workers overlap.
test: warmup
	.venv/bin/python -m pytest -q -n auto --maxprocesses 4 --dist loadfile tests

clean:
	rm -rf out .pytest_cache
