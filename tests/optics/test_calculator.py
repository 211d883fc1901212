"""`dstereo optics`: thesis Tables 5.1-5.3 pinned, DoF vs the thin-lens blur geometry, CLI errors, JSON, plots."""

import json
import math
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from dstereo.optics import calculator as optics
from dstereo.cli import app, main
from dstereo.errors import DstereoError

THESIS_SETUP = {"focus_distance": 1000.0, "focal_length": 50.0, "sensor": "22.5x16.9", "f_number": 16.0}
THESIS_FLAGS = ["--focus-distance", "1000", "--focal-length", "50", "--sensor", "22.5x16.9", "--f-number", "16"]


def _cli(args):
    """Run the CLI app on `optics` args (typer collapses a one-command app, so add the name only when needed)."""
    single = len(app.registered_commands) == 1 and app.registered_callback is None and not app.registered_groups
    return CliRunner().invoke(app, list(args) if single else ["optics", *args])


def _line(result) -> str:
    """The error as `dstereo optics` prints it: the library names parameters, the CLI line names their flags."""
    from dstereo.config.messages import with_flags

    return with_flags(str(result.exception), "optics")


# --- thesis truth ------------------------------------------------------------------------------------------
def test_table_5_2_and_5_3_from_the_sensor_unrounded():
    r = optics.compute_optics(optics.make_config(THESIS_SETUP))
    assert r["sensor_diagonal_mm"] == pytest.approx(28.14, abs=0.005)  # Table 5.2
    assert round(r["crop_factor"], 2) == 1.54
    assert r["effective_focal_length_mm"] == pytest.approx(76.88, abs=0.005)
    assert round(r["coc_mm"], 3) == 0.022
    expected = {  # Table 5.3
        "hyperfocal_mm": 16887.17, "near_mm": 947.94, "far_mm": 1058.11, "total_dof_mm": 110.16,
        "front_mm": 52.06, "behind_mm": 58.10, "front_percent": 47.25, "behind_percent": 52.75,
    }
    for key, value in expected.items():
        assert r[key] == pytest.approx(value, abs=0.01), key
    assert r["far_is_infinite"] is False


def test_rounded_crop_factor_and_coc_do_not_give_table_5_3():
    """The thesis's figures need the unrounded crop factor and CoC; the rounded ones shown in Table 5.2 miss."""
    rounded = optics.make_config({**THESIS_SETUP, "sensor": None, "crop_factor": 1.54, "coc": 0.022})
    r = optics.compute_optics(rounded)
    assert abs(r["hyperfocal_mm"] - 16887.17) > 10
    assert abs(r["total_dof_mm"] - 110.16) > 0.2


def test_table_5_1_diffraction_example():
    setup = optics.make_config({**THESIS_SETUP, "f_number": 8.0, "coc": 0.022, "pixel_size": 0.0055})
    r = optics.compute_optics(setup)
    assert round(r["airy_disk_mm"], 3) == 0.011
    assert r["airy_disk_mm"] == pytest.approx(2.44 * 8 * 0.00055)
    assert r["three_pixels_mm"] == pytest.approx(0.0165)  # the thesis shows 0.017 (0.0165 rounded half up)
    assert r["coc_mm"] == 0.022
    assert r["airy_below_coc"] and r["airy_below_three_pixels"] and not r["diffraction_limited"]


def test_diffraction_flags_small_apertures():
    check = optics.diffraction_check(optics.airy_disk_diameter(22.0), coc=0.022, pixel_size=0.0055)
    assert check["diffraction_limited"] and not check["airy_below_three_pixels"]
    by_coc = optics.diffraction_check(optics.airy_disk_diameter(16.0), coc=0.01, pixel_size=0.01)  # 0.0215 mm
    assert by_coc["diffraction_limited"] and not by_coc["airy_below_coc"] and by_coc["airy_below_three_pixels"]
    no_pixel = optics.diffraction_check(optics.airy_disk_diameter(8.0), coc=0.022, pixel_size=None)
    assert not no_pixel["diffraction_limited"] and no_pixel["three_pixels_mm"] is None


