"""Diagnosis: what the simulation gets wrong, the likely cause, the extended model, the gain.

    from foamlab.diagnosis import diagnose
    d = diagnose([run])            # RunData list (several runs: same specimen, other speeds)
    d.verdict                      # a cause name, "unexplained" or "none"
    d.to_dict()                    # the JSON of `foamlab diagnose --json`

See core.py for the procedure, causes.py for the catalogue (one class per cause,
the physics in foamlab.model.effects), design.py for how an effect extends the
model, residuals.py for the residual map and noise.py for the statistics.
"""

from foamlab.diagnosis.causes import CAUSES, Cause, register
from foamlab.diagnosis.core import diagnose_prepared
from foamlab.diagnosis.result import Diagnosis
from foamlab.diagnosis.run import diagnose

__all__ = ["CAUSES", "Cause", "Diagnosis", "diagnose", "diagnose_prepared", "register"]
