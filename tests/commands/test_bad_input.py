"""Bad input gets one honest line: `dstereo: error: ...` naming the file or parameter, exit 1, nothing written.

One test (or parametrised case) per row of issue 13's bad-input table, plus the cases found walking the commands
as a hostile user. Most cases are refused before any image is read, so they use tiny random images.
"""

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import refused as _refused
from conftest import require_data, run_cli


def _image(path: Path, seed: int, size=(48, 64)) -> Path:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, size, dtype=np.uint8))
    return path


@pytest.fixture
def pair(tmp_path):
    return _image(tmp_path / "l.png", 1), _image(tmp_path / "r.png", 2)


def _write_storage(path: Path, **mats) -> Path:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in mats.items():
        fs.write(key, np.asarray(value, dtype=float))
    fs.release()
    return path


K = np.array([[500.0, 0, 32], [0, 500, 24], [0, 0, 1]])


# --- 1. calibration files given to reconstruct ---------------------------------------------------------------------

def _calib_cases(folder: Path) -> dict[str, tuple[Path, str]]:
    from dstereo.io.results import write_camera_files

    (folder / "empty.yml").write_text("")
    (folder / "malformed.yml").write_text("%YAML:1.0\nM1: [1, 2\n  : :\n")
    _write_storage(folder / "t3x3.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3), T=np.eye(3))
    _write_storage(folder / "k2x3.yml", M1=K[:2], M2=K, R=np.eye(3), T=[-100.0, 0, 0])
    (folder / "words.yml").write_text("%YAML:1.0\n---\nM1: hello\nM2: hello\nR: hello\nT: hello\n")
    write_camera_files(folder, K, np.zeros(5), (64, 48), {})  # the one-camera file dstereo calibrate writes
    return {"empty": (folder / "empty.yml", "empty"), "malformed": (folder / "malformed.yml", "YAML"),
            "T 3x3": (folder / "t3x3.yml", "T has 9 values"), "M1 2x3": (folder / "k2x3.yml", "3x3"),
            "words": (folder / "words.yml", "not a matrix of numbers"),
            "mono": (folder / "camera.yml", "one-camera file")}


@pytest.mark.parametrize("case", ["empty", "malformed", "T 3x3", "M1 2x3", "words", "mono"])
def test_reconstruct_refuses_a_bad_calibration_file(tmp_path, pair, case):
    path, what = _calib_cases(tmp_path)[case]
    out = tmp_path / "out"
    line = _refused(("reconstruct", "--left", pair[0], "--right", pair[1], "--calib", path, "--out", out),
                    out, path.name, what)
    if case == "mono":
        assert "dstereo calibrate --left" in line  # says how to get a stereo calibration


# --- 2. output locations checked before any work -----------------------------------------------------------------

def _commands_with_out(tmp_path, pair, out):
    left_dir, right_dir = tmp_path / "L", tmp_path / "R"
    for i in range(3):
        _image(left_dir / f"left{i}.png", 10 + i), _image(right_dir / f"right{i}.png", 20 + i)
    calib = _write_storage(tmp_path / "stereo.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3),
                           T=[-100.0, 0, 0])
    (tmp_path / "seq" / "left").mkdir(parents=True)
    (tmp_path / "seq" / "right").mkdir()
    return {
        "calibrate": ("calibrate", "--images", left_dir, "--pattern", "9x6", "--out", out),
        "calibrate stereo": ("calibrate", "--left", left_dir, "--right", right_dir, "--pattern", "9x6", "--out", out),
        "reconstruct": ("reconstruct", "--left", pair[0], "--right", pair[1], "--out", out, "--focal-px", "500"),
        "optics --plots": ("optics", "--focus-distance", "1000", "--focal-length", "50", "--crop-factor", "1.5",
                           "--f-number", "8", "--plots", out),
        "refine": ("refine", "--calib", calib, "--left", pair[0], "--right", pair[1], "--board", "9x6", "--square",
                   "10", "--out", out),
        "recession": ("recession", tmp_path / "seq", "--calib", calib, "--out", out),
    }


@pytest.mark.parametrize("command", ["calibrate", "calibrate stereo", "reconstruct", "optics --plots", "refine",
                                     "recession"])
def test_an_output_folder_that_cannot_be_created_is_refused_first(tmp_path, pair, command):
    # Tests run as root, for whom permissions do not stop a write; a path under a regular file stops everyone.
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    out = blocker / "out"
    args = _commands_with_out(tmp_path, pair, out)[command]
    flag = "--plots" if command == "optics --plots" else "--out"
    _refused(args, None, flag, "file.txt", "is a file")
    assert blocker.read_text() == "x"


def test_creatable_locations_pass_the_check(tmp_path):
    from dstereo.io.output_location import check_creatable

    assert check_creatable(tmp_path / "a" / "b" / "c") == tmp_path / "a" / "b" / "c"  # missing parents are fine
    assert not (tmp_path / "a").exists()  # the check creates nothing


# --- 3. stereo partners matched by name --------------------------------------------------------------------------

@pytest.mark.parametrize("left, right, key", [
    ("left05.jpg", "right05.jpg", "05"), ("L_05.png", "R_05.png", "_05"), ("im0.png", "im1.png", "im"),
    ("cam0_0007.png", "cam1_0007.png", "cam_0007"), ("0003.png", "0003.png", "0003"),
    ("Left_7.tif", "Right_7.tif", "_7"), ("img_L5.png", "img_R5.png", "img_5"),
])
def test_partners_share_their_name_without_the_camera_token(left, right, key):
    from dstereo.io.pairing import pair_key, partner_name

    assert pair_key(left) == pair_key(right) == key
    assert partner_name(left) == right


def test_unrelated_names_do_not_pair():
    from dstereo.io.pairing import pair_by_name

    named = pair_by_name([Path("left05.jpg"), Path("left06.jpg")], [Path("right06.jpg"), Path("right5.jpg")])
    assert named.pairs == [(Path("left06.jpg"), Path("right06.jpg"))]  # 05 and 5 are different names
    assert named.left_alone == [Path("left05.jpg")] and named.right_alone == [Path("right5.jpg")]
    assert "left05.jpg" in named.warning() and "right5.jpg" in named.warning()


def test_stereo_pairs_follow_names_not_order(tmp_path):
    """left01..06 with right02..07: the same count on each side, so pairing by order would match left01 with
    right02; by name five pairs remain (the rig's frames), and the two strays are named in a warning."""
    from dstereo.calib.calibrations import StereoSources
    from dstereo.config.calibration import Config
    from dstereo.jobs.rig_sources import stereo_pair_sources

    left = tuple(tmp_path / f"left{i:02d}.jpg" for i in range(1, 7))
    right = tuple(tmp_path / f"right{i + 1:02d}.jpg" for i in range(1, 7))
    sources, warnings = stereo_pair_sources(StereoSources(left, right, left, right, "test"), Config(pattern=(9, 6)))
    assert [(f, p.name) for f, p in sources[0].frames] == [(f"{i:02d}", f"left{i:02d}.jpg") for i in range(2, 7)]
    assert [p.name for _, p in sources[1].frames] == [f"right{i:02d}.jpg" for i in range(2, 7)]
    assert len(warnings) == 1 and "left01.jpg" in warnings[0] and "right07.jpg" in warnings[0]


@pytest.mark.parametrize("layout", ["flags", "thesis folders"])
def test_stereo_folders_whose_names_do_not_match_are_refused(tmp_path, layout):
    left_dir, right_dir = (tmp_path / "p" / "images" / "images_left", tmp_path / "p" / "images" / "images_right")
    for i in range(4):  # two cameras numbering their files independently: nothing pairs by name
        _image(left_dir / f"IMG_{100 + i}.png", i), _image(right_dir / f"IMG_{200 + i}.png", 10 + i)
    out = tmp_path / "out"
    where = (["--left", left_dir, "--right", right_dir] if layout == "flags" else [tmp_path / "p"])
    _refused(("calibrate", *where, "--pattern", "9x6", "--out", out), out, "only 0 of 4 left images", "by name")


def test_the_same_images_for_both_cameras_are_refused(tmp_path):
    folder = tmp_path / "imgs"
    for i in range(3):
        _image(folder / f"left{i}.png", i), _image(folder / f"right{i}.png", 10 + i)
    out = tmp_path / "out"
    _refused(("calibrate", "--left", f"{folder}/left*.png", "--right", f"{folder}/left*.png", "--pattern", "9x6",
              "--out", out), out, "left0.png", "both the left and the right")
    _refused(("calibrate", "--left", folder, "--right", folder, "--pattern", "9x6", "--out", out), out,
             "same folder", "--left")


# --- 4. the same image as left and right --------------------------------------------------------------------------

@pytest.mark.parametrize("copy", ["same file", "byte copy", "re-encoded"])
def test_reconstruct_refuses_one_image_as_both_cameras(tmp_path, pair, copy):
    import cv2

    left = pair[0]
    right = {"same file": left, "byte copy": tmp_path / "copy.png", "re-encoded": tmp_path / "copy.bmp"}[copy]
    if copy == "byte copy":
        right.write_bytes(left.read_bytes())
    elif copy == "re-encoded":
        cv2.imwrite(str(right), cv2.imread(str(left), cv2.IMREAD_UNCHANGED))
    out = tmp_path / "out"
    _refused(("reconstruct", "--left", left, "--right", right, "--focal-px", "500", "--out", out), out,
             "left image", str(right))


# --- 6. thesis .ini files missing a section -----------------------------------------------------------------------

def _seed_text(name: str) -> str:
    from conftest import require_seed

    return require_seed(name).read_text()


def _without_section(text: str, title: str) -> str:
    """The file without `[ title ]` and everything up to the next one-bracket section."""
    out, skipping = [], False
    for line in text.splitlines():
        head = re.match(r"^\s*\[\s*([^\[\]]+?)\s*\]\s*$", line)
        if head:
            skipping = head.group(1).lower() == title.lower()
        if not skipping:
            out.append(line)
    return "\n".join(out) + "\n"


def test_ini_without_calibration_section_is_refused(tmp_path):
    ini = tmp_path / "init.ini"
    ini.write_text(_without_section(_seed_text("init-individual.ini"), "Calibration"))
    _image(tmp_path / "images" / "a.png", 0)
    out = tmp_path / "out"
    _refused(("calibrate", "--config", ini, "--images", tmp_path / "images", "--out", out), out,
             "init.ini", "no [ Calibration ] section")


@pytest.mark.parametrize("name, section", [("init-individual.ini", "Optimization"),
                                           ("init-stereo.ini", "Stereo Optimization")])
def test_ini_without_its_optimisation_section_says_so(name, section):
    from dstereo.config.calibration import config_from_thesis_ini

    full = config_from_thesis_ini(_seed_text(name), name)
    assert not [w for w in full.warnings if "section" in w]
    cut = config_from_thesis_ini(_without_section(_seed_text(name), section), name)
    assert cut.steps == () and cut.stereo_steps == ()
    assert [w for w in cut.warnings if f"no [ {section} ] section" in w and name in w]


# --- 7. optics: focus closer than the effective focal length ------------------------------------------------------

def test_optics_focus_beyond_the_lens_focal_length_is_accepted():
    """120 mm with a 100 mm lens on a 1.5 crop: a real image exists (s > f). The DoF then uses the lens's own f;
    near/far limits checked against the thin-lens closed form written out here (same float64 formula rearranged:
    agreement to 1e-12 relative)."""
    import json

    code, out, err = run_cli("optics", "--focus-distance", "120", "--focal-length", "100", "--crop-factor", "1.5",
                             "--f-number", "8", "--json")
    assert code == 0, err
    r = json.loads(out)
    s, f, n, c = 120.0, 100.0, 8.0, r["coc_mm"]
    assert r["dof_focal_length_mm"] == f
    hyper = f * f / (n * c) + f
    assert r["near_mm"] == pytest.approx(s * (hyper - f) / (hyper + s - 2 * f), rel=1e-12)
    assert r["far_mm"] == pytest.approx(s * (hyper - f) / (hyper - s), rel=1e-12)
    assert any("lens's own focal length" in note for note in r["notes"])
    assert any("close focus" in note for note in r["notes"])  # FoV/footprint assume v = f: off by v/f = 6


def test_optics_refuses_what_no_lens_can_do():
    _refused(("optics", "--focus-distance", "90", "--focal-length", "100", "--crop-factor", "1.5",
              "--f-number", "8"), None, "--focus-distance", "100 mm")
    _refused(("optics", "--focus-distance", "120", "--focal-length", "100", "--crop-factor", "1.5",
              "--f-number", "8", "--dof-focal-length", "effective"), None, "--dof-focal-length lens")


# --- 8. help reads as written --------------------------------------------------------------------------------------

@pytest.mark.parametrize("command, text", [("reconstruct", "TOML/JSON file with [reconstruct] and [sgbm]."),
                                           ("optics", "Circle of confusion, mm [from the sensor diagonal]."),
                                           ("optics", "Light wavelength, mm [0.00055].")])
def test_help_keeps_bracketed_text(command, text):
    code, out, _ = run_cli(command, "--help")
    assert code == 0
    assert text in " ".join(out.split())


# --- 9. stereo optimisation steps from the command line and the template -------------------------------------------

def test_stereo_steps_from_flags_reach_the_stereo_run(tmp_path):
    from dstereo.config.calibration import Step, parse_step_flags

    mono, stereo = parse_step_flags(["re=0.5", "stereo_re=3", "Tnorm=0.75,RV_norm=1"])
    assert mono == (Step(("re",), (0.5,)),)
    assert stereo == (Step(("stereo_re",), (3.0,)), Step(("Tnorm", "RVnorm"), (0.75, 1.0)))
    assert parse_step_flags([]) == (None, None)
    left_dir, right_dir = tmp_path / "L", tmp_path / "R"
    for i in range(3):
        _image(left_dir / f"left{i}.png", i), _image(right_dir / f"right{i}.png", 10 + i)
    out = tmp_path / "out"
    # accepted and routed to the stereo steps: the stereo run then asks for the subsets they filter
    _refused(("calibrate", "--left", left_dir, "--right", right_dir, "--pattern", "9x6", "--step", "stereo_re=3",
              "--out", out), out, "stereo steps need subsets")
    _refused(("calibrate", "--images", left_dir, "--pattern", "9x6", "--per-set", "3", "--step", "stereo_re=3",
              "--out", out), out, "--step stereo_re=3", "stereo steps need a rig")
    _refused(("calibrate", "--images", left_dir, "--pattern", "9x6", "--per-set", "3", "--step", "re=1,Tx=1",
              "--out", out), out, "re=1,Tx=1", "separate --step")


def test_init_template_carries_the_stereo_steps(tmp_path):
    from dstereo.config.calibration import config_from_thesis_ini, load_config

    assert run_cli("init", tmp_path / "p")[0] == 0
    text = (tmp_path / "p" / "dstereo.toml").read_text()
    assert "--step stereo_re=3" in text and "[[stereo.steps]]" in text
    thesis = config_from_thesis_ini(_seed_text("init-stereo.ini"), "init-stereo.ini")
    assert load_config(tmp_path / "p" / "dstereo.toml").stereo_steps == thesis.stereo_steps


# --- 5. views that do not fit: outlying RMS, stray corners, corner order -------------------------------------------

def _grid_image(pattern, angle_deg=10.0, shift=(100.0, 80.0), step=20.0):
    """A pattern's corners in the image: rows of `cols` points, rotated by `angle_deg`, OpenCV's order."""
    cols, rows = pattern
    yy, xx = np.mgrid[0:rows, 0:cols]
    pts = np.column_stack([xx.ravel(), yy.ravel()]) * step
    a = np.radians(angle_deg)
    return pts @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) + np.asarray(shift)


