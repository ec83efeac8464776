"""Shared helper for benchmarks: print a table and keep the latest copy in docs/benchmarks.md."""

from __future__ import annotations

import json
import os
import platform
import re
import statistics
import sys
import time
from datetime import date
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def on_independent_runs() -> None:
    """What a benchmark diagnosing runs of tests/independent_model.py sets before numpy or foamlab is
    imported: one BLAS thread a process (a diagnosis forks its own workers), and the repository and
    tests/ (the independent generator) on sys.path."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    root = Path(__file__).resolve().parents[1]
    for path in (root, root / "tests"):
        sys.path.insert(0, str(path))


def load_jsonl(out: Path) -> list[dict]:
    """The records a resumable benchmark has written so far, one JSON object a line."""
    if not out.exists():
        return []
    return [json.loads(line) for line in out.read_text(encoding="utf-8").splitlines() if line.strip()]


def publish(section: str, lines: list[str]) -> None:
    """Print the lines and replace (or append) `## section` in docs/benchmarks.md."""
    text = "\n".join(lines)
    print(text)
    body = (f"## {section}\n\n_{date.today().isoformat()}, {platform.machine()}, "
            f"{platform.python_implementation()} {platform.python_version()}; "
            f"regenerate with the script named below._\n\n{text}\n")
    old = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Benchmarks\n\nLatest results of the scripts in benchmarks/ (medians over repeats).\n"
    pattern = re.compile(rf"^## {re.escape(section)}\n.*?(?=^## |\Z)", re.S | re.M)
    new = pattern.sub(body + "\n", old) if pattern.search(old) else old.rstrip() + "\n\n" + body
    DOC.write_text(new, encoding="utf-8")


def cpu_seconds() -> tuple[float, float]:
    """CPU seconds (user + system) of this process, and of its children ended and reaped so far
    (forked diagnosis workers, a Dask cluster's processes, a subprocess)."""
    t = os.times()
    return t.user + t.system, t.children_user + t.children_system


def median_seconds(fn, repeats: int) -> float:
    """Median wall time of fn() over repeats (machine noise: medians, not single runs)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
