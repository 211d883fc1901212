"""Huge subset runs: lazy plans, the per-subset table on disk, block-by-block solves, estimates and refusals.

The end-to-end check runs the CLI twice on OpenCV's 13 left images (286 subsets): once as usual, once with
the table forced onto disk, blocks of a few dozen subsets and no solver outputs kept, as a run of millions
would. Both runs read the same numbers in the same order, so their files must be identical byte for byte.
"""

import itertools
import json
import math

import numpy as np
import pytest

from conftest import one_big_process_at_a_time, release_compiled_programs, require_data, run_cli
from dstereo.calib import subset_runs, subset_table
from dstereo.calib.robust_steps import run_steps
from dstereo.calib.subset_runs import estimate_run, solve_in_blocks
from dstereo.calib.subset_table import SubsetTable
from dstereo.calib.subsets import REJECTION_MAX, plan_subsets, unrank
from dstereo.runtime.tasks import eta_text
from dstereo.config.calibration import Step
from dstereo.errors import DstereoError


def test_unrank_is_itertools_order():
    ref = np.array(list(itertools.combinations(range(11), 5)))
    assert np.array_equal(unrank(np.arange(len(ref)), 11, 5), ref)
    assert np.array_equal(unrank(np.array([len(ref) - 1, 0, 17]), 11, 5), ref[[len(ref) - 1, 0, 17]])


def test_huge_plans_hold_no_index_table():
    # C(29, 20) = 10015005: exhaustive holds nothing per subset, a 1e7 sample 8 bytes (its ranks) per subset.
    full = plan_subsets(29, 20, cap=10015005)
    assert full.exhaustive and len(full) == math.comb(29, 20) and full._index is None
    assert np.array_equal(full.rows(0, 2), [list(range(20)), list(range(19)) + [20]])
    assert np.array_equal(full.rows(len(full) - 1, len(full)), [list(range(9, 29))])
    sample = plan_subsets(29, 20, cap=10 ** 7, seed=4)
    assert not sample.exhaustive and len(sample) == 10 ** 7 and sample._index is None
    assert sample._ranks.nbytes == 8 * 10 ** 7
    block = sample.rows(5_000_000, 5_020_000)
    assert (np.diff(block, axis=1) > 0).all() and len({tuple(r) for r in block}) == len(block)
    assert np.array_equal(block, plan_subsets(29, 20, cap=10 ** 7, seed=4).rows(5_000_000, 5_020_000))


def test_small_samples_are_the_samples_of_before():
    # Up to REJECTION_MAX the rejection sampler (and so every seeded sample of an existing project) is kept.
    rng = np.random.default_rng(3)
    chosen = set()
    while len(chosen) < 500:
        chosen.add(tuple(sorted(rng.choice(25, 12, replace=False).tolist())))
    assert np.array_equal(plan_subsets(25, 12, cap=500, seed=3).index, np.array(sorted(chosen)))
    assert 500 <= REJECTION_MAX


@pytest.mark.parametrize("limit", [None, 0])
def test_table_in_memory_and_on_disk_read_back_the_rows(tmp_path, limit):
    rows = np.random.default_rng(0).normal(size=(1000, 4))
    table = SubsetTable(("a", "b", "c", "d"), 1000, folder=tmp_path, memory_limit=limit)
    assert table.on_disk == (limit == 0)
    for a in range(0, 1000, 300):
        table.put(a, rows[a:a + 300], np.arange(a, min(a + 300, 1000)) % 3)
    assert np.array_equal(table.column("c"), rows[:, 2]) and np.array_equal(table.rows(250, 700), rows[250:700])
    assert np.array_equal(table.status, np.arange(1000) % 3)
    path = table.path
    assert path is None or not path.exists()  # unlinked on creation: nothing to leave behind
    table.close()