def test_outlying_views_and_stray_corners_are_named():
    from dstereo.calib.view_checks import outlying_views, stray_corners

    rms = np.array([0.20, 0.22, 0.19, 0.21, 0.25, 1.3])
    warnings = outlying_views([f"v{i}" for i in range(6)], rms)
    assert len(warnings) == 1 and "v5" in warnings[0] and "1.3 px" in warnings[0]
    assert outlying_views(["a", "b", "c", "d", "e"], [0.2, 0.21, 0.3, 0.25, 0.22]) == []  # a spread, no outlier
    res = np.full((4, 54, 2), 0.1)
    res[2, 7] = (5.0, 0.0)
    warnings = stray_corners(["a", "b", "c", "d"], res, (6, 9))
    assert len(warnings) == 1 and "view c: corner 7" in warnings[0] and "did you mean 9x6" in warnings[0]


def test_corner_order_mirrored_and_turned():
    from dstereo.calib.view_checks import align_order, mirrored_views

    q = _grid_image((9, 6))
    mirrored = q.reshape(6, 9, 2)[:, ::-1].reshape(-1, 2)  # columns numbered the other way: a mirror image
    views = {"a": q, "b": q + 3.0, "c": q - 2.0, "d": mirrored}
    warnings = mirrored_views(views, (9, 6))
    assert len(warnings) == 1 and "(d)" in warnings[0]
    assert mirrored_views({"a": q, "b": q + 1}, (9, 6)) == []
    turned = q[::-1]  # numbered from the opposite corner: the grid turned by 180 degrees
    aligned, turn = align_order(q + 5.0, turned, (9, 6))
    assert turn == 180 and np.array_equal(aligned, q)
    square = _grid_image((7, 7))
    rot = np.rot90(square.reshape(7, 7, 2), 1).reshape(-1, 2)
    aligned, turn = align_order(square, rot, (7, 7))
    assert turn in (90, 270) and np.array_equal(aligned, square)
    assert align_order(q, q + 1.0, (9, 6))[1] == 0


