"""`dstereo`: the entry point. It parses, calls one library function and prints; the runtime is around it.

`main` is the `dstereo` script: where the process runs only this command it first offers it to a running
`dstereo serve` (dstereo/runtime/client.py, standard library only, before typer, numpy or JAX load), and runs it
here when none takes it; DSTEREO_SERVE=0 always runs here. Each subcommand lives in `dstereo/commands/<name>.py`
(heavy imports inside the function body so `dstereo --help` stays instant). Errors a user can fix
(`DstereoError`) become one line on stderr, exit 1.
"""

from __future__ import annotations

import errno
import functools
import os
import sys

# One BLAS thread in the command's process, set before numpy loads OpenBLAS: its linear algebra is on matrices of
# ~100 rows, where a second thread only waits for a core. While the figure workers draw on both cores, OpenBLAS's
# spinning threads made the results folder's one 129 x 129 eigh (the full set's joint covariance) take 0.18 s
# instead of 2 ms (measured at load ~3). A user's own setting wins; without effect where numpy is loaded already;
# not under pytest (its subprocesses keep the environment they had).
if "pytest" not in sys.modules:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@functools.lru_cache(maxsize=None)
def _app():
    """The typer application with every command (built on first use: a served command never loads typer)."""
    import typer

    from dstereo.commands import register_all

    app = typer.Typer(
        name="dstereo",
        help="Differentiable stereo photogrammetry: calibrate, rectify, reconstruct, measure with error bars.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        rich_markup_mode=None,  # help reads as written: option texts use [brackets] for sections and defaults
    )
    register_all(app)

    @app.callback()
    def _root() -> None:
        """Keeps typer in multi-command mode even while only one subcommand is registered."""

    return app


def __getattr__(name: str):
    if name == "app":  # `dstereo.cli.app`, built on first use
        return _app()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# What a served calibration imports (test_startup lists the same modules): loaded at start-up, not at the first command;
# the second line: what a first served calibration still imported (typer's value coercion imports pydantic;
# OpenCV; scipy.linalg for LAPACK's kernels; the modules the pipeline and results folder import where used).
SERVER_PRELOAD = ("jax", "jax.numpy", "dstereo.cli", "dstereo.jobs.calibrate_camera", "dstereo.jobs.calibrate_stereo",
                  "dstereo.calib.misfit", "dstereo.calib.mono", "dstereo.io.results",
                  "pydantic", "cv2", "scipy.linalg", "jax.experimental.serialize_executable", "dstereo.calib.outliers",
                  "dstereo.calib.model_choice", "dstereo.calib.view_checks", "dstereo.io.plots", "dstereo.io.sigma_maps",
                  "dstereo.io.cameramodel", "dstereo.uncertainty.projection")


def _echo(text: str) -> None:
    import typer

    typer.echo(text, err=True)


def main(end_process: bool | None = None) -> None:
    """Run the command line; ends with SystemExit (its exit code), or, where this process runs only the command
    (`end_process`, default: started as the `dstereo` script or `python -m dstereo.cli`, never under pytest),
    offers it to a running server first (`runtime.client.run_served`) and ends the process itself once the
    command's work is done (`finish`)."""
    from dstereo.runtime import interrupts, request

    end_process = _command_process() if end_process is None else end_process
    request.set_command(main, SERVER_PRELOAD)  # what a server started from this process runs for its clients
    if end_process:
        interrupts.install()  # first: a signal at any moment from here on ends the command cleanly
        from dstereo.runtime.client import run_served

        try:
            code = run_served(sys.argv[1:])
        except interrupts.Interrupted as exc:  # while the server ran it: the client said the line
            interrupted(exc)
        if code is not None:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    try:
        _dispatch()
    except SystemExit as exc:
        if not end_process:
            raise
        finish(exc.code)
    except interrupts.Interrupted as exc:  # SIGINT, SIGTERM, SIGHUP (dstereo/runtime/interrupts.py), or a served
        if not end_process:  # client's; library use, pytest, the server: the caller decides; the line is said
            _echo(f"dstereo: error: {exc}")
            interrupts.mark_said()
            raise
        interrupted(exc)
    if end_process:
        finish(0)


