"""FitReport: one fit, frozen once it is made, saved and loaded exactly; it reports itself
(statistics, standard errors, correlations, warnings, information criteria) in the spirit of
lmfit's MinimizerResult. What the figures show is in it (the fitted force at every sample), so
the report and the window read a stored fit instead of fitting again."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import Fit
from foamlab.identification.apart import HeldOrders
from foamlab.identification.forms import FormChoice
from foamlab.identification.parameters import Parameter, Parameters, unit_of
from foamlab.identification.record import decode, encode, same
from foamlab.identification.statistics import GoodnessOfFit
from foamlab.identification.structure import StructureChoice
from foamlab.model import ModelParameters, stepped_force
from foamlab.model.layout import Orders

__all__ = ["FitReport", "FitWork", "FittedSamples", "Parameter", "Parameters", "TurnSamples", "unit_of"]

#: The steps of Table 5, plus the joint refinement.
STEPS = ("damping", "residual", "elastic", "joint")
#: The terminal summary lists at most this many warnings (all are in --json and the sidecar).
SUMMARY_WARNINGS = 3
#: The RMSE without the turn samples is shown when it is below this share of the whole run's.
TURNS_SHOWN = 0.9
#: The sample sets an RMSE is computed on (each RMSE says which, and how many samples).
RECORDED = "recorded"     # every recorded sample from the first cycle's start to the last one's end
CYCLES = "cycles"         # the samples of the half-cycles (the joint statistics' rows)
EVIDENCE = "evidence"     # those the fit uses: recorded less the samples at turns it cannot place
HELDOUT = "held-out"      # blocks left out of a fit and predicted by it (identification.forms)


def sample_set(name: str, count: int) -> dict:
    """How an RMSE's samples are named in the JSON: the set and how many."""
    return {"set": name, "count": int(count)}


#: What a sidecar's "report" entry is, and the version of its layout.
REPORT_FORMAT = "foamlab fit report"
REPORT_VERSION = 2        # 2: each turn's placement fitted (turn_parameters, turns_flipped)


def _num(v) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


@dataclass(frozen=True)
class TurnSamples:
    """The samples within a step of a turning point that the samples cannot place (predicted, not
    evidence: analysis.path.path_determined) and the fit's RMSE without them."""

    count: int
    rmse_without_N: float          # RMS of measured - fitted over the evidence samples
    max_abs_N: float               # the largest |measured - fitted| among the turn samples

    def to_dict(self, recorded: int | None = None) -> dict:
        """recorded: how many samples the whole-run RMSE covers (the evidence is those less these)."""
        out = {"count": self.count, "rmse_without": _num(self.rmse_without_N), "max_abs": _num(self.max_abs_N)}
        if recorded is not None:
            out["rmse_without_samples"] = sample_set(EVIDENCE, recorded - self.count)
        return out


@dataclass(frozen=True, eq=False)
class FittedSamples:
    """The run's samples and the force the fit reported at each: what every figure of the fit
    draws; and the path that drove the model (the samples' displacement without its noise, through
    the turns placed between samples), with which the stored
    parameters reproduce that force (FitReport.reproduced_force_N)."""

    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_N: np.ndarray
    predicted_force_N: np.ndarray  # what the load cell would read: max(model force, unloaded reading)
    cycle: np.ndarray              # 1-based cycle of each sample (the fit's labels)
    direction: np.ndarray          # +1 loading, -1 unloading, 0 neither
    observed: np.ndarray           # indices of the samples the joint fit used
    path_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))   # the path's nodes
    path_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    path_of_sample: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # node of each sample

    @property
    def residual_N(self) -> np.ndarray:
        return self.force_N - self.predicted_force_N

    @property
    def n_cycles(self) -> int:
        return int(self.cycle.max()) if len(self.cycle) else 0


