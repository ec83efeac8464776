"""The paper's combined model, defined once (used by identification, diagnosis and the simulator).

F = E(x) + V_D (loading half-cycles) + sum_k V_Rk (from the first unloading of cycle k on);
see docs/model.md for the equations as implemented and the choices made where the
paper is inconsistent.
"""

from foamlab.model.components import (
    damping_closed_form,
    elastic_force,
    residual_eq11,
    rl_derivative_piecewise_linear,
)
from foamlab.model.history import HistoryLabels, label_history, labels_from_extrema
from foamlab.model.operators import FractionalOperator, HereditaryOperator
from foamlab.model.params import ModelParameters
from foamlab.model.response import ModelResponse, closed_form, evaluate, triangular_history
from foamlab.model.state import ComponentForces, SpecimenState, stepped_force
from foamlab.model.thermo import thermodynamic_checks

__all__ = [
    "ComponentForces", "FractionalOperator", "HereditaryOperator", "HistoryLabels",
    "ModelParameters", "ModelResponse", "SpecimenState", "stepped_force", "closed_form", "damping_closed_form",
    "elastic_force", "evaluate", "label_history", "labels_from_extrema", "residual_eq11",
    "rl_derivative_piecewise_linear", "thermodynamic_checks", "triangular_history",
]
