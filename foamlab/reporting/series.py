"""A specimen series: several specimens tested with one method, as Bluehill and testXpert keep them.

    from foamlab.reporting import specimen_series
    s = specimen_series(["a.csv", "b.csv", "c.csv"])          # each run's own method (all the same)
    s.statistics[0].mean, .sd, .cv_percent                    # per result column
    s.write_csv("series.csv")                                 # one row per specimen + n/mean/sd/cv

Each specimen's method results are computed by the pipeline's method stage (foamlab.pipeline);
the statistics are over the specimens that have a value: mean, sample standard deviation
(n - 1, as the testing standards and Bluehill use) and coefficient of variation = sd / |mean|.
A run's series name (series_name) is its specimen label without the trailing run number
("PU45-03" -> "PU45"): the window's Series tab and `foamlab batch`'s summary use it.
Named SpecimenSeries: foamlab.analysis.design.Series is a run's samples for the analysis core.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from foamlab import FoamlabError
from foamlab.methods import Method, MethodResults, ResultValue, load_method, method_of_run
from foamlab.rundata import RunData

_RUN_NUMBER = re.compile(r"^(.*?)[\s_\-#./]*\d+$")


def series_name(label: str | None, path: str | Path) -> str:
    """The specimen series a run belongs to: its specimen label without the trailing run number
    ("PU45-03" -> "PU45", "PU45" -> "PU45"); a file without a label is in the series of its folder."""
    label = label.strip() if isinstance(label, str) else ""
    if label:
        m = _RUN_NUMBER.match(label)
        return m.group(1) if m and m.group(1) else label
    return Path(str(path)).parent.name or "(no series)"


#: Readable names of the per-cycle quantities (foamlab.methods); named values keep their own.
READABLE = {"loading_energy": "Loading energy", "unloading_energy": "Unloading energy",
            "hysteresis_loss": "Hysteresis loss", "residual_strain": "Residual strain"}


def readable_name(value: ResultValue) -> str:
    name = READABLE.get(value.name, value.name)
    return f"{name}, cycle {value.cycle}" if value.cycle and value.name in READABLE else name


def unit_text(unit: str) -> str:
    """A unit as printed: a dimensionless ratio shows as 'mm/mm', not as nothing."""
    return unit or "mm/mm"


@dataclass(frozen=True)
class Column:
    """One result of the method, the same in every specimen: (name, cycle) and its unit."""

    name: str
    cycle: int | None
    unit: str
    title: str                     # readable, e.g. "Hysteresis loss, cycle 2"

    @property
    def key(self) -> tuple[str, int | None]:
        return (self.name, self.cycle)

    @property
    def header(self) -> str:
        """The CSV header: the value's name and its unit, e.g. "hysteresis_loss_c2 [%]"."""
        cycle = f"_c{self.cycle}" if self.cycle and self.name in READABLE else ""
        return f"{self.name}{cycle} [{unit_text(self.unit)}]"


@dataclass(frozen=True)
class Statistic:
    column: Column
    n: int                         # specimens with a value
    mean: float | None
    sd: float | None               # sample standard deviation (n - 1); None below 2 values
    cv_percent: float | None       # sd / |mean| x 100; None when sd is None or mean is 0


@dataclass
class Specimen:
    """One specimen of the series: its run, where it came from and its method results."""

    path: Path
    run: RunData
    results: MethodResults
    error: str = ""                # why its results could not be computed ("" when they were)

    @property
    def label(self) -> str:
        return self.run.specimen.label or self.path.stem

    def value(self, column: Column) -> float | None:
        v = self.results.get(column.name, column.cycle)
        return v.value if v is not None else None