def test_steps_on_a_disk_table_equal_steps_on_the_array(tmp_path):
    rng = np.random.default_rng(1)
    rows = np.column_stack([np.abs(rng.normal(0.3, 0.1, 3000)), rng.standard_t(3, size=(3000, 2))])
    table = SubsetTable(("re", "x", "y"), 3000, folder=tmp_path, memory_limit=0)
    table.put(0, rows, np.ones(3000))
    steps = (Step(("re",), (0.45,)), Step(("x", "y"), (1.5, 1.5)))
    usable = rng.random(3000) > 0.01
    a, b = run_steps(rows, ("re", "x", "y"), steps, usable), run_steps(table, ("re", "x", "y"), steps, usable)
    assert np.array_equal(a.removed_at, b.removed_at) and a.stats(2) == b.stats(2)
    assert b.steps[1].passes >= 1 and b.stats(2)["x"]["count"] < b.stats(0)["x"]["count"]


def test_blocks_keep_no_solver_output_above_the_limit(tmp_path, monkeypatch):
    monkeypatch.setattr(subset_runs, "KEEP_SOLUTIONS", 100)
    monkeypatch.setattr(subset_runs, "BLOCK_TARGET", 64)
    plan = plan_subsets(12, 6)  # 924 subsets
    seen, notes, done = [], [], []

    def solve_block(block, report):
        seen.append(len(block))
        report(len(block), len(block))
        return block.index[:, :2].astype(float), np.ones(len(block)), object()

    table, kept = solve_in_blocks(plan, ("i0", "i1"), solve_block, chunk=8, folder=tmp_path,
                                  progress=lambda d, n: done.append((d, n)), note=notes.append, memory_limit=0)
    assert kept == [] and table.on_disk and max(seen) == 64 and sum(seen) == 924
    assert np.array_equal(table.column("i1"), plan.index[:, 1]) and done[-1] == (924, 924)
    assert len(notes) == 1 and "subsets/s on the first 64" in notes[0]
    table.close()


def test_estimate_refuses_what_cannot_fit(monkeypatch, tmp_path):
    est = estimate_run(10 ** 7, 10, 20, tmp_path)
    assert est.table_on_disk and est.ram_bytes < 1.5 * 2 ** 30  # the acceptance run's bound
    assert "10000000 to solve" in est.text() and "streamed" in est.text()
    monkeypatch.setattr(subset_runs, "available_memory", lambda: 2 ** 30)
    with pytest.raises(DstereoError, match=r"10000000000 subsets need about .* of memory but 1 GB is available; "
                                           r"lower --max-subsets to at most about \d+"):
        estimate_run(10 ** 10, 10, 20, tmp_path).check()


def test_eta_text():
    assert eta_text(0, 10, 5.0) == "" and eta_text(10, 10, 5.0) == ""
    assert eta_text(25, 100, 20.0) == "ETA 60 s" and eta_text(1, 100, 30.0) == "ETA 50 min"


@pytest.fixture(scope="module")
def left_images():
    return sorted(require_data("opencv_stereo").glob("left*.jpg"))


# The 5-coefficient model and 13 views of test_calibrate_cli.py: the suite compiles the solver once for both.
FLAGS = ["--pattern", "9x6", "--square", "10", "--model", "k1,k2,p1,p2,k3", "--per-set", "10",
         "--step", "re=0.5", "--step", "fx=1.5,fy=1.5", "-q"]


@pytest.mark.slow
def test_streamed_run_writes_the_same_folder(tmp_path, left_images, monkeypatch):
    images = tmp_path / "images"
    images.mkdir()
    for src in left_images:
        (images / src.name).symlink_to(src)
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "plain")
    assert code == 0, err
    monkeypatch.setattr(subset_table, "MEMORY_LIMIT_BYTES", 0)
    monkeypatch.setattr(subset_runs, "BLOCK_TARGET", 40)
    monkeypatch.setattr(subset_runs, "KEEP_SOLUTIONS", 0)
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "streamed")
    assert code == 0, err
    for name in ("subsets.csv", "camera.yml", "stats/step_2.txt", "stats/parameter_fx.txt"):
        assert (tmp_path / "plain" / name).read_bytes() == (tmp_path / "streamed" / name).read_bytes(), name
    plain, streamed = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("plain", "streamed"))
    assert plain["subsets"] == streamed["subsets"] and plain["final"] == streamed["final"]
    assert not list(tmp_path.glob(".dstereo-subsets-*"))  # the per-subset file is removed


