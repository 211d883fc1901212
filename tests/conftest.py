"""Shared test set-up: float64 JAX, paths to the real data, and skip reasons stated once."""

import contextlib
import io
import math
import os
import sys
from pathlib import Path

# One OpenBLAS thread per test process, as a `dstereo` command has (dstereo/cli.py; set before numpy loads it):
# the two xdist workers share two cores, and OpenBLAS's threads spin while they wait for one
# (dstereo/runtime/blas_threads.py measured a 3 x 3 product 6-20x slower so). A setting given wins. The workers
# start after this line has run in the controller, so their numpy and scipy load with it; one process without
# workers may have loaded numpy already (through a plugin) and keeps its count: no second worker competes there.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402 - after the thread count above
import pytest  # noqa: E402


def pytest_configure(config):
    """float64 JAX in every process that runs tests; xdist's controller, which only hands them out, never imports
    JAX (~120 MB less of the suite's 3 GB)."""
    controller = config.getoption("numprocesses", None) and not hasattr(config, "workerinput")
    if not controller:
        import jax

        jax.config.update("jax_enable_x64", True)

def pytest_collection_modifyitems(config, items):
    """`make test`'s second pass collects only the test files that contain the word "numerics" (Makefile,
    NUMERICS_FILES: collecting every module costs each worker ~3.5 s of imports): a numerics test marked from
    elsewhere (a mark imported from another module) would silently leave that pass. Refused here instead."""
    outside = marked_outside_their_file(items)
    if outside:
        raise pytest.UsageError(f"{len(outside)} test(s) marked numerics in files without the word 'numerics' "
                                f"(make test's second pass would miss them): {', '.join(outside[:3])}; write "
                                "the mark in the test file (@pytest.mark.numerics)")


def marked_outside_their_file(items) -> list[str]:
    """Node ids of the `items` marked numerics whose file's text does not contain "numerics"."""
    texts, out = {}, []
    for item in items:
        if item.get_closest_marker("numerics") is None:
            continue
        path = Path(str(item.path))
        if path not in texts:
            texts[path] = "numerics" in path.read_text(errors="replace")
        if not texts[path]:
            out.append(item.nodeid)
    return out


# `make test` is the tier a developer runs after each change (under 8 minutes on 2 cores); tests marked slow (whole
# commands end to end, studies over many solves: pyproject.toml) run in `make test-slow`, and CI runs both. A test
# left in the quick tier whose set-up or call took longer than this is named at the end of the run, so that the
# tier does not grow back unseen (a note, not a failure: no test fails on time).
QUICK_TIER_NOTE_S = 10.0
_long_in_quick_tier: list[str] = []


def pytest_runtest_logreport(report):
    """Runs in the process that reports (xdist's controller too): notes a long test not marked slow."""
    if report.when in ("setup", "call") and report.duration > QUICK_TIER_NOTE_S and "slow" not in report.keywords:
        _long_in_quick_tier.append(f"{report.duration:.0f} s {report.when} {report.nodeid}")


def pytest_terminal_summary(terminalreporter):
    if _long_in_quick_tier and not hasattr(terminalreporter.config, "workerinput"):
        terminalreporter.write_line(f"{len(_long_in_quick_tier)} test(s) not marked slow took over "
                                    f"{QUICK_TIER_NOTE_S:.0f} s (mark them slow, see pyproject.toml, or make them "
                                    "quicker):")
        for line in _long_in_quick_tier:
            terminalreporter.write_line(f"  {line}")


# Figures drawn in the test process, not in figure workers (dstereo.runtime.figure_pool; the files are the same
# either way, its docstring): each test process that ran a command in process kept two ~100 MB workers (the
# suite's two xdist workers, four) and paid their start. tests/runtime, which tests the workers, has the default
# for its tests and the processes they start (`_figure_workers_by_default_in_runtime_tests`).
# The setting as the suite found it ("" = unset), kept in the environment: xdist's workers inherit the "0" below.
os.environ.setdefault("DSTEREO_SUITE_FIGURE_WORKERS", os.environ.get("DSTEREO_FIGURE_WORKERS", ""))
os.environ["DSTEREO_FIGURE_WORKERS"] = "0"


