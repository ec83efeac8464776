"""Detection on runs foamlab never made: the eight causes hidden by tests/independent_effects.py.

For each catalogue cause and size (physical units: N/mm frame, N, ms, N/min, %/cycle), fixed
seeds (1000..) of the independent generator (three cycles at 16 Hz, noise 0.15 N), each
diagnosed with foamlab.diagnosis.diagnose (identification included): the share of seeds whose
verdict names the cause, what the others said, and the time each diagnosis took. Clean seeds
(2000..) give the false-alarm rate. rate_dependence: two runs, at the regime's speed and twice
it (seeds s, s + 1), diagnosed together.

Regime and residual form: by default seed i of a case uses COMBOS[i % 4] (A causal, B paper,
B causal, A paper), so ten seeds cover both regimes and both forms; --full runs every seed in
every combination (4x the work).

Results go line by line to --out (JSON lines): an interrupted run resumes where it stopped, and
--publish rebuilds the table in docs/benchmarks.md from whatever the file holds.

    python benchmarks/bench_detection_independent.py                       # all causes, both sizes
    python benchmarks/bench_detection_independent.py --sizes large --seeds 10 --clean-seeds 20
    python benchmarks/bench_detection_independent.py --workers 2           # dask LocalCluster (idle machine only)
    python benchmarks/bench_detection_independent.py --publish-only        # table from --out
    python benchmarks/bench_detection_independent.py --two --seeds 4       # two causes hidden together

--regime C: the other regime of tests/independent_model.py (OTHER_REGIMES), which no setting was
tuned on: clean seeds and each cause at both sizes in both forms, one seed each (its own section).

--drops: the damping change's drops (DROPS: -10 and -20 %/cycle, issue 27's blind runs' sizes) beside
its rises, with rows and a smallest size of their own.

--two: each pair of PAIRS hidden together at the causes' large sizes (seeds 4000 + 2i, the same
regime/form rotation): a run counts when its findings name both (issue 27 asks 3 of 4).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

from _table import cpu_seconds, load_jsonl as load, on_independent_runs, publish

on_independent_runs()

SECTION = "Diagnosis: detection on independent runs (benchmarks/bench_detection_independent.py)"
SECTION_PAIRS = "Diagnosis: two causes on independent runs (benchmarks/bench_detection_independent.py --two)"
SECTION_OTHER = "Diagnosis: a specimen no setting was tuned on (benchmarks/bench_detection_independent.py --regime C)"
#: --regime C: clean seeds 5000 + i (causal, paper alternating), then every cause but rate_dependence
#: at both sizes in both forms, seed 5100 + j in that order (fixed in session 39 before any diagnosis).
OTHER_CLEAN_SEED0, OTHER_SEED0, OTHER_CLEAN = 5000, 5100, 12
#: (small, large) size of each cause, in independent_effects.UNITS; large is the hidden-effect tests'.
SIZES = {
    "machine_compliance": (1000.0, 250.0),
    "direction_friction": (1.0, 3.0),
    "channel_lag": (50.0, 100.0),
    "memory_lag": (100.0, 300.0),
    "force_zero_drift": (0.1, 0.4),
    "cycle_softening": (1.0, 3.0),
    "damping_cycle_change": (30.0, 100.0),
    "rate_dependence": (0.2, 0.5),
}
#: --drops: the damping change's drops (negative sizes), as issue 27's blind runs had them: the third
#: cycle's damping force 20 and 40 % below the first's. Rows and a smallest size of their own.
DROPS = {"damping_cycle_change": (-10.0, -20.0)}
COMBOS = (("A", "causal"), ("B", "paper"), ("B", "causal"), ("A", "paper"))
SEED0, CLEAN_SEED0, PAIR_SEED0 = 1000, 2000, 4000
#: --two: causes of different families hidden together, each at its large size (fixed before looking,
#: session 28; the first and third are tests/test_diagnosis.py's TWO_CAUSES at other sizes and seeds).
PAIRS = (("cycle_softening", "force_zero_drift"), ("channel_lag", "direction_friction"),
         ("machine_compliance", "cycle_softening"), ("damping_cycle_change", "force_zero_drift"),
         ("memory_lag", "direction_friction"), ("machine_compliance", "channel_lag"))
NAMED_SHARE = 0.9


def one_case(cause: str | None, size: float, seed: int, regime: str, form: str, hz: float) -> dict:
    """Diagnose one seeded run (two for rate_dependence; a pair "a+b" of --two hidden together,
    each at its large size, size 0); a JSON-able record."""
    import independent_effects as ie
    from foamlab.diagnosis import diagnose

    pair = cause is not None and "+" in cause
    if cause == "rate_dependence":
        runs = ie.rate_pair(regime, seed, size, form=form, hz=hz)
    else:
        hidden = {c: SIZES[c][1] for c in cause.split("+")} if pair else {cause: size} if cause else None
        runs = [ie.independent_run(regime, seed, hidden, form=form, hz=hz)]
    t0, c0 = time.perf_counter(), sum(cpu_seconds())      # with the workers a diagnosis forked (reaped)
    d = diagnose(runs)
    seconds, cpu = time.perf_counter() - t0, sum(cpu_seconds()) - c0     # cpu: what load does not inflate
    rec = {"cause": cause or "clean", "size": size, "seed": seed, "regime": regime, "form": form, "hz": hz,
           "verdict": d.verdict, "findings": [f.name for f in d.findings], "seconds": round(seconds, 2),
           "cpu_seconds": round(cpu, 2), "load": round(os.getloadavg()[0], 1),
           "runs": len(runs), "samples": int(sum(len(r.time_s) for r in runs))}
    if pair:
        rec["both"] = set(hidden) <= set(rec["findings"])
    return rec


def plan_pairs(seeds: int, hz: float) -> list[tuple]:
    """Seed by seed across the pairs, the regime/form rotating as in plan()."""
    return [("+".join(p), 0.0, PAIR_SEED0 + 2 * j, *COMBOS[j % len(COMBOS)], hz)
            for j in range(seeds) for p in PAIRS]


def plan(causes: list[str], sizes: str, seeds: int, clean_seeds: int, full: bool, hz: float,
         drops: bool = False) -> list[tuple]:
    """Seed by seed across the causes (a run stopped early still covers every cause); drops: DROPS too."""
    which = {"small": (0,), "large": (1,), "all": (0, 1)}[sizes]
    cases = []
    for j in range(max(seeds, clean_seeds)):
        combos = COMBOS if full else (COMBOS[j % len(COMBOS)],)
        for cause in causes if j < seeds else ():
            sized = [SIZES[cause][i] for i in which] + [DROPS[cause][i] for i in which if drops and cause in DROPS]
            for size in sized:
                cases += [(cause, size, SEED0 + 2 * j, reg, form, hz) for reg, form in combos]
        for k in range(2 if j < clean_seeds else 0):        # two clean seeds a round: 20 by the 10th
            if 2 * j + k < clean_seeds:
                cases += [(None, 0.0, CLEAN_SEED0 + 2 * j + k, reg, form, hz) for reg, form in
                          (COMBOS if full else (COMBOS[(2 * j + k) % len(COMBOS)],))]
    return cases


def plan_other(regime: str, hz: float) -> list[tuple]:
    """--regime: a regime of independent_model.OTHER_REGIMES, one seed per cause, size and form."""
    cases = [(None, 0.0, OTHER_CLEAN_SEED0 + i, regime, ("causal", "paper")[i % 2], hz) for i in range(OTHER_CLEAN)]
    sized = [(cause, size) for cause, sizes in SIZES.items() if cause != "rate_dependence" for size in sizes]
    forms = [(cause, size, form) for cause, size in sized for form in ("causal", "paper")]
    return cases + [(cause, size, OTHER_SEED0 + j, regime, form, hz) for j, (cause, size, form) in enumerate(forms)]


def key(case: tuple) -> tuple:
    cause, size, seed, reg, form, hz = case
    return (cause or "clean", float(size), int(seed), reg, form, float(hz))


def record_key(r: dict) -> tuple:
    return (r["cause"], float(r["size"]), int(r["seed"]), r["regime"], r["form"], float(r["hz"]))


def run_all(cases: list[tuple], out: Path, workers: int) -> None:
    done = {record_key(r) for r in load(out)}
    todo = [c for c in cases if key(c) not in done]
    print(f"{len(cases)} cases, {len(cases) - len(todo)} already in {out}, {len(todo)} to run", flush=True)
    with out.open("a", encoding="utf-8") as fh:
        def keep(rec: dict) -> None:
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            print(f"{rec['cause']:>22} {rec['size']:>8g} {rec['regime']}/{rec['form']:<6} seed {rec['seed']}: "
                  f"{rec['verdict']:<22} {rec['seconds']:6.1f} s", flush=True)

        if workers > 0:
            from dask.distributed import Client, LocalCluster, as_completed
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True) as cluster, \
                    Client(cluster) as client:
                futures = [client.submit(one_case, *c, pure=False) for c in todo]
                for fut in as_completed(futures):
                    keep(fut.result())
        else:
            for c in todo:
                keep(one_case(*c))


INTRO = ("Runs of tests/independent_model.py with one catalogue cause hidden by tests/independent_effects.py "
         "(its own arithmetic, no foamlab model code): regimes A (~285 N peak) and B (~445 N), three cycles at "
         "{hz:g} Hz, noise 0.15 N, both residual forms; seed 1000 + 2i of a case in regime/form "
         "(A causal, B paper, B causal, A paper)[i % 4]; clean seeds 2000... `diagnose([run])` with identification "
         "(rate_dependence: two runs, the regime's speed and twice it, diagnosed together). Time: wall seconds of "
         "one diagnosis, this machine (2 cores shared).")
INTRO_OTHER = ("Regime C of tests/independent_model.py (REGIME_C: 50x50x40 mm firm foam, ~267 N peak, 100 mm/min, "
               "fast damping modes with a complex pair; fixed in session 39, before any diagnosis of it, and no "
               "setting tuned on it since), three cycles at {hz:g} Hz, noise 0.15 N: clean seeds 5000-5011 "
               "(causal, paper alternating), each cause but rate_dependence at both sizes in both forms, one seed "
               "each (5100 + j). `diagnose([run])` with identification. Few seeds: where foamlab stands on a "
               "specimen it never met, not a detection rate.")


def table(records: list[dict], subset: str, intro: str = INTRO) -> list[str]:
    import independent_effects as ie

    clean = [r for r in records if r["cause"] == "clean"]
    lines = [
        intro.format(hz=records[0]["hz"]),
        "",
        f"**Subset run**: {subset}",
        "",
        "| cause | size | named | by regime/form | other verdicts | median s | max s |",
        "|---|---:|---:|---|---|---:|---:|",
    ]
    smallest: dict[str, str] = {}
    groups = [(cause, sign) for cause in ie.CAUSES for sign in (1, -1)
              if any(r["cause"] == cause and sign * r["size"] >= 0 for r in records)]
    label = lambda cause, sign: cause if sign > 0 and cause not in DROPS else \
        f"{cause} ({'rise' if sign > 0 else 'drop'})"
    for cause, sign in groups:
        # smallest effect first (a frame's stiffness: the stiffer, the smaller)
        strength = (lambda v: 1.0 / v) if cause == "machine_compliance" else abs
        for size in sorted({r["size"] for r in records if r["cause"] == cause and sign * r["size"] >= 0}, key=strength):
            rows = [r for r in records if r["cause"] == cause and r["size"] == size]
            named = [r for r in rows if r["verdict"] == cause]
            share = len(named) / len(rows)
            if share >= NAMED_SHARE and label(cause, sign) not in smallest:
                smallest[label(cause, sign)] = f"{size:g} {ie.UNITS[cause]}"
            combos = {}
            for r in rows:
                c = combos.setdefault(f"{r['regime']}/{r['form']}", [0, 0])
                c[0] += r["verdict"] == cause
                c[1] += 1
            by = ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in sorted(combos.items()))
            lines.append(f"| {cause} | {size:g} {ie.UNITS[cause]} | {len(named)}/{len(rows)} | {by} | "
                         f"{_others(rows, cause)} | {statistics.median(r['seconds'] for r in rows):.1f} | "
                         f"{max(r['seconds'] for r in rows):.1f} |")
    if clean:
        none = sum(r["verdict"] == "none" for r in clean)
        lines.append(f"| clean | - | none {none}/{len(clean)} | | {_others(clean, 'none')} | "
                     f"{statistics.median(r['seconds'] for r in clean):.1f} | {max(r['seconds'] for r in clean):.1f} |")
    single = [r["seconds"] for r in records if r["runs"] == 1]
    lines += ["", "Smallest size named in >= 90 % of its seeds: " +
              "; ".join(f"{label(c, sign)} {smallest.get(label(c, sign), 'not reached at the sizes run')}"
                        for c, sign in groups) + "."]
    if clean:
        lines.append(f"False alarms on clean runs: {len(clean) - none}/{len(clean)} "
                     f"({100 * (len(clean) - none) / len(clean):.0f} %).")
    if single:
        lines.append(f"Time per one-run diagnosis: median {statistics.median(single):.1f} s, max {max(single):.1f} s "
                     f"over {len(single)} runs (issue 27 asks median <= 5 s, none over 15 s).")
    cpu = [r["cpu_seconds"] for r in records if r["runs"] == 1 and "cpu_seconds" in r]
    if cpu:
        loads = [r["load"] for r in records if "load" in r]
        lines.append(f"CPU seconds of the same diagnoses (what the machine's load does not inflate): median "
                     f"{statistics.median(cpu):.1f} s, max {max(cpu):.1f} s over the {len(cpu)} runs that recorded it; "
                     f"1-minute load {min(loads):g}-{max(loads):g}.")
    return lines


def table_pairs(records: list[dict]) -> list[str]:
    """--two's table: per pair, the runs whose findings name both causes."""
    import independent_effects as ie

    lines = ["Runs of tests/independent_model.py with two catalogue causes hidden together by "
             "tests/independent_effects.py, each at its large size (the detection table's), three cycles at "
             f"{records[0]['hz']:g} Hz; seed 4000 + 2i in regime/form (A causal, B paper, B causal, A paper)[i % 4]; "
             "`diagnose([run])` with identification. A run counts when its findings name both.", "",
             "| hidden | both named | a cause not hidden named | findings per seed (regime/form) | median s | max s |",
             "|---|---:|---:|---|---:|---:|"]
    for pair in dict.fromkeys(r["cause"] for r in records):
        rows = [r for r in records if r["cause"] == pair]
        hidden = " + ".join(f"{c} {SIZES[c][1]:g} {ie.UNITS[c]}" for c in pair.split("+"))
        found = "; ".join(f"{'+'.join(r['findings']) or r['verdict']} ({r['regime']}/{r['form']})" for r in rows)
        wrong = sum(bool(set(r["findings"]) - set(pair.split("+"))) for r in rows)
        lines.append(f"| {hidden} | {sum(r['both'] for r in rows)}/{len(rows)} | {wrong}/{len(rows)} | {found} | "
                     f"{statistics.median(r['seconds'] for r in rows):.1f} | {max(r['seconds'] for r in rows):.1f} |")
    both = sum(r["both"] for r in records)
    wrong = sum(bool(set(r["findings"]) - set(r["cause"].split("+"))) for r in records)
    lines += ["", f"Both named in {both} of {len(records)} runs ({100 * both / len(records):.0f} %; issue 27 asks 3 of 4); "
              f"a cause not hidden among the findings in {wrong}."]
    return lines