def test_a_run_that_cannot_fit_is_refused_before_any_solve(tmp_path, left_images, monkeypatch):
    monkeypatch.setattr(subset_runs, "available_memory", lambda: 100 * 2 ** 20)
    images = tmp_path / "images"
    images.mkdir()
    for src in left_images:
        (images / src.name).symlink_to(src)
    code, out, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "res")
    assert code == 1 and not (tmp_path / "res").exists()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dstereo: error: max-subsets: 286 subsets need about")
    assert "100 MB is available; free memory first" in lines[0]


def test_csv_lines_are_what_csv_writer_writes(tmp_path):
    import csv

    from dstereo.io.results import write_subsets_csv

    rng = np.random.default_rng(5)
    rows = np.column_stack([np.abs(rng.normal(0.3, 0.1, 50)), rng.normal(800, 1, 50), rng.normal(0, 1e-4, 50)])
    f = run_steps(rows, ("re", "fx", "p1"), (Step(("re",), (0.35,)),), rng.random(50) > 0.1)
    plan, status = plan_subsets(8, 4, cap=50, seed=1), rng.integers(-1, 3, 50)
    write_subsets_csv(tmp_path / "ours.csv", plan, f, status)
    with open(tmp_path / "ref.csv", "w", newline="") as fh:  # the writer of before, cell by cell
        w = csv.writer(fh)
        w.writerow(["subset", "images", "fx", "p1", "rms", "converged", "survives", "removed_at_step", "solver_status"])
        for i in range(50):
            fate = int(f.removed_at[i])
            w.writerow([i, " ".join(map(str, plan.index[i])), *(repr(float(rows[i, j])) for j in (1, 2, 0)),
                        int(fate != -1), int(fate == 0), fate if fate > 0 else "", int(status[i])])
    assert (tmp_path / "ours.csv").read_bytes() == (tmp_path / "ref.csv").read_bytes()




def test_a_stopped_run_resumes_from_its_kept_blocks(tmp_path, monkeypatch):
    """With a store (runtime.placement), each finished block is kept; a run stopped in its third block (Ctrl-C)
    resumes: the kept blocks are read back, only the others solved, and the table is the uninterrupted run's."""
    from dstereo.io.partial_store import PartialStore
    from dstereo.runtime.placement import Placement, placed

    monkeypatch.setattr(subset_runs, "KEEP_SOLUTIONS", 100)
    monkeypatch.setattr(subset_runs, "BLOCK_TARGET", 64)
    plan = plan_subsets(12, 6)  # 924 subsets: 15 blocks of 64
    solved = []

    def solve_block(block, report, stop_at=None):
        if stop_at is not None and len(solved) == stop_at:
            raise KeyboardInterrupt
        solved.append(int(block.index[0, 0] * 1000 + block.index[0, -1]))
        return block.index[:, :2] + 0.5, np.where(block.index[:, 0] == 0, 1, -1), None

    key = (np.arange(5.0), "model")
    stores = {}

    def store(k):
        stores.setdefault(k, PartialStore(tmp_path / k[:16], k).open(resume=True, force=False))
        return stores[k]

    whole, _ = solve_in_blocks(plan, ("a", "b"), solve_block, chunk=8)
    solved.clear()
    with placed(Placement(store=store)), pytest.raises(KeyboardInterrupt):
        solve_in_blocks(plan, ("a", "b"), lambda b, r: solve_block(b, r, stop_at=2), chunk=8, key=key)
    assert len(solved) == 2 and next(iter(stores.values())).count() == 2 and len(stores) == 1
    solved.clear()
    notes = []
    with placed(Placement(store=store)):
        table, kept = solve_in_blocks(plan, ("a", "b"), solve_block, chunk=8, key=key, note=notes.append)
    assert len(solved) == 15 - 2 and "resumed" in notes[0]
    assert np.array_equal(table.rows(0, len(plan)), whole.rows(0, len(plan)))
    assert np.array_equal(table.status, whole.status)
    with placed(Placement(store=store)):  # other inputs: a store of their own, nothing reused
        solved.clear()
        solve_in_blocks(plan, ("a", "b"), solve_block, chunk=8, key=(np.arange(6.0), "model"))
    assert len(solved) == 15


