"""config/capabilities.py: the one table of what `calibrate` does for each kind of rig, the refusals taken from
it, and the README's table generated from it."""

from pathlib import Path

import pytest

from dstereo.config.capabilities import CAPABILITIES, KINDS, SPLINED, STEREO_STEPS, markdown_table, refusal, refuse
from dstereo.errors import DstereoError

README = Path(__file__).resolve().parents[2] / "README.md"


def test_the_readme_holds_the_generated_table():
    assert markdown_table() in README.read_text(), "README.md: paste `python -m dstereo.config.capabilities`"


def test_every_cell_is_built_or_one_line_that_says_what_to_do():
    for feature, cells in CAPABILITIES.items():
        assert len(cells) == len(KINDS), feature
        for kind in KINDS:
            why = refusal(feature, kind)
            assert why is None or ("\n" not in why and len(why) > 20), (feature, kind, why)


def test_a_refused_request_gets_the_tables_line_with_how_it_was_asked():
    with pytest.raises(DstereoError, match=r"^--step Tnorm=1: stereo steps need a rig; give --left DIR"):
        refuse(STEREO_STEPS, "one camera", "--step Tnorm=1")
    refuse(STEREO_STEPS, "--cameras")  # built: nothing raised
    with pytest.raises(DstereoError, match="no such inverse"):
        refuse(SPLINED, "--left/--right", "--model splined")
    refuse(SPLINED, "one camera")  # built: nothing raised
