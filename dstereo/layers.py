"""The rooms of the package, lowest rank first. A room imports only rooms of a lower rank (never one of its own
rank, never one above it, not even inside a function); `tests/test_import_graph.py` enforces it on every import,
deferred and `importlib` loads included. The top-level modules `errors` and `layers` are rank 0, the package's own
`__init__` rank 1."""

RANKS: dict[str, int] = {
    "errors": 0, "layers": 0,  # the error type; this table
    "": 1,  # dstereo/__init__: the version and the JAX set-up on import (it raises the error type)
    "models": 2,  # pure-JAX lens, pose, rig and board models and their result types
    "runtime": 2,  # server, client, autostart, compiled programs, figure pool, tasks, jaxlib workarounds
    "solver": 3,  # batched Levenberg-Marquardt
    "optics": 3,  # the depth-of-field calculator
    "config": 4,  # options, defaults < file < flags, the capability table, the settings types
    "uncertainty": 5,  # covariances, projection maps, per-point sigma
    "calib": 6,  # one calibration problem and its stages for K cameras
    "stereo": 6,  # rectify, match, triangulate one pair
    "reference": 7,  # rig refinement from a known object
    "recession": 7,  # recession over time from reconstructed frames
    "io": 8,  # read inputs, write finished results (files, figures, reports)
    "synth": 9,  # renders with known truth, written as the commands read them
    "jobs": 10,  # each command's work from files to files: io -> compute -> io
    "demo": 11,  # `dstereo demo`: jobs on a rendered rig
    "commands": 12,  # parse, call one job, print
    "cli": 13,  # the entry point: the commands around the runtime
}


def rank_table() -> str:
    """The table as markdown (docs/design.md shows it)."""
    by_rank: dict[int, list[str]] = {}
    for room, rank in RANKS.items():
        by_rank.setdefault(rank, []).append(f"`{room}`" if room else "`dstereo/__init__`")
    rows = [f"| {rank} | {', '.join(rooms)} |" for rank, rooms in sorted(by_rank.items())]
    return "\n".join(["| rank | rooms |", "|---|---|", *rows])
