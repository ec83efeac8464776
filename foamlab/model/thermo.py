"""Thermodynamic checks of the paper (Eqs. 23-25), evaluated as printed, plus the
stability of the damping kernel (decaying modes), which Eqs. 23-25 do not cover."""

from __future__ import annotations

import numpy as np

from foamlab.model.params import ModelParameters


def thermodynamic_checks(params: ModelParameters) -> dict[str, bool]:
    """k_1 is the slope of the elastic force at x = 0 in N/mm (k_1 / x_scale in our scaling)."""
    k1 = params.elastic_k[1] / params.x_scale_mm if params.order_P >= 1 else 0.0
    a, al = params.damping_a, params.damping_alpha
    mod2 = (al * np.conj(al)).real
    with np.errstate(divide="ignore", invalid="ignore"):
        re_term = np.where(mod2 > 0, a * al.real / mod2, 0.0).sum()
        im_term = np.where(mod2 > 0, a * al.imag / mod2, 0.0).sum()
    return {
        "eq23_storage_nonnegative": bool(k1 - re_term >= 0),
        "eq24_loss_nonnegative": bool(im_term >= 0),
        "eq25_k1_nonnegative": bool(k1 >= 0),
        "damping_modes_decay": bool(np.all(al.real > 0)),
    }