@pytest.fixture(autouse=True, scope="module")
def _figure_workers_by_default_in_runtime_tests(request):
    """Module scope, autouse: in place before the module's other fixtures (a served command, a started server)."""
    if Path(str(request.node.path)).parent.name != "runtime":
        yield
        return
    with pytest.MonkeyPatch.context() as patch:
        default = os.environ["DSTEREO_SUITE_FIGURE_WORKERS"]
        if default:
            patch.setenv("DSTEREO_FIGURE_WORKERS", default)
        else:
            patch.delenv("DSTEREO_FIGURE_WORKERS")
        yield


DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# The suite runs in two worker processes (`make test`: pytest-xdist, -n 2) whose sum, with the CLI processes some
# tests start, must stay under 3 GB. A worker's RSS grows test by test with the programs it compiles (380 ->
# 1434 MB over tests/calib/test_engine.py alone); outside MEMORY_HEAVY, above this, the worker drops them after the
# test (the next test that needs one traces it again and loads its compiled code from the on-disk cache). Not in
# MEMORY_HEAVY: its modules reuse their programs test after test, and releasing there after every test that ends
# above 900 MB made them several times slower (re-tracing dominates); they run one at a time instead. At 1000 MB the
# other worker reached 1.1 GB beside the unit's 1.3 GB (a server, its client, the worker): 3.03 GB in all.
RELEASE_ABOVE_MB = 800

# Modules that each reach 1.2-1.5 GB in one test (measured per module, VmHWM), and those that start processes
# which import JAX (a calibration of ~1.3 GB, a server and its client 0.3-0.4 GB each, two frame workers 0.5 GB
# each): one unit of work, so that xdist runs them one after the other in the same worker and two of them never
# add up (two workers with one of each side by side measured 3.1 GB). Everything else is distributed a module at a
# time (module fixtures built once).
MEMORY_HEAVY = frozenset({
    "tests/calib/test_problem.py", "tests/calib/test_engine.py", "tests/calib/test_multiview.py",
    "tests/calib/test_rig_consistency.py", "tests/calib/test_calibrate_cameras.py",
    "tests/calib/test_final_solution.py", "tests/demo/test_run.py",
    "tests/jobs/test_frame_tasks.py", "tests/runtime/test_serve.py", "tests/runtime/test_serve_signals.py",
    "tests/runtime/test_serve_autostart.py", "tests/runtime/test_signals.py", "tests/runtime/test_aot.py",
    "tests/solver/test_concurrent_solves.py", "tests/commands/test_hostile_reconstruct.py",
    "tests/commands/test_every_feature.py",
})


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook (`make test` runs two workers)
def pytest_xdist_make_scheduler(config, log):
    """xdist's per-module scheduling (`--dist loadfile`: a module's fixtures built once), with MEMORY_HEAVY's
    modules as one unit. (Not `--dist loadgroup` with marks: under pytest 9 xdist 3.8 cannot attach the group to
    a test's id, and every test was then scheduled on its own.)"""
    from xdist.scheduler import LoadScopeScheduling

    class MemoryAwareScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "memory-heavy" if module in MEMORY_HEAVY else module

        def _assign_work_unit(self, node) -> None:
            # the first hand-out puts the longest units first (xdist's queue: most tests first); the queue is
            # reordered, not the collections, whose positions the workers are sent
            if not getattr(self, "_longest_first", False):
                self._longest_first = True
                order = longest_first(list(self.workqueue))
                self.workqueue = type(self.workqueue)((scope, self.workqueue[scope]) for scope in order)
            super()._assign_work_unit(node)

    return MemoryAwareScheduling(config, log)


# Units of work that take longest, handed out first (the longest-processing-time rule: a long unit started last
# leaves the other worker idle while it runs): the memory-heavy unit, a third to a half of the suite. xdist's own
# order is by number of tests, which sent the one-test module test_every_feature (seven calibrations, 2-6 min)
# last, one worker idle while it ran (2026-12-06, 318 s); handed out first beside the unit, its calibration child
# (1.3 GB) and the unit's heaviest module took the process tree to 3284 MiB: it is in the unit now.
LONGEST_FIRST = ("memory-heavy",)


