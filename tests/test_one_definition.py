"""One type per concept, built in one place (STYLE.md habit 11): a scan of the package's source that fails when
a second rig-parameter list, rotation log, Newton undistortion or board-corner grid appears."""

import re
from pathlib import Path

import dstereo

PACKAGE = Path(dstereo.__file__).parent
PENDING: set[str] = set()  # files allowed a second definition for now: none


def _sites(pattern: str) -> set[str]:
    rx = re.compile(pattern, re.MULTILINE)
    return {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py") if rx.search(p.read_text())} - PENDING


def test_rig_parameter_names_are_defined_once():
    assert _sites(r"^RIG_NAMES\b[^=\n]*=") == {"models/rig.py"}


def test_one_rotation_log():
    assert _sites(r"def log_rotation|def rotvec|as_rotvec\(|Rotation\.from_matrix") == {"models/pose.py"}


def test_one_newton_undistortion():
    # The projection uncertainty takes the distortion's Jacobian for its orientation test (a determinant), not
    # for a Newton step; every step is `models.distortion.newton_step`.
    assert _sites(r"jacfwd\(distort") == {"models/distortion.py", "uncertainty/projection.py"}
    assert _sites(r"def (newton_step|undistort)\b") == {"models/distortion.py", "uncertainty/point_jacobians.py"}


def test_board_corners_are_built_once():
    assert _sites(r"mgrid\[0:\s*(self\.)?rows|range\(rows\)\s+for\s+\w+\s+in\s+range\(cols\)") == {"models/board.py"}


def test_rig_carriers_hold_the_one_rig():
    from dstereo.reference import RigBase
    from dstereo.synth import StereoRig

    assert StereoRig.__dataclass_fields__["rig"].type == "Rig"
    assert RigBase.__annotations__["rig"] == "Rig"
