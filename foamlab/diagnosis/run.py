"""diagnose(runs): identification's fit as the base model, then the diagnosis."""

from __future__ import annotations

from typing import Callable

from foamlab import FoamlabError
from foamlab.analysis.prepared import prepare
from foamlab.analysis.solve import polish
from foamlab.diagnosis.core import diagnose_prepared
from foamlab.diagnosis.form import NAME, base_form_reason, check_other_form
from foamlab.diagnosis.result import Diagnosis
from foamlab.identification import FitResult, fit_run
from foamlab.rundata import RunData

Progress = Callable[[str, float], None]
#: Share of the progress a diagnosis that fits its run gives the fit.
FIT_SHARE = 0.15


def diagnose(runs: list[RunData], fit: FitResult | None = None,
             causes: list[str] | None = None, progress: Progress | None = None,
             form: str = "auto") -> Diagnosis:
    """Diagnose one run, or several runs of the same specimen (e.g. at other speeds).

    fit: identification's fit of the first run (the reference speed), as the run's own
    pipeline made it; identified here when not given. Its core fit is the base model of
    one run; with several runs the base is polished on all of them from its parameters.
    progress: called with (stage, fraction 0..1) as the work advances.
    form: the residual form of the base when it is fitted here ('auto': the data choose).
    A base in a form the user named is checked against the other form first (diagnosis.form).
    """
    report = progress or (lambda stage, fraction: None)
    if not runs:
        raise FoamlabError("no run to diagnose")
    names = _names(runs)
    if fit is None:
        fit = fit_run(runs[0], progress=lambda stage, f: report(f"fit: {stage}", FIT_SHARE * f), form=form)
    if fit.prepared is None:
        raise FoamlabError("the fit given carries no prepared run: fit it with foamlab.identification.fit_run")
    fit, form_finding = check_other_form(fit, lambda stage, f: report(f"the other residual form: {stage}",
                                                                         FIT_SHARE * f))
    fit.prepared.series.name = names[0]
    prepared = [fit.prepared] + [prepare(r, name=n) for r, n in zip(runs[1:], names[1:])]
    if len(prepared) == 1 and fit.core_fit is not None:
        base = fit.core_fit
    else:
        base = polish([p.series for p in prepared], fit.params)
    start = FIT_SHARE if progress else 0.0
    d = diagnose_prepared(prepared, base, causes,
                          progress=lambda stage, f: report(stage, start + (1.0 - start) * f))
    d.base_form_reason = base_form_reason(fit)
    if form_finding is not None:
        d.form_finding, d.verdict = form_finding, NAME
    d.notes += [f"{name}: {p.off_schedule} samples taken off the sampling schedule left out "
                "(their instants are unsure)" for name, p in zip(names, prepared) if p.off_schedule]
    return d


def _names(runs: list[RunData]) -> list[str]:
    out = []
    for i, r in enumerate(runs):
        name = r.source.replace("\\", "/").rsplit("/", 1)[-1] if r.source else f"run {i + 1}"
        if name in out:
            name = f"{name} ({i + 1})"
        out.append(name)
    return out
