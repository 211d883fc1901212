"""The CPU-runtime workarounds were measured on one jaxlib: an upgrade must re-measure them, not pass silently."""

from dstereo.runtime import jax_workarounds


def test_workarounds_were_measured_on_the_installed_jaxlib():
    # Fails after `make lock` brings another jaxlib: re-measure each entry of dstereo/runtime/jax_workarounds.py, then
    # update MEASURED_ON. The lock pins the version, so a fresh machine gets the one measured.
    assert jax_workarounds.version_mismatch() is None, jax_workarounds.version_mismatch()


def test_the_solver_uses_the_recorded_compile_options():
    from dstereo.solver import lm

    assert lm.COMPILE_OPTIONS is jax_workarounds.COMPILE_OPTIONS
