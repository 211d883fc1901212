"""Shared test set-up: float64 JAX, paths to the real data, and skip reasons stated once."""

import contextlib
import io
import sys
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def require_data(sub: str) -> Path:
    """Path to ../shared/data/<sub>; skip (with the reason) only where the shared data is absent."""
    path = DATA / sub
    if not path.exists():
        pytest.skip(f"real data {path} is absent on this machine (it is present in CI)")
    return path


def run_cli(*args) -> tuple[int, str, str]:
    """Run `dstereo ARGS` in-process through `dstereo.cli.main` (the real error handling and exit codes);
    returns (exit code, stdout, stderr)."""
    from dstereo.cli import main

    out, err, argv = io.StringIO(), io.StringIO(), sys.argv
    sys.argv = ["dstereo", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = argv
    return code, out.getvalue(), err.getvalue()
