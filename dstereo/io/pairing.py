"""Which left image goes with which right image: partners are matched by name, never by position in a list.

The rule: a left and a right image are partners when their file names (without the extension) are equal once the
first *camera token* is taken out. Camera tokens: the words `left`/`right` (any case), a lone `L`/`R` (not part
of a longer word: `L_05`, `img_R5`), and the camera number of `im0`/`im1`, `img0`/`img1`, `cam0`/`cam1`
(Middlebury's names; the prefix stays). So `left05.jpg` pairs with `right05.jpg`, `L_05.png` with `R_05.png`,
`im0.png` with `im1.png`, `cam0_0007.png` with `cam1_0007.png`, and `0003.png` with `0003.png` in two folders.
That common rest of the name is the pair's *key*; digits are compared as written (`05` and `5` differ).

Used by the stereo calibration (`jobs.rig_sources.stereo_pair_sources`) and by the recession sequence.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from dstereo.errors import DstereoError

CAMERA_TOKEN = re.compile(r"(?i)(left|right|(?<![a-z])[lr](?![a-z])|(?<![a-z])(?:im|img|cam)([01])(?!\d))")
# A stereo calibration needs a few pairs; below this (or when most images have no partner) it is refused.
MIN_PAIRS = 3
# The thesis's stereo project layout (4.2.2.2): each camera's images in a folder of its own
LEFT_FOLDERS = ("images_left", "calibrate_left")
RIGHT_FOLDERS = ("images_right", "calibrate_right")


def has_stereo_layout(images: Path) -> bool:
    """Whether `images` holds the thesis's stereo folders (images_left / calibrate_left). Here, not with the stereo
    pipeline: every `dstereo calibrate` asks this first, and that module's imports cost ~50 ms (measured)."""
    return any((Path(images) / name).is_dir() for name in LEFT_FOLDERS + RIGHT_FOLDERS)


def natural_key(text: str) -> list:
    """Sort key comparing digit runs as numbers: frame_2 before frame_10."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", text) if part]


def _drop_token(m: re.Match) -> str:
    word = m.group(0)
    return word[:-1] if m.group(2) is not None else ""  # im0 -> im, left -> ""


def pair_key(path: str | Path) -> str:
    """The file's stem without its first camera token (module docstring)."""
    return CAMERA_TOKEN.sub(_drop_token, Path(path).stem, count=1)


def partner_name(path: str | Path) -> str:
    """The name the partner of `path` would have with the other camera token (for messages)."""
    path = Path(path)
    swap = {"left": "right", "right": "left", "l": "r", "r": "l"}

    def repl(m: re.Match) -> str:
        word = m.group(0)
        if m.group(2) is not None:
            return word[:-1] + ("1" if word[-1] == "0" else "0")
        new = swap[word.lower()]
        return new.upper() if word.isupper() else (new.capitalize() if word[0].isupper() else new)

    return CAMERA_TOKEN.sub(repl, path.stem, count=1) + path.suffix


def by_key(files: list[Path]) -> dict[str, Path]:
    """{key: file}; two files of one camera with the same key are an error naming both."""
    out: dict[str, Path] = {}
    for path in files:
        key = pair_key(path)
        if key in out:
            raise DstereoError(f"{path} and {out[key]} have the same name {key!r} once the camera token is taken "
                               "out, so their partners cannot be told apart; keep one image per moment and camera")
        out[key] = Path(path)
    return out


@dataclass(frozen=True)
class NamePairing:
    """Partners found by name, in the left camera's order, and the images of each camera without one."""

    pairs: list[tuple[Path, Path]]
    left_alone: list[Path]
    right_alone: list[Path]

    def warning(self) -> str | None:
        """One line listing the unmatched images, or None when every image has its partner."""
        if not self.left_alone and not self.right_alone:
            return None
        parts = [f"{len(files)} {side} image(s) without a {other} partner named like them ({_names(files)})"
                 for side, other, files in (("left", "right", self.left_alone), ("right", "left", self.right_alone))
                 if files]
        return "; ".join(parts) + f"; they are left out (pairs are matched by name: {RULE})"


RULE = "equal names once left/right, L/R or im0/im1 is taken out, e.g. left05.jpg with right05.jpg"


def _names(files: list[Path], most: int = 6) -> str:
    shown = ", ".join(p.name for p in files[:most])
    return shown + (f" and {len(files) - most} more" if len(files) > most else "")


def pair_by_name(left: list[Path], right: list[Path]) -> NamePairing:
    """Match two cameras' image lists by name (module docstring); nothing is refused here."""
    keys_r = by_key(list(right))
    keys_l = by_key(list(left))
    pairs = [(path, keys_r[key]) for key, path in keys_l.items() if key in keys_r]
    return NamePairing(pairs, [p for k, p in keys_l.items() if k not in keys_r],
                       [p for k, p in keys_r.items() if k not in keys_l])