def _others(rows: list[dict], expected: str) -> str:
    counts: dict[str, int] = {}
    for r in rows:
        if r["verdict"] != expected:
            counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) or "-"


def main(argv=None) -> int:
    import independent_effects as ie

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--causes", default=",".join(ie.CAUSES), help="comma-separated catalogue names")
    ap.add_argument("--sizes", choices=("small", "large", "all"), default="all")
    ap.add_argument("--seeds", type=int, default=10, help="seeds per cause and size (1000, 1002, ...)")
    ap.add_argument("--clean-seeds", type=int, default=20, help="clean seeds (2000, 2001, ...)")
    ap.add_argument("--full", action="store_true", help="every seed in every regime and form")
    ap.add_argument("--drops", action="store_true", help="the damping change's drops too (DROPS)")
    ap.add_argument("--hz", type=float, default=16.0)
    ap.add_argument("--workers", type=int, default=0, help="dask LocalCluster workers (0: in this process)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_detection_independent.jsonl"))
    ap.add_argument("--subset", default="", help="what was run, for the table (default: from the arguments)")
    ap.add_argument("--two", action="store_true", help="two causes hidden together (PAIRS); --seeds per pair")
    ap.add_argument("--regime", default="", help="a regime no setting was tuned on (independent_model.OTHER_REGIMES: "
                                                 "C), one seed per cause, size and form")
    ap.add_argument("--publish-only", action="store_true")
    ap.add_argument("--no-publish", action="store_true")
    args = ap.parse_args(argv)
    causes = [c for c in args.causes.split(",") if c]
    unknown = set(causes) - set(ie.CAUSES)
    if unknown:
        print(f"error: not a catalogue cause: {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    if args.regime and args.regime not in ie.im.OTHER_REGIMES:
        print(f"error: not another regime: {args.regime} (known: {', '.join(ie.im.OTHER_REGIMES)})", file=sys.stderr)
        return 2
    if not args.publish_only:
        cases = (plan_pairs(args.seeds, args.hz) if args.two else plan_other(args.regime, args.hz) if args.regime
                 else plan(causes, args.sizes, args.seeds, args.clean_seeds, args.full, args.hz, args.drops))
        run_all(cases, args.out, args.workers)
    records = [r for r in load(args.out) if ("+" in r["cause"]) == args.two
               and (r["regime"] == args.regime if args.regime else r["regime"] in ("A", "B"))]
    if not records:
        print(f"error: no results in {args.out}", file=sys.stderr)
        return 1
    if args.two:
        lines = table_pairs(records)
        print("\n".join(lines)) if args.no_publish else publish(SECTION_PAIRS, lines)
        return 0
    subset = args.subset or (f"regime {args.regime}: {OTHER_CLEAN} clean seeds, every cause but rate_dependence at both "
                             "sizes in both forms, one seed each" if args.regime else
                             f"causes {args.causes}, sizes {args.sizes}, {args.seeds} seeds each, "
                             f"{args.clean_seeds} clean seeds{', every regime/form' if args.full else ''}"
                             f"{', damping drops (DROPS)' if args.drops else ''}")
    lines = table(records, subset, INTRO_OTHER if args.regime else INTRO)
    if args.no_publish:
        print("\n".join(lines))
    else:
        publish(SECTION_OTHER if args.regime else SECTION, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