def test_wrong_way_round_pattern_flags_the_bad_view(tmp_path):
    """OpenCV's left01..09 with --pattern 6x9: left02 (known blurred board corner) is named with its RMS, and the
    pattern hint, on stderr and in summary.json."""
    import json

    data = require_data("opencv_stereo")
    out = tmp_path / "out"
    code, _, err = run_cli("calibrate", "--images", data, "--glob", "left0*.jpg", "--pattern", "6x9", "--out", out,
                           "--quiet")
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    flagged = [w for w in summary["warnings"] if w.startswith("view left02.jpg")]
    assert flagged and all(w in err for w in flagged)
    assert any("did you mean 9x6" in w for w in flagged)


# --- found walking the commands as a hostile user ----------------------------------------------------------------

@pytest.mark.parametrize("flag, value", [("--focal-px", "-5"), ("--baseline-mm", "-3"), ("--outliers", "-3"),
                                         ("--alpha", "5"), ("--lr-check", "-1"), ("--max-jump", "-1"),
                                         ("--outlier-std", "0"), ("--sgbm", "min_disparity=-1000")])
def test_reconstruct_refuses_numbers_it_cannot_use(tmp_path, pair, flag, value):
    # before: --focal-px -5, --outliers -3, --alpha 5, --max-jump -1 and --outlier-std 0 ran and exited 0;
    # min_disparity=-1000 was an OpenCV allocation traceback
    out = tmp_path / "out"
    args = ["reconstruct", "--left", pair[0], "--right", pair[1], "--out", out, flag, value]
    if flag not in ("--focal-px", "--baseline-mm"):
        args += ["--focal-px", "500"]
    _refused(args, out, flag.split("=")[0] if flag != "--sgbm" else "min_disparity=-1000")