def longest_first(units: list[str]) -> list[str]:
    """Units of work in the order handed out: LONGEST_FIRST's, then the others in their given order."""
    rank = {unit: i for i, unit in enumerate(LONGEST_FIRST)}
    return sorted(units, key=lambda unit: rank.get(unit, len(rank)))  # stable: the others keep their order


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs(request):
    """After each test module: drop JAX's in-memory compiled programs and dstereo's caches of compiled functions.
    One process runs ~960 tests; kept, their executables grew the suite past 5 GB of RSS (the budget is 3 GB),
    and a fresh compile's serialization for the persistent cache aborted the process at ~76 % of the run (CI and
    here, in jax's put_executable_and_time). Measured: tests/calib alone 177 s and 4.0 GB peak RSS kept, 154 s
    cleared; the whole suite cleared 2.3 GB peak, no abort. The next module that needs a program fetches it from
    the on-disk cache (milliseconds), as a new command does."""
    yield
    log = os.environ.get("DSTEREO_RSS_LOG")  # a file: each module's peak RSS so far (where the suite's peak grows)
    if log:
        import resource

        with open(log, "a") as f:
            f.write(f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss} {request.module.__name__}\n")
    release_compiled_programs()


@pytest.fixture(autouse=True)
def _release_above_the_limit(request):
    """After a test outside MEMORY_HEAVY that leaves the process above RELEASE_ABOVE_MB: the module fixture's
    release, now."""
    yield
    if request.node.nodeid.split("::")[0] not in MEMORY_HEAVY and resident_mb() > RELEASE_ABOVE_MB:
        release_compiled_programs()


def resident_mb() -> float:
    """This process's resident memory (MB) from /proc (Linux); 0 elsewhere (no release between tests there)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def release_compiled_programs() -> None:
    """Drop JAX's compiled programs and dstereo's function caches, collect, and return the memory to the system.
    Also called by tests before they start a heavy CLI child process, so the two never hold their peaks at once."""
    import gc

    import jax

    jax.clear_caches()
    for name, module in list(sys.modules.items()):
        if name.startswith("dstereo"):
            for value in list(vars(module).values()):
                if callable(getattr(value, "cache_clear", None)):
                    value.cache_clear()
    gc.collect()
    _return_freed_memory()


def _return_freed_memory() -> None:
    """Hand the memory freed above back to the system: glibc keeps freed blocks in its arenas, so after
    `clear_caches` the process stayed near its peak. Measured after a module, before -> after `malloc_trim(0)`:
    test_problem 1328 -> 425 MB, test_multiview 1118 -> 505, test_engine 1497 -> 551. Not glibc (musl, macOS):
    nothing to trim, nothing done."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    if trim is not None:
        trim(0)


def require_data(sub: str) -> Path:
    """Path to ../shared/data/<sub>; skip (with the reason) only where the shared data is absent, and
    fail instead under CI (CI=true), where a skipped real-data test would leave the suite green untested."""
    path = DATA / sub
    if not path.exists():
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"real data {path} is absent, and CI=true requires it (put ../shared/data in place)")
        pytest.skip(f"real data {path} is absent on this machine (it is present in CI)")
    return path


SEED = DATA.parent / "seed"


def require_seed(name: str) -> Path:
    """Path to ../shared/seed/<name> (the thesis and its .ini files), with require_data's rule: skip only where
    it is absent on a developer's machine, fail under CI=true."""
    path = SEED / name
    if not path.is_file():
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"thesis file {path} is absent, and CI=true requires it (put ../shared/seed in place)")
        pytest.skip(f"thesis file {path} is absent on this machine (it is present in CI)")
    return path


