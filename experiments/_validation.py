"""The figures of docs/validation.md as a script's `--check` reads them: the markdown table under a heading, and
a comparison of recomputed values with it that prints recomputed / documented per value."""

from __future__ import annotations

from pathlib import Path

VALIDATION = Path(__file__).resolve().parents[1] / "docs" / "validation.md"


def table(heading: str) -> list[dict[str, str]]:
    """The rows of the first markdown table from the first line that starts with `heading` (a heading, a list
    item's bold start, or the table's own header row), as {column: cell}."""
    lines = VALIDATION.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.lstrip("#- *").startswith(heading.lstrip("#- *")))
    rows = []
    for line in lines[start if lines[start].startswith("|") else start + 1:]:
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif rows:
            break
    head, body = rows[0], rows[2:]
    return [dict(zip(head, r)) for r in body]


def decimals(cell: str) -> int:
    return len(cell.split(".")[1]) if "." in cell else 0


def compare(label: str, recomputed: float, documented: str) -> bool:
    """Print the ratio; True when `recomputed` rounds to the documented cell (its last digit, +- one unit)."""
    doc = float(documented)
    unit = 10.0 ** -decimals(documented)
    ok = abs(round(recomputed, decimals(documented)) - doc) <= unit * 1.0001
    ratio = recomputed / doc if doc else float("nan")
    print(f"{label}: recomputed {recomputed:.{decimals(documented) + 2}f}, docs/validation.md {documented}, "
          f"ratio {ratio:.4f}{'' if ok else '  DIFFERS'}", flush=True)
    return ok


def report(text: str, out: Path | None) -> None:
    """A script's result: printed, and written to `out` (its folder made) when given."""
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