def test_two_pairs_are_too_few_for_a_stereo_calibration(tmp_path):
    left_dir, right_dir = tmp_path / "L", tmp_path / "R"
    for i in range(2):
        _image(left_dir / f"left{i}.png", i), _image(right_dir / f"right{i}.png", 10 + i)
    out = tmp_path / "out"
    _refused(("calibrate", "--left", left_dir, "--right", right_dir, "--pattern", "9x6", "--out", out), out,
             "only 2 pair(s)", "at least 3")


def test_opencv_and_file_system_failures_give_one_line(monkeypatch):
    import cv2

    def opencv_fails(*_):
        raise cv2.error("OpenCV(5.0.0) alloc.cpp:73: error: (-4:Insufficient memory) Failed to allocate")

    def disk_full(*_):
        raise OSError(28, "No space left on device", "/data/out/plot.png")

    args = ("optics", "--focus-distance", "1000", "--focal-length", "50", "--crop-factor", "1.5", "--f-number", "8")
    for failure, needle in ((opencv_fails, "Insufficient memory"), (disk_full, "/data/out/plot.png")):
        monkeypatch.setattr("dstereo.optics.calculator.compute_optics", failure)
        _refused(args, None, needle)


@pytest.mark.parametrize("flag, value", [("--coc", "100"), ("--wavelength", "0.55"), ("--pixel-size", "4")])
def test_optics_refuses_unit_slips(flag, value):
    # before: accepted (a 100 mm circle of confusion, a 0.55 mm wavelength, a 4 mm pixel) and exit 0
    _refused(("optics", "--focus-distance", "1000", "--focal-length", "50", "--sensor", "22.5x16.9", "--f-number",
              "16", flag, value), None, flag, "in mm")