def lm_agreement(std, n_residuals: int, n_params: int, ftol: float | None = None):
    """How far apart two LM solves of one problem may end, per parameter (same units as `std`).

    Both stop once an accepted step lowers the SSE S by at most ftol * S (status 1). Next to the optimum a
    nearly undamped step lands close to it, so its gain is the remaining excess d' J'J d <= ftol * S, and
    for each parameter d_i^2 <= (d' J'J d) [(J'J)^-1]_ii <= ftol * S [(J'J)^-1]_ii = ftol (n - p) std_i^2
    (std_i^2 = S / (n - p) [(J'J)^-1]_ii). Two solves within this of the optimum differ by at most twice it.
    "Nearly undamped": the damping, relative to diag(J'J), well below the smallest eigenvalue of the scaled J'J
    (1 / its condition number, ~1e-5 for a camera); it falls 3x per good step from 1e-3 (1e-6 for subsets).
    Use it between different programs (batched vs single, two ISAs), with both statuses checked to be 1;
    measured agreement is ~30x inside it (batched vs single on AVX-512: 2e-6 std against 6e-5).
    """
    from dstereo.solver.lm import LMOptions

    ftol = LMOptions().ftol if ftol is None else ftol
    return 2.0 * math.sqrt(ftol * (n_residuals - n_params)) * np.asarray(std)


def subset_agreement(std, n_residuals: int, n_params: int):
    """How far a subset solve of the subset runner may end from a tight independent solve of the same frames, per
    parameter (same units as `std`, the subset's own standard deviations).

    The runner stops a subset on the noise-unit test (`subset_solve.SUBSET_DECREMENT_TOL` = eps,
    `lm._decrement_stop`): the point it returns, one Gauss-Newton step past its last linearised point, within
    sqrt(2 eps) std (~1e-2) of the optimum x*: for any contraction c <= 0.5 by its first rule, and by its second
    where the contraction is at most CONTRACTION_SAFETY times the one it estimated (measured on real corners:
    within 7.5e-3 std). The independent solve adds its own `lm_agreement`.
    """
    from dstereo.calib.subset_solve import SUBSET_DECREMENT_TOL

    return math.sqrt(2.0 * SUBSET_DECREMENT_TOL) * np.asarray(std) + lm_agreement(std, n_residuals, n_params)


def subset_rms_agreement(n_residuals: int, n_params: int) -> float:
    """How far (relative) a subset's RMS may sit above its tight optimum's: the RMS is the last linearised point's,
    where the model's remaining gain F - F* (F = SSE / 2) is <= s eps sigma^2 = s eps SSE / (n - p) (s =
    `lm.LINEARISED_SLACK`, the second stop rule's bound; 1 for the first); up to the contraction's
    (1/(1 - c))^2 <= 4 (c <= 0.5) that is SSE - SSE* <= 8 s eps SSE / (n - p), so RMS (the square root) is within
    4 s eps / (n - p) relative."""
    from dstereo.calib.subset_solve import SUBSET_DECREMENT_TOL
    from dstereo.solver.lm import LINEARISED_SLACK

    return 4.0 * LINEARISED_SLACK * SUBSET_DECREMENT_TOL / (n_residuals - n_params)


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


def refused(args, out: Path | None, *mentions: str) -> str:
    """Run the CLI in process; assert exit 1, one stderr line `dstereo: error: ...` holding each of `mentions`,
    and that neither `out` nor `out.partial` was created. Returns the line."""
    code, _, err = run_cli(*args)
    lines = err.strip().splitlines()
    assert code == 1, (code, err)
    assert len(lines) == 1 and lines[0].startswith("dstereo: error: "), err
    for m in mentions:
        assert m in lines[0], (m, lines[0])
    if out is not None:
        assert not Path(out).exists(), f"{out} was written"
        assert not Path(str(out) + ".partial").exists(), f"{out}.partial was left"
    return lines[0]


# --- reports in a real browser (report.html: tests in the rooms that write each kind) ---------------------------

