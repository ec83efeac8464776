"""What the results view shows, as plain data: headline results, the verdict in words,
data-quality flags, and the expert detail (parameters, Table 5, constraints, warnings,
diagnosis findings); also what Export CSV writes.

Filled from the typed results (foamlab.methods.MethodResults, foamlab.identification
FitReport, foamlab.diagnosis Diagnosis) or, for a diagnosis stored beside a run file,
from its JSON form (the `foamlab diagnose --json` contract of docs/DESIGN).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from foamlab.gui.status import Flag
from foamlab.reporting.series import READABLE

if TYPE_CHECKING:
    from foamlab.identification import FitReport
    from foamlab.methods import Method, MethodResults

#: Per-cycle results every method may have, by their names in foamlab.methods: the names the
#: specimen series (`foamlab series`, the Series tab) and the PDF report use.
READABLE_NAMES = READABLE

#: The thermodynamic checks of the fit (foamlab.model.thermo), in words: what a FAIL means.
CONSTRAINT_MEANINGS = {
    "eq23_storage_nonnegative": ("storage stiffness ≥ 0 (Eq. 23)",
                                 "the fitted model would give back more energy than it stores"),
    "eq24_loss_nonnegative": ("loss ≥ 0 (Eq. 24)",
                              "the fitted damping would create energy instead of dissipating it"),
    "eq25_k1_nonnegative": ("initial stiffness k1 ≥ 0 (Eq. 25)",
                            "the fitted foam would push back less the more it is compressed at first"),
    "damping_modes_decay": ("damping modes decay",
                            "a fitted damping mode grows with time instead of fading"),
}

PLAIN_VERDICTS = {
    "none": "the model fits within the noise",
    "unexplained": "the model misses something that none of the known causes explains",
}

STEP_NAMES = {"damping": "damping (step 1)", "residual": "residual (step 2)", "elastic": "elastic (step 3)",
              "joint": "joint refinement"}


def number(value: float | None, digits: int = 4) -> str:
    """`digits` significant digits, plain notation from 0.001 to a million, else 1.2e-12."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    v = float(value)
    if v == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(v)))
    if -3 <= magnitude < 6:
        return f"{v:.{max(digits - 1 - magnitude, 0)}f}"
    return f"{v:.{digits - 1}e}"


def headline_names(method: "Method") -> list[str]:
    """The results a method is run for: its declared values (CV40, CFD); a method without
    any (the paper's protocol) is read by its hysteresis loss."""
    return [v.name for v in method.values] or ["hysteresis_loss"]


@dataclass(frozen=True)
class ResultRow:
    name: str               # as the method names it
    label: str              # what the technician reads
    cycle: int | None
    value: float | None
    unit: str
    description: str
    note: str


@dataclass(frozen=True)
class ParameterRow:
    name: str
    value: float
    stderr: float | None        # None: the data do not determine it
    unit: str
    varied: bool = True         # False: held fixed by the fit


@dataclass(frozen=True)
class FindingRow:
    effect: str
    description: str
    meaning: str
    rmse_before: float | None
    rmse_after: float | None
    heldout_before: float | None
    heldout_after: float | None
    delta_bic: float | None


@dataclass(frozen=True)
class ForecastRow:
    """One cycle's forecast score (foamlab.prediction.CycleScore): predicted from the earlier cycles."""

    cycle: int
    from_cycles: int
    rmse: float
    ratio: float                # RMSE over the load cell's noise
    bias: float


#: What a departure during the run means for the results (shown with its one-line message).
DEPARTURE_MEANING = ("the specimen left what its first cycles predicted, by more than the noise allows: "
                     "it changed during the test (damage, slip, a machine change); the fit and the diagnosis "
                     "say more")


