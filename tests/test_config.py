"""Configuration: the thesis's initialisation files (Figures 5.5, 5.14) and dstereo's TOML load to one Config."""

from dataclasses import replace
from pathlib import Path

import pytest

from dstereo.config.calibration import (Config, Step, config_from_thesis_ini, config_from_toml, find_project_config,
                            load_config, parse_step_flag, template, to_toml, validate)
from dstereo.errors import DstereoError

SEED = Path(__file__).resolve().parents[1].parent / "shared" / "seed"
FIGURE_5_5_STEPS = (
    Step(("re",), (0.5,)), Step(("p1", "p2"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5, 1.5, 1.5)),
    Step(("fx", "fy", "cx", "cy"), (1.0, 1.0, 1.0, 1.0)),
)


def _seed(name: str) -> Path:
    from conftest import require_seed

    return require_seed(name)


def test_figure_5_5_file_loads_as_written():
    cfg = load_config(_seed("init-individual.ini"))
    assert cfg.mode == "individual"
    assert cfg.pattern == (9, 6)  # mesh width x mesh height = inner corners
    assert cfg.square == 10.0 and cfg.unit == "mm"
    assert cfg.image_format == "jpg"
    assert cfg.per_set == 10
    assert cfg.model == ("k1", "k2", "p1", "p2", "k3")  # 'k1, k2, k3, p1, p2' in OpenCV order
    assert cfg.steps == FIGURE_5_5_STEPS
    assert cfg.stereo_steps == ()
    assert cfg.warnings == ()
    assert validate(cfg) is cfg


def test_figure_5_14_file_keeps_stereo_steps_apart():
    cfg = load_config(_seed("init-stereo.ini"))
    assert cfg.mode == "stereo"
    assert cfg.steps == ()
    assert cfg.stereo_steps == (Step(("stereo_re",), (3.0,)), Step(("Tnorm",), (0.75,)), Step(("RVnorm",), (0.75,)))
    assert (cfg.image_format_left, cfg.image_format_right) == ("jpg", "jpg")


def test_template_toml_is_figure_5_5():
    ini = load_config(_seed("init-individual.ini"))
    toml = config_from_toml(to_toml(template()), "template")
    stereo = load_config(_seed("init-stereo.ini")).stereo_steps  # the template carries Figure 5.14's stereo steps
    assert toml == replace(ini, image_format_left=None, image_format_right=None, stereo_steps=stereo)


@pytest.mark.parametrize("cfg", [
    template(),
    Config(pattern=(7, 5), square=2.5, unit="cm", glob="left*.png", model=("k1", "k2"), per_set=6, max_subsets=50,
           seed=3, min_subsets=12, steps=(Step(("re", "fx"), (0.4, 2.0), min_subsets=20),),
           stereo_steps=(Step(("Tnorm", "RVx"), (0.75, 1.0)),)),
    Config(pattern=(4, 3)),
])
def test_toml_round_trip(cfg):
    for comments in (True, False):
        assert config_from_toml(to_toml(cfg, comments), "x") == cfg


def test_thesis_syntax_variants():
    text = """
# a comment line
[ Calibration ]
Individual calibration = 1   # trailing comment
image format = "PNG"
Square Size = 2.5 # in mm
mesh   width = 7
mesh height = 5,
images per set = 4,
camera matrix parameters = FX, fy, cx, CY,
distortion coefficients parameters = K1, k2,
[ Optimization ]
[[ Calibration steps ]]
number steps = 2
minimum subsets = 5
[[[ step 2 ]]]
    parameters = FX, fy,   # focal lengths
    max error = 1, 2.5,
[[[ step 1 ]]]
    parameters = RE
    max error = 0.8
    minimum subsets = 3
[ Disparity ]
block size = 5
"""
    cfg = config_from_thesis_ini(text, "t.ini")
    assert cfg.pattern == (7, 5) and cfg.square == 2.5 and cfg.image_format == "png" and cfg.per_set == 4
    assert cfg.model == ("k1", "k2")
    assert cfg.min_subsets == 5
    assert cfg.steps == (Step(("re",), (0.8,), 3), Step(("fx", "fy"), (1.0, 2.5)))
    assert len(cfg.warnings) == 1 and "block size" in cfg.warnings[0]  # other applications' sections: ignored


def _ini(steps: str, calibration: str = "mesh width = 9\nmesh height = 6\nimages per set = 10\n") -> str:
    return (f"[ Calibration ]\nIndividual calibration = 1\n{calibration}"
            f"[ Optimization ]\n[[ Calibration steps ]]\n{steps}")


