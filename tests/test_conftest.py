"""The suite's own rules: real-data tests (and the report.html browser tests) skip with the reason on a machine
without the data (the browser), and fail under CI."""

from pathlib import Path

import pytest

import conftest


@pytest.mark.parametrize("ci,outcome", [("", pytest.skip.Exception), ("true", pytest.fail.Exception)])
def test_absent_real_data_skips_locally_and_fails_under_ci(monkeypatch, tmp_path, ci, outcome):
    monkeypatch.setattr(conftest, "DATA", tmp_path / "no_data")
    monkeypatch.setenv("CI", ci)
    with pytest.raises(outcome, match="opencv_stereo"):
        conftest.require_data("opencv_stereo")


@pytest.mark.parametrize("ci,outcome", [("", pytest.skip.Exception), ("true", pytest.fail.Exception)])
def test_absent_browser_skips_locally_and_fails_under_ci(monkeypatch, tmp_path, ci, outcome):
    monkeypatch.setattr(conftest, "BROWSER", tmp_path / "no_chromium")
    monkeypatch.setenv("CI", ci)
    with pytest.raises(outcome, match="no_chromium"):
        conftest.require_browser()


def test_present_real_data_is_returned(monkeypatch, tmp_path):
    (tmp_path / "opencv_stereo").mkdir()
    monkeypatch.setattr(conftest, "DATA", tmp_path)
    monkeypatch.setenv("CI", "true")
    assert conftest.require_data("opencv_stereo") == tmp_path / "opencv_stereo"


def test_every_memory_heavy_module_exists():
    """A renamed module would silently leave the group that keeps the two workers' peaks apart."""
    root = Path(__file__).resolve().parents[1]
    missing = [m for m in conftest.MEMORY_HEAVY if not (root / m).is_file()]
    assert not missing, missing


def test_a_numerics_mark_outside_its_file_is_found(tmp_path):
    """make test's second pass collects only the files with the word "numerics"; a test marked otherwise is named."""
    plain, marked = tmp_path / "test_plain.py", tmp_path / "test_marked.py"
    plain.write_text("def test_x(): pass\n")
    marked.write_text("import pytest\n@pytest.mark.numerics\ndef test_y(): pass\n")

    class Item:
        def __init__(self, path, mark):
            self.path, self.nodeid, self._mark = path, f"{path.name}::t", mark

        def get_closest_marker(self, name):
            return self._mark if name == "numerics" else None

    items = [Item(plain, object()), Item(marked, object()), Item(plain, None)]
    assert conftest.marked_outside_their_file(items) == ["test_plain.py::t"]


def test_the_longest_units_are_handed_out_first():
    """LONGEST_FIRST's units lead (a renamed module would silently go back to the end), the others keep xdist's
    order (most tests first)."""
    root = Path(__file__).resolve().parents[1]
    assert all(u == "memory-heavy" or (root / u).is_file() for u in conftest.LONGEST_FIRST), conftest.LONGEST_FIRST
    queue = ["tests/b.py", "tests/a.py", "memory-heavy", "tests/c.py"]
    assert conftest.longest_first(queue)[: len(conftest.LONGEST_FIRST)] == list(conftest.LONGEST_FIRST)
    assert [u for u in conftest.longest_first(queue) if u not in conftest.LONGEST_FIRST] == [
        "tests/b.py", "tests/a.py", "tests/c.py"]


def test_a_long_test_left_in_the_quick_tier_is_named_and_a_slow_or_short_one_is_not(monkeypatch):
    """`make test` names the tests not marked slow whose set-up or call took over QUICK_TIER_NOTE_S."""
    from types import SimpleNamespace

    noted = []
    monkeypatch.setattr(conftest, "_long_in_quick_tier", noted)
    long_s = conftest.QUICK_TIER_NOTE_S + 1
    for when, duration, keywords, nodeid in [("call", long_s, {}, "a.py::long"),
                                             ("setup", long_s, {}, "a.py::long_setup"),
                                             ("call", long_s, {"slow": 1}, "a.py::marked"),
                                             ("teardown", long_s, {}, "a.py::teardown_only"),
                                             ("call", 0.5, {}, "a.py::short")]:
        conftest.pytest_runtest_logreport(SimpleNamespace(when=when, duration=duration, keywords=keywords,
                                                          nodeid=nodeid))
    assert [line.split()[-1] for line in noted] == ["a.py::long", "a.py::long_setup"]
