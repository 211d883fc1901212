"""`dstereo reconstruct` with several pairs: each pair an independent task on a `FrameRunner`, its folder written
as it finishes into OUT.partial/pairs/ (atomically: a temporary folder renamed), the results folder assembled
atomically at the end (the pair folders moved into it, and the index summary.json).

A pair's folder is written where the task runs: on a cluster OUT.partial must be on a file system the workers
share with the client (as the images must). `--resume` reuses the pair folders of an interrupted run with the
same fingerprint; one pair that fails (a DstereoError) stops the run, keeping the finished pairs.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path


@dataclass
class PairDone:
    """What the client keeps of a pair (its arrays stay in its folder)."""

    name: str
    summary: dict
    warnings: list


def pair_names(pairs) -> list[str]:
    names = [Path(left).stem for left, _ in pairs]
    if len(set(names)) != len(names):
        names = [f"{i:02d}_{n}" for i, n in enumerate(names)]
    return names


def reconstruct_pair(job, calib, config, folder: str) -> PairDone:
    """Task: reconstruct one pair and write its folder under `folder` (atomically)."""
    from dstereo.io.json_files import json_default
    from dstereo.io.reconstruction_files import write_pair
    from dstereo.stereo.reconstruct import check_pair, reconstruct_calibrated, reconstruct_uncalibrated
    from dstereo.io.images import read_image

    name, left_path, right_path = job
    left, right = read_image(left_path), read_image(right_path)
    check_pair(left, right, calib, names=(str(left_path), str(right_path)))
    stem = Path(left_path).stem
    r = (reconstruct_uncalibrated(left, right, config, stem) if calib is None
         else reconstruct_calibrated(calib, left, right, config, stem))
    r.name = name
    target = Path(folder) / name
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.tmp-", dir=folder))
    try:
        from dstereo.io.atomic_files import follow_umask

        follow_umask(tmp, folder=True)  # the pair's results folder is this one renamed
        write_pair(tmp, r, config)
        (tmp / "pair_done.json").write_text(json.dumps({"name": name, "warnings": r.warnings, "summary": r.summary},
                                                        default=json_default))
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return PairDone(name, r.summary, list(r.warnings))


def reconstruct_pairs(pairs, out, calib_path, config, force: bool, runner, store, progress=None) -> list[PairDone]:
    """Every pair on `runner`; `store` (a PartialStore, opened) holds the finished pair folders."""
    from functools import partial

    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.json_files import json_default
    from dstereo.io.reconstruction_files import write_atomically
    from dstereo.io.reconstruction_report import write_index

    calib = read_stereo_calibration(calib_path) if calib_path is not None else None
    names = pair_names(pairs)
    folder = store.folder / "pairs"
    folder.mkdir(parents=True, exist_ok=True)
    done: dict[int, PairDone] = {}
    todo = []
    for i, (name, (left, right)) in enumerate(zip(names, pairs)):
        marker = folder / name / "pair_done.json"
        if marker.is_file():  # written last, before the folder is renamed into place: the pair is whole
            kept = json.loads(marker.read_text())
            done[i] = PairDone(name, kept["summary"], kept["warnings"])
        else:
            shutil.rmtree(folder / name, ignore_errors=True)
            todo.append((i, (name, str(left), str(right))))

    def finished(task):
        if task.failed:
            from dstereo.errors import DstereoError

            raise DstereoError(f"pair {pairs[task.index][0]}: {task.failed}")
        done[task.index] = task.value

    runner.map(partial(reconstruct_pair, calib=calib, config=config, folder=str(folder)), todo, finished, progress,
               "pairs", len(pairs) - len(todo), len(pairs))
    results = [done[i] for i in range(len(pairs))]

    def fill(tmp: Path):
        for r in results:
            os.replace(folder / r.name, tmp / r.name)
            (tmp / r.name / "pair_done.json").unlink()
        index = {"pairs": [r.summary for r in results], "config": config.as_dict()}
        (tmp / "summary.json").write_text(json.dumps(index, indent=2, default=json_default))
        write_index(tmp, [r.summary for r in results], [r.name for r in results])

    write_atomically(out, force, fill)
    store.remove()
    return results