def interrupted(exc) -> None:
    """End the process of a command that a signal stopped: its one line, every child process killed (figure
    workers, multiprocessing's resource tracker, a local Dask cluster's workers: none may keep the caller's pipes
    open), exit 128 + the signal's number. Its staging folders were removed while it unwound."""
    from dstereo.runtime import interrupts

    interrupts.say(exc)
    # SIGKILL, not the pools' shutdown: joining a worker takes time, and a pool's manager thread, seeing its
    # worker gone, makes multiprocessing relaunch its resource tracker (with a warning on the caller's stderr)
    interrupts.kill_children()
    sys.stdout.flush()
    os._exit(exc.code)


def _command_process() -> bool:
    main_module = sys.modules.get("__main__")
    spec = getattr(main_module, "__spec__", None)
    name = spec.name if spec is not None else os.path.basename(getattr(main_module, "__file__", "") or "")
    # a `dstereo serve` process runs many commands: it ends none of them with the process (nor stops its warm
    # figure workers, which `finish` would)
    serving = "dstereo.runtime.server" in sys.modules
    # `dstereo` (the script) and `python -m dstereo.cli` end as the script does; `python -c` code calling this
    # `main` is library use unless it says `end_process=True` (as the tests' stand-ins for the script do)
    named = name in ("dstereo", "dstereo.cli")
    return named and "pytest" not in sys.modules and not serving


def finish(code) -> None:
    """End the command's process with `code` (SystemExit's: None = 0, a message = printed, 1) without the
    interpreter's teardown: ~0.4 s of freeing JAX's and matplotlib's modules and joining threads, with nothing
    left to write (measured at load ~2, rig640 C=4845). Everything the command wrote is complete by now: the
    results folder is in place (written and renamed before the command returns), the figure workers are joined
    here, the compilation cache and executable files are written synchronously as they compile, and stdout and
    stderr are flushed last."""
    from dstereo.runtime import figure_pool, interrupts

    if interrupts.received() is not None:  # a signal whose exception was lost (interrupts.check): not a success
        interrupted(interrupts.Interrupted(interrupts.received()))
    if code is not None and not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    figure_pool.stop()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code or 0)


def _dispatch() -> None:
    from dstereo.errors import DstereoError

    try:
        _app()()  # standalone: usage errors print and exit 2 by themselves
    except DstereoError as exc:  # the library names parameters; the line names the flags of the command that ran
        from dstereo.config.messages import command_of, with_flags

        _echo(f"dstereo: error: {with_flags(str(exc), command_of(sys.argv))}")
        sys.exit(1)
    except OSError as exc:  # a file system refusal while reading or writing (disk full, permissions): name the file
        if os.environ.get("DSTEREO_DEBUG"):
            raise
        if exc.errno in (errno.EMFILE, errno.ENFILE):  # the process ran out of descriptors: no file is at fault
            import resource

            limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
            opening = f" while opening {exc.filename}" if exc.filename else ""
            _echo(f"dstereo: error: {exc.strerror or exc}: this process (or the system) has run out of open "
                  f"files (limit {limit}, `ulimit -n`){opening}; the file is not at fault: give fewer --workers, "
                  "stop stray dstereo/Dask processes (`dstereo serve --stop`), or raise the limit")
            sys.exit(1)
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        _echo(f"dstereo: error:{where}: {exc.strerror or exc}; check the path, free space and permissions")
        sys.exit(1)
    except Exception as exc:
        # OpenCV's own errors on input no check above caught: one line instead of a traceback (DSTEREO_DEBUG=1
        # shows the traceback)
        cv = exc if _from_opencv(exc) else exc.__cause__ if _from_opencv(exc.__cause__) else None
        if cv is None or os.environ.get("DSTEREO_DEBUG"):
            raise
        detail = " ".join(str(cv).split()).rsplit("error: ", 1)[-1]
        _echo(f"dstereo: error: OpenCV refused the input ({detail}); check the images and parameters, and "
              "report this if they are right (DSTEREO_DEBUG=1 shows where)")
        sys.exit(1)


def _from_opencv(exc: BaseException | None) -> bool:
    return exc is not None and type(exc).__module__.split(".")[0] == "cv2"


if __name__ == "__main__":
    main()
