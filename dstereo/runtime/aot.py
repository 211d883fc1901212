"""Compiled programs kept on disk as executables, so a new process skips tracing and lowering as well as compiling.

JAX's persistent compilation cache (`dstereo/__init__.py`) saves the XLA compile, but its key is a hash of the
lowered program, so every new process still traces the Python function and lowers it to find that key (about
0.9 s for the calibration solver, measured in a new process with the cache warm, against 0.2 s to load it from
here). `jit(fn, name, static)` is `jax.jit(fn)` that looks first for an executable serialized by an earlier
process (`jax.experimental.serialize_executable`, JAX's API for this) under a key known before tracing:

- what the program is: `name`, the `static` values its closure was built from (a problem layout, options) and
  the arguments' tree structure, shapes, dtypes;
- what built it: a digest of the source files of the dstereo modules the program can depend on (the import
  closure of the module that defines it and of the classes of its static values, `source_modules`: an edit
  elsewhere in the package keeps the file, one inside the closure rebuilds it), the versions of Python, jax,
  jaxlib and numpy, the JAX options that change traced programs (x64, promotion, matmul precision),
  XLA_FLAGS, the compile options, the backend's platform and version, and the processor's instruction-set flags
  (an executable built for AVX-512 must not run on an AVX2 machine).

A build checks the closure against its own trace: every dstereo file in the traceback of an operation of the
program must be in it, else the executable is not stored (the function runs as plain `jax.jit`) and the event says
which file. The whole key is written at the head of the file and compared on load, so a stale or foreign file (another
version, edit or machine), a colliding, truncated or unreadable one is never used: it is rebuilt (traced and
compiled as `jax.jit` would) and overwritten. A loaded executable's first call is waited for, and a runtime
refusal there also rebuilds; the executable checks its arguments' types at every call. Without a compilation
cache folder (DSTEREO_JAX_CACHE=0), with DSTEREO_AOT=0, under `jax.disable_jit`, or where an executable cannot be
serialized, the function runs as plain `jax.jit`; a missing file is built only in the `dstereo` command's own
process or with DSTEREO_AOT=1 (`builds_here`), elsewhere (tests, library use) the function runs as plain `jax.jit`
then, and existing files are loaded everywhere. Results are the same either way, bit for bit (tests): the file
holds what the same compile produces. Two jaxlib 0.10.2 limits shape the build (`jax_workarounds`).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import platform
import sys
import tempfile
import threading
import uuid
from pathlib import Path
from typing import Callable, Hashable

import jax
import numpy as np

from dstereo.runtime import source_modules
from dstereo.runtime.jax_workarounds import fresh_compile, prepare_loaded_executables

FORMAT = "dstereo-aot-1"  # bump when the file layout below changes
FOLDER = "dstereo-aot"  # under the JAX compilation cache folder
# JAX options that change what a function traces to (the others change logging, caching or debugging only)
TRACE_OPTIONS = ("jax_enable_x64", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion",
                 "jax_default_matmul_precision", "jax_default_prng_impl", "jax_enable_checks", "jax_debug_nans",
                 "jax_debug_infs", "jax_platforms")
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
UNUSED_DAYS = 14  # a file neither loaded nor written for this long is removed when another is written (each edit
# of the package leaves its programs' files behind)

_state: dict = {}  # environment text, source digest, whether LAPACK is prepared, the cache-hit listener
_compiling = threading.local()  # .hits: persistent-cache hits counted in this thread while it compiles


def source_digest() -> str:
    """sha256 of every .py file of the dstereo package, names and contents (~4 ms for ~220 files, measured)."""
    return source_modules.digest()


def _cpu_flags() -> str:
    """The processor's instruction-set flags (Linux: /proc/cpuinfo), else what `platform` says."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith(("flags", "Features")):
                    return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment() -> str:
    """Everything outside a program's own description that decides the executable it compiles to, the whole
    package's source included (prebuild's record of what was built under it)."""
    return f"{environment_outside()}\ndstereo {source_digest()}"


