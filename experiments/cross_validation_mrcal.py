"""mrcal's own cross-validation on dstereo's corners, to read dstereo's beside it.

Random halves of the views (the same permutations as `dstereo calibrate --cross-validate`, seed 0), each calibrated
by mrcal-calibrate-cameras (its defaults: outlier rejection, regularisation and board warp on; extra flags such as
--skip-calobject-warp-solve are passed through), the difference by mrcal.projection_diff (its implied transform,
fitted near the centre with uncertainty weights) and the prediction as mrcal's users read it: the two halves'
mrcal.projection_uncertainty added, sqrt(tr C_A + tr C_B). That prediction does not remove what the implied
transform absorbs, so it is larger than the predicted difference itself (dstereo's cross-validation removes it).

mrcal is NOT a dependency: install it for the SYSTEM python (apt-get install -y mrcal python3-mrcal) and run
    /usr/bin/python3 experiments/cross_validation_mrcal.py RESULTS_DIR LENSMODEL_OPENCV5 [mrcal-calibrate-cameras flags]
with RESULTS_DIR a `dstereo calibrate` results folder (corners.npz, summary.json), pattern 9x6, unit squares."""
import json, subprocess, sys, tempfile
from pathlib import Path
import numpy as np
import mrcal

def write_vnl(path, names, corners):
    with open(path, "w") as f:
        f.write("# filename x y level\n")
        for n in names:
            for x, y in corners[n]:
                f.write(f"{n} {x:.6f} {y:.6f} 0\n")

EXTRA = []
def calibrate(names, corners, size, focal, model, out):
    out.mkdir(parents=True, exist_ok=True)
    write_vnl(out / "c.vnl", names, corners)
    cmd = ["mrcal-calibrate-cameras", "--corners-cache", str(out / "c.vnl"), "--lensmodel", model, "--focal", str(focal),
           "--object-spacing", "1", "--object-width-n", "9", "--object-height-n", "6", "--imagersize", str(size[0]),
           str(size[1]), "--outdir", str(out), *EXTRA, "*"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(r.stderr[-2000:])
    return mrcal.cameramodel(str(out / "camera-0.cameramodel"))

def main(res, model, splits=6):
    res = Path(res)
    s = json.loads((res / "summary.json").read_text()); c = np.load(res / "corners.npz")
    names = s["images"]["used"]; size = tuple(s["image_size"])
    corners = {n: c[n] for n in names}
    rng_ = s["projection_uncertainty"]["range"]
    focal = s["full_set"]["fx"]
    rng = np.random.default_rng(0)
    ratios, trs = [], []
    tmp = Path(tempfile.mkdtemp())
    for i in range(splits):
        perm = rng.permutation(len(names))
        a, b = np.sort(perm[: len(names) // 2]), np.sort(perm[len(names) // 2:])
        ms = [calibrate([names[j] for j in part], corners, size, focal, model, tmp / f"{i}{h}") for h, part in zip("ab", (a, b))]
        difflen, q0, _ = mrcal.projection_diff(ms, gridn_width=16, gridn_height=12, distance=rng_)[:3]
        q = q0.reshape(-1, 2)
        tr = 0
        for m in ms:
            p = mrcal.unproject(q, *m.intrinsics(), normalize=True) * rng_
            var = mrcal.projection_uncertainty(p, model=m, what="covariance")
            tr = tr + np.trace(var, axis1=-2, axis2=-1)
        d2 = difflen.ravel() ** 2
        ok = np.isfinite(d2) & np.isfinite(tr)
        ratios.append(float(np.sqrt(np.mean(d2[ok]) / np.mean(tr[ok]))))
    print(f"{res.name} {model}: mrcal observed/predicted per split {np.round(ratios, 2)}, geometric mean "
          f"{np.exp(np.mean(np.log(ratios))):.2f}", flush=True)

EXTRA[:] = sys.argv[3:]
print(EXTRA, end=" ")
main(sys.argv[1], sys.argv[2])