@dataclass(frozen=True, eq=False)
class FitWork:
    """The fit's working state (not saved): what diagnosis and the forecast extend."""

    prepared: PreparedRun | None = None   # the run as prepared for every fit (foamlab.analysis)
    core_fit: Fit | None = None           # the analysis core's fit: what diagnosis extends
    free_core: Fit | None = None          # where orders were held apart (identification.apart): the
                                          # fit with them free, diagnosis' base (all terms free)
    largest: "FitReport | None" = None    # the largest structure's fit when another was chosen
    alternatives: tuple["FitReport", ...] = ()   # the other residual forms' fits


@dataclass(frozen=True, eq=False)
class FitReport:
    """One fit of the model to one run, built once at its end (identification.fit)."""

    source: str
    orders: Orders
    params: ModelParameters
    parameters: Parameters            # flat ModelParameters order: value, stderr, bounds, vary, tie, why
    correlation: np.ndarray           # names x names, nan where not determined
    statistics: dict[str, GoodnessOfFit | None]
    rmse: float                       # whole run: RMS of measured - fitted, every sample of the cycles
    noise_N: float                    # the load cell's noise level estimated from the run
    constraints: dict[str, bool]
    warnings: tuple[str, ...]
    notes: tuple[str, ...]            # choices the fit made (e.g. a mode made real)
    aic: float
    bic: float
    n_obs: int
    n_params: int
    autocorrelation_time: float
    contact_zero_N: float             # unloaded load-cell reading (fitted with the rest if used)
    status: int                       # the final optimizer's (scipy least_squares): > 0 converged
    message: str
    samples: FittedSamples
    turns: TurnSamples | None = None  # the samples at turns the samples cannot place, and the RMSE without them
    form_choice: FormChoice | None = None    # which residual form, and why (identification.forms)
    structure: StructureChoice | None = None  # the structures tried and the one chosen (or forced)
    starts: tuple[str, ...] = ()
    elapsed_s: float = 0.0
    turns_between_samples: bool = True   # turns without a stop placed between samples (else at one)
    run_samples: int = 0              # the run's samples as given (samples: those on its schedule)
    turn_parameters: int = 0          # turns the samples cannot place: each one's placement fitted (in n_params)
    turns_flipped: tuple[int, ...] = ()      # of them, the turning points placed the other way from the rest
    turns_flipped_s: tuple[float, ...] = ()  # their extreme samples' instants
    held_orders: HeldOrders | None = None   # residual orders held apart: the choice, its cost, the free fit
    work: FitWork | None = field(default=None, compare=False, repr=False, metadata={"saved": False})

    def __eq__(self, other: object) -> bool:
        """Field by field (arrays by value); the working state is not part of the record."""
        return isinstance(other, FitReport) and same(self, other)

    __hash__ = None

    def with_work(self, **changes) -> "FitReport":
        """The same report with its working state changed (a new object: reports are frozen)."""
        return replace(self, work=replace(self.work or FitWork(), **changes))

    # -- views -----------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return self.parameters.names

    @property
    def values(self) -> np.ndarray:
        return self.parameters.column("value")

    @property
    def stderr(self) -> np.ndarray:
        return self.parameters.column("stderr")

    @property
    def stderr_autocorr(self) -> np.ndarray:
        return self.parameters.column("stderr_ac")

    @property
    def varied(self) -> np.ndarray:
        return self.parameters.column("vary", bool)

    @property
    def tied(self) -> dict[str, str]:
        return self.parameters.tied

    @property
    def predicted_force_N(self) -> np.ndarray:
        return self.samples.predicted_force_N

    def reproduced_force_N(self) -> np.ndarray:
        """The force this report's parameters give at its samples when the model is stepped
        along the stored path, as the simulator steps its specimen (model.stepped_force), read
        as the load cell reads it (the unloaded reading where the plate is off): the fitted
        force, to the model's operators' accuracy (tests/test_fit_reproduces.py)."""
        s = self.samples
        if not len(s.path_time_s):
            raise FoamlabError("this fit report holds no path (written by an older foamlab): fit the run again")
        force = stepped_force(self.params, s.path_time_s, s.path_mm)[s.path_of_sample]
        return np.maximum(force, self.contact_zero_N)

    @property
    def run_time_s(self) -> np.ndarray:
        return self.samples.time_s

    @property
    def run_displacement_mm(self) -> np.ndarray:
        return self.samples.displacement_mm

    @property
    def run_force_N(self) -> np.ndarray:
        return self.samples.force_N

    @property
    def observed(self) -> np.ndarray:
        return self.samples.observed

    @property
    def residual_N(self) -> np.ndarray:
        """Measured minus fitted force at every sample of the run."""
        return self.samples.residual_N

    @property
    def success(self) -> bool:
        """The final optimizer converged (not stopped by its iteration budget)."""
        return self.status > 0

    @property
    def rmse_count(self) -> int:
        """How many samples ``rmse`` covers: every recorded one from the first cycle's start to the
        last one's end (RECORDED)."""
        observed = self.samples.observed
        return int(observed[-1] + 1 - observed[0]) if len(observed) else 0

    @property
    def dropped(self) -> int:
        """The run's samples left out before the fit: taken off the sampling schedule."""
        return max(self.run_samples - len(self.samples.time_s), 0) if self.run_samples else 0

    def samples_dict(self) -> dict:
        """Which samples the JSON's figures cover, and how many were dropped."""
        return {"recorded": self.run_samples or len(self.samples.time_s), "off_schedule_dropped": self.dropped,
                "rmse": sample_set(RECORDED, self.rmse_count),
                # the paper's steps are fitted on their own half-cycles, the joint one on the cycles'
                "statistics": {step: sample_set(CYCLES if step == "joint" else f"{step} step", st.n)
                               for step in STEPS if (st := self.statistics.get(step)) is not None}}

    @property
    def convergence(self) -> str:
        """What the optimizer's end means for the numbers: one line."""
        if self.success:
            return f"converged ({self.message})"
        return (f"NOT CONVERGED: the optimizer stopped ({self.message}); the parameters, standard errors and "
                "RMSE are where it stopped, not the optimum (the optimum's RMSE is at most this one)")

    @property
    def prepared(self) -> PreparedRun | None:
        return self.work.prepared if self.work else None

    @property
    def core_fit(self) -> Fit | None:
        return self.work.core_fit if self.work else None

    @property
    def free_core(self) -> Fit | None:
        return self.work.free_core if self.work else None

    @property
    def largest(self) -> "FitReport | None":
        return self.work.largest if self.work else None

    @property
    def alternatives(self) -> tuple["FitReport", ...]:
        return self.work.alternatives if self.work else ()

    def value(self, name: str) -> float:
        return self.parameters[name].value

    def standard_error(self, name: str) -> float | None:
        return self.parameters[name].stderr

    # -- JSON ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The object of ``foamlab fit --json`` (DESIGN.md): parameters, statistics, rmse,
        constraints. Standard errors of parameters the data do not determine are null."""
        parameters = {p.name: p.to_dict() for p in self.parameters.values()}
        parameters["x_scale_mm"] = {"value": float(self.params.x_scale_mm), "stderr": None, "lower": None,
                                    "upper": None, "varied": False, "unit": "mm", "determined": False}
        statistics = {}
        for step in STEPS:
            st = self.statistics.get(step)
            statistics[step] = st.to_dict() if st is not None else {
                "sse": None, "r2": None, "adj_r2": None, "rmse": None}
        return {"parameters": parameters, "statistics": statistics, "rmse": _num(self.rmse),
                "constraints": {k: bool(v) for k, v in self.constraints.items()},
                "samples": self.samples_dict(),
                "noise": _num(self.noise_N),
                "converged": self.success,
                "optimizer": {"success": self.success, "status": self.status, "message": self.message,
                              "meaning": self.convergence},
                "turn_samples": self.turns.to_dict(self.rmse_count) if self.turns is not None else None,
                "turn_placement": {"parameters": self.turn_parameters,
                                   "rule": "between samples" if self.turns_between_samples else "at the sample",
                                   "placed_other_way_s": list(self.turns_flipped_s)},
                "dof": {"n_obs": self.n_obs, "n_params": self.n_params, "turn_parameters": self.turn_parameters},
                "form": self.params.residual_form, "forms": self._forms_dict(),
                "structure": self.structure.to_dict() if self.structure is not None else None,
                "held_apart": self.held_orders.to_dict() if self.held_orders is not None else None,
                "warnings": list(self.warnings), "notes": list(self.notes)}

    def _forms_dict(self) -> dict:
        """Each form's RMSE, held-out RMSE, BIC and its BIC minus the chosen one's, and why."""
        choice = self.form_choice
        if choice is None:
            return {"chosen": self.params.residual_form, "reason": "", "scores": []}
        mine = choice.score(choice.chosen)
        return {"chosen": choice.chosen, "reason": choice.reason(), "forced": choice.forced, "settled": choice.settled,
                "rmse_samples": RECORDED, "heldout_rmse_samples": HELDOUT,
                "scores": [{"form": s.form, "rmse": _num(s.rmse), "heldout_rmse": _num(s.heldout_rmse),
                            "bic": _num(s.bic), "delta_bic": _num(s.bic - mine.bic) if mine else None}
                           for s in choice.scores]}

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def sidecar_dict(self) -> dict:
        """What is stored beside the run: the JSON object, the model (so the file loads with
        ModelParameters.load as a simulator specimen) and the whole report, exactly ("report":
        what FitReport.load reads back)."""
        out = self.to_dict()
        out.update({
            "model": self.params.to_dict(),
            "orders": {"N": self.orders.N, "M": self.orders.M, "P": self.orders.P, "C": self.orders.C,
                       "form": self.orders.form, "shared": self.orders.shared},
            "stderr_autocorrelation_corrected": {p.name: p.stderr_ac for p in self.parameters.values()},
            "autocorrelation_time": _num(self.autocorrelation_time),
            "correlation": {"names": self.names, "matrix": [[_num(c) for c in row] for row in self.correlation]},
            "aic": _num(self.aic), "bic": _num(self.bic),
            "n_obs": self.n_obs, "n_params": self.n_params,
            "contact_zero_N": _num(self.contact_zero_N),
            "source": self.source,
            "elapsed_s": _num(self.elapsed_s),
            "report": {"format": REPORT_FORMAT, "version": REPORT_VERSION, **encode(self)},
        })
        return out

    def sidecar_text(self) -> str:
        """The sidecar's JSON: the readable part indented, the record (thousands of samples) one
        number after another."""
        data = self.sidecar_dict()
        record = data.pop("report")
        return json.dumps(data, indent=1)[:-2] + ',\n "report": ' + json.dumps(record, separators=(",", ":")) + "\n}"

    def save(self, path: str | Path) -> Path:
        """Write the sidecar JSON (atomically: a reader never sees half a file)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(self.sidecar_text(), encoding="utf-8")
        tmp.replace(path)
        return path

    @classmethod
    def from_sidecar(cls, data: dict) -> "FitReport":
        """The report a sidecar holds (its working state is not stored: None)."""
        record = data.get("report") if isinstance(data, dict) else None
        if not isinstance(record, dict) or record.get("format") != REPORT_FORMAT:
            raise FoamlabError("fit file holds no fit report (made by an older foamlab): fit the run again")
        if record.get("version") != REPORT_VERSION:
            raise FoamlabError(f"fit report version {record.get('version')!r}: this foamlab reads {REPORT_VERSION}")
        return decode(cls, record)

    @classmethod
    def load(cls, path: str | Path) -> "FitReport":
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise FoamlabError(f"{path}: cannot read the fit ({exc})") from None
        try:
            return cls.from_sidecar(data)
        except FoamlabError as exc:
            raise FoamlabError(f"{path}: {exc}") from None

    # -- text ---------------------------------------------------------------------------
    def brief(self) -> str:
        """What a terminal shows: fit quality, the parameters the data determine, the warnings
        that matter most (the full report is ``summary()``, --json and the sidecar)."""
        joint = self.statistics.get("joint")
        ratio = self.rmse / self.noise_N if self.noise_N > 0 else float("nan")
        lines = [self._headline(f"fit of {self.source or 'run'}: orders {self.orders}") + f", {self.elapsed_s:.2f} s",
                 f"  {self.form_choice.reason() if self.form_choice else self.params.residual_form + ' residual form'}",
                 f"  RMSE {self.rmse:.4g} N on all {self.rmse_count} recorded samples = {ratio:.2f} x the load "
                 f"cell's noise ({self.noise_N:.3g} N)"
                 + (f", R^2 {joint.r2:.6f}" if joint is not None else ""),
                 f"  optimizer: {self.convergence}"]
        if self.turns is not None and self.turns.count and self.turns.rmse_without_N < TURNS_SHOWN * self.rmse:
            t = self.turns
            lines.insert(len(lines) - 1, f"  without the {t.count} samples at turns the samples cannot place (predicted, not "
                            f"evidence; up to {t.max_abs_N:.3g} N off): RMSE {t.rmse_without_N:.4g} N on the "
                            f"{self.rmse_count - t.count} evidence samples = "
                            f"{t.rmse_without_N / self.noise_N:.2f} x the noise")
        if self.structure is not None:
            lines.append(f"  structure: {self.structure.why}"
                         + (f" ({len(self.structure.candidates)} tried, see --full)" if self.structure.candidates else ""))
        own = [p for p in self.parameters.values() if not p.tie]
        params = [p for p in own if p.determined]
        hidden = len(own) - len(params)
        shared = " (each order beta1_m is every cycle's: shared orders)" if self.tied else ""
        lines.append(f"  parameters the data determine ({len(params)} of {len(own)}; "
                     f"{hidden} fixed, not determined or within 2 standard errors of zero: see --full or --json)"
                     f"{shared}:")
        for p in params:
            lines.append(f"    {p.name:<11}{p.value:>13.5g} +/- {p.stderr:<10.2g} {p.unit}")
        held = [p for p in own if not p.vary and p.name.startswith("beta")]
        if held:       # identification.apart
            lines.append("  orders held apart, not fitted (their terms coalesce; the data determine their sum): "
                         + ", ".join(f"{p.name} {p.value:.3g}" for p in held)
                         + (f"; {self.held_orders.brief()}" if self.held_orders is not None else ""))
        failed = [k for k, ok in self.constraints.items() if not ok]
        if failed:
            lines.append("  thermodynamic checks failed: " + ", ".join(failed))
        if self.warnings:
            lines.append(f"  warnings ({len(self.warnings)}; the first {min(SUMMARY_WARNINGS, len(self.warnings))}):")
            lines += [f"    - {w}" for w in self.warnings[:SUMMARY_WARNINGS]]
        return "\n".join(lines)

    def summary(self) -> str:
        """A readable report: statistics per step (Table 5), parameters, checks, warnings."""
        lines = [self._headline(f"[[Fit]] {self.source or 'run'}"),
                 f"    orders            {self.orders}",
                 f"    residual form     {self.form_choice.reason() if self.form_choice else self.params.residual_form}",
                 f"    samples fitted    {self.n_obs} of the cycles  (parameters {self.n_params}, of them "
                 f"{self.turn_parameters} turn placements)",
                 f"    RMSE              {self.rmse:.4g} N  (all {self.rmse_count} recorded samples)",
                 f"    AIC / BIC         {self.aic:.1f} / {self.bic:.1f}",
                 f"    optimizer         {self.convergence}",
                 f"    time              {self.elapsed_s:.2f} s",
                 "[[Statistics]] (Table 5; joint = all parameters on the raw signal)",
                 f"    {'step':<10}{'SSE':>12}{'R^2':>10}{'adj R^2':>10}{'RMSE':>10}{'n':>7}{'p':>5}"]
        for step in STEPS:
            st = self.statistics.get(step)
            if st is None:
                lines.append(f"    {step:<10}{'(skipped)':>12}")
            else:
                lines.append(f"    {step:<10}{st.sse:>12.5g}{st.r2:>10.5f}{st.adj_r2:>10.5f}"
                             f"{st.rmse:>10.4g}{st.n:>7d}{st.p:>5d}")
        lines += self._forms_lines()
        lines.append("[[Parameters]] (value, standard error, relative; 'ac' = corrected for "
                     f"residual autocorrelation, tau = {self.autocorrelation_time:.1f})")
        lines.append(f"    {'name':<11}{'value':>14}{'stderr':>12}{'rel':>9}{'stderr ac':>12}")
        for p in self.parameters.values():
            n, v, s, sa = p.name, p.value, p.stderr, p.stderr_ac
            if p.tie:
                lines.append(f"    {n:<11}{v:>14.6g}  = {p.tie} (shared orders)")
            elif not p.vary:
                lines.append(f"    {n:<11}{v:>14.6g}  held: {p.why}")
            elif s is not None:
                rel = f"{abs(s / v) * 100:8.1f}%" if v != 0 else f"{'-':>9}"
                lines.append(f"    {n:<11}{v:>14.6g}{s:>12.3g}{rel}{sa if sa is not None else math.nan:>12.3g}")
            else:
                lines.append(f"    {n:<11}{v:>14.6g}{'(not determined)':>33}")
        lines.append(f"    {'x_scale_mm':<11}{self.params.x_scale_mm:>14.6g}{'(fixed)':>12}")
        lines.append("[[Constraints]] (thermodynamic checks, Eqs. 23-25)")
        for k, ok in self.constraints.items():
            lines.append(f"    {k:<28}{'pass' if ok else 'FAIL'}")
        if self.structure is not None:
            lines.append(f"[[Structure]] {self.structure.why}")
            if self.structure.candidates:
                lines += self.structure.lines()
        if self.held_orders is not None:
            lines += self.held_orders.lines()
        if self.notes:
            lines.append("[[Notes]]")
            lines += [f"    - {w}" for w in self.notes]
        if self.warnings:
            lines.append("[[Warnings]]")
            lines += [f"    - {w}" for w in self.warnings]
        return "\n".join(lines)

    def _headline(self, what: str) -> str:
        """The first line: what was fitted, on how many samples, how many were dropped, and first
        of all whether the optimizer did not converge."""
        line = f"{what}, {self.n_obs} samples fitted"
        if self.dropped:
            line += f", {self.dropped} of {self.run_samples} dropped (off the sampling schedule)"
        return line if self.success else f"NOT CONVERGED ({self.message}) - {line}"

    def _forms_lines(self) -> list[str]:
        """Each residual form's RMSE, held-out RMSE and BIC against the chosen one's."""
        choice = self.form_choice
        if choice is None or len(choice.scores) < 2:
            return []
        mine = choice.score(choice.chosen)
        lines = ["[[Residual form]] (both fitted; the one predicting held-out blocks better kept; RMSE on all "
                 "recorded samples)",
                 f"    {'form':<10}{'RMSE':>10}{'held-out':>10}{'dBIC':>10}"]
        for sc in choice.scores:
            mark = "  (kept)" if sc.form == choice.chosen else ""
            lines.append(f"    {sc.form:<10}{sc.rmse:>10.4g}{sc.heldout_rmse:>10.4g}{sc.bic - mine.bic:>10.1f}{mark}")
        return lines

    def __str__(self) -> str:
        return self.summary()