BROWSER = Path(os.environ.get("DSTEREO_TEST_BROWSER", "/usr/bin/chromium"))  # Debian's chromium; .ci/run installs it
# Headless, and nothing that reaches out on its own (updates, sync, metrics): a request seen is the page's.
# WebGL draws in software (SwiftShader) without a GPU; measured: plotly's 3D canvas draws with these flags alone.
# One process (`--single-process --no-zygote`), not chromium's usual eleven: each of its processes maps the same
# libraries, so the suite's process tree counted them once per process. Measured on a reconstruction's report
# (a 3D view, 2026-12-07): summed RSS 1741 -> 1226 MiB, PSS 1151 -> 1192 MiB, the same pixels drawn, the same
# images decoded; the suite's peak summed RSS is such a page beside the two workers.
BROWSER_ARGS = ("--headless", "--no-sandbox", "--disable-gpu", "--single-process", "--no-zygote",
                "--disable-background-networking", "--disable-component-update", "--no-first-run", "--disable-sync",
                "--disable-default-apps", "--disable-extensions", "--metrics-recording-only", "--mute-audio")


# A 3D view is drawn when more than this share of its canvas is coloured: the same scene with no data reads 0
# (tests/io/test_report_html.py's control), a 640 x 480 reconstruction's cloud 1-5 %.
DRAWN_SHARE = 0.002


def require_browser() -> Path:
    """The chromium binary that playwright drives; skip (with the reason) where it or playwright is absent on a
    developer's machine, fail under CI=true (.ci/run installs chromium, `make test` playwright)."""
    missing = None
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        missing = "the playwright package is not installed (it is in the lock's test extra: make install)"
    if missing is None and not BROWSER.is_file():
        missing = f"no browser at {BROWSER} (apt-get install chromium; .ci/run installs it)"
    if missing:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{missing}, and CI=true requires the browser tests to run")
        pytest.skip(f"{missing}: the report.html browser tests need it")
    return BROWSER


def open_reports(folders, screenshot: Path | None = None) -> list[dict]:
    """Open each folder's report.html from file:// in one headless chromium and return what the page did (see
    `tests/report_browser.py`); `screenshot`: the first page's top, saved there. This process's compiled programs
    are dropped first (as before a Dask cluster): chromium with a page holding a 3D view measured ~1.1 GB PSS over
    its processes (0.4 GB with a page of figures alone), beside the suite's two workers."""
    require_browser()
    release_compiled_programs()
    from report_browser import browse

    with one_big_process_at_a_time():
        return browse([Path(f) / "report.html" for f in folders], BROWSER, BROWSER_ARGS, screenshot)


@contextlib.contextmanager
def one_big_process_at_a_time():
    """An exclusive lock across the suite's processes while a test runs processes of its own that hold ~0.7-1.3 GB
    (a browser, a calibration's child process, a Dask cluster's workers): two such tests met beside the two
    workers and the process tree's summed RSS peaked at 3535 MiB (two chromiums, 2026-12-06) and 3239 MiB (a rig
    calibration's child beside a Dask cluster's two workers, 2026-12-07). The other worker waits its turn (5-30 s
    a time). No fcntl (not POSIX): no lock."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    import tempfile

    with open(Path(tempfile.gettempdir()) / "dstereo-suite-browser.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def assert_reports_render(folders) -> list[dict]:
    """Each folder's report.html, opened in the browser: no console error, no request outside the file, every
    image decoded, and a 3D view (where the page has one) drawn."""
    import re

    seen = open_reports(folders)
    for folder, page in zip(folders, seen):
        assert not page["errors"], (page["path"], page["errors"])
        assert not page["outside"], (page["path"], page["outside"])
        figures = [s for s in (Path(folder) / "report.md").read_text().splitlines()
                   if re.fullmatch(r"!\[[^\]]*\]\([^)\s]+\)", s.strip())]
        assert len(page["images"]) == len(figures), (page["path"], len(page["images"]), figures)
        assert all(w > 0 for w in page["images"]), (page["path"], page["images"])
        assert not page["has_view3d"] or page["views3d"], (page["path"], "a 3D view without a canvas")
        for view in page["views3d"]:
            assert view["webgl"] and view["coloured_share"] > DRAWN_SHARE, (page["path"], view)
    return seen
