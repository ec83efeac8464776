"""The fitted parameters as lmfit names them (value, vary, min/max, tie, stderr) and why each held
one is held; one frozen record per parameter, one ordered set per fit.

Written here rather than taken from lmfit: lmfit's Parameters are mutable and evaluate ties with
an expression interpreter, where a fit report needs a frozen record it saves and loads exactly.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

#: Unit of each parameter family (foamlab.model.params), by name prefix.
UNITS = (("alpha", "1/s"), ("beta", ""), ("k", "N"), ("a", "N/(mm s)"), ("r", "N s^beta/mm"))


def unit_of(name: str) -> str:
    return next((unit for prefix, unit in UNITS if name.startswith(prefix)), "")


def _num(v) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


@dataclass(frozen=True)
class Parameter:
    """One fitted parameter: its value and standard error, the bounds of the search, whether it
    was varied, the parameter it is tied to and why it is held or tied."""

    name: str
    value: float
    stderr: float | None = None           # None: the data do not determine it
    lower: float = -math.inf              # -inf: unbounded
    upper: float = math.inf
    vary: bool = True                     # False: held (a real damping mode, an order held apart)
    unit: str = ""
    tie: str | None = None                # a shared order in a later cycle: the parameter it is
    why: str = ""                         # why it is held or tied ("" when varied freely)
    stderr_ac: float | None = None        # stderr x sqrt(autocorrelation time of the residuals)

    @property
    def determined(self) -> bool:
        """Varied, with a standard error, and its 95 % interval excludes zero."""
        return self.vary and self.stderr is not None and abs(self.value) > 1.96 * self.stderr

    def to_dict(self) -> dict:
        """As `foamlab fit --json` writes it ("varied", "same_as": the names it has always had)."""
        out = {"value": self.value, "stderr": self.stderr, "lower": _num(self.lower),
               "upper": _num(self.upper), "varied": self.vary, "unit": self.unit,
               "determined": self.determined}
        if self.tie:
            out["same_as"] = self.tie
        if self.why:
            out["why"] = self.why
        return out


@dataclass(frozen=True)
class Parameters:
    """The parameters of one fit, in the model's flat order (ModelParameters.names)."""

    entries: tuple[Parameter, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index", {p.name: i for i, p in enumerate(self.entries)})

    @classmethod
    def of(cls, names, values, stderr, lower, upper, vary, stderr_ac, tied: dict[str, str],
           why: dict[str, str]) -> Parameters:
        """From identification's per-name values (stderr nan: not determined)."""
        return cls(tuple(Parameter(n, float(v), _num(s), float(lo), float(hi), bool(var), unit_of(n),
                                   tied.get(n), why.get(n, ""), _num(sa))
                         for n, v, s, lo, hi, var, sa in zip(names, values, stderr, lower, upper, vary, stderr_ac)))

    def __getitem__(self, name: str) -> Parameter:
        return self.entries[self._index[name]]

    def __contains__(self, name: str) -> bool:
        return name in self._index

    def __iter__(self) -> Iterator[str]:
        return (p.name for p in self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def values(self) -> tuple[Parameter, ...]:
        return self.entries

    def items(self) -> list[tuple[str, Parameter]]:
        return [(p.name, p) for p in self.entries]

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.entries]

    def column(self, attribute: str, dtype=float) -> np.ndarray:
        """One attribute of every parameter as an array (None as nan)."""
        return np.array([np.nan if getattr(p, attribute) is None else getattr(p, attribute) for p in self.entries],
                        dtype=dtype)

    @property
    def tied(self) -> dict[str, str]:
        return {p.name: p.tie for p in self.entries if p.tie}
