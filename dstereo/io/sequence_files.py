"""A recession sequence on disk: stereo pairs over time, paired by name, with a timestamp each.

Layout (SEQUENCE is a folder):

    SEQUENCE/left/*.png   and SEQUENCE/right/*.png      (or images_left/ + images_right/, the thesis layout)
    SEQUENCE/timestamps.csv                             optional: `name,time_s` (one row per frame)

A left and a right image are partners when their names are equal once the camera token is taken out
(`dstereo.io.pairing`, shared with the stereo calibration): `left_007.png` pairs with `right_007.png`,
`L_t=3.5s.png` with `R_t=3.5s.png`, `0003.png` with `0003.png`. That common rest of
the name is the frame's *key*. Frames are ordered by key (numbers in it compared as numbers).

Timestamps, first found wins: `--timestamps CSV` (or SEQUENCE/timestamps.csv), whose `name` column holds the
left file name, its stem or the key; `fps` with the frame number (the last integer of the key); else the time
written in the name: `t=12.5s`, `_12.500s`, `12.5s` or `250ms` (a number followed by s or ms, standing alone
between separators). Times must increase strictly with the frame order.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

from dstereo.errors import DstereoError
from dstereo.recession.frame import Frame  # noqa: F401 - what discover returns
from dstereo.io.pairing import by_key, natural_key, pair_key, partner_name  # noqa: F401 - pair_key re-exported

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
FOLDER_PAIRS = (("left", "right"), ("images_left", "images_right"), ("L", "R"))
TIME_IN_NAME = re.compile(r"(?i)(?:^|[_\-\s.=])(?:t=?)?(\d+(?:\.\d*)?|\.\d+)(ms|s)(?=$|[_\-\s])")
LAST_INTEGER = re.compile(r"(\d+)(?!.*\d)")


def find_folders(sequence: Path) -> tuple[Path, Path]:
    """The left and right image folders of a sequence folder."""
    if not sequence.is_dir():
        raise DstereoError(f"sequence {sequence} is not a folder; give the folder that holds left/ and right/")
    for a, b in FOLDER_PAIRS:
        if (sequence / a).is_dir() and (sequence / b).is_dir():
            return sequence / a, sequence / b
    raise DstereoError(f"sequence {sequence} has no left/ + right/ (or images_left/ + images_right/) image folders; "
                       "put each camera's images in its own folder")


def _images(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]


def pair_images(left_dir: Path, right_dir: Path) -> list[tuple[str, Path, Path]]:
    """(key, left, right) for every frame, in natural key order; a missing partner is an error naming the file."""
    left, right = by_key(sorted(_images(left_dir))), by_key(sorted(_images(right_dir)))
    for mine, theirs, other in ((left, right, right_dir), (right, left, left_dir)):
        alone = sorted(set(mine) - set(theirs), key=natural_key)
        if alone:
            raise DstereoError(f"{mine[alone[0]]} has no partner in {other} (expected an image named like it with the "
                               f"other side word, e.g. {partner_name(mine[alone[0]])}); add it or remove this frame"
                               + (f" ({len(alone) - 1} more unpaired)" if len(alone) > 1 else ""))
    return [(k, left[k], right[k]) for k in sorted(left, key=natural_key)]


def time_from_name(key: str) -> float | None:
    """Seconds written in a name (`t=12.5s`, `_12.500s`, `250ms`), or None."""
    found = TIME_IN_NAME.findall(key)
    if not found:
        return None
    number, unit = found[-1]
    return float(number) * (1e-3 if unit.lower() == "ms" else 1.0)


def read_timestamps(path: Path) -> dict[str, float]:
    """`name,time_s` rows (a header line is optional) -> {name: seconds}."""
    if not path.is_file():
        raise DstereoError(f"timestamps file {path} does not exist")
    out: dict[str, float] = {}
    with path.open(newline="") as fh:
        for line_no, row in enumerate(csv.reader(fh), 1):
            cells = [c.strip() for c in row]
            if not cells or not cells[0] or cells[0].startswith("#"):
                continue
            if len(cells) < 2:
                raise DstereoError(f"{path}:{line_no}: expected `name,time_s`, got {','.join(cells)!r}")
            try:
                value = float(cells[1])
            except ValueError:
                if line_no == 1:
                    continue  # header
                raise DstereoError(f"{path}:{line_no}: time {cells[1]!r} is not a number (seconds)") from None
            if not math.isfinite(value):
                raise DstereoError(f"{path}:{line_no}: time {cells[1]!r} is not finite")
            out[cells[0]] = value
    if not out:
        raise DstereoError(f"{path}: no `name,time_s` rows")
    return out


def _lookup(table: dict[str, float], key: str, left: Path, where: Path) -> float:
    for name in (left.name, left.stem, key):
        if name in table:
            return table[name]
    raise DstereoError(f"{where} has no time for {left} (looked for {left.name!r}, {left.stem!r} or {key!r}); add a "
                       "row `name,time_s` for it")


def discover(sequence: str | Path, timestamps: str | Path | None = None, fps: float | None = None) -> list[Frame]:
    """The frames of a sequence folder with their times (module docstring), checked: at least 2 frames, every
    image with a partner, strictly increasing times."""
    sequence = Path(sequence)
    left_dir, right_dir = find_folders(sequence)
    pairs = pair_images(left_dir, right_dir)
    if fps is not None and not fps > 0:
        raise DstereoError(f"`fps` {fps}: need a positive frame rate")
    csv_path = Path(timestamps) if timestamps is not None else sequence / "timestamps.csv"
    table = read_timestamps(csv_path) if timestamps is not None or csv_path.is_file() else None
    frames = []
    for key, left, right in pairs:
        if table is not None:
            t = _lookup(table, key, left, csv_path)
        elif fps is not None:
            m = LAST_INTEGER.search(key)
            if m is None:
                raise DstereoError(f"{left}: `fps` needs a frame number in the name; none found in {key!r}")
            t = int(m.group(1)) / fps
        else:
            t = time_from_name(key)
            if t is None:
                raise DstereoError(f"{left}: no time for this frame: give `timestamps` CSV (name,time_s), put "
                                   "timestamps.csv in the sequence folder, give `fps`, or write the time in the "
                                   "name (e.g. left_t=12.5s.png)")
        frames.append(Frame(key, left, right, float(t)))
    if len(frames) < 2:
        raise DstereoError(f"sequence {sequence}: {len(frames)} stereo pair(s) found; recession needs at least 2 "
                           "frames")
    for prev, cur in zip(frames, frames[1:]):
        if not cur.time_s > prev.time_s:
            what = "the same time as" if cur.time_s == prev.time_s else "an earlier time than"
            raise DstereoError(f"{cur.left}: time {cur.time_s:g} s is {what} the frame before it ({prev.left}, "
                               f"{prev.time_s:g} s); times must increase with the frame order (names sorted "
                               "naturally); fix the timestamps")
    return frames


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the file header, or None when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return tuple(int(v) for v in im.size)
    except Exception:  # noqa: BLE001 - any unreadable file: the frame is reported and skipped later
        return None


def check_sizes(frames: list[Frame], calib_size: tuple[int, int] | None, calib_source: str = "") -> tuple[int, int]:
    """Every readable image has the size of the first one (and the calibration's); returns (width, height)."""
    expected, first = None, None
    for frame in frames:
        for path in (frame.left, frame.right):
            size = image_size(path)
            if size is None:
                continue  # unreadable: that frame fails and is reported
            if expected is None:
                expected, first = size, path
                if calib_size is not None and tuple(calib_size) != size:
                    raise DstereoError(f"{path} is {size[0]}x{size[1]} but the calibration {calib_source} is for "
                                       f"{calib_size[0]}x{calib_size[1]} images; use images of the calibrated size")
            elif size != expected:
                raise DstereoError(f"{path} is {size[0]}x{size[1]} but {first} is {expected[0]}x{expected[1]}; all "
                                   "images of a sequence must have one size (crop or resize them the same way)")
    if expected is None:
        raise DstereoError(f"no image of the sequence ({frames[0].left.parent}) can be read; give PNG, JPEG or "
                           "TIFF files")
    return expected
