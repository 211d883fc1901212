"""The screenshots of report.html in README.md and docs/guide.md, taken by the browser tests' own machinery
(tests/report_browser.py: Debian's chromium driven by playwright, every check run on the page first).

    python -m experiments.report_screenshots demo_out   # after `make demo` (or `dstereo demo --quick --out demo_out`)

writes docs/figures/report_reconstruction.png (the top of the reconstruction's report: the summary and the cloud
in 3D) and docs/figures/report_calibration.png (the rig's report: its summary and self-checks), each downscaled to
WIDTH px; a page that fails a browser check is refused.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WIDTH = 900  # px of the committed PNG (README width)
SHOTS = (("reconstruction", "report_reconstruction.png", (1200, 1500)),
         ("calibration", "report_calibration.png", (1200, 1000)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="a `dstereo demo` output folder")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    import cv2

    from conftest import BROWSER, BROWSER_ARGS, DRAWN_SHARE
    from report_browser import browse

    for sub, name, viewport in SHOTS:
        target = args.out / name
        page, = browse([args.demo / sub / "report.html"], BROWSER, BROWSER_ARGS, target, viewport=viewport,
                       settle_ms=1500)
        if page["errors"] or page["outside"] or 0 in page["images"] or any(
                v["coloured_share"] <= DRAWN_SHARE for v in page["views3d"]):
            target.unlink()
            raise SystemExit(f"{page['path']}: a browser check failed: {page}")
        image = cv2.imread(str(target))
        h, w = image.shape[:2]
        small = cv2.resize(image, (WIDTH, round(h * WIDTH / w)), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(target), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        print(f"{target}: {small.shape[1]} x {small.shape[0]} px, {target.stat().st_size / 1e3:.0f} kB, "
              f"page opened and checked in {page['seconds']:.1f} s")


if __name__ == "__main__":
    main()
