"""Identification: the paper's three-step fit, a joint refinement, honest statistics.

``fit_run(run, orders=(N, M, P), progress=None) -> FitReport`` identifies the combined
model (foamlab.model) from one run; see docs/identification.md.
"""

from foamlab.identification.fit import fit_run
from foamlab.identification.result import FitReport
from foamlab.model.layout import Orders

__all__ = ["FitReport", "Orders", "fit_run"]
