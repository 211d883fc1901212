"""Where `dstereo calibrate`'s subset blocks run (`runtime.placement`: here, or on a Dask cluster with --workers /
--scheduler), the blocks of long runs kept for --resume, and the background build of the run's programs for other
view counts once it has ended (`runtime.prebuild`)."""

from __future__ import annotations

import typer


def subset_placement(workers, scheduler, resume, force, out, project):
    """Where subset blocks run (`runtime.placement`): on a Dask cluster with --workers N (N > 1) or --scheduler, else
    here; with the blocks of long runs kept in OUT.partial (--resume continues from them; removed once the run has
    ended with its results). Refuses bad values and an earlier run's blocks without --resume or --force, first."""
    import contextlib

    from dstereo.errors import DstereoError
    from dstereo.runtime.placement import Placement, placed

    runner = None
    if workers is not None or scheduler is not None:
        from dstereo.runtime.tasks import FrameRunner

        runner = FrameRunner(workers if workers is not None else 1, scheduler)
    target = out if out is not None else (project / "results" if project is not None else None)
    store = None
    if target is not None:
        from dstereo.io.partial_store import PartialStore, partial_folder

        folder = partial_folder(target)
        if folder.exists() and not resume and not force:
            raise DstereoError(f"{folder} holds the subset blocks of an earlier run; pass --resume to continue it, or "
                               "--force to start afresh")
        if resume and not folder.exists():
            raise DstereoError(f"--resume: {folder} does not exist: no earlier run of {target} to continue; run "
                               "without --resume")
        opened: dict = {}

        def store(key):
            """The blocks of one subset stage (a run may have several: each camera's, the rig's) in a folder of
            their own in OUT.partial, named by the stage's inputs."""
            if key not in opened:
                opened[key] = PartialStore(folder / key[:16], key).open(resume, force)
            return opened[key]

    @contextlib.contextmanager
    def around():
        with placed(Placement(runner, store)):
            yield
        build_ahead()
        if target is not None:  # the run ended with its results: its kept blocks are done with
            from dstereo.io.partial_store import PartialStore

            PartialStore(target, "").remove()

    return around()


def build_ahead() -> None:
    """The programs this run used whose shapes follow the view count, built for the other view buckets in the
    background (`runtime/prebuild.py`); said once per executables folder."""
    from dstereo.runtime import buckets, prebuild

    records, sizes = buckets.noted(), buckets.noted_sizes()
    buckets.clear_noted()
    if prebuild.start(records, sizes):
        told = prebuild.folder() / "told"
        if not told.exists():
            told.touch()
            typer.echo("dstereo: note: building this calibration's programs for other view counts (5-60) in the "
                       "background, one core at low priority, so that a data set of another size starts without "
                       "compiling; off: DSTEREO_PREBUILD=0 (this note is shown once)", err=True)
