"""Chessboard corner detection at the OpenCV edge, with a per-image-content cache.

Every image either yields a full board (corners in OpenCV's order, sub-pixel refined) or is listed in
`rejected` with the reason; nothing is dropped silently. Mixed image sizes are an error, not a rejection,
because one camera cannot have two sizes.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dstereo.config.values import parse_pattern  # noqa: F401 - the readers' name for it
from dstereo.errors import DstereoError
from dstereo.models.board import Board

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
_DETECTOR_VERSION = "v1"  # bump when detection parameters change so cached corners are not reused


@dataclass
class Detection:
    """Corners of the usable images (name -> (n, 2) float64), rejects (name -> reason), image size (w, h), and
    the board they were detected on (the one carrier of the pattern and the square size)."""

    corners: dict[str, np.ndarray]
    rejected: dict[str, str]
    image_size: tuple[int, int]
    board: Board
    folder: str = ""
    from_cache: int = 0
    names: list[str] = field(default_factory=list)  # every image considered, sorted

    # Read-only views of `board`, for callers that need only one of its parts.
    @property
    def object_points(self) -> np.ndarray:
        return self.board.object_points()

    @property
    def pattern(self) -> tuple[int, int]:
        return self.board.pattern

    @property
    def square(self) -> float:
        return self.board.square


def board_points(pattern: tuple[int, int], square: float) -> np.ndarray:
    """(cols*rows, 3) object points of the inner corners (`dstereo.models.board.Board.object_points`)."""
    return Board.from_pattern(pattern, square).object_points()


def list_images(folder: Path, suffix: str | None = None) -> list[Path]:
    folder = Path(folder)
    if folder.is_file():
        raise DstereoError(f"images: {folder} is a file; point `images` at the folder that holds the chessboard "
                           "images (or the folder plus `glob` 'name*.jpg')")
    if not folder.is_dir():
        raise DstereoError(f"images: folder {folder} does not exist; point `images` at the chessboard images")
    suffixes = (("." + suffix.lstrip(".").lower()),) if suffix else IMAGE_SUFFIXES
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    if not files:
        raise DstereoError(f"images: no {'/'.join(suffixes)} images in {folder}; check the folder or the image format")
    return files


def _cache_dir() -> Path | None:
    """DSTEREO_CACHE/corners, else XDG_CACHE_HOME/dstereo/corners, else ~/.cache/dstereo/corners; None for a user
    without a home folder (an empty variable counts as unset: "" would put the cache in the working folder)."""
    root = os.environ.get("DSTEREO_CACHE")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME")
        if not base:
            try:
                base = str(Path.home() / ".cache")
            except RuntimeError:  # no HOME and no password entry
                return None
        root = os.path.join(base, "dstereo")
    return Path(root) / "corners"


def corner_cache_problem() -> str | None:
    """Why the corner cache cannot be used here (one line for a warning), or None when it can: its folder is made
    and a file written in it, so a cache that cannot be written is found before any detection, not in the middle
    of it as a file error that does not say it is the cache."""
    import tempfile

    folder = _cache_dir()
    advice = ("running without it (as --no-cache); set DSTEREO_CACHE to a writable folder, or pass --no-cache to "
              "skip the cache and this warning")
    if folder is None:
        return f"no home folder for the corner cache (~/.cache/dstereo/corners); {advice}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as exc:
        return f"the corner cache {folder} cannot be written ({exc.strerror or exc}); {advice}"
    return None


def _detect_one(gray: np.ndarray, pattern: tuple[int, int]) -> tuple[np.ndarray | None, str]:
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found or corners is None or len(corners) != pattern[0] * pattern[1]:
        return None, f"no full {pattern[0]}x{pattern[1]} board found"
    pts = corners.reshape(-1, 2).astype(np.float32)
    # Window from the board's own scale: half a square at most, so the window never reaches the next corner.
    grid = pts.reshape(pattern[1], pattern[0], 2)
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    half = int(np.clip(round(0.4 * spacing), 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    refined = cv2.cornerSubPix(gray, pts.reshape(-1, 1, 2), (half, half), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64), ""


def _cached_entry(path: Path) -> tuple[np.ndarray | None, str, tuple[int, int] | None] | None:
    """(corners or None, reason, image size or None if the entry predates sizes) of a cache entry, None if none."""
    try:
        with np.load(path) as z:
            size = tuple(int(v) for v in z["size"]) if "size" in z.files else None
            return (z["corners"] if z["found"] else None), str(z["reason"]), size
    except (OSError, ValueError, KeyError, EOFError):  # missing, unreadable or damaged: detect the image again
        return None


def _write_entry(cache: Path, path: Path, pts: np.ndarray | None, reason: str, size: tuple[int, int]) -> None:
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez(tmp, found=pts is not None, corners=pts if pts is not None else np.zeros((0, 2)), reason=reason,
             size=np.array(size, np.int64))
    os.replace(tmp, path)


def detect_folder(
    folder: Path | str,
    pattern: tuple[int, int],
    square: float,
    suffix: str | None = None,
    files: list[Path] | None = None,
    use_cache: bool = True,
    progress=None,
) -> Detection:
    """Detect the board in every image of `folder` (or the given `files`); cache by image content. A cache entry
    holds the image's size too (the file was decoded when it was written: the bytes it is keyed by are an image),
    so a cached image is not decoded again (20 webcam images: ~35 ms of a served run, measured); an entry written
    before sizes were kept is completed on its first hit."""
    import cv2

    files = list_images(Path(folder), suffix) if files is None else files
    cache = _cache_dir()
    use_cache = use_cache and cache is not None
    corners: dict[str, np.ndarray] = {}
    rejected: dict[str, str] = {}
    sizes: dict[tuple[int, int], str] = {}
    hits = 0
    for i, path in enumerate(files):
        data = path.read_bytes()
        key = hashlib.sha256(data + f"{pattern}{_DETECTOR_VERSION}".encode()).hexdigest()[:32]
        cached = cache / f"{key}.npz"
        entry = _cached_entry(cached) if use_cache and data else None
        if entry is not None and entry[2] is not None:
            pts, reason, size = entry
        else:
            gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
            if gray is None:
                rejected[path.name] = "unreadable: not an image file OpenCV can decode"
                continue
            size = (gray.shape[1], gray.shape[0])
            pts, reason = entry[:2] if entry is not None else _detect_one(gray, pattern)
            if use_cache:
                try:
                    _write_entry(cache, cached, pts, reason, size)
                except OSError:  # the cache is only a shortcut: a folder that stopped taking files (full, removed)
                    use_cache = False  # does not stop the detection; the commands check it first (corner_cache_problem)
        hits += entry is not None
        sizes.setdefault(size, path.name)
        if pts is None:
            rejected[path.name] = reason
        else:
            corners[path.name] = pts
        if progress is not None:
            progress(i + 1, len(files))
    if len(sizes) > 1:
        listing = ", ".join(f"{w}x{h} (e.g. {name})" for (w, h), name in sizes.items())
        raise DstereoError(f"images: {folder} mixes image sizes {listing}; one camera's images must share one size")
    unreadable = [name for name, why in rejected.items() if why.startswith("unreadable")]
    if unreadable and len(unreadable) == len(files):
        raise DstereoError(f"images: none of the {len(files)} images in {folder} can be decoded (e.g. {unreadable[0]}); "
                           "they are not image files OpenCV reads (damaged, empty, or another format)")
    if not corners:
        raise DstereoError(
            f"images: no image in {folder} shows a full {pattern[0]}x{pattern[1]} board; "
            "check `pattern` (inner corners, COLSxROWS, e.g. 9x6)"
            + (f" ({len(unreadable)} of the {len(files)} images could not be decoded)" if unreadable else "")
        )
    size = next(iter(sizes))
    return Detection(corners, rejected, size, Board.from_pattern(pattern, square), str(folder), hits,
                     [p.name for p in files])
