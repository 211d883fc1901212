"""The source an executable's key covers (dstereo/runtime/source_modules.py): the import closure of the modules a
program is defined in, read from the files; an edit outside it keeps the digest, an edit inside changes it, and a
name imported at run time makes it the whole package. Checked on a small package written here (every kind of
import the closure must follow) and on the package's own calibration solver."""

import pytest

from dstereo.runtime import source_modules

FILES = {
    "__init__.py": "",
    "top.py": "import os\nfrom dstereo.mid import helper\nfrom . import sibling\n",
    "mid.py": "def helper():\n    from dstereo.low import deep  # deferred\n    return deep\n",
    "low.py": "import importlib\nX = importlib.import_module('dstereo.named')\ndeep = 1\n",
    "named.py": "from .pkg import (\n    leaf,\n    other as o,\n)\n",
    "sibling.py": "",
    "pkg/__init__.py": "",
    "pkg/leaf.py": "",
    "pkg/other.py": "",
    "apart.py": "import dstereo.top\n",  # imports the others, imported by none
    "dynamic.py": "import importlib\nname = 'dstereo.apart'\nimportlib.import_module(name)\n",
    "uses_dynamic.py": "from dstereo import dynamic\n",
}


@pytest.fixture
def package(tmp_path, monkeypatch):
    root = tmp_path / "dstereo"
    for name, text in FILES.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    monkeypatch.setattr(source_modules, "ROOT", root)
    monkeypatch.setattr(source_modules, "_state", {})
    return root


def test_the_closure_follows_every_kind_of_import_and_nothing_else(package):
    reach = source_modules.closure(["dstereo.top"])
    assert reach == {"dstereo", "dstereo.top", "dstereo.mid", "dstereo.sibling", "dstereo.low", "dstereo.named",
                     "dstereo.pkg", "dstereo.pkg.leaf", "dstereo.pkg.other"}
    assert source_modules.closure(["dstereo.pkg.leaf"]) == {"dstereo", "dstereo.pkg", "dstereo.pkg.leaf"}


def test_a_name_imported_at_run_time_makes_it_the_whole_package(package):
    assert source_modules.closure(["dstereo.uses_dynamic"]) is None
    assert source_modules.digest(["dstereo.uses_dynamic"]) == source_modules.digest()
    assert source_modules.digest(["json"]) == source_modules.digest()  # a module outside the package


def test_an_edit_outside_the_closure_keeps_the_digest_and_one_inside_changes_it(package):
    before = source_modules.digest(["dstereo.top"])
    (package / "apart.py").write_text("import dstereo.top\nEDITED = 1\n")
    source_modules._state.clear()
    assert source_modules.digest(["dstereo.top"]) == before
    (package / "pkg" / "other.py").write_text("EDITED = 1\n")
    source_modules._state.clear()
    assert source_modules.digest(["dstereo.top"]) != before


def test_the_calibration_solver_depends_on_its_engine_not_on_the_writers_or_commands():
    from dstereo.calib.problem import Problem, compiled_solver
    from dstereo.solver.lm import LMOptions

    solver = compiled_solver(Problem.of([("k1", "k2")]), LMOptions())
    reach = source_modules.closure(solver.modules)
    assert {"dstereo.calib.problem", "dstereo.solver.lm", "dstereo.models.camera"} <= reach
    rooms = {name.split(".")[1] for name in reach if name.count(".") >= 1}
    assert not rooms & {"io", "jobs", "commands", "stereo", "recession", "demo"}, sorted(reach)


def test_what_a_program_captures_counts_among_its_modules():
    """A value `fn` captures (a partial's argument, a closure cell) brings its module into the key's roots, as
    the classes of the static values do; a function defined outside the package makes it the whole package."""
    import functools

    from dstereo.models.pose import rodrigues
    from dstereo.runtime import aot
    from dstereo.solver.cholesky import cholesky

    assert aot.defining_modules(functools.partial(rodrigues), ()) == ("dstereo.models.pose",)
    captured = functools.partial(rodrigues, helper=cholesky)
    assert aot.defining_modules(captured, ()) == ("dstereo.models.pose", "dstereo.solver.cholesky")
    assert aot.defining_modules(lambda x: x, ()) is None