@pytest.mark.parametrize("steps, message", [
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fz,\nmax error = 1,\n", "unknown parameter 'fz'"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = -1,\n", "must be a positive number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = 0,\n", "must be a positive number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = big,\n", "is not a number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fy\n", "max error is missing"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fy\nmax error = 1,\n",
     "2 parameter(s) (fx, fy) but 1 max error"),
    ("number steps = 1\n[[[ step 1 ]]]\nmax error = 1,\n", "no parameters"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fx\nmax error = 1, 1\n", "listed twice"),
    ("number steps = 2\n[[[ step 1 ]]]\nparameters = fx\nmax error = 1\n", "number steps = 2 but"),
    ("[[[ step 2 ]]]\nparameters = fx\nmax error = 1\n", "numbered [2]"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx\nmax error = 1\nalpha = 3\n", "unknown key 'alpha'"),
])
def test_bad_steps_name_the_problem(steps, message):
    with pytest.raises(DstereoError) as exc:
        config_from_thesis_ini(_ini(steps), "bad.ini")
    assert message in str(exc.value) and "bad.ini" in str(exc.value)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("calibration, message", [
    ("mesh wdth = 9\n", "unknown key 'mesh wdth'"),
    ("mesh width = 9\n", "both mesh width and mesh height"),
    ("Stereo calibration = 1\n", "both Individual calibration and Stereo calibration are 1"),
    ("camera matrix parameters = fx, fy\n", "always solves fx, fy, cx, cy"),
    ("distortion coefficients parameters = k1, q2\n", "unknown distortion coefficient"),
    ("images per set = 2\n", "m >= 3"),
    ("square size = ten\n", "is not a valid value"),
])
def test_bad_calibration_section(calibration, message):
    with pytest.raises(DstereoError, match=message.replace("(", r"\(")):
        config_from_thesis_ini(_ini("", calibration), "b.ini")


def test_toml_errors():
    base = "[pattern]\ncolumns = 9\nrows = 6\n[calibration]\nper_set = 10\n"
    cases = {
        base + "[[steps]]\nparameters = ['fx', 'k9']\nmax_error = [1, 1]\n": "unknown parameter 'k9'",
        base + "[[steps]]\nparameters = ['fx']\nmax_error = [-0.5]\n": "must be a positive number",
        base + "[[steps]]\nparameters = ['fx', 'fy']\nmax_error = [1]\n": "but 1 max error",
        base + "[[steps]]\nparameters = ['fx']\n": "max error is missing",
        base + "[[steps]]\nparameters = ['fx']\nmax_error = [1]\nmax = 2\n": "unknown key(s) ['max']",
        base + "[images]\nfolde = 'x'\n": "unknown key(s) ['folde'] in [images]",
        base + "[patern]\n": "unknown key or table 'patern'",
        "[pattern]\ncolumns = 9\n": "needs both columns and rows",
        "[calibration]\nper_set = 2\n": "per_set",
        "[calibration]\nmodel = 'k1,k7'\n": "unknown distortion coefficient",
        "x = [": "not valid TOML",
    }
    for text, message in cases.items():
        with pytest.raises(DstereoError) as exc:
            config_from_toml(text, "c.toml")
        assert message in str(exc.value), (text, str(exc.value))


def test_toml_ignores_other_commands_tables():
    cfg = config_from_toml("[pattern]\ncolumns = 9\nrows = 6\n[reconstruct]\nalpha = 0\n[sgbm]\nblock_size = 5\n", "d")
    assert cfg.pattern == (9, 6)


def test_validate_cross_checks():
    with pytest.raises(DstereoError, match="no board pattern"):
        validate(Config())
    with pytest.raises(DstereoError, match="need subsets"):
        validate(Config(pattern=(9, 6), steps=(Step(("fx",), (1.0,)),)))
    with pytest.raises(DstereoError, match="step 1 filters k3 but the distortion model"):
        validate(Config(pattern=(9, 6), per_set=5, model=("k1", "k2"), steps=(Step(("k3",), (1.0,)),)))
    with pytest.raises(DstereoError, match="square size"):
        validate(Config(pattern=(9, 6), square=-1.0))


def test_step_flags():
    assert parse_step_flag("re=0.5", 1) == Step(("re",), (0.5,))
    assert parse_step_flag("P1=1.5, p2=1.5", 2) == Step(("p1", "p2"), (1.5, 1.5))
    with pytest.raises(DstereoError, match="NAME=MAX_ERROR"):
        parse_step_flag("fx,fy=1", 1)
    with pytest.raises(DstereoError, match="unknown parameter 'tx'"):
        parse_step_flag("tx=1", 1)  # stereo names are not mono step parameters


def test_project_config_discovery(tmp_path):
    assert find_project_config(tmp_path) is None
    (tmp_path / "my.ini").write_text("[ Calibration ]\n")
    assert find_project_config(tmp_path) == tmp_path / "my.ini"
    (tmp_path / "other.toml").write_text("")
    with pytest.raises(DstereoError, match="several configuration files"):
        find_project_config(tmp_path)
    (tmp_path / "dstereo.toml").write_text("")
    assert find_project_config(tmp_path) == tmp_path / "dstereo.toml"
    with pytest.raises(DstereoError, match="does not exist"):
        find_project_config(tmp_path / "nope")
    with pytest.raises(DstereoError, match="does not exist"):
        load_config(tmp_path / "nope.toml")