@pytest.mark.slow
def test_blocks_on_a_dask_cluster_give_the_serial_files(tmp_path, left_images, monkeypatch):
    """`--workers 2`: the subset blocks are tasks of a local Dask cluster (two processes); the run's files are the
    serial run's, byte for byte (the blocks are the same problems in the same compiled program)."""
    images = tmp_path / "images"
    images.mkdir()
    for src in left_images:
        (images / src.name).symlink_to(src)
    monkeypatch.setattr(subset_runs, "BLOCK_TARGET", 64)
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "serial")
    assert code == 0, err
    release_compiled_programs()
    with one_big_process_at_a_time():  # two worker processes of ~350 MB each: not beside a browser or a child run
        code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "dask", "--workers", "2")
    assert code == 0, err
    for name in ("subsets.csv", "camera.yml", "stats/step_2.txt", "stats/parameter_fx.txt"):
        assert (tmp_path / "serial" / name).read_bytes() == (tmp_path / "dask" / name).read_bytes(), name
    assert not (tmp_path / "dask.partial").exists()


def test_resume_without_an_earlier_run_and_blocks_without_resume_are_refused_first(tmp_path, left_images):
    """--resume with no OUT.partial, and an OUT.partial without --resume or --force: one line, exit 1, before any
    work (no results folder)."""
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", *FLAGS,
                           "--out", tmp_path / "res", "--resume")
    assert code == 1 and "--resume" in err and "does not exist" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "res.partial").mkdir()
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", *FLAGS,
                           "--out", tmp_path / "res")
    assert code == 1 and "holds the subset blocks of an earlier run" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "res").exists()


@pytest.mark.slow
def test_a_stopped_calibration_resumes_and_writes_the_uninterrupted_files(tmp_path, left_images, monkeypatch):
    """The command: a run of streamed blocks (as above) stopped by Ctrl-C in its third block keeps two blocks in
    OUT.partial and no results folder; `--resume` solves only the others and writes the uninterrupted run's files,
    then removes OUT.partial."""
    from dstereo.calib import mono

    images = tmp_path / "images"
    images.mkdir()
    for src in left_images:
        (images / src.name).symlink_to(src)
    monkeypatch.setattr(subset_table, "MEMORY_LIMIT_BYTES", 0)
    monkeypatch.setattr(subset_runs, "BLOCK_TARGET", 40)
    monkeypatch.setattr(subset_runs, "KEEP_SOLUTIONS", 0)
    solve, calls, stop = mono.solve_subsets, [], []

    def counted(*a, **k):  # one call per block of subsets
        calls.append(1)
        if stop and len(calls) == 3:
            raise KeyboardInterrupt
        return solve(*a, **k)

    monkeypatch.setattr(mono, "solve_subsets", counted)
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "whole")
    assert code == 0, err
    blocks, calls[:] = len(calls), []
    assert blocks > 3
    stop.append(True)
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "res")
    assert code != 0 and not (tmp_path / "res").exists()
    assert len(list((tmp_path / "res.partial").glob("*/frames/*.json"))) == 2
    stop.clear()
    calls[:] = []
    code, _, err = run_cli("calibrate", "--images", images, *FLAGS, "--out", tmp_path / "res", "--resume")
    assert code == 0, err
    assert len(calls) == blocks - 2  # the kept blocks read back, not solved again
    for name in ("subsets.csv", "camera.yml", "stats/step_2.txt"):
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "res" / name).read_bytes(), name
    assert not (tmp_path / "res.partial").exists()
