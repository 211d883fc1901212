"""Executables kept on disk (dstereo/runtime/aot.py): the same results as the traced program, bit for bit, and a
stale, foreign or broken file is detected and rebuilt, never used.

Bit for bit is the right tolerance: a loaded file holds the executable that the same XLA compile of the same
program produces, and XLA's CPU code is deterministic for one executable and input. The in-process tests use a
small function (a while loop, a Cholesky solve: LAPACK, the custom call that needs `jax_workarounds`); the
cross-process test runs the calibration solver itself through `problem.run` in two new processes, since a new
process is where loading differs (nothing traced, LAPACK not initialised by a lowering).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.runtime import aot


def _toy(a, b):
    """A small program with a loop and a LAPACK call."""
    def body(state):
        i, x = state
        return i + 1, jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(a), True), x + b)

    return jax.lax.while_loop(lambda s: s[0] < 3, body, (0, b))[1]


def _args(n=4):
    rng = np.random.default_rng(0)
    m = rng.normal(size=(n, n))
    return m @ m.T + n * np.eye(n), rng.normal(size=n)


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setattr(aot, "cache_folder", lambda: tmp_path)
    monkeypatch.setenv("DSTEREO_AOT", "1")  # build here (a test process is not the command's)
    return tmp_path


def test_loaded_equals_traced_and_each_signature_has_its_file(folder):
    args = _args()
    traced = np.asarray(jax.jit(_toy)(*args))
    built = aot.jit(_toy, "test.toy", ("static", 1))
    assert np.array_equal(np.asarray(built(*args)), traced) and built.events == ["built"]
    assert np.array_equal(np.asarray(built(*args)), traced) and built.events == ["built"]  # kept in memory
    loaded = aot.jit(_toy, "test.toy", ("static", 1))  # as a new process would: from the file
    assert np.array_equal(np.asarray(loaded(*args)), traced) and loaded.events == ["loaded"]
    # another shape, another static value: programs of their own, never the file above
    assert np.array_equal(np.asarray(loaded(*_args(5))), np.asarray(jax.jit(_toy)(*_args(5))))
    other = aot.jit(_toy, "test.toy", ("static", 2))
    other(*args)
    assert loaded.events == ["loaded", "built"] and other.events == ["built"]
    assert len(list(folder.glob("*.jaxexe"))) == 3


def test_stale_foreign_or_broken_files_are_rebuilt(folder, monkeypatch):
    args = _args()
    traced = np.asarray(jax.jit(_toy)(*args))
    first = aot.jit(_toy, "test.toy", ())
    first(*args)
    (old,) = folder.glob("*.jaxexe")
    # An edited package (or another jax, machine, flags: all in the key): a new key and so a new file name.
    # A file under that name that another key wrote (a collision, a copied cache) is foreign: rebuilt.
    monkeypatch.setitem(aot._state, "environment", aot.environment() + "\nedited")
    edited = aot.jit(_toy, "test.toy", ())
    new_path = edited.path(edited.key(aot.signature(args)))
    assert new_path != old
    new_path.write_bytes(old.read_bytes())
    assert np.array_equal(np.asarray(edited(*args)), traced)
    assert edited.events == ["rebuilt: stale or foreign (its recorded key differs)"]
    assert new_path.read_bytes().startswith(edited.key(aot.signature(args)).encode() + b"\0")
    # A truncated file (a full disk, a killed writer without the atomic rename): rebuilt, not used.
    new_path.write_bytes(new_path.read_bytes()[:-1000])
    again = aot.jit(_toy, "test.toy", ())
    assert np.array_equal(np.asarray(again(*args)), traced)
    assert again.events[0].startswith("rebuilt: unusable")


def test_outside_the_command_files_are_loaded_but_not_built(folder, monkeypatch):
    args = _args()
    monkeypatch.delenv("DSTEREO_AOT")
    assert not aot.builds_here()  # pytest's process
    plain = aot.jit(_toy, "test.toy", ())
    assert np.array_equal(np.asarray(plain(*args)), np.asarray(jax.jit(_toy)(*args)))
    assert plain.events[0].startswith("plain jit: no file") and not list(folder.glob("*.jaxexe"))
    monkeypatch.setenv("DSTEREO_AOT", "1")
    aot.jit(_toy, "test.toy", ())(*args)  # a command run would have built it
    monkeypatch.delenv("DSTEREO_AOT")
    loaded = aot.jit(_toy, "test.toy", ())
    loaded(*args)
    assert loaded.events == ["loaded"]


def test_without_a_cache_folder_it_is_plain_jit(monkeypatch):
    monkeypatch.setattr(aot, "cache_folder", lambda: None)
    f = aot.jit(_toy, "test.toy", ())
    assert np.array_equal(np.asarray(f(*_args())), np.asarray(jax.jit(_toy)(*_args())))
    assert f.events[0].startswith("plain jit")


# The calibration solver in two new processes sharing one cache folder: the first builds, the second loads, and
# its results equal the traced solver's (plain jax.jit of the same function) in that process, bit for bit.
SOLVE = r'''
import json, sys
import numpy as np
import dstereo, jax
from dstereo.calib.problem import Problem, compiled_solver, run, shared_data
from dstereo.models.camera import project
from dstereo.models.pose import rodrigues
from dstereo.solver.lm import LMOptions

rng = np.random.default_rng(0)
n_frames, free = 4, ("k1", "k2")
obj = np.c_[np.arange(12) % 4, np.arange(12) // 4, np.zeros(12)].astype(float)
k, coeffs = np.array([500.0, 505.0, 320.0, 240.0]), np.r_[-0.1, 0.05, np.zeros(6)]
poses = np.c_[rng.normal(0, 0.3, (n_frames, 3)), rng.normal(0, 0.5, (n_frames, 2)), np.full(n_frames, 10.0)]
obs = np.stack([np.stack([np.asarray(project(k, coeffs, obj[i] @ np.asarray(rodrigues(p[:3])).T + p[3:]))
                          for i in range(12)]) for p in poses]) + rng.normal(0, 0.2, (n_frames, 12, 2))
problem, options = Problem.of([free]), LMOptions()
g0 = np.r_[k * 1.02, 0.0, 0.0][None]
args = (g0, poses[None] + 0.01, obs[None, :, None], np.ones((1, n_frames)), np.array([1e-3]),
        shared_data(obj, np.zeros(4), np.zeros(8)))
out = run(problem, options, *args)
solver = compiled_solver(problem, options._replace(lambda0=0.0))
result = {"events": solver.events, "g": out.g.tolist(), "status": out.status.tolist()}
if sys.argv[1] == "compare":  # the traced solver: the same call through plain jax.jit
    solver._loaded.clear()
    solver._load_or_build = lambda sig, a: (solver.jitted, solver.jitted(*a))
    traced = run(problem, options, *args)
    result["traced_g"] = traced.g.tolist()
print(json.dumps(result))
'''


def _solve(cache: Path, mode: str) -> dict:
    env = dict(os.environ, DSTEREO_JAX_CACHE=str(cache), DSTEREO_AOT="1")
    done = subprocess.run([sys.executable, "-c", SOLVE, mode], capture_output=True, text=True, env=env,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_solver_loads_in_a_new_process_and_equals_the_traced_solver(tmp_path):
    first = _solve(tmp_path, "build")
    assert first["events"] == ["built"] and first["status"] == [1]
    assert len(list((tmp_path / aot.FOLDER).glob("*.jaxexe"))) == 1
    second = _solve(tmp_path, "compare")
    assert second["events"] == ["loaded"]
    assert second["g"] == first["g"] == second["traced_g"]  # bit for bit (module docstring)


def test_a_build_whose_trace_runs_code_outside_its_keys_modules_is_not_stored(folder):
    """The key's digest covers the import closure of `modules`; a trace that ran package code outside it (here:
    the closure narrowed by hand to a module that imports nothing of the rotation's) is used in this process
    but not written, and the event names the file."""
    from dstereo.models.pose import rodrigues

    narrowed = aot.jit(rodrigues, "test.rodrigues", ())
    assert narrowed.modules == ("dstereo.models.pose",)  # where the function is defined
    narrowed.modules = ("dstereo.errors",)
    r = np.array([0.1, -0.2, 0.3])
    assert np.array_equal(np.asarray(narrowed(r)), np.asarray(jax.jit(rodrigues)(r)))
    assert narrowed.events[0].startswith("built; not stored (its trace ran dstereo code outside its key's modules: "
                                         "dstereo/models/pose.py"), narrowed.events
    assert not list(folder.glob("*.jaxexe"))
    kept = aot.jit(rodrigues, "test.rodrigues", ())
    kept(r)
    assert kept.events == ["built"] and len(list(folder.glob("*.jaxexe"))) == 1
