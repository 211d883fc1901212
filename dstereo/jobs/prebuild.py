"""The background builder of `runtime/prebuild.py`: each recorded program compiled for every view bucket of 5-60.

`python -m dstereo.jobs.prebuild FOLDER` (started by a command, detached): takes the lock, then the lists
FOLDER/todo-*.pkl one after another (a list left by a command while it runs included), and for each (kind, spec)
calls the program through the code that calls it in a calibration (`REPLAY`), on placeholder data at each bucket's
view count: the same arguments' shapes and types as a real call, so the executable it stores (`runtime/aot.py`) is
the one a real call of that count loads. Each program's marker is written once all its buckets are built.
"""

from __future__ import annotations

import fcntl
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

POSE = np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 1000.0]  # a placeholder board pose in front of the camera


def _solver(spec, views: int) -> None:
    from dstereo.calib.problem import run

    problem, key, one, k, n_pts, shared = spec
    run(problem, key, np.zeros((1, problem.n_shared)), np.tile(POSE, (1, views, 1)),
        np.full((1, views, k, n_pts, 2), np.nan), np.ones((1, views)), np.array([1e-3]), shared,
        rows=1 if one else None)


def _per_row(factory):
    def replay(spec, views: int) -> None:
        factory_args, template, row_args = spec
        fn = factory(*factory_args)
        fn(*(np.repeat(np.asarray(a), views, axis=0) if i in row_args else a for i, a in enumerate(template)))
    return replay


def _refit(*args):
    from dstereo.calib.final_solution import _refit as make

    return make(*args)


def _normalised_points(*args):
    from dstereo.calib.board_poses import normalised_points as make

    return make(*args)


def _pose_refit(*args):
    from dstereo.calib.model_choice import _pose_refit as make

    return make(*args)


def _projection_map(spec, views: int) -> None:
    from dstereo.uncertainty.projection import _map_fn

    index, method, model, params, q, range_ = spec
    n = len(index) + 6 * views
    _map_fn(index, method, model)(params, np.tile(POSE, (views, 1)), np.ones(views), 1e-6 * np.eye(n), q, range_)


def _rig_residuals(spec, views: int) -> None:
    from dstereo.calib.problem import batched_residuals
    from dstereo.calib.rig_subsets import RESIDUAL_BLOCK

    problem, shared, n_g = spec
    k, n_pts = len(shared[1]), len(shared[0])
    batched_residuals(problem)(np.zeros((RESIDUAL_BLOCK, n_g)), np.tile(POSE, (RESIDUAL_BLOCK, views, 1)),
                               np.full((RESIDUAL_BLOCK, views, k, n_pts, 2), np.nan), shared)


def _rig_covariance(spec, views: int) -> None:
    from dstereo.calib.rig_projection import _residual_jacobian

    problem, n_g, frame_shape, shared = spec
    _residual_jacobian(problem, n_g, views)(np.r_[np.zeros(n_g), np.tile(POSE, views)],
                                            np.full((views, *frame_shape), np.nan),
                                            np.zeros((views, int(np.prod(frame_shape)))), shared)


def _rig_camera_poses(spec, views: int) -> None:
    from dstereo.calib.rig_projection import _camera_poses_fn

    problem, k, n_g = spec
    _camera_poses_fn(problem, k, n_g, views)(np.r_[np.zeros(n_g), np.tile(POSE, views)])


REPLAY = {"solver": _solver, "refit": _per_row(_refit), "normalised_points": _per_row(_normalised_points),
          "pose_refit": _per_row(_pose_refit), "projection_map": _projection_map, "rig_residuals": _rig_residuals,
          "rig_covariance": _rig_covariance, "rig_camera_poses": _rig_camera_poses}


def build(records, views, deadline: float = float("inf"), log=print) -> int:
    """Build every (kind, spec) of `records` at each view count of `views` (bucket sizes, in that order: each count
    for every program before the next count), marking each program once built at every count; returns how many
    (program, count) were called. Stops at `deadline` (time.monotonic)."""
    from dstereo.runtime import prebuild

    where = prebuild.folder()
    if where is None:
        return 0
    todo = [(kind, spec) for kind, spec in records
            if kind in REPLAY and not (where / prebuild.marker(kind, spec)).exists()]
    failed: set[int] = set()
    calls = 0
    for v in views:
        t0, c0 = time.perf_counter(), time.process_time()
        for i, (kind, spec) in enumerate(todo):
            if i in failed:
                continue
            if time.monotonic() > deadline:
                return calls
            try:
                REPLAY[kind](spec, v)
                calls += 1
            except Exception as exc:  # noqa: BLE001 - one program that cannot be built leaves the others to build
                failed.add(i)
                log(f"prebuild: {kind} not built ({type(exc).__name__}: {exc})")
        log(f"prebuild: bucket {v} done ({len(todo) - len(failed)} program(s), {time.perf_counter() - t0:.1f} s, "
            f"{time.process_time() - c0:.1f} s CPU)")
    where.mkdir(parents=True, exist_ok=True)
    for i, (kind, spec) in enumerate(todo):
        if i not in failed:
            (where / prebuild.marker(kind, spec)).write_text(f"{kind}: {len(views)} view counts\n")
    return calls


def main(argv=None) -> int:
    from dstereo.runtime import buckets, prebuild

    where = Path((argv or sys.argv[1:])[0])
    try:
        os.nice(19)
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core: the others stay the user's
    except (OSError, AttributeError):
        pass
    lock = os.open(where / "lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return 0  # a builder is running: it takes this list too
    t0 = time.monotonic()
    deadline = t0 + prebuild.LIMIT_S
    views = buckets.sizes_between(*prebuild.VIEWS)
    print(f"prebuild: started, pid {os.getpid()}, {len(views)} view buckets", flush=True)
    while time.monotonic() < deadline:
        lists = sorted(where.glob("todo-*.pkl"))
        if not lists:
            break
        for path in lists:
            try:
                todo = pickle.loads(path.read_bytes())
                records, used = todo["records"], todo["sizes"]
            except (OSError, ValueError, pickle.UnpicklingError, EOFError, AttributeError, ImportError, KeyError,
                    TypeError):
                records, used = [], ()  # unreadable, or from another version: dropped
            build(records, buckets.nearest_first(views, used), deadline, log=lambda s: print(s, flush=True))
            if time.monotonic() < deadline:
                path.unlink(missing_ok=True)
    print(f"prebuild: done in {time.monotonic() - t0:.1f} s, {time.process_time():.1f} s CPU", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
