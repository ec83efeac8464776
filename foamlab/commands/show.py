"""`foamlab show PATH`: import a data file and summarise what it holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from foamlab import FoamlabError

if TYPE_CHECKING:
    from foamlab.segmentation import Segmentation

HELP = "import a data file and print its summary (format, cycles, turning points, contact loss)"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "show", help=HELP,
        description="Import a foamlab run file, plain CSV (time_s,displacement_mm,force_N), "
                    "Instron Bluehill (2 or 3) raw-data CSV, Instron WaveMatrix tracking CSV, "
                    "MTS 793 MPT specimen.dat or ZwickRoell testXpert export and print what "
                    "it holds: samples, rate, cycles, turning points, contact-loss spans, the "
                    "first-cycle linear region and what the import had to do (notes).")
    parser.add_argument("path", metavar="PATH", help="data file to read")
    parser.add_argument("--plot", metavar="OUT.png",
                        help="also draw force-displacement per cycle and force-time to this image")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from foamlab.importers import load_run  # noqa: PLC0415 (keep `foamlab --help` fast)

    data = load_run(args.path)
    seg = data.segments()
    summary = summarize(seg)
    if args.json:
        print(json.dumps(summary, ensure_ascii=False))
    else:
        print(format_summary(summary))
    if args.plot:
        plot(seg, Path(args.plot))
        if not args.json:
            print(f"plot:          {args.plot}")
    return 0


def _span(seg: Segmentation, a: int, b: int) -> dict:
    r = seg.run
    return {"start": a, "stop": b, "t0_s": float(r.time_s[a]), "t1_s": float(r.time_s[b - 1]),
            "x0_mm": float(r.displacement_mm[a]), "x1_mm": float(r.displacement_mm[b - 1])}


def summarize(seg: Segmentation) -> dict:
    import numpy as np  # noqa: PLC0415 (keep `foamlab --help` fast)

    r = seg.run
    out: dict = {
        "path": r.source,
        "format": r.metadata.get("format", ""),
        "encoding": r.metadata.get("encoding", ""),
        "specimen": r.specimen.label,
        "started_at": r.started_at,
        "operator": r.metadata.get("operator", ""),
        "status": r.status,
        "samples": len(r),
        "sampling_hz": round(r.sampling_hz, 4),
        "duration_s": float(r.time_s[-1] - r.time_s[0]),
        "displacement_mm": [float(r.displacement_mm.min()), float(r.displacement_mm.max())],
        "force_N": [float(r.force_N.min()), float(r.force_N.max())],
        "stroke_mm": round(seg.stroke_mm, 4),
        "cycles": seg.n_cycles,
        "turning_points": [
            {"index": int(i), "time_s": float(r.time_s[i]),
             "displacement_mm": float(r.displacement_mm[i]), "force_N": float(r.force_N[i]),
             "kind": "max" if k % 2 == (0 if seg.leading_unloading is None else 1) else "min"}
            for k, i in enumerate(seg.turning_points)],
        "half_cycles": [dict(_span(seg, h.start, h.stop), cycle=h.cycle, direction=h.direction)
                        for h in seg.half_cycles],
        "holds": [_span(seg, a, b) for a, b in seg.holds],
        "contact_zero_N": seg.contact_zero_N,
        "contact_threshold_N": seg.contact_threshold_N,
        "contact_lost": [dict(_span(seg, a, b), cycle=seg.cycle_of(b - 1))
                         for a, b in seg.contact_lost_spans],
        "linear_region": None,
        "import_notes": list(r.metadata.get("import_notes", [])),
    }
    if seg.first_cycle_linear_region:
        a, b = seg.first_cycle_linear_region
        x, f = r.displacement_mm[a:b], r.force_N[a:b]
        slope, intercept = np.polyfit(x, f, 1)
        resid = f - (slope * x + intercept)
        r2 = 1.0 - float(np.sum(resid ** 2) / np.sum((f - f.mean()) ** 2)) if np.ptp(f) > 0 else 1.0
        out["linear_region"] = dict(_span(seg, a, b), slope_N_per_mm=float(slope), r2=r2)
    return out


def format_summary(s: dict) -> str:
    lines = [
        f"file:          {s['path']}",
        f"format:        {s['format']} ({s['encoding']})",
    ]
    if s["specimen"] or s["started_at"] or s.get("operator"):
        operator = f"   operator {s['operator']}" if s.get("operator") else ""
        lines.append(f"specimen:      {s['specimen'] or '-'}   started {s['started_at'] or '-'}"
                     f"{operator}")
    for note in s.get("import_notes", []):
        lines.append(f"import note:   {note}")
    lines += [
        f"samples:       {s['samples']} at {s['sampling_hz']:g} Hz over {s['duration_s']:.2f} s",
        f"displacement:  {s['displacement_mm'][0]:.3f} .. {s['displacement_mm'][1]:.3f} mm "
        f"(stroke {s['stroke_mm']:.3f} mm)",
        f"force:         {s['force_N'][0]:.3f} .. {s['force_N'][1]:.3f} N",
        f"cycles:        {s['cycles']}",
        "turning points:",
    ]
    for k, tp in enumerate(s["turning_points"], 1):
        lines.append(f"  {k}. {tp['kind']:3s} sample {tp['index']:>7d}  t={tp['time_s']:9.3f} s  "
                     f"x={tp['displacement_mm']:8.3f} mm  F={tp['force_N']:9.3f} N")
    if not s["turning_points"]:
        lines.append("  (none)")
    lines.append("half-cycles:")
    for h in s["half_cycles"]:
        lines.append(f"  cycle {h['cycle']} {h['direction']:9s} samples {h['start']:>7d}-{h['stop'] - 1:<7d} "
                     f"{h['t0_s']:9.3f}-{h['t1_s']:9.3f} s  {h['x0_mm']:7.3f} -> {h['x1_mm']:7.3f} mm")
    for h in s["holds"]:
        lines.append(f"  hold          samples {h['start']:>7d}-{h['stop'] - 1:<7d} "
                     f"{h['t0_s']:9.3f}-{h['t1_s']:9.3f} s  at {h['x0_mm']:7.3f} mm")
    lines.append(f"contact lost (force <= {s['contact_threshold_N']:.3f} N; "
                 f"unloaded reading {s['contact_zero_N']:.3f} N):")
    for c in s["contact_lost"]:
        lines.append(f"  {c['t0_s']:9.3f}-{c['t1_s']:9.3f} s  {c['x0_mm']:7.3f} -> {c['x1_mm']:7.3f} mm"
                     f"  (samples {c['start']}-{c['stop'] - 1})")
    if not s["contact_lost"]:
        lines.append("  (never)")
    lin = s["linear_region"]
    if lin:
        lines.append(f"linear region: first loading, samples {lin['start']}-{lin['stop'] - 1}, "
                     f"{lin['t0_s']:.2f}-{lin['t1_s']:.2f} s, {lin['x0_mm']:.3f}-{lin['x1_mm']:.3f} mm, "
                     f"slope {lin['slope_N_per_mm']:.3f} N/mm, R² {lin['r2']:.4f}")
    else:
        lines.append("linear region: not found")
    return "\n".join(lines)


def plot(seg: Segmentation, out: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    r = seg.run
    fig, (ax_fx, ax_ft) = plt.subplots(1, 2, figsize=(12, 4.8))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for cycle in seg.cycles:
        color = colors[(cycle.number - 1) % len(colors)]
        for half, style in ((cycle.loading, "-"), (cycle.unloading, "--")):
            if half is None:
                continue
            _, x, f = seg.arrays(half)
            ax_fx.plot(x, f, style, color=color, lw=1.2, label=half.label)
    lost = seg.contact_lost
    if lost.any():
        ax_fx.plot(r.displacement_mm[lost], r.force_N[lost], ".", color="0.6", ms=2,
                   label="contact lost")
    if seg.first_cycle_linear_region:
        a, b = seg.first_cycle_linear_region
        ax_fx.plot(r.displacement_mm[a:b], r.force_N[a:b], color="k", lw=3, alpha=0.35,
                   label="linear region")
    ax_fx.set_xlabel("displacement (mm, compression +)")
    ax_fx.set_ylabel("force (N)")
    ax_fx.set_title(Path(r.source).name if r.source else "run")
    ax_fx.legend(fontsize=7)
    ax_fx.grid(alpha=0.3)

    ax_ft.plot(r.time_s, r.force_N, lw=1, label="force")
    tp = seg.turning_points
    ax_ft.plot(r.time_s[tp], r.force_N[tp], "v", color="C3", label="turning points")
    for a, b in seg.contact_lost_spans:
        ax_ft.axvspan(r.time_s[a], r.time_s[b - 1], color="0.85", lw=0)
    ax_ft.set_xlabel("time (s)")
    ax_ft.set_ylabel("force (N)")
    ax_x = ax_ft.twinx()
    ax_x.plot(r.time_s, r.displacement_mm, color="C2", lw=0.8, alpha=0.7)
    ax_x.set_ylabel("displacement (mm)", color="C2")
    ax_ft.legend(fontsize=7, loc="upper right")
    ax_ft.grid(alpha=0.3)
    fig.tight_layout()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=110)
    except (OSError, ValueError) as exc:
        raise FoamlabError(f"{out}: cannot write the plot ({exc})") from None
    finally:
        plt.close(fig)
