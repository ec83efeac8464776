"""Wall time of `foamlab --help` and `foamlab COMMAND --help` (median of 5 fresh processes).

The target is < 0.3 s each: building the parser imports no numerical library (each
command imports what it needs when it runs; tests/test_cli_imports.py keeps that).

    python benchmarks/bench_cli_startup.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import publish  # noqa: E402

from foamlab.cli import COMMAND_MODULES  # noqa: E402

TARGET_S = 0.3


def _foamlab() -> list[str]:
    """The installed console script beside this interpreter, else `python -m foamlab.cli`."""
    script = Path(sys.executable).with_name("foamlab")
    if script.exists():
        return [str(script)]
    found = shutil.which("foamlab")
    return [found] if found else [sys.executable, "-m", "foamlab.cli"]


def wall_s(argv: list[str], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    base = _foamlab()
    lines = [f"Median wall time of {args.repeats} fresh processes each (target < {TARGET_S} s).", "",
             "| command | wall (s) |", "|---|---:|"]
    worst = 0.0
    for command in ["", *COMMAND_MODULES]:
        argv = base + ([command] if command else []) + ["--help"]
        t = wall_s(argv, args.repeats)
        worst = max(worst, t)
        lines.append(f"| `foamlab {command + ' ' if command else ''}--help` | {t:.3f} |")
    lines += ["", f"slowest {worst:.3f} s ({'within' if worst < TARGET_S else 'OVER'} the {TARGET_S} s target); "
              "before issue 25 `foamlab --help` took 1.6 s here (every command module imported "
              "the diagnosis, scipy and statsmodels while the parser was built)."]
    publish("CLI start-up (benchmarks/bench_cli_startup.py)", lines)


if __name__ == "__main__":
    main()
