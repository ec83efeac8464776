"""The fit's optimizer budgets in one frozen object, passed explicitly (DEFAULT unless given).

Why these values: docs/identification.md ("Convergence"). `foamlab fit --full` prints them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from foamlab.analysis.solve import POLISH_NFEV


def _setting(default, meaning: str, **kw):
    return field(default=default, metadata={"meaning": meaning}, **kw)


@dataclass(frozen=True)
class FitSettings:
    """How long the optimizer runs on every sample: a step of the search, and the fit kept."""

    polish_nfev: int = _setting(POLISH_NFEV, "evaluations of a polish on every sample while fits are compared")
    max_nfev: int = _setting(60, "evaluations the kept fit's optimizer is carried on for until it converges")

    def lines(self) -> list[str]:
        """`name = value  (meaning)`, one line each, in declaration order."""
        width = max(len(f.name) for f in fields(self))
        return [f"{f.name:<{width}} = {getattr(self, f.name):<8g} {f.metadata['meaning']}" for f in fields(self)]


#: The values every fit uses unless given others.
DEFAULT = FitSettings()
