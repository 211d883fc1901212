"""Shared test set-up: float64 JAX, paths to the real data, and skip reasons stated once."""

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
