# Everything a fresh machine needs: `make demo` and `make test` create .venv and install on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench install lock clean

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

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python -m experiments.bench_subsets

# Refresh the lock from pyproject.toml (pip-tools in a throw-away venv; the project venv stays as locked).
lock:
	$(PY) -m venv .lockenv
	.lockenv/bin/pip install -q pip-tools
	.lockenv/bin/pip-compile -q --generate-hashes --extra test --strip-extras --allow-unsafe \
		--no-emit-index-url --no-emit-find-links --upgrade -o $(LOCK) pyproject.toml
	rm -rf .lockenv

clean:
	rm -rf $(VENV) demo_out .pytest_cache
