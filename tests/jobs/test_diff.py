"""`dstereo diff A B` from files to files: the two camera folders as `calibrate` writes them (camera.yml,
calibration_covariance.npz) read back to the numbers `camera_diff.projection_diff` gets in memory; a rig's
camera from its stereo.yml covariance block; the results folder; one-line errors, nothing half-written."""

import dataclasses
import json

import numpy as np
import pytest

from conftest import refused, run_cli
from dstereo.uncertainty import camera_diff as cd

SIZE = (640, 480)
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def _camera(seed: int) -> cd.LensCamera:
    """A camera around the synthetic truth with a made-up (positive definite) covariance, no poses."""
    rng = np.random.default_rng(seed)
    std = np.array([1.0, 1.0, 0.8, 0.8, 3e-3, 1e-2, 2e-4, 2e-4, 2e-2])
    corr = np.eye(9) + 0.3 * (np.ones((9, 9)) - np.eye(9))
    cov = corr * np.outer(std, std)
    params = np.r_[800.0, 805.0, 322.0, 238.0, -0.25, 0.1, 1e-3, -5e-4, -0.02, 0, 0, 0]
    params[:9] += np.linalg.cholesky(cov) @ rng.normal(size=9)
    return cd.LensCamera("pinhole", params, NAMES, cov, SIZE)


def _write_folder(folder, cam: cd.LensCamera, unit: str = "mm", size=SIZE):
    """camera.yml and calibration_covariance.npz as a results folder holds them."""
    from types import SimpleNamespace

    from dstereo.io.covariance_file import write_calibration_covariance
    from dstereo.io.results import write_camera_files

    folder.mkdir(parents=True)
    p = cam.params
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
    write_camera_files(folder, K, p[4:9], size, {}, unit=unit)
    cov = SimpleNamespace(names=cam.names, values=p[:9], cov=cam.cov, jacobian=cam.cov, kind="jacobian", views=10,
                          joint=None, poses=None)
    write_calibration_covariance(folder, cov, "pinhole", 500.0, (12, 9), size)
    return folder


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("diff")
    a, b = _camera(1), _camera(2)
    return root, _write_folder(root / "a", a), _write_folder(root / "b", b), a, b


@pytest.fixture(scope="module")
def diffed(folders):
    """`dstereo diff A B --out OUT` on the module's two folders, run once: (OUT, stdout); read by the statistic's
    test and the browser's."""
    root, fa, fb, _, _ = folders
    code, out, err = run_cli("diff", fa, fb, "--out", root / "out")
    assert code == 0, err
    return root / "out", out


def test_the_files_give_the_statistic_computed_in_memory(folders, diffed):
    """camera.yml holds K and D as OpenCV's %.16e (17 significant digits: a float64 round trip, exact) and the
    covariance file the covariance exactly: the ratio read from the files equals the in-memory one to 1e-9
    (measured 1e-14); the distance and grid are the covariance file's (A's map)."""
    root, fa, fb, a, b = folders
    out = diffed[1]
    s = json.loads((root / "out" / "diff.json").read_text())
    d = cd.projection_diff(a, b, 500.0, (12, 9))
    assert s["distance"] == 500.0 and s["grid"] == [12, 9] and "A's projection-uncertainty map" in s["distance_source"]
    assert s["prediction"]["ratio"] == pytest.approx(d.ratio, rel=1e-9)
    assert s["prediction"]["mahalanobis_median"] == pytest.approx(d.mahalanobis_median, rel=1e-9)
    assert s["weighting"].startswith("uniform")  # no joint covariance: said, in a note too
    assert any("weights every pixel alike" in n for n in s["notes"])
    assert f"ratio {d.ratio:.2f}" in out and "wrote" in out
    # the same program on the same (round-tripped) numbers, run by the CLI and here on one machine: measured equal
    with np.load(root / "out" / "diff.npz") as z:
        np.testing.assert_allclose(z["diff"], d.diff, rtol=1e-9, atol=1e-12)
        assert z["cov"].shape == (9, 12, 2, 2)
    assert (root / "out" / "diff.png").stat().st_size > 1000
    report = (root / "out" / "report.md").read_text()
    assert s["verdict"] in report and f"{d.ratio:.3f}" in report
    assert "data:image/png;base64," in (root / "out" / "report.html").read_text()  # the figure embedded
    # swapping A and B: the same comparison from the other side, so nearly the same ratio (first order: equal)
    code, _, _ = run_cli("diff", fb, fa, "--distance", "500", "--grid", "12x9")
    assert code == 0