def test_pairs_from_two_different_rigs_are_refused(tmp_path):
    """left01..04 of OpenCV's sample with right01..04 of rig640: named alike, boards at unrelated poses. Before: exit
    0 and a stereo.yml (rig RMS 39.7 px against 0.61 / 0.14 px for the cameras alone). The K-camera job finds it
    before the rig solve: a frame's two board poses cannot be one rig's."""
    opencv, rig640 = require_data("opencv_stereo"), require_data("rig640")
    (tmp_path / "L").mkdir(), (tmp_path / "R").mkdir()
    for i in range(1, 5):
        (tmp_path / "L" / f"left{i:02d}.jpg").symlink_to(opencv / f"left{i:02d}.jpg")
        (tmp_path / "R" / f"right{i:02d}.jpg").symlink_to(rig640 / f"right{i:02d}.jpg")
    out = tmp_path / "out"
    _refused(("calibrate", "--left", tmp_path / "L", "--right", tmp_path / "R", "--pattern", "9x6", "--out", out,
              "--quiet"), out, "implies a board pose", "check that image")


def test_recession_refuses_a_frame_whose_images_are_copies(tmp_path):
    seq = tmp_path / "seq"
    for t in (0, 1):
        left = _image(seq / "left" / f"left_t={t}s.png", t)
        (seq / "right").mkdir(exist_ok=True)
        (seq / "right" / f"right_t={t}s.png").write_bytes(left.read_bytes())
    calib = _write_storage(tmp_path / "stereo.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3),
                           T=[-100.0, 0, 0])
    out = tmp_path / "out"
    _refused(("recession", seq, "--calib", calib, "--out", out), out, "left_t=0s.png", "byte-identical")


