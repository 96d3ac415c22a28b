# `make demo` and `make test` do all set-up on a fresh Debian bookworm machine (see .ci/setup).
.PHONY: setup demo test clean

setup:
	@bash .ci/setup

# The full disk comparison (§8, §9): J = 3 levels, finest h ≈ 0.025, ~10k vertices.
demo: setup
	.venv/bin/membranes report --scene disk --h 0.16 --levels 3 --out out/report

test: setup
	.venv/bin/python -m pytest -q tests

clean:
	rm -rf out .pytest_cache