def test_full_frame_coc_and_crop_factor_eq_2_3_to_2_6():
    assert optics.crop_factor_from_sensor((36.0, 24.0)) == pytest.approx(1.0)
    full_frame = 0.25 * math.sqrt(36**2 + 24**2) / math.sqrt(250**2 + 200**2)
    assert optics.coc_from_sensor((36.0, 24.0)) == pytest.approx(full_frame)
    assert round(optics.coc_from_sensor((36.0, 24.0)), 3) == 0.034  # eq. 2.6


def test_sensor_from_crop_factor_is_3_by_2_and_round_trips():
    w, h = optics.sensor_from_crop_factor(1.5)
    assert w / h == pytest.approx(1.5)
    assert (w, h) == pytest.approx((24.0, 16.0))
    assert optics.crop_factor_from_sensor((w, h)) == pytest.approx(1.5)


# --- DoF vs an independent thin-lens computation --------------------------------------------------------------
def _blur_diameter(d, s, f, n):
    """Blur circle (mm) on the sensor of a point at distance d for a thin lens f/n focused at s."""
    v_s, v_d = f * s / (s - f), f * d / (d - f)
    return (f / n) * abs(v_d - v_s) / v_d


def _bisect(g, lo, hi):
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(lo) * g(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize(
    "s, f, n, c", [(1000, 50, 16, 0.022), (500, 35, 2.8, 0.03), (3000, 100, 8, 0.015), (250, 60, 22, 0.005)])
def test_near_far_limits_are_where_the_blur_circle_equals_the_coc(s, f, n, c):
    dof = optics.depth_of_field(s, f, n, c)
    assert _blur_diameter(dof["near_mm"], s, f, n) == pytest.approx(c, rel=1e-10)
    assert _blur_diameter(dof["far_mm"], s, f, n) == pytest.approx(c, rel=1e-10)
    near = _bisect(lambda d: _blur_diameter(d, s, f, n) - c, f * 1.0001, s)
    far = _bisect(lambda d: _blur_diameter(d, s, f, n) - c, s, 1e9)
    assert dof["near_mm"] == pytest.approx(near, rel=1e-9)
    assert dof["far_mm"] == pytest.approx(far, rel=1e-9)
    assert dof["total_dof_mm"] == pytest.approx(far - near, rel=1e-9)


def test_hyperfocal_is_where_infinity_blurs_to_the_coc():
    f, n, c = 50.0, 8.0, 0.03
    h = float(optics.hyperfocal_distance(f, n, c))
    blur_at_infinity = (f / n) * (f * h / (h - f) - f) / f  # v_inf = f
    assert blur_at_infinity == pytest.approx(c, rel=1e-12)


@pytest.mark.parametrize("beyond", [0.0, 1.0, 5000.0])
def test_far_limit_infinite_at_and_beyond_hyperfocal(beyond):
    f, n, c = 50.0, 16.0, 0.022
    h = float(optics.hyperfocal_distance(f, n, c))
    dof = optics.depth_of_field(h + beyond, f, n, c)
    assert math.isinf(dof["far_mm"]) and math.isinf(dof["total_dof_mm"]) and dof["far_is_infinite"]
    assert dof["near_mm"] == pytest.approx(float(optics.near_limit(h + beyond, f, h)))
    if beyond == 0.0:
        assert dof["near_mm"] == pytest.approx(h / 2)


def test_total_dof_broadcasts_and_is_inf_beyond_hyperfocal():
    total = optics.total_depth_of_field(1000.0, np.array([20.0, 50.0]), np.array([[8.0], [32.0]]), 0.022)
    assert total.shape == (2, 2)
    assert np.isfinite(total[0, 1]) and np.isinf(total[1, 0])  # f = 20 mm at N = 32: H < 1000 mm
    assert total[0, 1] == pytest.approx(optics.depth_of_field(1000.0, 50.0, 8.0, 0.022)["total_dof_mm"])


def test_lens_focal_length_option_uses_the_lens_itself():
    r = optics.compute_optics(optics.make_config({**THESIS_SETUP, "dof_focal_length": "lens"}))
    assert r["dof_focal_length_mm"] == 50.0
    assert r["hyperfocal_mm"] == pytest.approx(50.0**2 / (16 * r["coc_mm"]) + 50.0)
    assert r["total_dof_mm"] > 2 * 110.16


# --- stereo, field of view ----------------------------------------------------------------------------------
def test_depth_per_pixel_is_the_derivative_of_triangulated_depth():
    z, f, b, p = 1000.0, 50.0, 200.0, 0.0055
    res = optics.stereo_depth_resolution(z, f, b, p, precision_px=0.25)
    d0 = res["disparity_at_focus_px"]
    depth = lambda d: f * b / (d * p)  # noqa: E731
    assert depth(d0) == pytest.approx(z)
    slope = (depth(d0 - 1e-3) - depth(d0 + 1e-3)) / 2e-3
    assert res["depth_per_pixel_mm"] == pytest.approx(slope, rel=1e-6)
    assert res["depth_resolution_mm"] == pytest.approx(0.25 * slope, rel=1e-6)


def test_field_of_view_matches_footprint():
    r = optics.compute_optics(optics.make_config(THESIS_SETUP))
    s = r["focus_distance_mm"]
    assert r["footprint_width_mm"] == pytest.approx(2 * s * math.tan(math.radians(r["fov_horizontal_deg"] / 2)))
    assert r["footprint_height_mm"] == pytest.approx(2 * s * math.tan(math.radians(r["fov_vertical_deg"] / 2)))
    assert r["footprint_width_mm"] == pytest.approx(22.5 * 1000 / 50)


# --- CLI -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flag, value", [
    ("--focus-distance", "0"), ("--focal-length", "-5"), ("--f-number", "0"), ("--coc", "-0.01"),
    ("--pixel-size", "0"), ("--baseline", "-1"), ("--wavelength", "0"), ("--disparity-precision", "-0.5"),
])
def test_cli_rejects_non_positive_values(flag, value):
    args = [a for a in THESIS_FLAGS]
    if flag in args:
        args[args.index(flag) + 1] = value
    else:
        args += [flag, value]
    if flag == "--baseline":
        args += ["--pixel-size", "0.0055"]
    result = _cli(args)
    assert result.exit_code != 0
    assert isinstance(result.exception, DstereoError)
    message = _line(result)
    assert "\n" not in message and flag in message


