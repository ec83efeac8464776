"""FitResult: a fit that reports itself (statistics, standard errors, correlations,
warnings, information criteria), in the spirit of lmfit's MinimizerResult."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import Fit
from foamlab.identification.forms import FormChoice
from foamlab.identification.paper import PaperResult
from foamlab.identification.statistics import GoodnessOfFit
from foamlab.identification.structure import StructureChoice
from foamlab.model import ModelParameters, ModelResponse
from foamlab.model.layout import Orders

#: The steps of Table 5, plus the joint refinement.
STEPS = ("damping", "residual", "elastic", "joint")


#: Unit of each parameter family (foamlab.model.params), by name prefix.
UNITS = (("alpha", "1/s"), ("beta", ""), ("k", "N"), ("a", "N/(mm s)"), ("r", "N s^beta/mm"))
#: The terminal summary lists at most this many warnings (all are in --json and the sidecar).
SUMMARY_WARNINGS = 3
#: The RMSE without the turn samples is shown when it is below this share of the whole run's.
TURNS_SHOWN = 0.9


def unit_of(name: str) -> str:
    return next((unit for prefix, unit in UNITS if name.startswith(prefix)), "")


@dataclass(frozen=True)
class Parameter:
    """One fitted parameter as lmfit reports it: value, standard error, bounds, varied."""

    name: str
    value: float
    stderr: float | None              # None: the data do not determine it
    lower: float                      # -inf: unbounded
    upper: float
    varied: bool                      # False: held fixed (e.g. Im alpha of a real damping mode)
    unit: str
    same_as: str | None = None        # a shared order in a later cycle: the parameter it is

    @property
    def determined(self) -> bool:
        """Varied, with a standard error, and its 95 % interval excludes zero."""
        return self.varied and self.stderr is not None and abs(self.value) > 1.96 * self.stderr

    def to_dict(self) -> dict:
        out = {"value": self.value, "stderr": self.stderr, "lower": _num(self.lower),
               "upper": _num(self.upper), "varied": self.varied, "unit": self.unit,
               "determined": self.determined}
        if self.same_as:
            out["same_as"] = self.same_as
        return out


def _num(v) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


@dataclass(frozen=True)
class TurnSamples:
    """The samples within a step of a turning point that the samples cannot place (predicted, not
    evidence: analysis.path.path_determined) and the fit's RMSE without them."""

    count: int
    rmse_without_N: float          # RMS of measured - fitted over the evidence samples
    max_abs_N: float               # the largest |measured - fitted| among the turn samples

    def to_dict(self) -> dict:
        return {"count": self.count, "rmse_without": _num(self.rmse_without_N), "max_abs": _num(self.max_abs_N)}