def environment_outside() -> str:
    """`environment` but the package's source: the versions, options, flags, backend and processor."""
    if "environment" not in _state:
        import jaxlib

        device = jax.devices()[0]
        options = {name: getattr(jax.config, name, None) for name in TRACE_OPTIONS}
        _state["environment"] = "\n".join([
            f"python {sys.version}", f"jax {jax.__version__}", f"jaxlib {jaxlib.__version__}",
            f"numpy {np.__version__}", f"options {sorted(options.items())}",
            f"XLA_FLAGS {os.environ.get('XLA_FLAGS', '')}",
            f"backend {device.platform} {device.client.platform_version} {device.device_kind}",
            f"machine {platform.machine()} {_cpu_flags()}"])
    return _state["environment"]


def signature(args: tuple) -> tuple:
    """The arguments' tree structure and (shape, dtype, weak type) per leaf: what a compiled program is for."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    return (str(tree), tuple((tuple(np.shape(x)), str(x.dtype) if hasattr(x, "dtype") else type(x).__name__,
                              bool(getattr(x, "weak_type", False))) for x in leaves))


def cache_folder() -> Path | None:
    """Where executables go: FOLDER in JAX's compilation cache folder; None when the cache or this is off."""
    base = jax.config.jax_compilation_cache_dir
    if not base or os.environ.get("DSTEREO_AOT", "") == "0":
        return None
    return Path(base) / FOLDER


def builds_here() -> bool:
    """Whether a missing executable is compiled afresh and stored (DSTEREO_AOT=1), or the function runs as plain
    `jax.jit` instead (the persistent cache still fetches its compile). Default: only in the `dstereo` command's
    own process. A fresh compile costs about a cold one, and every edit of the package asks for one per program:
    a test session or a library user after an edit would pay it where the persistent cache alone fetched the
    compile; a command run pays it once and loads the file from then on. Measured on the suite (2 workers,
    2026-12-07): with DSTEREO_AOT=1 its run that built every file took 29:35 against 14:35 without, the runs after
    it ~12 min; an edit of the engine's modules (models, solver, calib.problem) asks for most files again, so the
    suite does not build (its command processes do)."""
    setting = os.environ.get("DSTEREO_AOT", "")
    if setting:
        return setting == "1"
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return (getattr(spec, "name", None) == "dstereo.cli"
            or Path(getattr(main, "__file__", "") or "").name in ("dstereo", "dstereo.exe", "dstereo-script.py"))


def _count_cache_hits(event: str, **_) -> None:
    if event == CACHE_HIT_EVENT and hasattr(_compiling, "hits"):
        _compiling.hits += 1


class StaleExecutable(Exception):
    """A file whose recorded key is not the one asked for."""