@pytest.mark.parametrize("args, needle", [
    (["--focus-distance", "1000", "--focal-length", "50", "--f-number", "16"], "--sensor"),
    ([*THESIS_FLAGS, "--crop-factor", "1.5"], "--crop-factor"),
    (["--focus-distance", "1000", "--sensor", "22.5x16.9", "--f-number", "16"], "--focal-length"),
    ([*THESIS_FLAGS[:1], "40", *THESIS_FLAGS[2:]], "--focus-distance"),  # inside the 50 mm focal length
    ([*THESIS_FLAGS[:1], "60", *THESIS_FLAGS[2:], "--dof-focal-length", "effective"], "--dof-focal-length lens"),
    ([*THESIS_FLAGS[:5], "0x16.9", *THESIS_FLAGS[6:]], "--sensor"),
    ([*THESIS_FLAGS[:5], "big", *THESIS_FLAGS[6:]], "--sensor"),
    ([*THESIS_FLAGS, "--baseline", "200"], "--pixel-size"),
    ([*THESIS_FLAGS, "--dof-focal-length", "equivalent"], "--dof-focal-length"),
])
def test_cli_rejects_inconsistent_inputs(args, needle):
    result = _cli(args)
    assert result.exit_code != 0 and isinstance(result.exception, DstereoError)
    assert needle in _line(result) and "\n" not in _line(result)


def test_cli_entry_prints_one_line_and_exits_1(monkeypatch, capsys):
    single = len(app.registered_commands) == 1 and app.registered_callback is None and not app.registered_groups
    args = [*THESIS_FLAGS[:6], "--f-number", "-2"]
    monkeypatch.setattr(sys, "argv", ["dstereo", *([] if single else ["optics"]), *args])
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("dstereo: error:") and "\n" not in err and "--f-number" in err


