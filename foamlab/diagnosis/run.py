"""diagnose(runs): identification's fit as the base model, then the diagnosis."""

from __future__ import annotations

from foamlab import FoamlabError
from foamlab.diagnosis.core import Diagnosis, diagnose_series
from foamlab.diagnosis.data import on_schedule, series_from_run
from foamlab.model import ModelParameters
from foamlab.rundata import RunData


def base_parameters(run: RunData) -> ModelParameters:
    """The paper's model identified on one run (foamlab.identification.fit_run).

    Diagnosis keeps its nonlinear parameters (alpha, beta) and re-solves the linear
    ones jointly with each candidate's parameters.
    """
    from foamlab.identification.fit import fit_run

    return fit_run(run).params


def diagnose(runs: list[RunData], params: ModelParameters | None = None,
             causes: list[str] | None = None) -> Diagnosis:
    """Diagnose one run, or several runs of the same specimen (e.g. at other speeds).

    The base model is identified on the first run (the reference speed) unless
    ``params`` is given; all runs are then fitted together.
    """
    if not runs:
        raise FoamlabError("no run to diagnose")
    names = _names(runs)
    scheduled = [on_schedule(r) for r in runs]
    runs = [r for r, _ in scheduled]
    series = [series_from_run(r, n) for r, n in zip(runs, names)]
    if params is None:
        params = base_parameters(runs[0])
    d = diagnose_series(series, params, causes)
    d.notes += [f"{name}: {n} samples taken off the sampling schedule left out (their instants are unsure)"
                for name, (_, n) in zip(names, scheduled) if n]
    return d


def _names(runs: list[RunData]) -> list[str]:
    out = []
    for i, r in enumerate(runs):
        name = r.source.replace("\\", "/").rsplit("/", 1)[-1] if r.source else f"run {i + 1}"
        if name in out:
            name = f"{name} ({i + 1})"
        out.append(name)
    return out
