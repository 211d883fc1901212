"""dstereo: differentiable stereo photogrammetry in JAX.

JAX is imported only by the modules that compute (a command's `--help`, the figure workers and the file writers
start without it, ~1-3 s less): importing `dstereo` installs a one-shot import hook that configures JAX (float64,
the on-disk compilation cache) the moment anything imports it, before any array can be created.
"""

import importlib.abc
import importlib.util
import sys


def _configure_jax(jax) -> None:
    # Calibration needs float64 everywhere: enable it before any array is created.
    jax.config.update("jax_enable_x64", True)
    _enable_compilation_cache(jax)


def _enable_compilation_cache(jax) -> None:
    """Keep compiled solvers on disk: a cold compile costs seconds per shape, a cached one almost nothing.

    Off with DSTEREO_JAX_CACHE=0; the folder is DSTEREO_JAX_CACHE or ~/.cache/dstereo/jax.
    """
    import os

    setting = os.environ.get("DSTEREO_JAX_CACHE", "")
    if setting == "0":
        return
    base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
    if not setting and base.startswith("~"):
        return  # a user without a home: expanduser leaves "~", which would be a folder named ~ in the working folder
    folder = setting or os.path.join(base, "dstereo", "jax")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return  # read-only home: run without the cache
    if not os.access(folder, os.W_OK | os.X_OK):
        return  # a folder that exists but takes no files: JAX would warn at every compile; run without the cache
    # (the executables' folder, runtime/aot.py, lives in this one: no cache folder, no executables either)
    jax.config.update("jax_compilation_cache_dir", folder)
    # Every program, however quick to compile: a warm run compiled ~10 small ones (eager ops, rotations) afresh
    # each time under the 0.5 s threshold JAX suggests, 10-540 ms each, where a fetch takes a few ms.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


class _ConfigureJaxOnImport(importlib.abc.MetaPathFinder):
    """Finds `jax` with the other finders and runs `_configure_jax` right after `jax/__init__.py` has run."""

    def find_spec(self, name, path=None, target=None):
        if name != "jax":
            return None
        sys.meta_path.remove(self)  # one shot; also keeps the lookup below from coming back here
        spec = importlib.util.find_spec("jax")
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            _configure_jax(module)

        spec.loader.exec_module = exec_module  # this spec's own loader instance
        return spec


if "jax" in sys.modules:
    _configure_jax(sys.modules["jax"])
elif not any(isinstance(f, _ConfigureJaxOnImport) for f in sys.meta_path):
    sys.meta_path.insert(0, _ConfigureJaxOnImport())

from dstereo.errors import DstereoError  # noqa: E402

__all__ = ["DstereoError"]
__version__ = "0.1.0"
