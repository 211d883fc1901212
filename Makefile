# Everything a fresh machine needs: `make demo` and `make test` create .venv and install on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow bench bench-check install lock clean

LOCK := requirements.lock

# Exact versions with hashes from the lock; the project itself without its (already locked) dependencies.
$(STAMP): pyproject.toml $(LOCK)
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --require-hashes -r $(LOCK)
	$(BIN)/pip install -q --no-deps -e .
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/dstereo demo --out demo_out --force

# Two tiers: `make test` runs every test not marked slow (a whole command end to end, or a study over many solves:
# pyproject.toml's marker), `make test-slow` those; CI runs both (.ci/run). Each tier then runs its numerically
# sensitive tests (marker `numerics`) again on a second CPU code path: XLA limited to SSE4.2 vector code, the farthest
# from AVX-512/AVX2 machines, so no tolerance depends on one processor.
# Exit 5 (no test collected) fails: the second pass must check something.
# Two worker processes (pytest-xdist; tests/conftest.py schedules by module and keeps the memory-heavy modules in
# one worker, so that the two stay under 3 GB together); TEST_WORKERS=0 runs one process.
SECOND_ISA := SSE4_2
# Only the files that mention the marker are collected (every module's imports cost each worker ~3.5 s);
# tests/conftest.py refuses a numerics mark written outside its test file, which this would miss.
NUMERICS_FILES = $(shell grep -rlw --include='test_*.py' numerics tests | sort)
TEST_WORKERS ?= 2
# $(1): the tier's marker expression
define run_tier
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m "$(1)"
	@echo "--- numerics tests again with XLA_FLAGS=--xla_cpu_max_isa=$(SECOND_ISA)"
	@[ "$$(uname -m)" = x86_64 ] || echo "make test: $$(uname -m) is not x86-64; the flag names an x86 ISA and changes nothing here" >&2
	@XLA_FLAGS="$$XLA_FLAGS --xla_cpu_max_isa=$(SECOND_ISA)" $(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m "numerics and ($(1))" -p no:cacheprovider $(NUMERICS_FILES); \
	rc=$$?; if [ $$rc -eq 5 ]; then echo "make test: no test is marked numerics; the second pass checked nothing" >&2; fi; \
	exit $$rc
endef

test: $(STAMP)
	$(call run_tier,not slow)
	@echo "make test: the tests marked slow were left out; make test-slow runs them (CI runs both)"

test-slow: $(STAMP)
	$(call run_tier,slow)

# Two figures of docs/validation.md recomputed and compared with the file (each prints recomputed / documented;
# a figure off by more than its last digit fails): the Middlebury table (seconds) and the rig-consistency table
# (120 exact-corner rig solves, ~2 min on 2 cores).
bench-check: $(STAMP)
	$(BIN)/python -m experiments.middlebury --no-refine --check
	$(BIN)/python -m experiments.rig_consistency_seeds --check

# The spot checks, the solver alone (bench_subsets), then whole runs in new processes against the thesis approach
# and cv2 (bench_end_to_end), a data set of a new size against its repeat (bench_new_size, shape buckets) and, served,
# against mrcal-calibrate-cameras where Debian's mrcal is installed (bench_vs_mrcal, skipped with the reason where
# not); all write experiments/results/
bench: bench-check
	$(BIN)/python -m experiments.bench_subsets
	$(BIN)/python -m experiments.bench_end_to_end
	$(BIN)/python -m experiments.bench_new_size
	@if command -v mrcal-calibrate-cameras >/dev/null; then $(BIN)/python -m experiments.bench_vs_mrcal; \
	else echo "make bench: bench_vs_mrcal skipped: mrcal-calibrate-cameras is absent (apt-get install mrcal)"; fi

# Refresh the lock from pyproject.toml (pip-tools in a throw-away venv; the project venv stays as locked).
lock:
	$(PY) -m venv .lockenv
	.lockenv/bin/pip install -q pip-tools
	.lockenv/bin/pip-compile -q --generate-hashes --extra test --strip-extras --allow-unsafe \
		--no-emit-index-url --no-emit-find-links --upgrade -o $(LOCK) pyproject.toml
	rm -rf .lockenv

clean:
	rm -rf $(VENV) demo_out .pytest_cache