class AotFunction:
    """`jax.jit(fn, compiler_options=...)` backed by executables on disk (module docstring)."""

    def __init__(self, fn: Callable, name: str, static: Hashable, compiler_options: dict | None = None):
        self.fn, self.name, self.static = fn, name, static
        self.modules = defining_modules(fn, static)  # the roots of the source the key covers
        self.compiler_options = dict(compiler_options or {})
        self.jitted = jax.jit(fn, compiler_options=compiler_options or None)
        self._loaded: dict[tuple, Callable] = {}
        self._lock = threading.Lock()
        self.events: list[str] = []  # per new signature: "loaded", "built", "rebuilt: <why>", "plain jit: <why>"

    def __call__(self, *args):
        sig = signature(args)
        exe = self._loaded.get(sig)
        if exe is not None:
            return exe(*args)
        with self._lock:  # two threads' first calls build once
            exe = self._loaded.get(sig)
            if exe is not None:
                return exe(*args)
            exe, out = self._load_or_build(sig, args)
            self._loaded[sig] = exe
            return out

    def key(self, sig: tuple) -> str:
        return "\n".join([FORMAT, f"program {self.name}", f"static {self.static!r}", f"arguments {sig!r}",
                          f"compiler options {sorted(self.compiler_options.items())!r}", environment_outside(),
                          f"dstereo modules {source_modules.digest(self.modules)}"])

    def path(self, key: str) -> Path | None:
        folder = cache_folder()
        if folder is None:
            return None
        return folder / f"{_safe(self.name)}-{hashlib.sha256(key.encode()).hexdigest()[:40]}.jaxexe"

    def _load_or_build(self, sig: tuple, args: tuple):
        """(callable, its output on `args`)."""
        key = None if jax.config.jax_disable_jit or cache_folder() is None else self.key(sig)
        path = None if key is None else self.path(key)
        if path is None:
            self.events.append("plain jit: no cache folder, DSTEREO_AOT=0 or jit disabled")
            return self.jitted, self.jitted(*args)
        why = "no file"
        if path.exists():
            try:
                exe = _load(path, key)
                out = exe(*args)
                jax.block_until_ready(out)  # a runtime refusal surfaces here, not in the caller
                self.events.append("loaded")
                return exe, out
            except StaleExecutable as exc:
                why = str(exc)
            except Exception as exc:  # noqa: BLE001 - unreadable, truncated, refused by the runtime: rebuild it
                why = f"unusable ({type(exc).__name__}: {str(exc)[:200]})"
        if not builds_here():
            self.events.append(f"plain jit: {why}, and this process does not build (DSTEREO_AOT)")
            return self.jitted, self.jitted(*args)
        compiled, fresh, outside = self._compile(args)
        if outside:
            why += f"; not stored (its trace ran dstereo code outside its key's modules: {', '.join(outside)})"
        elif fresh:
            try:
                _store(path, key, compiled)
            except Exception as exc:  # noqa: BLE001 - not serializable here, or no room: this process only
                why += f"; not stored ({type(exc).__name__})"
        else:
            why += "; not stored (the compile came from the persistent cache)"
        self.events.append(("built" if why.startswith("no file") else "rebuilt: ") + why.removeprefix("no file"))
        return compiled, compiled(*args)

    def _compile(self, args: tuple):
        """Trace, lower and compile under a name of this build's own, so that XLA compiles afresh
        (`jax_workarounds`); returns (compiled, fresh: no persistent-cache hit in this thread meanwhile, the
        package's files that the trace ran but the key's digest does not cover)."""
        if "listener" not in _state:
            jax.monitoring.register_event_listener(_count_cache_hits)
            _state["listener"] = True
        fn = self.fn

        def program(*a):
            return fn(*a)

        program.__name__ = program.__qualname__ = f"{_safe(self.name)}_{uuid.uuid4().hex[:12]}"
        _compiling.hits = 0
        try:
            with fresh_compile():
                traced = jax.jit(program, compiler_options=self.compiler_options or None).trace(*args)
                compiled = traced.lower().compile()
            return compiled, _compiling.hits == 0, self._outside_the_key(traced.jaxpr)
        finally:
            del _compiling.hits


    def _outside_the_key(self, jaxpr) -> list[str]:
        """The package's files (relative paths) in the program's own frames of its operations' tracebacks that
        are not in the key's module closure (all of a traceback where the program's frame is not in it: a
        sub-program traced first elsewhere; conservative, never a file left out)."""
        covered = source_modules.closure(self.modules) if self.modules else None
        if covered is None:
            return []  # the key holds the whole package's digest: nothing can be outside it
        files = {str(source_modules.modules()[m]) for m in covered}
        me = str(Path(__file__).resolve())
        outside = set()
        for frames in _tracebacks(jaxpr):
            for frame in frames:
                if frame.file_name == me and frame.function_name.endswith("program"):
                    break  # frames above are the caller's, outside the program
                if frame.file_name.startswith(str(source_modules.ROOT)) and frame.file_name not in files:
                    outside.add(str(Path(frame.file_name).relative_to(source_modules.ROOT.parent)))
        return sorted(outside)


def _tracebacks(closed):
    """Each operation's traceback frames (innermost first) in a traced program and the programs inside it."""
    from jax._src import core

    stack, seen = [closed.jaxpr], set()
    while stack:
        jaxpr = stack.pop()
        if id(jaxpr) in seen:
            continue
        seen.add(id(jaxpr))
        for eqn in jaxpr.eqns:
            tb = eqn.source_info.traceback
            if tb is not None:
                yield tb.frames
            stack.extend(j.jaxpr if hasattr(j, "jaxpr") else j for j in core.jaxprs_in_params(eqn.params))


