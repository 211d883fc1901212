"""The dstereo modules a traced program can depend on, and a digest of their source (runtime/aot.py's key).

A compiled program is the trace of one function: what its trace runs is code its module reaches by imports
(module-level or deferred, `importlib.import_module` of a literal name included) and the methods of the values its
closure was built from. `closure(roots)` is the transitive import closure of `roots` within the package, read
from the source files (not from `sys.modules`: a module imported later, or by another path, counts the same);
`digest(roots)` hashes those files' names and contents. An edit outside the closure leaves the digest, and so
the program's executable on disk, as it was; an edit inside it changes both.

Conservative where the source cannot say: a module in the closure that imports a name computed at run time
(`import_module` or `__import__` of anything but a string literal) makes the closure the whole package. Read with
regular expressions over the text (about 10 ms for the package; `ast` took 1.2 s), which may see an import inside
a string or a comment: that only adds a module, never leaves one out.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

PACKAGE = "dstereo"
ROOT = Path(__file__).resolve().parents[1]

_FROM = re.compile(r"^[ \t]*from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#]*)", re.M)
_IMPORT = re.compile(r"^[ \t]*import[ \t]+([^\n#]+)", re.M)
_LITERAL = re.compile(r"(?:import_module|__import__)\(\s*[\"']([\w.]+)[\"']")
_DYNAMIC = re.compile(r"(?:import_module|__import__)\(\s*[^\"'\s)]")

_state: dict = {}  # module -> path; module -> its imports; the whole package's digest


def modules() -> dict[str, Path]:
    """Every module of the package: dotted name -> file (a package's name -> its __init__.py)."""
    if "modules" not in _state:
        found = {}
        for path in sorted(ROOT.rglob("*.py")):
            parts = (PACKAGE, *path.relative_to(ROOT).with_suffix("").parts)
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
        _state["modules"] = found
    return _state["modules"]


def _imports(name: str) -> set[str] | None:
    """The package's modules that `name` imports; None where it imports a name computed at run time."""
    cache = _state.setdefault("imports", {})
    if name not in cache:
        path = modules()[name]
        text = path.read_text()
        if _DYNAMIC.search(text):
            cache[name] = None
            return None
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        named = set(_LITERAL.findall(text))
        for dots, base, names in _FROM.findall(text):
            if dots:  # relative: from the module's package, one level up per dot after the first
                up = package.split(".")[: len(package.split(".")) - (len(dots) - 1)]
                base = ".".join(up + ([base] if base else []))
            named.add(base)
            for item in names.strip("()").split(","):
                item = item.split(" as ")[0].strip()
                if item and item != "*":
                    named.add(f"{base}.{item}")  # a submodule imported by name
        for clause in _IMPORT.findall(text):
            named.update(item.split(" as ")[0].strip() for item in clause.split(","))
        known = modules()
        found = set()
        for dotted in named:
            while dotted:  # a module and the packages above it (importing a.b.c runs a and a.b too)
                if dotted in known:
                    found.add(dotted)
                dotted = dotted.rpartition(".")[0]
        cache[name] = found
    return cache[name]


def closure(roots) -> set[str] | None:
    """The package's modules that `roots` reach by imports, themselves and the packages above them included;
    None where one of them imports a computed name (then only the whole package is safe)."""
    known = modules()
    seen: set[str] = set()
    stack = [r for r in roots if r in known]
    for r in list(stack):
        while "." in r:
            r = r.rpartition(".")[0]
            stack.append(r)
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        found = _imports(name)
        if found is None:
            return None
        stack.extend(found - seen)
    return seen


def digest(roots=None) -> str:
    """sha256 over the names and contents of the files of `closure(roots)`; the whole package's where `roots` is
    None, holds a module outside the package, or reaches a computed import."""
    reach = None if roots is None or any(r.split(".")[0] != PACKAGE for r in roots) else closure(roots)
    if reach is None:
        if "whole" not in _state:
            _state["whole"] = _hash(sorted(modules()))
        return _state["whole"]
    return _hash(sorted(reach))


def _hash(names) -> str:
    h = hashlib.sha256()
    for name in names:
        path = modules()[name]
        h.update(str(path.relative_to(ROOT)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()
