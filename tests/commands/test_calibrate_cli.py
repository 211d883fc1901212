"""`dstereo calibrate` / `dstereo init` on OpenCV's left sample images (the thesis's section 5.2.1 set).

One full run with the thesis's Figure 5.5 file (all 286 subsets) is shared by the module; the TOML and
flags-only runs reuse the compiled solver (same shapes) and must give identical results.
"""

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import require_data, run_cli, subset_agreement, subset_rms_agreement
from dstereo.jobs.calibrate_camera import corner_coverage, suggest_model
from dstereo.errors import DstereoError
from test_robust_steps import reference_removed_at

SEED = Path(__file__).resolve().parents[2].parent / "shared" / "seed"
THESIS_FLAGS = ["--pattern", "9x6", "--square", "10", "--model", "k1,k2,k3,p1,p2", "--per-set", "10",
                "--step", "re=0.5", "--step", "p1=1.5,p2=1.5", "--step", "k1=1.5,k2=1.5,k3=1.5",
                "--step", "fx=1.0,fy=1.0,cx=1.0,cy=1.0", "--no-board-sag"]  # a flat board: compared with OpenCV
PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def _link_images(folder: Path, sources) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for src in sources:
        (folder / src.name).symlink_to(src)
    return folder


@pytest.fixture(scope="module")
def left_images():
    return sorted(require_data("opencv_stereo").glob("left*.jpg"))


@pytest.fixture(scope="module")
def thesis_run(tmp_path_factory, left_images):
    """PROJECT = init-individual.ini + images/ (links to the 13 left images); `dstereo calibrate PROJECT`."""
    from conftest import require_seed

    ini = require_seed("init-individual.ini")
    project = tmp_path_factory.mktemp("thesis")
    _link_images(project / "images", left_images)
    shutil.copy(ini, project)
    code, out, err = run_cli("calibrate", project, "--no-board-sag")  # a flat board, as OpenCV's (compared below)
    assert code == 0, err
    return project / "results", out, err


def test_report_html_in_a_browser(thesis_run):
    from conftest import assert_reports_render

    assert_reports_render([thesis_run[0]])


def _summary(folder: Path) -> dict:
    return json.loads((folder / "summary.json").read_text())


