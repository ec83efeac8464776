"""Import, segmentation and run-file writing speed (medians over repeats).

    .venv/bin/python benchmarks/bench_storage.py

What it shows: load_run and segment() grow linearly with the number of samples
(10^4 .. 10^6 samples of a 3-cycle run), the bundled Bluehill file imports in a
few tens of ms, and RunWriter's flushed line per sample costs microseconds, far
below any sampling period a testing machine uses.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _table import median_seconds, publish  # noqa: E402

from foamlab.importers import load_run  # noqa: E402
from foamlab.segmentation import segment  # noqa: E402
from foamlab.storage.runfile import RunWriter, write_run_file  # noqa: E402
from tests.synthetic import triangle_run  # noqa: E402

REAL = ROOT / "tests" / "data" / "real" / "Specimen_RawData_6.csv"



def main() -> None:
    lines = ["| what | samples | median | per sample |", "|---|---:|---:|---:|"]

    def row(what: str, n: int, seconds: float) -> None:
        lines.append(f"| {what} | {n:,} | {seconds * 1e3:.1f} ms | {seconds / n * 1e6:.2f} µs |")

    run = load_run(REAL)
    row("load_run, real Bluehill file", len(run), median_seconds(lambda: load_run(REAL), 5))
    row("segment, real Bluehill file", len(run), median_seconds(lambda: segment(run), 5))

    sizes, load_times, seg_times = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for rate in (50 / 1.8, 50 / 0.18, 50 / 0.018):   # ~1e4, 1e5, 1e6 samples
            synthetic, _ = triangle_run(rate_hz=rate)
            path = write_run_file(Path(tmp) / f"run{len(synthetic)}.csv", synthetic)
            repeats = 5 if len(synthetic) < 500_000 else 3
            t_load = median_seconds(lambda: load_run(path), repeats)
            t_seg = median_seconds(lambda: segment(synthetic), repeats)
            row("load_run, run file", len(synthetic), t_load)
            row("segment, 3 cycles", len(synthetic), t_seg)
            sizes.append(len(synthetic))
            load_times.append(t_load)
            seg_times.append(t_seg)

        n_write = 20_000
        path = Path(tmp) / "writer.csv"

        def write() -> None:
            path.unlink(missing_ok=True)
            writer = RunWriter(path, {"method": "bench"})
            for i in range(n_write):
                writer.write_sample(i * 0.02, 0.001 * i, 0.5 * i, 1.2)
            writer.finish()

        row("RunWriter.write_sample (flush each, fsync <= 2/s)", n_write, median_seconds(write, 3))

    slope = lambda t: float(np.polyfit(np.log(sizes), np.log(t), 1)[0])  # noqa: E731
    lines.append("")
    lines.append(f"growth exponent 10^4..10^6 samples: load_run {slope(load_times):.2f}, "
                 f"segment {slope(seg_times):.2f} (1.0 = linear)")
    publish("Import, segmentation, run files (benchmarks/bench_storage.py)", lines)


if __name__ == "__main__":
    main()
