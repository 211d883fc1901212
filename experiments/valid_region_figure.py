"""docs/figures/valid_region_fisheye640.png: the valid-intrinsics region dstereo writes into camera.cameramodel, as
mrcal's own `mrcal-show-valid-intrinsics-region` draws it from the file, beside dstereo's mask it came from.

fisheye640 calibrated with the 5-coefficient model (a polynomial that folds back beyond the corners, so the map
masks part of the image). Needs Debian's `mrcal` (the tool, run by the system Python; never a dependency):
    .venv/bin/python -m experiments.valid_region_figure
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "fisheye640"
OUT = REPO / "docs" / "figures" / "valid_region_fisheye640.png"


def main() -> None:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        images = tmp / "images"
        images.mkdir()
        for image in sorted(DATA.glob("view*.jpg")):
            (images / image.name).symlink_to(image)  # read in place
        res = tmp / "results"
        subprocess.run([sys.executable, "-m", "dstereo.cli", "calibrate", "--images", str(images), "--pattern", "9x6",
                        "--square", "1", "--model", "default", "--out", str(res), "-q"], check=True, cwd=REPO,
                       env={"DSTEREO_SERVE": "0", "PATH": "/usr/bin:/bin"})
        # the tool writes its picture beside the image it is given: a scratch copy, not the shared folder
        shown = tmp / "view08.jpg"
        shown.write_bytes((DATA / "view08.jpg").read_bytes())
        subprocess.run(["mrcal-show-valid-intrinsics-region", "--write-image", "--image", str(shown),
                        str(res / "camera.cameramodel")], check=True, capture_output=True)
        drawn = cv2.imread(str(tmp / "view08-valid-intrinsics-region.jpg"))[..., ::-1]
        grid = np.load(res / "projection_uncertainty.npz")
        text = (res / "camera.cameramodel").read_text()
        polygon = np.array(ast.literal_eval(text[text.index("{"):])["valid_intrinsics_region"])
        corners = np.load(res / "corners.npz")
        pts = np.concatenate([corners[k].reshape(-1, 2) for k in corners.files if k.startswith("view")])
    u, v, mask = grid["u"], grid["v"], grid["mask"]
    du, dv = u[1] - u[0], v[1] - v[0]
    fig, ax = plt.subplots(1, 2, figsize=(11, 5.6))
    ax[0].imshow(drawn)
    ax[0].set_title("mrcal-show-valid-intrinsics-region, dstereo's file", fontsize=10)
    ax[1].imshow(np.where(mask, 1.0, 0.35), extent=(u[0] - du / 2, u[-1] + du / 2, v[-1] + dv / 2, v[0] - dv / 2),
                 cmap="gray", vmin=0, vmax=1)
    ax[1].plot(pts[:, 0], pts[:, 1], ".", ms=1, color="tab:blue", label="detected corners")
    ax[1].plot(polygon[:, 0], polygon[:, 1], "-", color="tab:red", lw=2, label="valid_intrinsics_region written")
    ax[1].set_xlim(0, 639)
    ax[1].set_ylim(639, 0)
    ax[1].legend(loc="lower right", fontsize=8)
    ax[1].set_title(f"dstereo: invertible (white; {int((~mask).sum())} of {mask.size} masked), corners", fontsize=10)
    fig.suptitle("fisheye640, 5-coefficient model: the valid-intrinsics region")
    fig.tight_layout()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=70)
    print(f"{OUT.relative_to(REPO)}: {int((~mask).sum())} of {mask.size} grid pixels masked; region of "
          f"{len(polygon)} points")


if __name__ == "__main__":
    main()
