"""The package's import graph: no cycles, and each room imports only the rooms below it.

The graph is read from the source with `ast`, not by importing: every `import` and `from ... import` counts,
at module level, inside functions (a deferred import is still a dependency, and one that hides a cycle is
still a cycle) and under `if TYPE_CHECKING:` (a type named in a signature ties the two modules as well).
Relative imports are resolved against the importing module's package. `from pkg import name` is an edge to
`pkg.name` when that is a module of the package, else to `pkg`. Importing `a.b.c` also runs `a/__init__` and
`a/b/__init__`; those implied edges are left out, as import-linter and pydeps leave them out, because a
package's `__init__` re-exporting its own modules would otherwise put every room in a cycle with itself.
"""

import ast
import textwrap
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dstereo"

# Rooms that compute: they take arrays and finished results, never a command-line option or a file format.
COMPUTE_ROOMS = ("models", "solver", "calib", "stereo", "uncertainty", "recession", "reference", "optics",
                 "synth", "frames")

# Compute-room modules whose job is to run a whole stage from files to files, or to read a room's input folder:
# they may call `io` (reading the inputs, writing the results folder). Each is orchestration, not computation.
ORCHESTRATION = {
    "stereo.pipeline",  # `reconstruct`: images + stereo.yml in, a results folder out (run_reconstruction)
    "reference.files",  # `refine`: a calibration, a pair and a reference object in, a refined folder out
    "recession.sequence",  # reads a sequence folder (pairs by file name, the times file)
    "recession.synthetic",  # writes a synthetic sequence folder (images, stereo.yml) the command reads
    "frames.pairs",  # one frame of a run: reads the calibration, reconstructs, writes the frame's folder
    "frames.store",  # the per-frame results store on disk (one JSON a frame)
    "synth.truth",  # writes and reads the truth files beside a synthetic render
    "calib.pipeline",  # `calibrate`, one camera: an image folder in (corner detection), a finished job out
    "calib.stereo_pipeline",  # `calibrate`, a stereo rig: the pairs' folders in, a finished job out
    "calib.stereo_folders",  # the same from two folders alone, for tests and experiments
}

LEAD_TO_CLEAR: set[str] = set()  # calibration modules waived while the core was rewritten: none left

# Compute modules waived to import io.calib_files for the `StereoCalibration` type while it lived there.
RIG_TYPE_IN_IO: set[str] = set()  # `StereoCalibration` now lives in models/stereo_calibration.py: none left

# Cycles waived while the calibration core was rewritten: none left (`rig_covariance` moved to uncertainty/rig.py).
LEAD_CYCLES: list[set[str]] = []


def module_names(package: Path) -> dict[str, Path]:
    """Every module of `package` by dotted name relative to it ('' for its own __init__, 'io.results', ...)."""
    names = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        names[".".join(parts)] = path
    return names


def _absolute(node: ast.ImportFrom, module: str, is_package: bool, top: str) -> str:
    """The absolute dotted name `from <node.level dots><node.module>` refers to, inside `module`."""
    if node.level == 0:
        return node.module or ""
    base = f"{top}.{module}".rstrip(".").split(".")
    if not is_package:
        base.pop()
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(path: Path, module: str, top: str, known: set[str]) -> set[str]:
    """The package modules that `module` (file `path`) imports, as names relative to the package `top`."""
    is_package = path.name == "__init__.py"
    found = set()

    def add(absolute: str) -> bool:
        if absolute != top and not absolute.startswith(top + "."):
            return False
        relative = absolute[len(top) + 1:]
        if relative in known:
            found.add(relative)
            return True
        return False

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(node, module, is_package, top)
            # Each imported name is a submodule or an attribute of `source`.
            if not all([add(f"{source}.{alias.name}") for alias in node.names]):
                add(source)
    found.discard(module)
    return found


