# `make demo` and `make test` do all set-up on a fresh Debian bookworm machine (see .ci/setup).
.PHONY: setup demo test clean

setup:
	@bash .ci/setup

demo: setup
	.venv/bin/python demos/demo_disk.py

test: setup
	.venv/bin/python -m pytest -q tests

clean:
	rm -rf out .pytest_cache
