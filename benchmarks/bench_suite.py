"""The test suite's cost by test: the README's test command (scripts/test.sh) run with this file as
a pytest plugin, which writes each test's wall seconds and CPU seconds (its process's own and its
reaped children's: forked diagnosis workers, a Dask cluster at its teardown) to a JSON-lines file.

The suite's target is 15 minutes on a fresh clone of this 2-core machine (`bash .ci/run`: setup,
then scripts/test.sh). The suite is bound by its CPU (docs/benchmarks.md, session 55): the table
says where the CPU goes, by file and by test, beside the whole run's wall and CPU.

    python benchmarks/bench_suite.py [--out FILE] [--top 15]     # ~15 min: the whole suite
    python benchmarks/bench_suite.py --publish-only --out FILE   # the table from a file written before
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import pytest

from _table import cpu_seconds, load_jsonl, publish

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT_ENV = "BENCH_SUITE_OUT"
SECTION = "The test suite's CPU by test (benchmarks/bench_suite.py)"


_failed: dict[str, str] = {}


def pytest_runtest_logreport(report):
    """Which phase of a test failed (setup, call, teardown): kept with the test's record."""
    if report.failed:
        _failed[report.nodeid] = report.when


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """The plugin: one record per test (setup, call and teardown together)."""
    t0, (own0, child0) = time.time(), cpu_seconds()
    yield
    (own1, child1), out = cpu_seconds(), os.environ.get(OUT_ENV)
    if out:
        record = {"id": item.nodeid, "worker": os.environ.get("PYTEST_XDIST_WORKER", "phase 2"),
                  "wall": time.time() - t0, "cpu": own1 - own0 + child1 - child0,
                  "failed": _failed.pop(item.nodeid, "")}
        with open(out, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")


def run_suite(out: Path) -> dict:
    """scripts/test.sh with this plugin; the whole run's wall and CPU (every reaped descendant). Its
    output goes to FILE.pytest.log beside the records."""
    out.unlink(missing_ok=True)
    env = dict(os.environ, PYTEST_ADDOPTS=f"{os.environ.get('PYTEST_ADDOPTS', '')} -p bench_suite".strip(),
               PYTHONPATH=os.pathsep.join(p for p in (str(HERE), os.environ.get("PYTHONPATH", "")) if p),
               **{OUT_ENV: str(out)})
    t0, (_, child0) = time.time(), cpu_seconds()
    with out.with_suffix(".pytest.log").open("w", encoding="utf-8") as log:
        code = subprocess.call(["bash", "scripts/test.sh"], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    whole = {"wall": time.time() - t0, "cpu": cpu_seconds()[1] - child0, "exit": code}
    out.with_suffix(".run.json").write_text(json.dumps(whole), encoding="utf-8")
    return whole


def table(records: list[dict], whole: dict | None, top: int) -> list[str]:
    phase1 = [r for r in records if r["worker"] != "phase 2"]
    phase2 = [r for r in records if r["worker"] == "phase 2"]
    by_file: dict[str, list[dict]] = defaultdict(list)
    for r in phase1:
        by_file[r["id"].split("::")[0]].append(r)
    lines = [f"scripts/test.sh with this plugin (not a fresh clone: `bash .ci/run` adds its setup, ~30 s). "
             f"Phase 1 (parallel workers): {len(phase1)} tests, {sum(r['cpu'] for r in phase1):.0f} CPU s; "
             f"phase 2 (schedule tests, beside it): {len(phase2)} tests, {sum(r['cpu'] for r in phase2):.0f} CPU s. "
             "A child's CPU counts when it is reaped: a module's Dask cluster in the test its teardown follows."]
    if whole:
        lines.append(f"The whole run: {whole['wall']:.0f} s wall, {whole['cpu']:.0f} CPU s, exit {whole['exit']}.")
    failed = [f"{r['id']} ({r['failed']})" for r in records if r.get("failed")]
    lines.append(f"Failed: {', '.join(failed)}." if failed else "No test failed.")
    lines += ["", "| file (phase 1) | tests | CPU s | worker wall s |", "|---|---:|---:|---:|"]
    rows = [(name, len(rs), sum(r["cpu"] for r in rs), sum(r["wall"] for r in rs)) for name, rs in by_file.items()]
    for name, n, cpu, wall in sorted(rows, key=lambda row: -row[2])[:top]:
        lines.append(f"| {name} | {n} | {cpu:.0f} | {wall:.0f} |")
    lines += ["", "| test (either phase) | CPU s | wall s |", "|---|---:|---:|"]
    for r in sorted(records, key=lambda r: -r["cpu"])[:top]:
        lines.append(f"| {r['id']} | {r['cpu']:.1f} | {r['wall']:.1f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_suite.jsonl")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--publish-only", action="store_true")
    a = ap.parse_args(argv)
    whole = None if a.publish_only else run_suite(a.out)
    side = a.out.with_suffix(".run.json")
    if whole is None and side.exists():
        whole = json.loads(side.read_text(encoding="utf-8"))
    records = load_jsonl(a.out)
    if not records:
        print(f"bench_suite: no records in {a.out}", file=sys.stderr)
        return 1
    publish(SECTION, table(records, whole, a.top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