def import_graph(package: Path) -> dict[str, set[str]]:
    """module -> the package modules it imports (names relative to the package)."""
    names = module_names(package)
    return {module: imports_of(path, module, package.name, set(names)) for module, path in names.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle path [a, b, ..., a] through each strongly connected group of modules (Tarjan's algorithm)."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.add(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(group)

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return [_cycle_in(group, graph) for group in groups]


def _cycle_in(group: set[str], graph: dict[str, set[str]]) -> list[str]:
    """A shortest cycle through the group's first member (breadth-first inside the group)."""
    start = min(group)
    came_from = {start: None}
    queue = [start]
    for node in queue:
        for nxt in sorted(graph[node] & group):
            if nxt == start:
                path = [node]
                while came_from[path[-1]] is not None:
                    path.append(came_from[path[-1]])
                return path[::-1] + [start]
            if nxt not in came_from:
                came_from[nxt] = node
                queue.append(nxt)
    raise AssertionError(f"no cycle inside the group {sorted(group)}")


def room(module: str) -> str:
    return module.split(".")[0]


def layering_breaches(graph: dict[str, set[str]], orchestration=ORCHESTRATION,
                      waived=LEAD_TO_CLEAR | RIG_TYPE_IN_IO) -> list[str]:
    """Every import that crosses a room boundary the wrong way, as 'a -> b: the rule'."""
    breaches = []
    for source, targets in sorted(graph.items()):
        for target in sorted(targets):
            for rule in _broken_rules(source, target, orchestration, waived):
                breaches.append(f"{source} -> {target}: {rule}")
    return breaches


def _broken_rules(source: str, target: str, orchestration, waived):
    if room(source) == "models" and room(target) not in ("models", "errors"):
        yield "models/ imports only models and errors"
    if room(source) == "runtime" and room(target) not in ("runtime", "errors", ""):  # "": the package's version
        yield ("runtime/ imports only runtime and errors (it runs the command line it is given: "
               "runtime.request.set_command)")
    if room(source) in COMPUTE_ROOMS and room(target) in ("commands", "cli"):
        yield "a compute room never imports commands or the cli"
    if room(target) == "commands" and room(source) not in ("commands", "cli"):
        yield "only cli and commands import commands"
    if room(source) == "io" and room(target) == "commands":
        yield "io never imports commands"
    if (room(source) in COMPUTE_ROOMS and room(target) == "io" and source not in orchestration
            and source not in waived):
        yield "a compute room imports io only from its orchestration modules (ORCHESTRATION)"
    if source in RIG_TYPE_IN_IO and room(target) == "io" and target != "io.calib_files":
        yield "a module waived for the rig type (RIG_TYPE_IN_IO) imports no other io module"


# --- the real package ---------------------------------------------------------------------------------------

def test_the_graph_is_read_from_every_module():
    graph = import_graph(PACKAGE)
    # Sanity: a module known to import another shows that edge, so an empty graph cannot pass the tests below.
    assert len(graph) == len(list(PACKAGE.rglob("*.py")))
    assert "errors" in graph[""], "dstereo/__init__ imports dstereo.errors"


def test_no_import_cycle():
    cycles = [c for c in find_cycles(import_graph(PACKAGE)) if set(c) not in LEAD_CYCLES]
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_rooms_import_only_downwards():
    breaches = layering_breaches(import_graph(PACKAGE))
    assert not breaches, "layering breaches:\n" + "\n".join(breaches)


def test_named_exceptions_still_exist_and_still_need_their_waiver():
    graph = import_graph(PACKAGE)
    stale = sorted(m for m in ORCHESTRATION | LEAD_TO_CLEAR | RIG_TYPE_IN_IO if m not in graph)
    assert not stale, f"ORCHESTRATION/LEAD_TO_CLEAR/RIG_TYPE_IN_IO name modules that no longer exist: {stale}"
    cleared = sorted(m for m in ORCHESTRATION | LEAD_TO_CLEAR | RIG_TYPE_IN_IO
                     if "io" not in {room(t) for t in graph[m]})
    assert not cleared, f"these no longer import io; take them out of their exception set: {cleared}"
    gone = [c for c in LEAD_CYCLES if set(c) not in [set(f) for f in find_cycles(graph)]]
    assert not gone, f"these cycles are broken; take them out of LEAD_CYCLES: {gone}"


# --- the checker on a planted package -----------------------------------------------------------------------

def _write_package(root: Path, files: dict[str, str]) -> Path:
    package = root / "fakepkg"
    for name, text in files.items():
        path = package / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return package


@pytest.fixture
def planted(tmp_path):
    return _write_package(tmp_path, {
        "__init__.py": "",
        "errors.py": "",
        "models/__init__.py": "from .camera import Camera\n",
        "models/camera.py": "from fakepkg import errors\nclass Camera: ...\n",
        # A cycle hidden in a deferred, relative import: stereo.a -> stereo.b -> (inside a function) stereo.a.
        "stereo/__init__.py": "",
        "stereo/a.py": "from fakepkg.stereo import b\n",
        "stereo/b.py": "def f():\n    from . import a\n    return a\n",
        # Layering breaches: a model importing a compute room, a compute room importing a command and io.
        "models/rig.py": "import fakepkg.stereo.a\n",
        "calib/__init__.py": "",
        "calib/job.py": "from ..commands.run import main\nfrom fakepkg.io import files\n",
        "io/__init__.py": "",
        "io/files.py": "from fakepkg.models import Camera\n",
        "io/report.py": "import fakepkg.commands.run\n",  # io reaching up into a command
        "commands/__init__.py": "",
        "commands/run.py": "def main(): ...\n",
        # The runtime reaching up to the command line it serves (it must be handed it instead)
        "runtime/__init__.py": "",
        "runtime/server.py": "def serve():\n    from fakepkg.commands.run import main\n    main()\n",
    })


def test_checker_resolves_relative_and_deferred_imports(planted):
    graph = import_graph(planted)
    assert graph["stereo.b"] == {"stereo.a"}  # `from . import a` inside a function
    assert graph["calib.job"] == {"commands.run", "io.files"}  # `from ..commands.run import main`
    assert graph["io.files"] == {"models"}  # `Camera` is an attribute of the package, not a module
    assert graph["models"] == {"models.camera"}


def test_checker_reports_the_planted_cycle_as_a_path(planted):
    cycles = find_cycles(import_graph(planted))
    assert cycles == [["stereo.a", "stereo.b", "stereo.a"]]


def test_checker_reports_the_planted_breaches(planted):
    breaches = layering_breaches(import_graph(planted), orchestration=set(), waived=set())
    assert breaches == [
        "calib.job -> commands.run: a compute room never imports commands or the cli",
        "calib.job -> commands.run: only cli and commands import commands",
        "calib.job -> io.files: a compute room imports io only from its orchestration modules (ORCHESTRATION)",
        "io.report -> commands.run: only cli and commands import commands",
        "io.report -> commands.run: io never imports commands",
        "models.rig -> stereo.a: models/ imports only models and errors",
        "runtime.server -> commands.run: runtime/ imports only runtime and errors (it runs the command line it is "
        "given: runtime.request.set_command)",
        "runtime.server -> commands.run: only cli and commands import commands",
    ]
    waived = layering_breaches(import_graph(planted), orchestration={"calib.job"}, waived=set())
    assert not any("io.files" in b for b in waived)
