"""dstereo: differentiable stereo photogrammetry in JAX."""

import jax

# Calibration needs float64 everywhere: enable it before any array is created.
jax.config.update("jax_enable_x64", True)


def _enable_compilation_cache() -> None:
    """Keep compiled solvers on disk: a cold compile costs seconds per shape, a cached one almost nothing.

    Off with DSTEREO_JAX_CACHE=0; the folder is DSTEREO_JAX_CACHE or ~/.cache/dstereo/jax.
    """
    import os

    setting = os.environ.get("DSTEREO_JAX_CACHE", "")
    if setting == "0":
        return
    folder = setting or os.path.join(os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "dstereo", "jax")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return  # read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


_enable_compilation_cache()

from dstereo.errors import DstereoError  # noqa: E402

__all__ = ["DstereoError"]
__version__ = "0.1.0"
