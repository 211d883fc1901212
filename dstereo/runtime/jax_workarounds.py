"""Behaviour of jaxlib's CPU runtime that the code works around, in one place, with the version it was measured on.

Each entry below was measured on the version in `MEASURED_ON` (the one `requirements.lock` pins). After an
upgrade (`make lock`), re-measure each: `tests/runtime/test_jax_workarounds.py` fails until `MEASURED_ON` names the
installed jaxlib, so an upgrade cannot pass silently.

Settings (used by the code through the names below):
- `COMPILE_OPTIONS`: the CPU backend's newer fusion emitters make the solver loop about 15 % faster per pass
  but take twice as long to compile it (1.9 s against 1.0 s for a mono calibration); a calibration compiles
  once and runs for seconds, so compile time wins. Set per jit, so the user's other JAX programs are untouched.
- `CALL_POINTS`, `MAX_CHUNK`, `MAX_CONCURRENT_CALLS`: the size of one compiled call of subsets and how many run at
  once (no gain past two on the 2-core machines measured; `DSTEREO_THREADS=1` runs one call at a time). They
  were first set to dodge a hang of two concurrent calls (0 % CPU, never returned) that a size limit only made
  rarer (issue 28: it came back at 10 problems x 34 views x 48 corners). Its cause, found with gdb: jaxlib's
  batched LAPACK kernels (`lapack_dtrsm_ffi`, `ParallelBatchMap`) block an XLA pool thread until pieces queued
  on the same pool are done; two of them fill a 2-core machine's pool and wait on each other. The solver now
  factors with XLA's own operations (`solver/cholesky.py`; `tests/solver/test_cholesky.py` fails if a custom
  call comes back into it), so these numbers are chunk sizes only, kept where the chunk timings were measured.
  Every compiled solver call also runs under `dstereo/runtime/watchdog.py`: a call that stops making progress ends the
  command with one line, never a silent wait.

Executables loaded from disk (`runtime/aot.py`, `jax.experimental.serialize_executable`):
- `prepare_loaded_executables`: a loaded executable that calls LAPACK (Cholesky, LU) segfaulted in a new process
  until something had lowered a LAPACK op there: jaxlib sets its LAPACK kernel pointers while lowering
  (`prepare_lapack_call`), and a loaded executable is never lowered (jax issues 24982, 28908). Initialising them
  first makes it run and match the traced program bit for bit.
- `fresh_compile`: an executable that the compile fetched from JAX's persistent compilation cache, serialized
  again, fails in a new process ("NOT_FOUND: Function ..._fusion not found"); only a fresh compile serializes
  whole. `aot` compiles its programs under a name of their own (a cache key no earlier program has), inside this
  context, which also keeps that one-off compile out of the persistent cache (a thread-local setting of a JAX
  option that jax exposes only under jax._src), and it does not keep an executable whose compile was a cache hit.

Closed forms written instead of a LAPACK call (code where they are used; listed here so they are re-checked):
- `models/distortion.py` undistortion (`newton_step`, which `undistort` iterates and `point_jacobians.py`, the
  projection uncertainty, the renderer and the reference refinement call): a 2 x 2 Newton step solved in
  closed form; `jnp.linalg.solve` vmapped over many points hung the CPU runtime (and compiled to far more code),
  and in `point_jacobians.py`, vmapped over large chunks, deadlocked intermittently.
"""

MEASURED_ON = "0.10.2"

COMPILE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

CALL_POINTS = 16 * 20 * 54
MAX_CHUNK = 32
MAX_CONCURRENT_CALLS = 2


def prepare_loaded_executables() -> None:
    """Initialise jaxlib's LAPACK kernels before running executables loaded from disk (see above)."""
    try:
        from jax._src.lib import lapack

        lapack._lapack.initialize()  # what lowering a LAPACK op does first
    except (ImportError, AttributeError):  # moved in another jaxlib: lower one, which initialises them
        import jax
        import numpy as np

        jax.jit(jax.numpy.linalg.cholesky).lower(np.eye(1))


def fresh_compile():
    """Context (this thread): compiles are not written to the persistent compilation cache (see above)."""
    try:
        from jax._src import config

        return config.persistent_cache_min_compile_time_secs(float("inf"))
    except (ImportError, AttributeError, TypeError):  # another jax: the one-off entries are written, harmlessly
        import contextlib

        return contextlib.nullcontext()


def installed_jaxlib() -> str:
    import jaxlib

    return jaxlib.__version__


def version_mismatch() -> str | None:
    """A sentence saying the workarounds were measured on another jaxlib, or None when they match."""
    have = installed_jaxlib()
    if have == MEASURED_ON:
        return None
    return (f"jaxlib {have} is installed but the CPU-runtime workarounds in dstereo/runtime/jax_workarounds.py were "
            f"measured on {MEASURED_ON}; re-measure them (see that module) and update MEASURED_ON")