def test_a_results_folder_holding_the_inputs_is_refused(tmp_path, pair):
    """`--out` = the images folder with --force used to replace the folder, deleting the images."""
    folder = tmp_path / "imgs"
    for i in range(3):
        _image(folder / f"left{i}.png", i)
    _refused(("calibrate", "--images", folder, "--pattern", "9x6", "--out", folder, "--force"), None,
             "holds the input")
    _refused(("reconstruct", "--left", pair[0], "--right", pair[1], "--focal-px", "500", "--out", tmp_path,
              "--force"), None, "holds the input")
    assert sorted(p.name for p in folder.iterdir()) == ["left0.png", "left1.png", "left2.png"]


def test_reconstruct_pairs_given_against_their_names_are_refused(tmp_path):
    images = [_image(tmp_path / f"{side}0{i}.png", 10 * k + i) for k, side in enumerate(("left", "right"))
              for i in (1, 2)]
    out = tmp_path / "out"
    _refused(("reconstruct", "--left", images[0], "--left", images[1], "--right", images[3], "--right", images[2],
              "--focal-px", "500", "--out", out), out, "left01.png", "right01.png")


def test_one_camera_calibration_of_both_cameras_images_is_refused(tmp_path):
    """Before: a folder of left* and right* images calibrated as one camera, exit 0 (OpenCV's pairs 01-06: fx 539.5
    px, between the cameras' own 538.3 and 542.0 px, with an RMS of 0.574 px between theirs, 0.519 and 0.599: no
    figure shows the mix)."""
    folder = tmp_path / "imgs"
    for i in range(3):
        _image(folder / f"left{i}.png", i), _image(folder / f"right{i}.png", 10 + i)
    out = tmp_path / "out"
    _refused(("calibrate", "--images", folder, "--pattern", "9x6", "--out", out), out, "both cameras' images",
             "--glob")
    from dstereo.io.pairing import camera_side

    assert [camera_side(n) for n in ("left05.jpg", "R_05.png", "im0.png", "cam1_7.png", "view05.png")] == \
        ["left", "right", "left", "right", None]


def test_calibrating_unreadable_images_says_so(tmp_path):
    """Every image of the folder fails to decode: the message says that, not 'no full board'."""
    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        (images / f"view{i}.jpg").write_bytes(b"not a jpeg at all")
    line = _refused(["calibrate", "--images", images, "--pattern", "9x6", "--out", tmp_path / "out"], tmp_path / "out",
                    str(images), "decoded")
    assert "full 9x6 board" not in line


def test_calibrating_a_single_file_as_the_images_folder_says_it_is_a_file(tmp_path):
    image = _image(tmp_path / "view.png", 3)
    _refused(["calibrate", "--images", image, "--pattern", "9x6", "--out", tmp_path / "out"], tmp_path / "out",
             str(image), "is a file")
    _refused(["calibrate", "--images", image, "--glob", "*.png", "--pattern", "9x6", "--out", tmp_path / "out"],
             tmp_path / "out", "is a file")
