"""The package's import graph: no cycles, and each room imports only the rooms below it.

The graph is read from the source with `ast`, not by importing: every `import` and `from ... import` counts,
at module level, inside functions (a deferred import is still a dependency, and one that hides a cycle is
still a cycle) and under `if TYPE_CHECKING:` (a type named in a signature ties the two modules as well), and
`importlib` loads: `import_module("dstereo.io.results")` is an edge to that module, `import_module(f"dstereo.commands.
{name}")` an edge to every module under that prefix, and a "dstereo.config.x:Config" string (the entry-point form
loaded by name) an edge to its module. A name held in a variable (a tuple of modules to preload) is not followed.
Relative imports are resolved against the importing module's package. `from pkg import name` is an edge to
`pkg.name` when that is a module of the package, else to `pkg`. Importing `a.b.c` also runs `a/__init__` and
`a/b/__init__`; those implied edges are left out, as import-linter and pydeps leave them out, because a
package's `__init__` re-exporting its own modules would otherwise put every room in a cycle with itself.
"""

import ast
import re
import textwrap
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dstereo"

from dstereo.layers import RANKS


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


_ENTRY_STRING = re.compile(r"^[A-Za-z_]\w*(\.\w+)+:\w+$")


def _is_import_call(node: ast.Call) -> bool:
    """`importlib.import_module(...)`, `import_module(...)` or `__import__(...)`."""
    f = node.func
    return (isinstance(f, ast.Attribute) and f.attr == "import_module") or \
        (isinstance(f, ast.Name) and f.id in ("import_module", "__import__"))


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
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and _ENTRY_STRING.match(node.value):
            add(node.value.split(":")[0])  # a "module:attribute" reference, loaded with importlib
        elif isinstance(node, ast.Call) and _is_import_call(node) and node.args:
            name = node.args[0]
            if isinstance(name, ast.Constant) and isinstance(name.value, str):
                add(name.value)
            elif isinstance(name, ast.JoinedStr) and name.values and isinstance(name.values[0], ast.Constant):
                prefix = str(name.values[0].value)  # f"pkg.commands.{name}": every module under the prefix
                if prefix.startswith(top + "."):
                    found.update(k for k in known if k.startswith(prefix[len(top) + 1:]) and k != module)
        elif isinstance(node, ast.Import):
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


def layering_breaches(graph: dict[str, set[str]], ranks: dict[str, int] = RANKS) -> list[str]:
    """Every import against the rank table, as 'a -> b: the rule'."""
    breaches = []
    for source, targets in sorted(graph.items()):
        for target in sorted(targets):
            a, b = room(source), room(target)
            if a == b:
                continue
            for r in (a, b):
                if r not in ranks:
                    breaches.append(f"{source} -> {target}: room '{r}' is not in the rank table (dstereo/layers.py)")
            if a in ranks and b in ranks and ranks[b] >= ranks[a]:
                rule = "of the same rank" if ranks[b] == ranks[a] else "of a higher rank"
                breaches.append(f"{source} -> {target}: {a} ({ranks[a]}) imports {b} ({ranks[b]}), a room {rule}")
    return breaches


# --- the real package ---------------------------------------------------------------------------------------

def test_the_graph_is_read_from_every_module():
    graph = import_graph(PACKAGE)
    # Sanity: a module known to import another shows that edge, so an empty graph cannot pass the tests below.
    assert len(graph) == len(list(PACKAGE.rglob("*.py")))
    assert "errors" in graph[""], "dstereo/__init__ imports dstereo.errors"


def test_no_import_cycle():
    cycles = find_cycles(import_graph(PACKAGE))
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_rooms_import_only_downwards():
    breaches = layering_breaches(import_graph(PACKAGE))
    assert not breaches, "layering breaches:\n" + "\n".join(breaches)


def test_every_room_has_a_rank_and_every_rank_a_room():
    rooms = {room(m) for m in import_graph(PACKAGE)}
    assert rooms == set(RANKS), f"rooms without a rank: {sorted(rooms - set(RANKS))}; ranks without a room: " \
        f"{sorted(set(RANKS) - rooms)}"


def test_no_two_rooms_import_each_other():
    graph = import_graph(PACKAGE)
    edges = {(room(s), room(t)) for s, ts in graph.items() for t in ts if room(s) != room(t)}
    mutual = sorted({tuple(sorted(e)) for e in edges if e[::-1] in edges})
    assert not mutual, f"rooms importing each other: {mutual}"


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
        # importlib loads by name: a plain string, a "module:attribute" reference, an f-string over a package
        "config/__init__.py": "",
        "config/options.py": "import importlib\nTYPE = 'fakepkg.calib.job:Job'\n",
        "cli.py": "import importlib\ndef load(n):\n    return importlib.import_module(f'fakepkg.commands.{n}')\n",
        "solver/__init__.py": "",
        "solver/lm.py": "import importlib\nimportlib.import_module('fakepkg.stereo.a')\n",
    })


def test_checker_resolves_relative_and_deferred_imports(planted):
    graph = import_graph(planted)
    assert graph["stereo.b"] == {"stereo.a"}  # `from . import a` inside a function
    assert graph["calib.job"] == {"commands.run", "io.files"}  # `from ..commands.run import main`
    assert graph["io.files"] == {"models"}  # `Camera` is an attribute of the package, not a module
    assert graph["models"] == {"models.camera"}
    assert graph["config.options"] == {"calib.job"}  # "module:attribute"
    assert graph["cli"] == {"commands.run"}  # f"fakepkg.commands.{n}": every module under the prefix
    assert graph["solver.lm"] == {"stereo.a"}


