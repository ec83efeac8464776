"""How sharp detection is: the share of runs like one that name a cause, size by size.

A detection limit is "the size named in 90 % of runs like this one" (foamlab.diagnosis.limits).
Runs like one are the same specimen and machine with the noise and the motion's start phase drawn
again: tests/independent_model.py's regime and residual form with other seeds. Here each cause
size of each regime/form is hidden by tests/independent_effects.py (its own arithmetic, no foamlab
model code) in the same seeds, and each run is diagnosed for its verdict alone (`limit_injections`
0: the limits' check changes no verdict). The table gives the share named per size, and per
regime/form the largest size named in <= 10 % and the smallest named in >= 90 % (and at every
larger size tried), each with its neighbour tried. Issue 27's bar, named in >= 90 % at 1.5 x a run's
limit and <= 10 % at 0.5 x, needs the two crossings within a factor of 3 for any limit to meet it,
however exact.

    python benchmarks/bench_naming_curve.py                         # the damping change, 12 seeds
    python benchmarks/bench_naming_curve.py --seeds 20 --cells "A:causal:8,16,32"
    python benchmarks/bench_naming_curve.py --publish-only          # the table from --out

Results go line by line to --out (JSON lines): an interrupted run resumes where it stopped. The
table in docs/benchmarks.md: the default run, then `--cells "A:paper:0.15,0.3,0.42,0.6,1.2"`, then
`--seeds 24 --cells "B:causal:4,8,16,22.6,32,45,64"`, into one --out.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

from _table import load_jsonl, on_independent_runs, publish

on_independent_runs()

SECTION = "Diagnosis: how sharp detection is (benchmarks/bench_naming_curve.py)"
#: Seeds 3400.. (fixed in session 58 before any run of them), the same for every cell.
SEED0 = 3400
#: regime:form:sizes (the generator's units, independent_effects.UNITS) of the damping change.
CELLS = "A:causal:4,8,16,22.6,32;B:causal:4,8,16,32,64,100;B:paper:0.15,0.3,0.42,0.6,1.2"
LOW, HIGH = 0.1, 0.9


def parse_cells(text: str) -> list[tuple[str, str, float]]:
    """'A:causal:4,8;B:paper:0.3' -> [(regime, form, size), ...]; ValueError with what is wrong."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(";"))):
        try:
            regime, form, sizes = part.split(":")
            out += [(regime, form, float(s)) for s in sizes.split(",") if s.strip()]
        except ValueError:
            raise ValueError(f"cell {part!r}: expected REGIME:FORM:SIZE,SIZE,...") from None
    return out


def run_cell(cause: str, regime: str, form: str, size: float, seed: int) -> dict:
    import independent_effects as ie
    from diagnosis_support import VERDICT_ONLY

    from foamlab.diagnosis import diagnose

    t = time.perf_counter()
    d = diagnose([ie.independent_run(regime, seed, {cause: size}, form=form, hz=16.0)], settings=VERDICT_ONLY)
    return dict(cause=cause, regime=regime, form=form, size=size, seed=seed, verdict=d.verdict,
                findings=[c.name for c in d.findings], seconds=round(time.perf_counter() - t, 2))


def crossings(shares: list[tuple[float, float]]) -> tuple[float, float, float, float] | None:
    """Where the share named crosses LOW and HIGH, as bounds from the sizes tried: (low, the next size
    tried above it, high, the size tried below it). high: the first size from which every one is named
    in >= HIGH; low: the largest size below it named in <= LOW. None where the sizes do not show both."""
    sizes = sorted(shares)
    high = None
    for size, share in reversed(sizes):
        if share < HIGH:
            break
        high = size
    if high is None:
        return None
    lows = [s for s, share in sizes if share <= LOW and s < high]
    if not lows:
        return None
    tried = [s for s, _ in sizes]
    low = lows[-1]
    return low, tried[tried.index(low) + 1], high, tried[tried.index(high) - 1]


def _bar(low: float, above_low: float, high: float, below_high: float) -> str:
    """Whether some limit L has L * 1.5 at or past the HIGH crossing and L * 0.5 at or below the LOW
    one (the HIGH crossing within 3 x the LOW one), from the crossings' bounds."""
    if below_high / above_low > 3:
        return "no limit can meet the bar"
    if high / low <= 3:
        return "a limit can meet the bar"
    return "the sizes tried do not tell whether a limit can meet the bar"


def table(records: list[dict]) -> list[str]:
    by = defaultdict(list)
    for r in records:
        by[(r["cause"], r["regime"], r["form"], float(r["size"]))].append(r)
    seeds = sorted({r["seed"] for r in records})
    lines = [f"Seeds {seeds[0]}-{seeds[-1]} of tests/independent_model.py, each cause size hidden by "
             "tests/independent_effects.py in every seed of its regime/form, three cycles at 16 Hz, noise 0.15 N; "
             "`diagnose([run])` with identification, the verdict alone. Sizes in the generator's units.", "",
             "| cause | regime/form | size | named | other verdicts |", "|---|---|---:|---:|---|"]
    curves = defaultdict(list)
    for (cause, regime, form, size), rs in sorted(by.items()):
        named = sum(r["verdict"] == cause for r in rs)
        others = Counter(r["verdict"] for r in rs if r["verdict"] != cause)
        lines.append(f"| {cause} | {regime}/{form} | {size:g} | {named}/{len(rs)} | "
                     f"{', '.join(f'{v} {n}' for v, n in others.most_common()) or '-'} |")
        curves[(cause, regime, form)].append((size, named / len(rs)))
    lines.append("")
    for (cause, regime, form), shares in curves.items():
        found = crossings(shares)
        if found is None:
            lines.append(f"{cause}, {regime}/{form}: the sizes tried do not reach both {LOW:.0%} and {HIGH:.0%}.")
            continue
        low, above_low, high, below_high = found
        lines.append(f"{cause}, {regime}/{form}: named in <= {LOW:.0%} at {low:g} (more at {above_low:g}), in >= "
                     f"{HIGH:.0%} from {high:g} (less at {below_high:g}): {_bar(*found)}.")
    seconds = [r["seconds"] for r in records]
    lines.append(f"Time per diagnosis (verdict alone): median {statistics.median(seconds):.1f} s over {len(seconds)}.")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cause", default="damping_cycle_change")
    ap.add_argument("--cells", default=CELLS, help="REGIME:FORM:SIZE,SIZE;... (sizes in the generator's units)")
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_naming_curve.jsonl")
    ap.add_argument("--publish-only", action="store_true")
    a = ap.parse_args(argv)
    try:
        cells = parse_cells(a.cells)
    except ValueError as exc:
        print(f"bench_naming_curve: {exc}", file=sys.stderr)
        return 2
    if not a.publish_only:
        done = {(r["cause"], r["regime"], r["form"], float(r["size"]), r["seed"]) for r in load_jsonl(a.out)}
        with a.out.open("a", encoding="utf-8") as fh:
            for seed in range(SEED0, SEED0 + a.seeds):
                for regime, form, size in cells:
                    if (a.cause, regime, form, size, seed) in done:
                        continue
                    rec = run_cell(a.cause, regime, form, size, seed)
                    fh.write(json.dumps(rec) + "\n")
                    fh.flush()
                    print(f"seed {seed} {regime}/{form:<6} {a.cause} {size:g}: {rec['verdict']} {rec['seconds']:.1f} s",
                          flush=True)
    records = [r for r in load_jsonl(a.out) if r["cause"] == a.cause]
    if not records:
        print(f"bench_naming_curve: no results for {a.cause} in {a.out}", file=sys.stderr)
        return 1
    publish(SECTION, table(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