def test_the_report_renders_in_a_browser(diffed):
    """diff's report.html, as every results folder's: no console error, no request outside the file, its figure
    decoded (issue 34: every kind of report passes the browser test). The module's run (`diffed`): the same
    command as a run of its own, which this test made before."""
    from conftest import assert_reports_render

    (page,) = assert_reports_render([diffed[0]])
    assert len(page["images"]) >= 1


def test_a_camera_without_covariance_diffs_without_a_prediction(folders, tmp_path):
    root, fa, fb, a, b = folders
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "camera.yml").write_text((fb / "camera.yml").read_text())
    code, out, err = run_cli("diff", fa, bare / "camera.yml", "--out", tmp_path / "o")
    assert code == 0, err
    s = json.loads((tmp_path / "o" / "diff.json").read_text())
    assert s["prediction"] is None and "no prediction" in s["verdict"] and "calibration_covariance.npz" in err


def test_a_rig_camera_reads_its_block_of_the_pairs_covariance(folders, tmp_path):
    """stereo.yml:left gives the left camera's intrinsics and its rows and columns of the pair's covariance."""
    from dstereo.io.diff_files import read_diff_input
    from dstereo.io.stereo_files import write_stereo_yml
    from dstereo.jobs.diff import _camera

    root, fa, fb, a, b = folders
    K = lambda c: np.array([[c.params[0], 0, c.params[2]], [0, c.params[1], c.params[3]], [0, 0, 1.0]])  # noqa: E731
    names = tuple(f"left.{n}" for n in NAMES) + tuple(f"right.{n}" for n in NAMES) + ("Tx",)
    cov = np.zeros((19, 19))
    cov[:9, :9], cov[9:18, 9:18], cov[18, 18] = a.cov, b.cov, 0.01
    cov[0, 9] = cov[9, 0] = 0.1  # a cross term, not the left block's
    path = write_stereo_yml(tmp_path / "stereo.yml", K(a), a.params[4:12], K(b), b.params[4:12], np.eye(3),
                            np.r_[-60.0, 0, 0], np.eye(3), np.eye(3), SIZE, cov=cov, cov_names=names)
    for side, cam in (("left", a), ("right", b)):
        inp = read_diff_input(f"{path}:{side}", "A")
        got = _camera(inp, [])
        assert got.names == NAMES and np.array_equal(got.cov, cam.cov)
        # written and read back as text (17 significant digits round-trip a float64): equal, 1e-12 for the decimal
        np.testing.assert_allclose(got.params, cam.params, rtol=1e-12)
    code, out, err = run_cli("diff", f"{tmp_path}:right", fb, "--distance", "500", "--grid", "12x9")
    assert code == 0 and "ratio" in out, err


def test_a_covariance_of_another_solve_is_said(folders, tmp_path):
    """camera.yml holding values 1 sigma away from those its covariance belongs to (another solve, e.g. the
    survivors' of --per-set): diffed, with a note naming the parameter."""
    root, fa, fb, a, b = folders
    moved = dataclasses.replace(a, params=a.params + np.r_[np.sqrt(a.cov[0, 0]), np.zeros(11)])
    other = _write_folder(tmp_path / "moved", a)
    _write_folder(tmp_path / "tmp", moved)
    (other / "camera.yml").write_text((tmp_path / "tmp" / "camera.yml").read_text())
    code, _, err = run_cli("diff", other, fb)
    assert code == 0 and "differ from those its covariance belongs to" in err and "(fx)" in err


def test_bad_input_is_one_line_and_writes_nothing(folders, tmp_path):
    root, fa, fb, a, b = folders
    out = tmp_path / "out"
    refused(["diff", tmp_path / "nothing", fb, "--out", out], out, "camera A", "does not exist")
    refused(["diff", fa, fb, "--grid", "12", "--out", out], out, "--grid", "COLSxROWS")
    refused(["diff", fa, fb, "--grid", "1x9", "--out", out], out, "--grid", "at least 2x2")
    refused(["diff", fa, fb, "--distance=-3", "--out", out], out, "--distance")
    refused(["diff", f"{fa}:middle", fb, "--out", out], out, "left or right")
    small = _write_folder(tmp_path / "small", a, size=(320, 240))
    refused(["diff", fa, small, "--out", out], out, "image sizes differ")
    squares = _write_folder(tmp_path / "squares", b, unit="squares")
    refused(["diff", fa, squares, "--out", out], out, "units differ")
    rig = tmp_path / "rig"
    rig.mkdir()
    (rig / "stereo.yml").write_text("%YAML:1.0\n")
    refused(["diff", rig, fb, "--out", out], out, "rig's folder", f"{rig}:left")
    out.mkdir()
    (out / "keep").write_text("x")
    refused(["diff", fa, fb, "--out", out], None, "already exists", "--force")
    assert (out / "keep").read_text() == "x"
    refused(["diff", fa, fb, "--out", fa], None, "already exists")
    refused(["diff", fa, fb, "--out", fa, "--force"], None, "holds the input")
    assert (fa / "camera.yml").is_file()