def test_checker_reports_the_planted_cycle_as_a_path(planted):
    cycles = find_cycles(import_graph(planted))
    assert cycles == [["stereo.a", "stereo.b", "stereo.a"]]


def test_checker_reports_the_planted_breaches(planted):
    breaches = layering_breaches(import_graph(planted))
    assert breaches == [
        "calib.job -> commands.run: calib (6) imports commands (12), a room of a higher rank",
        "calib.job -> io.files: calib (6) imports io (8), a room of a higher rank",
        "config.options -> calib.job: config (4) imports calib (6), a room of a higher rank",
        "io.report -> commands.run: io (8) imports commands (12), a room of a higher rank",
        "models.rig -> stereo.a: models (2) imports stereo (6), a room of a higher rank",
        "runtime.server -> commands.run: runtime (2) imports commands (12), a room of a higher rank",
        "solver.lm -> stereo.a: solver (3) imports stereo (6), a room of a higher rank",
    ]


def test_checker_reports_same_rank_and_unranked_rooms(planted):
    graph = import_graph(planted)
    graph["stereo.a"] = graph["stereo.a"] | {"calib.job"}  # calib and stereo share rank 6
    graph["calib.job"] = {"extra.x"}
    graph["extra.x"] = set()
    breaches = layering_breaches(graph)
    assert "stereo.a -> calib.job: stereo (6) imports calib (6), a room of the same rank" in breaches
    assert "calib.job -> extra.x: room 'extra' is not in the rank table (dstereo/layers.py)" in breaches


# --- io computes nothing ----------------------------------------------------------------------------------------

COMPUTE_ROOMS = ("solver", "uncertainty", "calib", "stereo", "reference", "recession", "optics")
# Functions of a compute room that io may call, each with why it is reading or writing, not computing a result.
IO_MAY_CALL: dict[tuple[str, str, str], str] = {}


def io_imports_from_compute_rooms(package: Path) -> list[tuple[str, str, str]]:
    """(io module, compute module, name) of every `from dstereo.<compute room>... import name` inside io/."""
    names, found = module_names(package), []
    for module, path in names.items():
        if room(module) != "io":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("dstereo."):
                source = node.module[len("dstereo."):]
                if room(source) in COMPUTE_ROOMS:
                    found += [(module, source, alias.name) for alias in node.names]
    return found


def test_io_takes_finished_results_and_computes_nothing():
    """io may import types and constants from the rooms that compute, never a function that computes (the job
    computes, then hands io the finished result), except IO_MAY_CALL."""
    import importlib
    import inspect

    calls = []
    for io_module, source, name in io_imports_from_compute_rooms(PACKAGE):
        value = getattr(importlib.import_module(f"dstereo.{source}"), name)
        if callable(value) and not inspect.isclass(value) and (io_module, source, name) not in IO_MAY_CALL:
            calls.append(f"{io_module} calls {source}.{name}")
    assert not calls, "io computing (compute it in the job and pass the result):\n" + "\n".join(calls)
    assert set(IO_MAY_CALL) <= set(io_imports_from_compute_rooms(PACKAGE)), "IO_MAY_CALL names an import gone"


# --- the tests and the package never import experiments/ ------------------------------------------------------

TESTS = Path(__file__).resolve().parent
_EXPERIMENTS_NAME = re.compile(r"^experiments(\.\w+)*$")
_EXPERIMENTS_SCRIPT = re.compile(r"^(\./)?experiments/\w+\.py$")


def experiment_uses(path: Path) -> list[tuple[int, str]]:
    """(line, name) where `path` imports `experiments` (import, from-import) or names one to load or run: a string
    that is a whole module name under it (`import_module("experiments.x")`, `[python, "-m", "experiments.x"]`) or
    a path to one of its scripts ("experiments/x.py"). Prose that mentions experiments/ is not a use."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names = [node.module or ""]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names = [node.value] if _EXPERIMENTS_NAME.match(node.value) or _EXPERIMENTS_SCRIPT.match(node.value) else []
        found += [(node.lineno, n) for n in names if n.split(".")[0].split("/")[0] == "experiments"]
    return sorted(found)


def test_no_test_and_no_module_of_the_package_imports_experiments():
    """experiments/ regenerates docs/validation.md's figures and `make bench`; what a test needs lives in
    dstereo/synth/ or a helper module under tests/ (tests/calib/opencv_reference.py)."""
    uses = [f"{p.relative_to(TESTS.parent)}:{line}: {name}" for root in (TESTS, PACKAGE)
            for p in sorted(root.rglob("*.py")) if p != Path(__file__).resolve()  # this file names the forms
            for line, name in experiment_uses(p)]
    assert not uses, "experiments used:\n" + "\n".join(uses)


def test_the_experiments_check_sees_each_form(tmp_path):
    planted = tmp_path / "planted.py"
    planted.write_text("import experiments.a\nfrom experiments import b\nfrom experiments.c import d\n"
                       "importlib.import_module('experiments.e')\nsubprocess.run([sys.executable, '-m', "
                       "'experiments.f'])\nrun('experiments/g.py')\n# experiments/h.py in a comment\n"
                       "'''see experiments/results/i.md'''\n")
    found = [name for _, name in experiment_uses(planted)]
    assert found == ["experiments.a", "experiments", "experiments.c", "experiments.e", "experiments.f",
                     "experiments/g.py"]