def defining_modules(fn, static) -> tuple[str, ...] | None:
    """The modules whose import closure the key's source digest covers: where `fn` (or the function a
    `functools.partial`, `jax.jit` or `jax.vmap` wraps) is defined, where the functions and values its closure
    captured are from, and where the classes of `static`'s values are (their methods may run in the trace). None
    (the whole package's digest) where `fn` is defined outside the package or a module cannot be told."""
    import functools

    inner = fn
    while isinstance(inner, functools.partial) or hasattr(inner, "__wrapped__"):
        inner = inner.func if isinstance(inner, functools.partial) else inner.__wrapped__
    home = getattr(inner, "__module__", None)
    if not home or home.split(".")[0] != source_modules.PACKAGE:
        return None  # a function outside the package: its own source is in no digest but the whole one's
    found, visited = {home}, set()
    stack = [fn, static]
    while stack and len(visited) < 10000:
        value = stack.pop()
        if id(value) in visited:
            continue
        visited.add(id(value))
        found.add(type(value).__module__)
        if isinstance(value, (tuple, list, set, frozenset)):
            stack.extend(value)
        elif isinstance(value, dict):
            stack.extend(value.keys())
            stack.extend(value.values())
        elif hasattr(value, "__dataclass_fields__"):
            stack.extend(getattr(value, f) for f in value.__dataclass_fields__)
        elif isinstance(value, functools.partial):
            stack.extend([value.func, *value.args, *value.keywords.values()])
        elif callable(value) and not isinstance(value, type):
            found.add(getattr(value, "__module__", None))
            if hasattr(value, "__wrapped__"):
                stack.append(value.__wrapped__)
            # what a closure captured (the residual functions a solver closes over, a problem layout) runs in the
            # trace as well
            stack.extend(cell.cell_contents for cell in (getattr(value, "__closure__", None) or ())
                         if _filled(cell))
    if stack or None in found:
        return None
    return tuple(sorted(m for m in found if m and m.split(".")[0] == source_modules.PACKAGE)) or None


def _filled(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:  # an empty cell (a name assigned after the function was made)
        return False
    return True


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c == "_" else "_" for c in name)


def _load(path: Path, key: str) -> Callable:
    from jax.experimental.serialize_executable import deserialize_and_load

    data = path.read_bytes()
    head, sep, rest = data.partition(b"\0")
    if not sep or head.decode(errors="replace") != key:
        raise StaleExecutable("stale or foreign (its recorded key differs)")
    if "lapack" not in _state:
        prepare_loaded_executables()
        _state["lapack"] = True
    blob, in_tree, out_tree = pickle.loads(rest)
    exe = deserialize_and_load(blob, in_tree, out_tree)
    try:
        os.utime(path)  # in use: kept by `_prune`
    except OSError:
        pass
    return exe


def _store(path: Path, key: str, compiled) -> None:
    """Write key NUL pickle(executable, trees) atomically (a reader never sees half a file)."""
    from jax.experimental.serialize_executable import serialize

    payload = key.encode() + b"\0" + pickle.dumps(serialize(compiled), protocol=pickle.HIGHEST_PROTOCOL)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _prune(path.parent)


def _prune(folder: Path) -> None:
    """Remove executables unused for UNUSED_DAYS (other processes may be reading any newer one)."""
    import time

    limit = time.time() - UNUSED_DAYS * 86400
    for old in folder.glob("*.jaxexe"):
        try:
            if old.stat().st_mtime < limit:
                old.unlink()
        except OSError:
            pass


def jit(fn: Callable, name: str, static: Hashable, compiler_options: dict | None = None) -> AotFunction:
    """`jax.jit(fn)` with executables kept on disk. `static` must hold every value `fn`'s closure was built from
    (its repr is part of the key); `name` names the program (one name per function that builds `fn`)."""
    return AotFunction(fn, name, static, compiler_options)