def _subsets(folder: Path) -> list[dict]:
    with open(folder / "subsets.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_thesis_file_run_and_console(thesis_run):
    results, out, err = thesis_run
    s = _summary(results)
    assert s["image_size"] == [640, 480]
    assert len(s["images"]["used"]) == 13 and s["images"]["rejected"] == {}
    sub = s["subsets"]
    assert (sub["per_set"], sub["total_combinations"], sub["initial_count"]) == (10, 286, 286)
    assert sub["unconverged"] == {"count": 0, "subsets": []}
    assert [st["parameters"] for st in sub["steps"]] == [
        ["re"], ["p1", "p2"], ["k1", "k2", "k3"], ["fx", "fy", "cx", "cy"]]
    assert [st["max_error"] for st in sub["steps"]] == [[0.5], [1.5, 1.5], [1.5, 1.5, 1.5], [1.0] * 4]
    assert sub["steps"][0]["survivors"] == 286  # every subset RMS is below 0.5 px, as in the thesis
    assert sub["final_count"] == sub["steps"][-1]["survivors"] < 286
    for name in ("full set", "subset mean", "fx", "k3", "timings", "step 4"):
        assert name in out
    assert "subsets" in err  # progress on stderr


def test_survivors_equal_an_independent_reimplementation(thesis_run):
    from dstereo.config.calibration import load_config

    results = thesis_run[0]
    rows = _subsets(results)
    columns = ("re",) + PARAMS
    table = [[float(r["rms"])] + [float(r[p]) for p in PARAMS] for r in rows]
    expected = reference_removed_at(table, columns, load_config(SEED / "init-individual.ini").steps)
    got = np.array([int(r["removed_at_step"] or 0) for r in rows])
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal([int(r["survives"]) for r in rows], expected == 0)
    steps = _summary(results)["subsets"]["steps"]
    assert [st["survivors"] for st in steps] == [int(((expected == 0) | (expected > k)).sum()) for k in (1, 2, 3, 4)]
    final = _summary(results)["subset_mean"]  # the thesis's mean (camera.yml holds the survivors' solve)
    alive = np.array(table)[expected == 0]
    for j, name in enumerate(columns):
        assert final[name] == pytest.approx(alive[:, j].mean(), rel=1e-12)


def test_subset_values_match_opencv(thesis_run):
    """Spot-check 3 subsets against cv2.calibrateCamera on the same corners (corners.npz, less the outliers that
    summary.json lists as rejected) with a tight criterion."""
    import cv2

    results = thesis_run[0]
    summary = _summary(results)
    used = summary["images"]["used"]
    rows = _subsets(results)
    out = {(c["image"], c["corner"]) for c in summary["outliers"]["corners"]}
    with np.load(results / "corners.npz") as z:
        obj_all = z["object_points"].astype(np.float32)
        keep = [np.array([(name, c) not in out for c in range(len(obj_all))]) for name in used]
        corners = [z[name][k] for name, k in zip(used, keep)]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    for row in (rows[0], rows[143], rows[285]):
        idx = [int(i) for i in row["images"].split()]
        rms, K, D, _, _, std, _, _ = cv2.calibrateCameraExtended(
            [obj_all[keep[i]] for i in idx], [corners[i].astype(np.float32) for i in idx], (640, 480), None, None,
            criteria=crit)
        ref = dict(zip(("fx", "fy", "cx", "cy"), (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
        ref.update(zip(("k1", "k2", "p1", "p2", "k3"), D.ravel()))
        sd = dict(zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), std.ravel()))
        n_res, n_par = 2 * sum(int(keep[i].sum()) for i in idx), len(PARAMS) + 6 * len(idx)
        # OpenCV's SSE within its 1e-15 of the optimum's, the subset's within the noise-unit stop's reach
        # (subset_rms_agreement, ~5e-6 relative); the CSV's 17 digits are exact enough.
        assert float(row["rms"]) == pytest.approx(rms, rel=subset_rms_agreement(n_res, n_par) + 1e-12)
        for name in PARAMS:
            # Within the two stopping rules' reach, in units of the subset's own std (subset_agreement, ~1e-2 std):
            # k2 and k3 share a flat valley (correlation ~ -0.98), so a relative bound would be tight there.
            bound = subset_agreement(sd[name], n_res, n_par)
            assert abs(float(row[name]) - ref[name]) <= bound, (row["subset"], name)


def test_results_folder_is_complete_and_well_formed(thesis_run):
    import cv2

    results = thesis_run[0]
    s = _summary(results)
    for key in ("full_set", "subsets", "final", "images", "image_size", "coverage", "comparison", "model_advice"):
        assert key in s
    assert set(PARAMS) | {"rms", "std"} <= set(s["full_set"]) and set(s["full_set"]["std"]) == set(PARAMS)
    assert set(PARAMS) <= set(s["final"])
    assert s["model_advice"] is None and s["full_set"]["conditioning"]["identifiable"]
    fs = cv2.FileStorage(str(results / "camera.yml"), cv2.FILE_STORAGE_READ)
    K, D = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) == (640, 480)
    fs.release()
    f = s["final"]
    np.testing.assert_array_equal(K, [[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]])
    np.testing.assert_array_equal(D, [f["k1"], f["k2"], f["p1"], f["p2"], f["k3"]])
    cam = json.loads((results / "camera.json").read_text())
    np.testing.assert_array_equal(cam["camera_matrix"], K)
    np.testing.assert_array_equal(cam["distortion_coefficients"], D)
    with np.load(results / "corners.npz") as z:
        assert set(z.files) == set(s["images"]["used"]) | {"object_points"}
        assert z["object_points"].shape == (54, 3) and z["object_points"][1, 0] == 10.0  # board units (mm)
        assert all(z[n].shape == (54, 2) and z[n].dtype == np.float64 for n in s["images"]["used"])
    assert len(_subsets(results)) == 286
    stats = sorted(p.name for p in (results / "stats").iterdir())
    assert stats == sorted([f"parameter_{n}.txt" for n in ("re",) + PARAMS]
                           + ["step_0_initial.txt", "step_1.txt", "step_2.txt", "step_3.txt", "step_4.txt"])
    history = (results / "stats" / "parameter_fx.txt").read_text().splitlines()
    assert history[:2] == ["[CALIBRATION PARAMETERS] = [[fx ]]", "STEP 0 (before optimization)"]
    mean = s["subset_mean"]  # stats/ keeps the thesis's subset mean (camera.yml: the survivors' solve)
    assert history[-4:-1] == [f"Average = {mean['fx']!r}", f"Standard deviation = {s['final_spread']['fx']!r}",
                              f"Error = {100 * s['final_spread']['fx'] / mean['fx']!r}"]
    text = (results / "stats" / "step_4.txt").read_text()
    fx = s["subsets"]["final"]["fx"]
    assert f"[CALIBRATION PARAMETERS] = [[fx ]]\nAverage = {fx['mean']!r}\nStandard deviation = {fx['std']!r}" in text
    assert f"Subsets = {s['subsets']['final_count']} " in text and "[REPROJECTION ERROR]" in text
    for name in PARAMS + ("re", "coverage", "per_image_rms", "residuals"):
        data = (results / "plots" / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, name
    undistorted = sorted((results / "undistorted").iterdir())
    assert len(undistorted) == 3 and cv2.imread(str(undistorted[0])).shape == (480, 2 * 640 + 8, 3)
    cov = s["coverage"]["percent"]
    assert sum(cov[q] for q in ("upper_left", "lower_left", "upper_right", "lower_right")) == pytest.approx(100)
    report = (results / "report.md").read_text()
    for piece in ("plots/fx.png", "camera.yml", "stats/step_4.txt", "| 4 | fx, fy, cx, cy |", "upper left"):
        assert piece in report
    board = s["pattern"]  # report.md and summary.json read the board from one carrier: they agree
    assert f"- board: {board['columns']} x {board['rows']} inner corners, square {board['square']:g} " in report
    assert not [p for p in results.parent.iterdir() if p.name.startswith(".results.")]  # no temporary left


@pytest.mark.slow
def test_toml_and_flags_alone_give_identical_results(thesis_run, tmp_path, left_images):
    reference = thesis_run[0]
    project = tmp_path / "proj"
    code, out, err = run_cli("init", project)
    assert code == 0 and (project / "dstereo.toml").is_file() and (project / "images").is_dir(), err
    _link_images(project / "images", left_images)
    toml = project / "dstereo.toml"
    assert "[calibration]\n" in toml.read_text()
    toml.write_text(toml.read_text().replace("[calibration]\n", "[calibration]\nboard_sag = false\n", 1))
    code, out, err = run_cli("calibrate", project, "--quiet")
    assert code == 0, err
    assert out == ""  # --quiet
    data = left_images[0].parent
    flags_out = tmp_path / "flags"
    code, out, err = run_cli("calibrate", "--images", data, "--glob", "left*.jpg", *THESIS_FLAGS, "--out", flags_out)
    assert code == 0, err
    for other in (project / "results", flags_out):
        assert (other / "subsets.csv").read_bytes() == (reference / "subsets.csv").read_bytes()
        a, b = _summary(other), _summary(reference)
        for key in ("final", "full_set", "image_size", "comparison"):
            assert a[key] == b[key], key
        assert a["subsets"]["steps"] == b["subsets"]["steps"]
        assert a["images"]["used"] == b["images"]["used"]


def test_full_set_only_without_per_set(tmp_path, left_images):
    out = tmp_path / "full"
    code, stdout, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg",
                                "--pattern", "9x6", "--out", out)
    assert code == 0, err
    s = _summary(out)
    assert s["subsets"] is None and not (out / "subsets.csv").exists() and not (out / "stats").exists()
    assert {n: s["final"][n] for n in PARAMS} == {n: s["full_set"][n] for n in PARAMS}
    assert "full-set solve" in s["final_source"]
    # --force replaces an existing folder; without it the run is refused before any work
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--out", out)
    assert code == 1 and "already exists" in err and "--force" in err
    (out / "marker").write_text("old")
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--out", out, "--force", "-q")
    assert code == 0, err
    assert not (out / "marker").exists() and (out / "summary.json").exists()


def test_unidentifiable_model_gets_a_simpler_one(tmp_path, left_images):
    out = tmp_path / "rational"
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--model", "rational", "--out", out, "-q")
    assert code == 0, err
    s = _summary(out)
    assert not s["full_set"]["conditioning"]["identifiable"]
    assert "--model k1k2k3p1p2" in s["model_advice"] and "--model k1k2k3p1p2" in err


def test_model_advice_rule():
    assert suggest_model(("k1", "k2"), True, []) is None
    assert "--model k1k2p1p2 " in suggest_model(("k1", "k2", "p1", "p2", "k3"), False, ["k2", "k3"])
    assert "--model k1 " in suggest_model(("k1", "k2"), False, ["k2"])
    assert "add views" in suggest_model((), False, ["fx"])


def test_coverage_regions():
    pts = np.array([[10.0, 10.0], [600.0, 20.0], [20.0, 470.0], [630.0, 470.0], [320.0, 240.0], [300.0, 200.0]])
    cov = corner_coverage(pts, (640, 480))
    assert cov.percent["upper_left"] == pytest.approx(100 * 2 / 6)  # (10, 10) and (300, 200)
    assert cov.percent["lower_right"] == pytest.approx(100 * 2 / 6)  # (320, 240) is right of and below the centre
    assert cov.percent["centre"] == pytest.approx(100 * 2 / 6)
    assert cov.corner_percent == pytest.approx({k: 100 / 6 for k in cov.corner_percent})
    sparse = corner_coverage(np.array([[320.0, 240.0]] * 10), (640, 480))
    assert len(sparse.warnings) == 3 + 4  # three empty quadrants, four empty image corners


def _bad_ini(tmp_path: Path, steps: str) -> Path:
    path = tmp_path / "bad.ini"
    path.write_text("[ Calibration ]\nIndividual calibration = 1\nmesh width = 9\nmesh height = 6\n"
                    "images per set = 10\n"
                    f"[ Optimization ]\n[[ Calibration steps ]]\nnumber steps = 1\n[[[ step 1 ]]]\n{steps}")
    return path


@pytest.mark.parametrize("case, message", [
    ("step-name", "unknown parameter 'fz'"),
    ("negative", "max error '-1' must be a positive number"),
    ("missing", "max error is missing"),
    ("lengths", "2 parameter(s) (fx, fy) but 1 max error"),
    ("m>N", "only 13 usable images"),
    ("zero-left", "would remove all 32 remaining subsets"),
    ("unreadable", "broken.jpg is not an image file"),
    ("non-image", "notes.txt is not an image file"),
    ("no-images", "does not exist"),
    ("stereo", "a stereo configuration needs the stereo images"),
    ("no-pattern", "no board pattern"),
    ("bad-pattern", "is not COLSxROWS"),
])
def test_bad_input_is_one_line_and_leaves_no_folder(case, message, tmp_path, left_images):
    data = left_images[0].parent
    images = ["--images", data, "--glob", "left*.jpg"]
    own = _link_images(tmp_path / "imgs", left_images)  # the 13 images plus a bad file
    (own / ("notes.txt" if case == "non-image" else "broken.jpg")).write_text("not an image")
    args = {
        "step-name": lambda: [*images, "--pattern", "9x6", "--per-set", "10", "--step", "fz=1"],
        "negative": lambda: ["--config", _bad_ini(tmp_path, "parameters = fx\nmax error = -1\n"), *images],
        "missing": lambda: ["--config", _bad_ini(tmp_path, "parameters = fx, fy\n"), *images],
        "lengths": lambda: ["--config", _bad_ini(tmp_path, "parameters = fx, fy\nmax error = 1,\n"), *images],
        "m>N": lambda: [*images, "--pattern", "9x6", "--per-set", "14"],
        "zero-left": lambda: [*images, "--pattern", "9x6", "--per-set", "10", "--max-subsets", "32",
                              "--step", "re=0.1"],
        "unreadable": lambda: ["--images", own, "--pattern", "9x6"],
        "non-image": lambda: ["--images", own, "--glob", "*", "--pattern", "9x6"],
        "no-images": lambda: ["--images", tmp_path / "nowhere", "--pattern", "9x6"],
        "stereo": lambda: ["--config", SEED / "init-stereo.ini", *images],
        "no-pattern": lambda: images,
        "bad-pattern": lambda: [*images, "--pattern", "9by6"],
    }[case]()
    out = tmp_path / "out"
    code, stdout, err = run_cli("calibrate", *args, "--out", out, "-q")
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dstereo: error: "), err
    assert message in lines[0]
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_a_failure_after_the_early_figures_leaves_nothing(tmp_path, left_images, monkeypatch):
    """The parameter figures are drawn as soon as the steps end (io.results.EarlyFigures), into a staging folder
    next to the results: a command that fails after that (here in the survivors' solve) removes it too."""
    from dstereo.jobs import calibrate_camera as pipeline

    def fail(*args, **kwargs):
        raise DstereoError("survivors: refused for this test")

    monkeypatch.setattr(pipeline, "_final_solution", fail)
    out = tmp_path / "out"
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--per-set", "12", "--out", out, "-q")
    assert code == 1 and "refused for this test" in err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_init_refuses_to_overwrite(tmp_path):
    assert run_cli("init", tmp_path / "p")[0] == 0
    code, _, err = run_cli("init", tmp_path / "p")
    assert code == 1 and "already exists" in err
    assert run_cli("init", tmp_path / "p", "--force")[0] == 0


def test_a_camera_solved_with_the_board_sag_refits_on_the_solved_board(tmp_path, left_images):
    """Default: the board's sag is solved. camera.yml then fits its corners on the board it was solved with
    (corners.npz object_points_solved, camera.yml says so): OpenCV's own pose refit (solvePnP + RefineLM) on that
    board reproduces the solve's RMS (the same least-squares optimum per view: 1e-6 relative is far above the two
    pose solvers' disagreement, far below any model difference), and on the flat nominal board it is worse."""
    import cv2

    from dstereo.io.camera_file import read_camera_file

    out = tmp_path / "sag"
    code, _, err = run_cli("calibrate", "--images", left_images[0].parent, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--no-outlier-rejection", "--out", out, "-q")
    assert code == 0, err
    summary = _summary(out)
    cam = read_camera_file(out / "camera.yml")
    assert "object_points_solved" in (out / "camera.yml").read_text()
    sag = json.loads((out / "camera.json").read_text())["board_sag"]
    assert summary["full_set"]["std"]["board_sag_y"] > 0 and sag["x"] == summary["full_set"]["board_sag_x"]

    def refit_rms(board_key):
        with np.load(out / "corners.npz") as z:
            board = z[board_key].astype(np.float64)
            sse, n = 0.0, 0
            for name in summary["images"]["used"]:
                q = z[name].astype(np.float64)
                ok, r, t = cv2.solvePnP(board, q, cam.K, cam.D)
                r, t = cv2.solvePnPRefineLM(board, q, cam.K, cam.D, r, t, (
                    cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
                sse += float(np.sum((cv2.projectPoints(board, r, t, cam.K, cam.D)[0].reshape(-1, 2) - q) ** 2))
                n += len(q)
        return np.sqrt(sse / n)

    assert refit_rms("object_points_solved") == pytest.approx(summary["full_set"]["rms"], rel=1e-6)
    assert refit_rms("object_points") > summary["full_set"]["rms"]