@dataclass
class Report:
    run: list[tuple[str, str]] = field(default_factory=list)
    results: list[ResultRow] = field(default_factory=list)
    headline: list[str] = field(default_factory=list)         # names of the results shown large
    parameters: list[ParameterRow] = field(default_factory=list)
    statistics: list[tuple[str, Any, Any, Any, Any]] = field(default_factory=list)  # step, sse, r2, adj_r2, rmse
    constraints: list[tuple[str, bool]] = field(default_factory=list)
    rmse: float | None = None
    fit_warnings: list[str] = field(default_factory=list)
    fit_notes: list[str] = field(default_factory=list)
    fit_note: str = ""
    verdict: str = ""                                          # the catalogue name (or none/unexplained)
    findings: list[FindingRow] = field(default_factory=list)
    limits: list[str] = field(default_factory=list)           # what the run could have seen, in words
    diagnosis_note: str = ""
    flags: list[Flag] = field(default_factory=list)
    forecast: list[ForecastRow] = field(default_factory=list)
    forecast_note: str = ""

    # -- filling ----------------------------------------------------------------------
    def set_method_results(self, results: "MethodResults", headline: list[str] | None = None) -> None:
        self.results = [ResultRow(v.name, _label(v.name), v.cycle, v.value, v.unit, v.description, v.note)
                        for v in results]
        self.headline = list(headline or [])

    def set_fit(self, fit: "FitReport") -> None:
        self.parameters = [ParameterRow(p.name, p.value, p.stderr, p.unit or "–", p.vary)
                           for p in fit.parameters.values()]
        self.statistics = [(step, st.sse, st.r2, st.adj_r2, st.rmse) for step, st in fit.statistics.items()
                           if st is not None]
        self.constraints = list(fit.constraints.items())
        self.rmse = float(fit.rmse)
        self.fit_warnings = list(fit.warnings)
        self.fit_notes = list(fit.notes)

    def set_diagnosis(self, diagnosis: Any) -> None:
        """A foamlab.diagnosis Diagnosis, or the JSON dict stored beside a run file."""
        data = diagnosis if isinstance(diagnosis, dict) else diagnosis.to_dict()
        self.verdict = str(data.get("verdict", ""))
        self.limits = [str(item["text"]) for item in data.get("detection_limits") or [] if item.get("text")]
        self.findings = []
        for f in data.get("findings") or []:
            gain = f.get("gain") or {}
            self.findings.append(FindingRow(
                str(f.get("effect", "?")), str(f.get("description", "")), str(f.get("meaning", "")),
                gain.get("rmse_before"), gain.get("rmse_after"), gain.get("heldout_rmse_before"),
                gain.get("heldout_rmse_after"), gain.get("delta_bic")))

    def set_forecast(self, scores: Any) -> None:
        """foamlab.prediction.ForecastScores: each cycle's forecast from the earlier ones."""
        self.forecast = [ForecastRow(s.cycle, s.from_cycles, s.rmse_N, s.ratio, s.bias_N) for s in scores.scores]
        self.forecast_note = scores.note

    def add_departure(self, departure: Any) -> None:
        """A foamlab.prediction.Departure seen during the run (or found by a forecast that came
        after it): a flag in words, once."""
        if all(f.name != departure.message for f in self.flags):
            self.flags.append(Flag(departure.message, DEPARTURE_MEANING))

    # -- views ------------------------------------------------------------------------
    def headline_rows(self) -> list[ResultRow]:
        """The headline results; a per-cycle one (hysteresis loss) from the last cycle."""
        rows = []
        for name in self.headline:
            matching = [r for r in self.results if r.name == name]
            if matching:
                rows.append(max(matching, key=lambda r: r.cycle or 0))
        return rows

    def verdict_text(self) -> str:
        """One line in plain words: the diagnosis if there is one, else how well the fit did."""
        if self.verdict:
            if self.verdict in PLAIN_VERDICTS:
                text = PLAIN_VERDICTS[self.verdict]
                if self.verdict == "none" and self.limits:
                    text += " (" + "; ".join(self.limits) + ")"
            else:
                first = next((f for f in self.findings if f.effect == self.verdict), None)
                text = f"{first.description}: {first.meaning}" if first else self.verdict.replace("_", " ")
            return text[0].upper() + text[1:] + "."
        if self.diagnosis_note:
            return f"Diagnosis {self.diagnosis_note}"
        if self.rmse is not None:
            return f"Model fitted: RMSE {number(self.rmse, 3)} N (diagnosis not run)."
        return f"Model fit {self.fit_note}" if self.fit_note else ""

    def all_flags(self) -> list[Flag]:
        """Data-quality flags: the run's own, and every thermodynamic check the fit fails."""
        flags = list(self.flags)
        for name, ok in self.constraints:
            if not ok:
                title, meaning = CONSTRAINT_MEANINGS.get(name, (name, "the fitted model fails this check"))
                flags.append(Flag(f"fit fails {title}", f"{meaning}: read the parameters with care"))
        return flags

    # -- CSV ----------------------------------------------------------------------------
    def csv_rows(self) -> list[list[str]]:
        rows = [["section", "name", "value", "stderr_or_unit", "extra"]]
        rows += [["run", k, v, "", ""] for k, v in self.run]
        rows += [["flag", f.name, f.meaning, "", ""] for f in self.flags]
        rows += [["parameter", p.name, _num(p.value), _num(p.stderr), p.unit] for p in self.parameters]
        for step, sse, r2, adj, rmse in self.statistics:
            for key, value in (("sse", sse), ("r2", r2), ("adj_r2", adj), ("rmse", rmse)):
                if value is not None:
                    rows.append(["statistic", f"{step}.{key}", _num(value), "", ""])
        rows += [["constraint", n, "pass" if ok else "FAIL", "", ""] for n, ok in self.constraints]
        rows += [["fit_warning", "", w, "", ""] for w in self.fit_warnings]
        rows += [["method_result", r.name + (f" (cycle {r.cycle})" if r.cycle else ""), _num(r.value), r.unit,
                  r.note] for r in self.results]
        if self.verdict:
            rows.append(["diagnosis", "verdict", self.verdict, "", ""])
        rows += [["finding", f.effect, _num(f.rmse_before), _num(f.rmse_after), _num(f.delta_bic)]
                 for f in self.findings]
        rows += [["detection_limit", text, "", "", ""] for text in self.limits]
        rows += [["forecast", f"cycle {f.cycle} from cycles 1-{f.from_cycles}", _num(f.rmse), "N",
                  f"{f.ratio:.3g} x noise"] for f in self.forecast]
        return rows

    def write_csv(self, path: str) -> None:
        with open(path, "w", newline="", encoding="utf-8") as f:
            csv.writer(f).writerows(self.csv_rows())


def _label(name: str) -> str:
    return READABLE_NAMES.get(name, name.replace("_", " "))


def _num(value: Any) -> str:
    if value is None:
        return ""
    return repr(float(value)) if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value)