@dataclass
class SpecimenSeries:
    method: Method
    specimens: list[Specimen]
    columns: list[Column] = field(default_factory=list)
    statistics: list[Statistic] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.specimens)

    def statistic(self, name: str, cycle: int | None = None) -> Statistic | None:
        return next((s for s in self.statistics if s.column.name == name
                     and (cycle is None or s.column.cycle == cycle)), None)

    def rows(self) -> list[list[str]]:
        """The table a report shows and the CSV holds: header, specimens, then n/mean/sd/cv."""
        table = [["specimen", "file"] + [c.header for c in self.columns]]
        for s in self.specimens:
            table.append([s.label, s.path.name] + [_cell(s.value(c)) for c in self.columns])
        for title, attr in (("n", "n"), ("mean", "mean"), ("sd", "sd"), ("cv [%]", "cv_percent")):
            table.append([title, ""] + [_cell(getattr(st, attr)) for st in self.statistics])
        return table

    def write_csv(self, out: str | Path) -> Path:
        out = Path(out)
        tmp = out.with_name(out.name + ".tmp")
        try:
            with open(tmp, "w", encoding="utf-8", newline="") as fh:
                fh.write(f"# foamlab specimen series: method {self.method.name} ({self.method.title}); "
                         "sd = sample standard deviation (n - 1), cv = sd / |mean|\n")
                csv.writer(fh).writerows(self.rows())
            tmp.replace(out)
        except OSError as exc:
            raise FoamlabError(f"{out}: cannot write the series ({exc.strerror or exc})") from None
        return out


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, int):
        return str(v)
    return f"{v:.6g}"


def statistic(column: Column, values: list[float | None]) -> Statistic:
    have = [float(v) for v in values if v is not None and math.isfinite(v)]
    n = len(have)
    if n == 0:
        return Statistic(column, 0, None, None, None)
    mean = sum(have) / n
    if n < 2:
        return Statistic(column, n, mean, None, None)
    sd = math.sqrt(sum((v - mean) ** 2 for v in have) / (n - 1))
    cv = 100.0 * sd / abs(mean) if mean != 0 else None
    return Statistic(column, n, mean, sd, cv)


def series_from_runs(runs: list[tuple[Path, RunData]], method: Method | str | None = None) -> SpecimenSeries:
    """The series of these runs (all made with one method: `method`, else each run's own)."""
    from foamlab import pipeline  # noqa: PLC0415 (pipeline imports the diagnosis: heavy)

    if not runs:
        raise FoamlabError("a series needs at least one specimen")
    if isinstance(method, (str, Path)):
        method = load_method(method)
    if method is None:
        names = {r.method for _, r in runs}
        if names == {""}:
            raise FoamlabError("the files record no test method: give it with --method")
        if len(names) > 1:
            each = ", ".join(f"{p.name}: {r.method or '(none)'}" for p, r in runs)
            raise FoamlabError(f"a series is one method; these files were tested with several ({each}); "
                               "choose one with --method")
        method = method_of_run(runs[0][1])
    specimens = []
    for path, run in runs:
        a = pipeline.method_stage(pipeline.Analysis(run, path), method)
        specimens.append(Specimen(path, run, a.method_results or MethodResults(), a.method_error))
    columns: dict[tuple, Column] = {}
    for s in specimens:
        for v in s.results:
            columns.setdefault((v.name, v.cycle), Column(v.name, v.cycle, v.unit, readable_name(v)))
    cols = list(columns.values())
    stats = [statistic(c, [s.value(c) for s in specimens]) for c in cols]
    return SpecimenSeries(method, specimens, cols, stats)


def specimen_series(paths: list[str | Path], method: Method | str | None = None) -> SpecimenSeries:
    """Read each file (run file or export) and make the series."""
    from foamlab.importers import load_run  # noqa: PLC0415

    seen: set[Path] = set()
    runs = []
    for p in map(Path, paths):
        if p.resolve() in seen:
            raise FoamlabError(f"{p}: given twice (a specimen counts once in a series)")
        seen.add(p.resolve())
        runs.append((p, load_run(p)))
    return series_from_runs(runs, method)
