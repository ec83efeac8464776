"""What a diagnosis returns: the candidates it tested (with why each was or was not named)
and the verdict, as typed objects; ``Diagnosis.to_dict()`` is `foamlab diagnose --json`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from foamlab.analysis.design import Series
from foamlab.analysis.noise import Whiteness
from foamlab.analysis.solve import Fit
from foamlab.diagnosis.causes import Cause
from foamlab.diagnosis.residuals import ResidualAnalysis
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings
from foamlab.model import ModelParameters

if TYPE_CHECKING:
    from foamlab.diagnosis.form import FormFinding
    from foamlab.diagnosis.limits import DetectionLimit


@dataclass
class Candidate:
    cause: type[Cause]
    fit: Fit
    before: Fit
    coarse_fit: Fit | None = None      # the same model on the decimated search samples
    share: float = float("nan")        # of the structure left above the noise it explains
    delta_bic: float = float("nan")
    lr_p: float = float("nan")
    passed: bool = False
    reason: str = ""
    heldout_gain_se: float | None = None  # N: standard error of its held-out RMSE gain (rule_heldout)
    effect: int = -1                   # its effect's place in fit's model (a pair's first member: 0)

    @property
    def name(self) -> str:
        return self.cause.name

    @property
    def values(self) -> dict:
        return self.fit.effect_values()[self.effect]

    @property
    def z_score(self) -> float:
        """The effect's first parameter in standard errors from zero (nan: undetermined)."""
        v = self.values
        name = self.cause.effect.fitted_parameters()[0].name
        se = v["stderr"].get(name, float("nan"))
        return abs(v["values"][name]) / se if se and np.isfinite(se) and se > 0 else float("nan")

    def pinned(self, fraction: float) -> str:
        """'' - or which fitted parameter ended within `fraction` of its range of a limit other than zero.

        The optimum lies beyond what the effect can physically be (a damping change that
        would make a later cycle's damping vanish): the data ask for something else, which
        this effect imitates at its limit (docs/analysis.md, "The acceptance rules").
        """
        lo, hi = self.cause.bounds()
        v = self.values["values"]
        for p, a, b in zip(self.cause.effect.fitted_parameters(), lo, hi):
            tol = fraction * (b - a)
            for limit in (a, b):
                if limit != 0 and abs(v[p.name] - limit) <= tol:
                    return f"{p.name} = {v[p.name]:.4g} at the limit of its range ({limit:g})"
        return ""

    def description(self) -> str:
        v = self.values
        return self.cause.describe(v["values"], v["stderr"])

    def gain(self) -> dict:
        return {
            "rmse_before": self.before.rmse,
            "rmse_after": self.fit.rmse,
            "heldout_rmse_before": self.before.heldout_rmse,
            "heldout_rmse_after": self.fit.heldout_rmse,
            "heldout_gain_se": self.heldout_gain_se,
            "delta_bic": self.delta_bic,
        }


@dataclass
class Diagnosis:
    verdict: str
    findings: list[Candidate]
    partial: list[Candidate]               # pass the tests but explain only part of the structure
    tested: list[list[Candidate]]          # every candidate of every round
    skipped: dict[str, str]                # cause -> why it was not tested
    base: Fit
    final: Fit
    base_analysis: ResidualAnalysis
    final_analysis: ResidualAnalysis
    final_whiteness: Whiteness
    explained_share: float
    noise_sigma: float
    series: list[Series]
    params: ModelParameters
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    base_form_reason: str = ""                  # which residual form the base uses, and why
    form_finding: "FormFinding | None" = None   # the other form is what the base got wrong
    settings: DiagnosisSettings = DEFAULT       # the thresholds it was decided by
    limits: list["DetectionLimit"] = field(default_factory=list)   # what this run could have seen

    def to_dict(self) -> dict:
        """The JSON object of `foamlab diagnose --json` (see docs/DESIGN: verdict, findings)."""
        findings = [self.form_finding.to_dict()] if self.form_finding is not None else []
        if self.verdict == "unexplained":
            findings.append({
                "effect": "unexplained",
                "gain": {"rmse_before": self.base.rmse, "rmse_after": self.final.rmse,
                         "heldout_rmse_before": self.base.heldout_rmse,
                         "heldout_rmse_after": self.final.heldout_rmse, "delta_bic": 0.0},
                "where": self.final_analysis.where(),
                "residuals": self.final_analysis.to_dict(),
                "explained_share": self.explained_share,
            })
        for i, c in enumerate(self.findings + self.partial):
            findings.append({
                "effect": c.name,
                "gain": c.gain(),
                "parameters": {k: {"value": v, "stderr": c.values["stderr"].get(k)}
                               for k, v in c.values["values"].items()},
                "description": c.description(),
                "meaning": c.cause.meaning,
                "p_value": c.lr_p,
                "rank": i + 1 + (self.form_finding is not None),
                "named": self.verdict == c.name,
                "explained_share": c.share,
            })
        return {"verdict": self.verdict, "findings": _jsonable(findings),
                "base": {"form": self.params.residual_form, "why": self.base_form_reason,
                         "miss": _jsonable(self.base_analysis.miss().to_dict())},
                "skipped": dict(self.skipped),
                "detection_limits": _jsonable([limit.to_dict() for limit in self.limits])}


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
