"""Compare model orders (N, M, P) on one run by AIC and BIC."""

from __future__ import annotations

from dataclasses import dataclass

from foamlab.identification.fit import fit_run
from foamlab.identification.result import FitReport
from foamlab.model.layout import Orders
from foamlab.rundata import RunData


@dataclass
class OrderFit:
    orders: Orders
    n_params: int
    rmse: float
    aic: float
    bic: float
    result: FitReport
    best: bool = False


def compare_orders(run: RunData, candidates: list[Orders], known: dict | None = None) -> list[OrderFit]:
    """Fit each candidate (reusing ``known`` results), sorted by BIC, the best marked.

    Both criteria are Gaussian, n ln(SSE/n) + penalty, on the same samples, so they
    compare fits of the same run only. BIC penalises parameters harder (ln n per
    parameter); with autocorrelated residuals both favour too many parameters."""
    known = dict(known or {})
    rows = []
    for orders in dict.fromkeys(candidates):
        result = known.get(orders) or fit_run(run, orders)
        rows.append(OrderFit(orders, result.n_params, result.rmse, result.aic, result.bic, result))
    rows.sort(key=lambda r: r.bic)
    if rows:
        rows[0].best = True
    return rows