@pytest.mark.slow
def test_a_splined_camera_diffs_through_its_files(tmp_path):
    """A splined lens (camera.yml's splined section, its knots' covariance): read back and compared; against
    itself the difference is 0, and a knot moved by its std gives a finite ratio with a prediction."""
    from types import SimpleNamespace

    from dstereo.io.covariance_file import write_calibration_covariance
    from dstereo.io.results import write_camera_files
    from dstereo.models import splined
    from dstereo.models.camera import INTRINSIC_NAMES

    nx, ny = 6, 5
    free = splined.knot_names(nx, ny)
    rng = np.random.default_rng(2)
    knots = rng.normal(0, 0.5, 2 * nx * ny)
    names = INTRINSIC_NAMES + free
    cov = np.diag(np.r_[1.0, 1.0, 0.5, 0.5, np.full(len(free), 0.01)])
    folders = []
    for i, shift in enumerate((0.0, 0.1)):
        folder = tmp_path / f"s{i}"
        folder.mkdir()
        k = knots + shift * (np.arange(len(knots)) == 7)
        K = np.array([[330.0, 0, 320.0], [0, 331.0, 240.0], [0, 0, 1.0]])
        write_camera_files(folder, K, np.zeros(0), SIZE, {}, model="splined",
                           splined=(k, free, np.ones((ny - 3, nx - 3), bool)))
        write_calibration_covariance(folder, SimpleNamespace(
            names=names, values=np.r_[330.0, 331.0, 320.0, 240.0, k], cov=cov, jacobian=None, kind="jacobian",
            views=10, joint=None, poses=None), "splined", 400.0, (12, 9), SIZE)
        folders.append(folder)
    from dstereo.jobs.diff import compute_diff

    same = compute_diff(str(folders[0]), str(folders[0])).projection
    assert same.ok.mean() > 0.9 and np.nanmax(np.abs(same.diff)) < 1e-9
    code, out, err = run_cli("diff", folders[0], folders[1], "--out", tmp_path / "o")
    assert code == 0, err
    s = json.loads((tmp_path / "o" / "diff.json").read_text())
    assert s["observed_rms_px"] > 0 and np.isfinite(s["prediction"]["ratio"])


def test_a_fisheye_camera_diffs_through_its_files(tmp_path):
    """A fisheye camera.yml (cv2.fisheye's k1..k4) with its covariance over fk1..fk4: read back into the fisheye
    slots; a moved k1 gives a finite prediction, and itself a zero difference."""
    from types import SimpleNamespace

    from dstereo.io.covariance_file import write_calibration_covariance
    from dstereo.io.results import write_camera_files
    from dstereo.jobs.diff import compute_diff

    names = ("fx", "fy", "cx", "cy", "fk1", "fk2", "fk3", "fk4")
    cov = np.diag([1.0, 1.0, 0.5, 0.5, 1e-4, 1e-4, 1e-4, 1e-4])
    folders = []
    for i, k1 in enumerate((0.05, 0.0512)):
        folder = tmp_path / f"f{i}"
        folder.mkdir()
        d = np.array([k1, -0.01, 0.002, -0.0005])
        write_camera_files(folder, np.array([[300.0, 0, 320.0], [0, 301.0, 240.0], [0, 0, 1.0]]), d, SIZE, {},
                           model="fisheye")
        write_calibration_covariance(folder, SimpleNamespace(
            names=names, values=np.r_[300.0, 301.0, 320.0, 240.0, d], cov=cov, jacobian=None, kind="jacobian",
            views=10, joint=None, poses=None), "fisheye", 300.0, (12, 9), SIZE)
        folders.append(folder)
    same = compute_diff(str(folders[0]), str(folders[0])).projection
    assert same.ok.mean() > 0.9 and np.nanmax(np.abs(same.diff)) < 1e-9
    moved = compute_diff(str(folders[0]), str(folders[1]))
    # the values match their covariance's (files written without a corners' field: said, the whole grid used)
    assert not moved.notes or all("alike" in n or "no corners' field" in n for n in moved.notes)
    assert moved.projection.rms > 0 and np.isfinite(moved.projection.ratio)
