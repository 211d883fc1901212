"""`dstereo ...` in this process with a breakdown on stderr (one line `PROFILE {json}` at exit): when JAX finished
importing, JAX's own compile-pipeline durations (jax.monitoring: tracing, lowering to MLIR, XLA compile, persistent
cache retrieval) and the time spent loading executables from disk (runtime/aot.py). Used by
experiments/bench_end_to_end.py; run as `python -m experiments._profiled_cli calibrate ...`."""

from __future__ import annotations

import collections
import json
import sys
import time

T0 = time.perf_counter()
EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace_s",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
          "/jax/core/compile/backend_compile_duration": "xla_compile_or_fetch_s",
          "/jax/compilation_cache/cache_retrieval_time_sec": "cache_fetch_s"}
totals: dict = collections.defaultdict(float)
counts: collections.Counter = collections.Counter()


def _listen(event: str, duration: float, **_) -> None:
    if event in EVENTS:
        totals[EVENTS[event]] += duration
        counts[EVENTS[event]] += 1


def _after_jax(configure):
    def wrapped(jax):
        configure(jax)
        totals["jax_imported_at_s"] = time.perf_counter() - T0
        jax.monitoring.register_event_duration_secs_listener(_listen)
    return wrapped


def _time_aot() -> None:
    """Wrap runtime/aot.py's loading once it is imported (it imports JAX, so after the hook above)."""
    from dstereo.runtime import aot

    load, compile_ = aot._load, aot.AotFunction._compile

    def timed_load(*a, **k):
        t = time.perf_counter()
        try:
            return load(*a, **k)
        finally:
            totals["aot_load_s"] += time.perf_counter() - t
            counts["aot_load_s"] += 1

    def timed_compile(self, *a, **k):
        t = time.perf_counter()
        try:
            return compile_(self, *a, **k)
        finally:
            totals["aot_build_s"] += time.perf_counter() - t
            counts["aot_build_s"] += 1

    aot._load, aot.AotFunction._compile = timed_load, timed_compile


CALIBRATIONS: list = []  # what calibrate_camera returned: its `timings` are complete at exit


def _keep_calibrations() -> None:
    from dstereo.jobs import calibrate_camera as pipeline

    run = pipeline.calibrate_camera

    def kept(*a, **k):
        cal = run(*a, **k)
        CALIBRATIONS.append(cal)
        return cal

    pipeline.calibrate_camera = kept


def _report() -> None:
    totals["total_s"] = time.perf_counter() - T0
    for cal in CALIBRATIONS[-1:]:
        totals.update({name.removesuffix("_s"): value for name, value in cal.timings.items()})
    print("PROFILE " + json.dumps({"totals": totals, "counts": counts}), file=sys.stderr)


if __name__ == "__main__":
    import os

    os.environ.setdefault("DSTEREO_AOT", "1")  # builds executables as the `dstereo` command's process does
    import dstereo

    dstereo._configure_jax = _after_jax(dstereo._configure_jax)
    import importlib.abc

    class _AfterAot(importlib.abc.MetaPathFinder):  # time aot once it exists, without importing JAX early
        def find_spec(self, name, path=None, target=None):
            if name == "dstereo.runtime.aot":
                sys.meta_path.remove(self)
                spec = importlib.util.find_spec(name)
                run = spec.loader.exec_module

                def exec_module(module):
                    run(module)
                    sys.modules[name] = module
                    _time_aot()

                spec.loader.exec_module = exec_module
                return spec
            return None

    import importlib.util

    sys.meta_path.insert(0, _AfterAot())
    _keep_calibrations()
    from dstereo.cli import finish, main

    sys.argv = ["dstereo", *sys.argv[1:]]
    code = 0
    try:
        main(end_process=False)
    except SystemExit as exc:
        code = exc.code
    _report()
    finish(code)  # the process ends as the `dstereo` script's does