@dataclass
class FitResult:
    params: ModelParameters
    orders: Orders
    names: list[str]                  # flat ModelParameters order
    values: np.ndarray
    stderr: np.ndarray                # nan: not determined
    stderr_autocorr: np.ndarray       # stderr x sqrt(autocorrelation time)
    correlation: np.ndarray           # names x names, nan where not determined
    statistics: dict[str, GoodnessOfFit | None]
    rmse: float                       # whole run: RMS of measured - fitted, every sample of the cycles
    constraints: dict[str, bool]
    warnings: list[str]
    aic: float
    bic: float
    n_obs: int
    n_params: int
    autocorrelation_time: float
    contact_zero_N: float             # unloaded load-cell reading (fitted with the rest if used)
    response: ModelResponse           # the model's components at every sample (foamlab.model.evaluate)
    predicted_force_N: np.ndarray     # what the load cell would read: max(model force, unloaded reading)
    observed: np.ndarray              # sample indices the joint fit used
    paper: PaperResult
    notes: list[str] = field(default_factory=list)   # choices the fit made (e.g. a mode made real)
    source: str = ""
    elapsed_s: float = 0.0
    starts: list[str] = field(default_factory=list)
    run_time_s: np.ndarray | None = None
    run_displacement_mm: np.ndarray | None = None
    run_force_N: np.ndarray | None = None
    lower: np.ndarray | None = None   # bounds of each parameter in the search (flat order; +-inf: none)
    upper: np.ndarray | None = None
    varied: np.ndarray | None = None  # bool, flat order: False for parameters held fixed
    status: int = 0                   # the final optimizer's (scipy least_squares): > 0 converged
    message: str = ""
    noise_N: float = float("nan")     # the load cell's noise level estimated from the run
    prepared: PreparedRun | None = None   # the run as prepared for every fit (foamlab.analysis)
    core_fit: Fit | None = None           # the analysis core's fit: what diagnosis extends
    free_core: Fit | None = None          # where orders were held apart (identification.apart): the
                                          # fit with them free, diagnosis' base (all terms free)
    form_choice: FormChoice | None = None  # which residual form, and why (identification.forms)
    alternatives: list["FitResult"] = field(default_factory=list)   # the other forms' fits
    structure: StructureChoice | None = None   # the structures tried and the one chosen (or forced)
    tied: dict[str, str] = field(default_factory=dict)   # shared orders: later cycle's beta -> first's
    largest: "FitResult | None" = None   # the largest structure's fit when another was chosen (diagnosis' base)
    turns: TurnSamples | None = None     # the samples at turns the samples cannot place, and the RMSE without them

    # -- views -----------------------------------------------------------------------
    @property
    def predicted(self) -> np.ndarray:
        return self.predicted_force_N

    @property
    def residual_N(self) -> np.ndarray:
        """Measured minus fitted force at every sample of the run."""
        return self.run_force_N - self.predicted_force_N

    @property
    def success(self) -> bool:
        """The final optimizer converged (not stopped by its iteration budget)."""
        return self.status > 0

    @property
    def parameters(self) -> dict[str, Parameter]:
        n = len(self.names)
        lower = self.lower if self.lower is not None else np.full(n, -np.inf)
        upper = self.upper if self.upper is not None else np.full(n, np.inf)
        varied = self.varied if self.varied is not None else np.ones(n, bool)
        return {name: Parameter(name, float(v), _num(s), float(lo), float(hi), bool(var), unit_of(name),
                                self.tied.get(name))
                for name, v, s, lo, hi, var in zip(self.names, self.values, self.stderr, lower, upper, varied)}

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def standard_error(self, name: str) -> float | None:
        return _num(self.stderr[self.names.index(name)])

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
                "noise": _num(self.noise_N),
                "optimizer": {"success": self.success, "status": self.status, "message": self.message},
                "turn_samples": self.turns.to_dict() if self.turns is not None else None,
                "form": self.params.residual_form, "forms": self._forms_dict(),
                "structure": self.structure.to_dict() if self.structure is not None else None,
                "warnings": list(self.warnings), "notes": list(self.notes)}

    def _forms_dict(self) -> dict:
        """Each form's RMSE, held-out RMSE, BIC and its BIC minus the chosen one's, and why."""
        choice = self.form_choice
        if choice is None:
            return {"chosen": self.params.residual_form, "reason": "", "scores": []}
        mine = choice.score(choice.chosen)
        return {"chosen": choice.chosen, "reason": choice.reason(), "forced": choice.forced,
                "scores": [{"form": s.form, "rmse": _num(s.rmse), "heldout_rmse": _num(s.heldout_rmse),
                            "bic": _num(s.bic), "delta_bic": _num(s.bic - mine.bic) if mine else None}
                           for s in choice.scores]}

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def sidecar_dict(self) -> dict:
        """What is stored beside the run: the JSON object plus the model (so the file
        loads with ModelParameters.load as a simulator specimen) and the rest."""
        out = self.to_dict()
        corr = [[_num(c) for c in row] for row in self.correlation]
        out.update({
            "model": self.params.to_dict(),
            "orders": {"N": self.orders.N, "M": self.orders.M, "P": self.orders.P, "C": self.orders.C,
                       "form": self.orders.form, "shared": self.orders.shared},
            "stderr_autocorrelation_corrected": {n: _num(s) for n, s in zip(self.names, self.stderr_autocorr)},
            "autocorrelation_time": _num(self.autocorrelation_time),
            "correlation": {"names": self.names, "matrix": corr},
            "warnings": list(self.warnings),
            "notes": list(self.notes),
            "aic": _num(self.aic), "bic": _num(self.bic),
            "n_obs": self.n_obs, "n_params": self.n_params,
            "contact_zero_N": _num(self.contact_zero_N),
            "source": self.source,
            "elapsed_s": _num(self.elapsed_s),
        })
        return out

    def save(self, path: str | Path) -> Path:
        """Write the sidecar JSON (atomically: a reader never sees half a file)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.sidecar_dict(), indent=2), encoding="utf-8")
        tmp.replace(path)
        return path

    # -- text ---------------------------------------------------------------------------
    def brief(self) -> str:
        """What a terminal shows: fit quality, the parameters the data determine, the warnings
        that matter most (the full report is ``summary()``, --json and the sidecar)."""
        joint = self.statistics.get("joint")
        ratio = self.rmse / self.noise_N if self.noise_N > 0 else float("nan")
        lines = [f"fit of {self.source or 'run'}: orders {self.orders}, {self.n_obs} samples, {self.elapsed_s:.2f} s",
                 f"  {self.form_choice.reason() if self.form_choice else self.params.residual_form + ' residual form'}",
                 f"  RMSE {self.rmse:.4g} N = {ratio:.2f} x the load cell's noise ({self.noise_N:.3g} N)"
                 + (f", R^2 {joint.r2:.6f}" if joint is not None else ""),
                 f"  optimizer: {'converged' if self.success else 'stopped'} ({self.message})"]
        if self.turns is not None and self.turns.count and self.turns.rmse_without_N < TURNS_SHOWN * self.rmse:
            t = self.turns
            lines.insert(3, f"  without the {t.count} samples at turns the samples cannot place (predicted, not "
                            f"evidence; up to {t.max_abs_N:.3g} N off): RMSE {t.rmse_without_N:.4g} N = "
                            f"{t.rmse_without_N / self.noise_N:.2f} x the noise")
        if self.structure is not None:
            lines.append(f"  structure: {self.structure.why}"
                         + (f" ({len(self.structure.candidates)} tried, see --full)" if self.structure.candidates else ""))
        own = [p for p in self.parameters.values() if not p.same_as]
        params = [p for p in own if p.determined]
        hidden = len(own) - len(params)
        shared = " (each order beta1_m is every cycle's: shared orders)" if self.tied else ""
        lines.append(f"  parameters the data determine ({len(params)} of {len(own)}; "
                     f"{hidden} fixed, not determined or within 2 standard errors of zero: see --full or --json)"
                     f"{shared}:")
        for p in params:
            lines.append(f"    {p.name:<11}{p.value:>13.5g} +/- {p.stderr:<10.2g} {p.unit}")
        held = [p for p in own if not p.varied and p.name.startswith("beta")]
        if held:       # identification.apart
            lines.append("  orders held apart, not fitted (their terms coalesce; the data determine their sum): "
                         + ", ".join(f"{p.name} {p.value:.3g}" for p in held))
        failed = [k for k, ok in self.constraints.items() if not ok]
        if failed:
            lines.append("  thermodynamic checks failed: " + ", ".join(failed))
        if self.warnings:
            lines.append(f"  warnings ({len(self.warnings)}; the first {min(SUMMARY_WARNINGS, len(self.warnings))}):")
            lines += [f"    - {w}" for w in self.warnings[:SUMMARY_WARNINGS]]
        return "\n".join(lines)

    def summary(self) -> str:
        """A readable report: statistics per step (Table 5), parameters, checks, warnings."""
        lines = [f"[[Fit]] {self.source or 'run'}",
                 f"    orders            {self.orders}",
                 f"    residual form     {self.form_choice.reason() if self.form_choice else self.params.residual_form}",
                 f"    samples fitted    {self.n_obs}  (parameters {self.n_params})",
                 f"    RMSE (whole run)  {self.rmse:.4g} N",
                 f"    AIC / BIC         {self.aic:.1f} / {self.bic:.1f}",
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
        for n, v, s, sa in zip(self.names, self.values, self.stderr, self.stderr_autocorr):
            if n in self.tied:
                lines.append(f"    {n:<11}{v:>14.6g}{'= ' + self.tied[n] + ' (shared orders)':>33}")
            elif n in self._fixed_names():
                why = "(fixed: real mode)" if n.startswith("alpha") else "(held apart: see notes)"
                lines.append(f"    {n:<11}{v:>14.6g}{why:>33}")
            elif math.isfinite(s):
                rel = f"{abs(s / v) * 100:8.1f}%" if v != 0 else f"{'-':>9}"
                lines.append(f"    {n:<11}{v:>14.6g}{s:>12.3g}{rel}{sa:>12.3g}")
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
        if self.notes:
            lines.append("[[Notes]]")
            lines += [f"    - {w}" for w in self.notes]
        if self.warnings:
            lines.append("[[Warnings]]")
            lines += [f"    - {w}" for w in self.warnings]
        return "\n".join(lines)

    def _forms_lines(self) -> list[str]:
        """Each residual form's RMSE, held-out RMSE and BIC against the chosen one's."""
        choice = self.form_choice
        if choice is None or len(choice.scores) < 2:
            return []
        mine = choice.score(choice.chosen)
        lines = ["[[Residual form]] (both fitted; the one predicting held-out blocks better kept)",
                 f"    {'form':<10}{'RMSE':>10}{'held-out':>10}{'dBIC':>10}"]
        for sc in choice.scores:
            mark = "  (kept)" if sc.form == choice.chosen else ""
            lines.append(f"    {sc.form:<10}{sc.rmse:>10.4g}{sc.heldout_rmse:>10.4g}{sc.bic - mine.bic:>10.1f}{mark}")
        return lines

    def _fixed_names(self) -> set[str]:
        if self.varied is not None:
            return {n for n, v in zip(self.names, self.varied) if not v}
        return {note.split(" ", 1)[0] for note in self.notes if "(fixed)" in note}

    def __str__(self) -> str:
        return self.summary()