def test_cli_json_has_the_quantities_and_nothing_else():
    result = _cli([*THESIS_FLAGS, "--pixel-size", "0.0055", "--baseline", "200", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in ("hyperfocal_mm", "near_mm", "far_mm", "total_dof_mm", "front_mm", "behind_mm", "airy_disk_mm",
                "three_pixels_mm", "coc_mm", "crop_factor", "effective_focal_length_mm", "fov_horizontal_deg",
                "footprint_width_mm", "depth_per_pixel_mm", "depth_resolution_mm", "diffraction_limited"):
        assert key in data, key
    assert data["hyperfocal_mm"] == pytest.approx(16887.17, abs=0.01)
    assert data["depth_per_pixel_mm"] == pytest.approx(1000.0**2 * 0.0055 / (50 * 200))


def test_cli_json_far_limit_beyond_hyperfocal_is_null():
    result = _cli([*THESIS_FLAGS[:1], "20000", *THESIS_FLAGS[2:], "--json"])
    data = json.loads(result.stdout)
    assert data["far_mm"] is None and data["total_dof_mm"] is None and data["far_is_infinite"] is True


def test_cli_table_is_plain_text():
    result = _cli(THESIS_FLAGS)
    assert result.exit_code == 0, result.output
    assert "hyperfocal distance (mm)" in result.stdout and "16887.17" in result.stdout
    assert "947.94" in result.stdout and "110.16" in result.stdout


def test_cli_crop_factor_only_says_the_sensor_is_derived():
    result = _cli(["--focus-distance", "1000", "--focal-length", "50", "--crop-factor", "1.5", "--f-number", "8"])
    assert result.exit_code == 0, result.output
    assert "3:2" in result.stdout


def test_config_file_and_flag_override(tmp_path):
    cfg = tmp_path / "setup.toml"
    cfg.write_text('[optics]\nfocus_distance = 1000\nfocal_length = 50\nsensor = "22.5x16.9"\nf_number = 8\n')
    result = _cli(["--config", str(cfg), "--f-number", "16", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["f_number"] == 16 and data["near_mm"] == pytest.approx(947.94, abs=0.01)
    crop = json.loads(_cli(["--config", str(cfg), "--crop-factor", "1.5", "--json"]).stdout)
    assert crop["crop_factor"] == 1.5  # the flag replaces the file's sensor


@pytest.mark.parametrize("body, needle", [
    ('[optics]\nfocus_distance = 1000\nfocal_length = 50\nsensor = [22.5, 16.9]\napperture = 2\n', "apperture"),
    ('[optics]\nfocal_length = 50\nsensor = [22.5, 16.9]\nf_number = 8\n', "focus_distance"),
    ('[optics]\nfocus_distance = 1000\nfocal_length = 50\nsensor = [22.5, 16.9]\nf_number = -8\n', "f_number"),
    ('[optics]\nfocus_distance = 1000\nfocal_length = "fifty"\nsensor = [22.5, 16.9]\nf_number = 8\n', "focal_length"),
    ('[camera]\nfocus_distance = 1000\n', "[optics]"),
    ('[optics\n', "TOML"),
])
def test_config_file_errors_name_the_key(tmp_path, body, needle):
    cfg = tmp_path / "setup.toml"
    cfg.write_text(body)
    result = _cli(["--config", str(cfg)])
    assert result.exit_code != 0 and isinstance(result.exception, DstereoError)
    assert needle in str(result.exception)


def test_plots_written(tmp_path):
    out = tmp_path / "figs"
    result = _cli([*THESIS_FLAGS, "--plots", str(out)])
    assert result.exit_code == 0, result.output
    for name in optics.PLOT_NAMES:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    # no partial files left; the report (its figures embedded) beside them
    assert sorted(p.name for p in out.iterdir()) == sorted([*optics.PLOT_NAMES, "report.html", "report.md"])
    from conftest import assert_reports_render

    assert_reports_render([out])
