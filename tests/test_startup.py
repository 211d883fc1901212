"""Start-up: a command's --help and `import dstereo` do not import JAX (or OpenCV, matplotlib, scipy, trimesh);
JAX, once something imports it, is configured as before (float64, the compilation cache). A new process each,
since this test process has imported everything already."""

import subprocess
import sys

HEAVY = ("jax", "cv2", "matplotlib", "scipy", "trimesh")


def _run(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_help_imports_no_heavy_library():
    loaded = _run("import sys\nfrom dstereo.cli import app\ntry:\n    app(['calibrate', '--help'])\n"
                  "except SystemExit:\n    pass\n"
                  f"print('loaded:', *[m for m in {HEAVY!r} if m in sys.modules])")
    assert loaded.splitlines()[-1] == "loaded:", loaded


def test_jax_imported_later_is_configured():
    out = _run("import dstereo, sys\nassert 'jax' not in sys.modules\nimport jax.numpy as jnp, jax\n"
               "print(jnp.ones(1).dtype, bool(jax.config.jax_compilation_cache_dir))")
    assert out == "float64 True"


def test_jax_imported_first_is_configured():
    assert _run("import jax, dstereo, jax.numpy as jnp\nprint(jnp.ones(1).dtype)") == "float64"


def test_a_one_camera_run_imports_neither_scipy_stats_nor_spatial():
    # The modules a one-camera `calibrate` imports (the stereo ones too: the command checks for a stereo layout):
    # scipy.stats alone cost ~0.7 s CPU and scipy.spatial.transform ~0.3 s of every run (measured); the one
    # function of each in use is imported where it is called, or a lighter one (scipy.special's chdtrc) stands in.
    loaded = _run("import sys\nimport dstereo.jobs.calibrate_camera, dstereo.jobs.calibrate_stereo, dstereo.calib.misfit, "
                  "dstereo.calib.mono, dstereo.io.results\n"
                  "print(*[m for m in ('scipy.stats', 'scipy.spatial') if m in sys.modules])")
    assert loaded == "", loaded