def check_enough_pairs(pairing: NamePairing, where_left: str, where_right: str, minimum: int = MIN_PAIRS) -> None:
    """Refuse when fewer than `minimum` pairs were matched, or when fewer than half of either camera's images found a
    partner (the two cameras then most likely follow different naming schemes)."""
    n = len(pairing.pairs)
    n_l, n_r = n + len(pairing.left_alone), n + len(pairing.right_alone)
    if n >= minimum and 2 * n >= n_l and 2 * n >= n_r:
        return
    if not pairing.left_alone and not pairing.right_alone:
        raise DstereoError(f"stereo images: only {n} pair(s) ({where_left}, {where_right}); a stereo calibration needs "
                           f"at least {minimum}, better 10-20 at varied positions and tilts")
    example = pairing.left_alone[0] if pairing.left_alone else None
    hint = f" (e.g. {example.name} would pair with {partner_name(example)})" if example is not None else ""
    raise DstereoError(
        f"stereo images: only {n} of {n_l} left images ({where_left}) and {n_r} right images ({where_right}) pair up "
        f"by name{hint}; pairs are matched by name: {RULE}; rename the images so partners share their name"
        + (f" (a stereo calibration needs at least {minimum} pairs)" if n < minimum else ""))


def _example_image(folder: Path, side: str) -> Path:
    """An image of `folder` to quote in a message: the first one named for `side` (left01.jpg), else the first."""
    from dstereo.io.corners import IMAGE_SUFFIXES

    try:
        images = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    except OSError:
        images = []
    named = [p for p in images if camera_side(p) == side]
    return (named or images or [folder / f"{side}01.png"])[0]


def check_distinct_images(left: str | Path, right: str | Path, decode: bool = True) -> None:
    """Refuse a 'pair' that is one image twice: the same file, a byte-identical copy, or (with `decode`) the same
    decoded pixels. (An image matched with itself gives zero disparity everywhere: a plausible-looking but
    meaningless cloud.)"""
    left, right = Path(left), Path(right)
    for side, other, path in (("left", "right", left), ("right", "left", right)):
        if path.is_dir():  # checked first, before any work: read later it was "an image that does not exist"
            raise DstereoError(f"`{side}` {path} is a folder, not an image: `{side}` takes one image file, e.g. "
                               f"`{side}` {_example_image(path, side)}, with its partner as `{other}`; for several "
                               "pairs repeat `left` and `right` in pair order")
    if not (left.is_file() and right.is_file()):
        return  # a missing file is reported where the images are read
    what = None
    if left.resolve() == right.resolve():
        what = "the same file"
    elif left.stat().st_size == right.stat().st_size and left.read_bytes() == right.read_bytes():
        what = "byte-identical copies"
    elif decode:
        import cv2
        import numpy as np

        a, b = cv2.imread(str(left), cv2.IMREAD_UNCHANGED), cv2.imread(str(right), cv2.IMREAD_UNCHANGED)
        if a is not None and b is not None and a.shape == b.shape and np.array_equal(a, b):
            what = "the same image (identical pixels)"
    if what is not None:
        raise DstereoError(f"left image {left} and right image {right} are {what}; a stereo pair needs the left "
                           "and the right camera's images taken at the same moment")


def check_order_agrees_with_names(left: list[Path], right: list[Path]) -> None:
    """Pairs given in order (reconstruct's repeated --left/--right) must not contradict the names: when every image
    has a partner by name and the order pairs them otherwise, refuse naming the first disagreement."""
    if len(left) < 2:
        return
    try:
        named = pair_by_name([Path(p) for p in left], [Path(p) for p in right])
    except DstereoError:
        return  # names that do not identify partners: the order is all there is
    if named.left_alone or named.right_alone:
        return
    by_name = {a: b for a, b in named.pairs}
    for a, b in zip(map(Path, left), map(Path, right)):
        if by_name[a] != b:
            raise DstereoError(f"`left` {a} is given with `right` {b}, but by name its partner is {by_name[a]}; give "
                               "the `right` images in the order of the `left` ones")


def camera_side(path: str | Path) -> str | None:
    """'left' or 'right' from the file name's first camera token (im0/cam0 count as left), None without one."""
    m = CAMERA_TOKEN.search(Path(path).stem)
    if m is None:
        return None
    word = m.group(0).lower()
    return "left" if word in ("left", "l") or word.endswith("0") else "right"


def check_one_camera(files: list[Path], where: str) -> None:
    """Refuse a one-camera calibration whose images are named as both cameras' (left05 and right05 together)."""
    sides: dict[str, list[Path]] = {}
    for path in files:
        side = camera_side(path)
        if side is not None:
            sides.setdefault(side, []).append(Path(path))
    if len(sides) == 2:
        raise DstereoError(
            f"images: {where} holds both cameras' images ({len(sides['left'])} left, e.g. {sides['left'][0].name}; "
            f"{len(sides['right'])} right, e.g. {sides['right'][0].name}); a calibration is of one camera: give "
            "`glob` (e.g. `glob` 'left*.jpg'), or calibrate the rig with `left` and `right`")
