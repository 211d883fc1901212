"""io.corner_order: every camera numbers a frame's corners from the board's dark corner square.

Renders and a real image are turned 180 degrees with cv2.rotate (an exact pixel permutation); whichever order
OpenCV and the caller hand in, the canonical corners must land on the same physical corners as the unturned
image's. Refusals: patterns whose opposite corner squares share a colour, and images too blurred to tell.
"""

import cv2
import numpy as np
import pytest
from conftest import require_data

from dstereo.errors import DstereoError
from dstereo.io.corner_order import MIN_CONTRAST, canonical_order, end_contrasts, order_detection
from dstereo.io.corners import detect_folder
from dstereo.models.camera import Camera
from dstereo.synth import Board, render_board
from dstereo.synth.multiview import MULTIVIEW_BOARD, MULTIVIEW_OPTIONS

PATTERN = (9, 6)
# cornerSubPix on the turned image sees the same pixels in the turned order; its sums run in another order, so
# the refined corners agree to float32 rounding (~1e-5 px at 640 px), not exactly. 1e-3 px leaves room for its
# 1e-4 px stopping rule; a wrong numbering is off by whole squares (tens of pixels).
TURN_TOL_PX = 1e-3


def detect(tmp_path, name, image):
    path = tmp_path / name
    cv2.imwrite(str(path), image)
    det = detect_folder(tmp_path, PATTERN, 1.0, files=[path], use_cache=False)
    assert name in det.corners, det.rejected
    return det.corners[name]


def turned_back(q, size):
    """Corners found in the image turned 180 degrees, mapped back into the unturned image (same index order)."""
    w, h = size
    return np.array([w - 1, h - 1]) - q


@pytest.fixture(scope="module")
def render():
    cam = Camera.create(820.0, 820.0, 322.0, 238.0, (-0.12, 0.16), image_size=(640, 480))
    pose = np.array([0.25, -0.2, 0.4, -90.0, -60.0, 700.0])
    image, truth = render_board(cam, pose, MULTIVIEW_BOARD, MULTIVIEW_OPTIONS)
    return image, truth


def check_both_orders_agree(tmp_path, image, name):
    """canonical_order on an image and on its 180-degree turn, fed either order, gives one physical numbering."""
    q = detect(tmp_path, f"{name}.png", image)
    turned = cv2.rotate(image, cv2.ROTATE_180)
    q_turned = detect(tmp_path, f"{name}_turned.png", turned)
    size = (image.shape[1], image.shape[0])
    ref, _ = canonical_order(image, q, PATTERN, name)
    for given in (q, q[::-1]):
        out, flipped = canonical_order(image, given, PATTERN, name)
        np.testing.assert_array_equal(out, ref)
        assert flipped == (not np.array_equal(given, ref))
    for given in (q_turned, q_turned[::-1]):
        out, _ = canonical_order(turned, given, PATTERN, f"{name}_turned")
        np.testing.assert_allclose(turned_back(out, size), ref, atol=TURN_TOL_PX)
    return ref


def test_render_and_its_turn_are_numbered_like_the_truth(tmp_path, render):
    image, truth = render
    ref = check_both_orders_agree(tmp_path, image, "render")
    # The truth numbers corners as synth.board prints them (dark square outside corner 0). Detected corners sit
    # within ~0.1 px of the truth on these renders; the other order is off by the board's length.
    assert np.max(np.abs(ref - truth["corners"])) < 0.3
    first, last = end_contrasts(image, ref, PATTERN)
    assert first > MIN_CONTRAST and last < -MIN_CONTRAST


def test_real_image_and_its_turn_agree(tmp_path):
    path = require_data("opencv_stereo") / "left01.jpg"
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    ref = check_both_orders_agree(tmp_path, image, "left01")
    first, last = end_contrasts(image, ref, PATTERN)
    print(f"left01.jpg end contrasts {first:.0f}, {last:.0f} grey levels")
    assert first > MIN_CONTRAST and last < -MIN_CONTRAST


def test_order_detection_renumbers_a_reversed_view(tmp_path, render):
    image, _ = render
    q = detect(tmp_path, "a.png", image)
    cv2.imwrite(str(tmp_path / "b.png"), image)
    det = detect_folder(tmp_path, PATTERN, 1.0, use_cache=False)
    det.corners["b.png"] = det.corners["b.png"][::-1].copy()  # as a camera numbering from the other end would
    ordered, reversed_names = order_detection(det)
    assert reversed_names == ["b.png"]
    np.testing.assert_array_equal(ordered.corners["a.png"], q)
    np.testing.assert_array_equal(ordered.corners["b.png"], q)


@pytest.mark.parametrize("pattern", [(8, 6), (7, 7), (6, 6)])
def test_patterns_whose_ends_look_alike_are_refused(render, pattern):
    image, _ = render
    q = np.zeros((pattern[0] * pattern[1], 2))
    with pytest.raises(DstereoError, match=r"cam7/f01\.png: a .* same colour"):
        canonical_order(image, q, pattern, "cam7/f01.png")


def test_blurred_image_is_refused_by_name(tmp_path, render):
    image, _ = render
    q = detect(tmp_path, "sharp.png", image)
    spacing = float(np.median(np.linalg.norm(np.diff(q.reshape(6, 9, 2), axis=1), axis=2)))
    # Blurred over a square's width, a square's centre is the average of it and its neighbours: no colour left.
    blurred = cv2.GaussianBlur(image, (0, 0), spacing)
    with pytest.raises(DstereoError, match=r"blurred\.png: the board's corner squares cannot be told apart"):
        canonical_order(blurred, q, PATTERN, "blurred.png")


def test_uniform_image_is_refused(render):
    image, _ = render
    flat = np.full_like(image, 128)
    q = np.column_stack([np.tile(np.arange(9) * 30 + 100, 6), np.repeat(np.arange(6) * 30 + 100, 9)]).astype(float)
    with pytest.raises(DstereoError, match="cannot be told apart"):
        canonical_order(flat, q, PATTERN, "flat.png")


def test_negative_board_is_numbered_from_its_dark_end():
    """Printed in negative, the square outside corner 0 is light: the canonical order starts at the other end."""
    board = Board((9, 6), 20.0, 20.0, black=0.92, white=0.08, background=0.35)
    cam = Camera.create(820.0, 820.0, 322.0, 238.0, image_size=(640, 480))
    image, truth = render_board(cam, np.array([0.0, 0.0, 0.0, -90.0, -60.0, 700.0]), board, MULTIVIEW_OPTIONS)
    out, flipped = canonical_order(image, truth["corners"], PATTERN, "negative.png")
    assert flipped
    np.testing.assert_array_equal(out, truth["corners"][::-1])
