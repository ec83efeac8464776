"""The model's orders and the flat parameter layout, defined once.

``ModelParameters.to_vector()`` orders the parameters k_0..k_P, then (a_i, Re alpha_i,
Im alpha_i) per damping mode, then (r_cm, beta_cm) per cycle and term. Fitting splits
them into linear ones (the design columns) and nonlinear ones (alpha, beta): ``Layout``
maps between the two, for identification, diagnosis and anything else that fits.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from foamlab import FoamlabError

#: Decay rates are searched over [ALPHA_LO, ALPHA_HI] / (loading time).
ALPHA_LO, ALPHA_HI = 0.1, 100.0
#: Fractional orders are searched in [BETA_LO, BETA_HI] (beta < 1, Eq. 10).
BETA_LO, BETA_HI = -3.0, 0.99


#: Cycles with residual terms of their own by default (the paper's Table 3 has three
#: columns); later cycles reuse the last one's terms, so a long run costs no more parameters.
OWN_RESIDUAL_CYCLES = 3

#: The residual memory's two forms (docs/model.md, "Two forms of the residual force"):
#: 'causal', Eq. 10 continued through later half-cycles; 'paper', each cycle's Eq. 11 as a
#: function of x, added again in every later half-cycle as Eqs. 20b-f print it.
RESIDUAL_FORMS = ("causal", "paper")


def check_form(form: str) -> str:
    if form not in RESIDUAL_FORMS:
        raise FoamlabError(f"residual form {form!r}: expected one of {', '.join(RESIDUAL_FORMS)}")
    return form


@dataclass(frozen=True)
class Orders:
    """Model orders: N damping modes, M residual terms per cycle, elastic polynomial order P,
    C, the cycles with residual terms of their own (later cycles reuse the last one's;
    None: every cycle its own, the paper's per-cycle table), the residual form, and shared: the
    M fractional orders are common to every cycle, each cycle keeps amplitudes of its own (the
    paper's Table 3 finds nearly the same orders in its three cycles)."""

    N: int = 3
    M: int = 3
    P: int = 7
    C: int | None = OWN_RESIDUAL_CYCLES
    form: str = "causal"
    shared: bool = False

    def __post_init__(self) -> None:
        check_form(self.form)
        if self.N < 0 or self.M < 0 or self.P < 1:
            raise FoamlabError(f"orders N={self.N}, M={self.M}, P={self.P}: need N >= 0, M >= 0, P >= 1")
        if self.C is not None and self.C < 1:
            raise FoamlabError(f"orders C={self.C}: at least one cycle has residual terms of its own")
        if self.N > 6 or self.M > 6 or self.P > 12:
            raise FoamlabError(f"orders N={self.N}, M={self.M}, P={self.P}: at most N=6, M=6, P=12 "
                               "(higher orders are not identifiable from one run)")

    @classmethod
    def parse(cls, text: str) -> "Orders":
        """'N,M,P' (e.g. '3,3,7'), 'N,M,P,C' (C cycles with terms of their own), either with
        ',shared' (orders common to every cycle, amplitudes per cycle), or 'paper' (3,3,7 with
        every cycle's own terms, the paper's Table 3 for any number of cycles)."""
        if str(text).strip().lower() == "paper":
            return cls(3, 3, 7, None)
        parts = [p.strip().lower() for p in str(text).split(",")]
        shared = bool(parts) and parts[-1] == "shared"
        try:
            values = [int(v) for v in parts[:len(parts) - shared]]
        except ValueError:
            values = []
        if len(values) not in (3, 4):
            raise FoamlabError(f"orders {text!r}: expected N,M,P or N,M,P,C (integers, e.g. 3,3,7), "
                               "optionally followed by ',shared', or 'paper'")
        return cls(*values, shared=shared)

    def residual_cycles(self, cycles: int) -> int:
        """Cycles with residual terms of their own in a run with this many unloadings."""
        return cycles if self.C is None else max(1, min(self.C, cycles))

    def __str__(self) -> str:
        own = "every cycle" if self.C is None else f"C={self.C}"
        return (f"N={self.N}, M={self.M}, P={self.P}, {own}" + (", shared orders" if self.shared else "")
                + f", {self.form} residual")

    def layout(self, cycles: int) -> "Layout":
        """The flat layout of a run with this many unloadings."""
        return Layout(P=self.P, N=self.N, M=self.M, C=self.residual_cycles(cycles), form=self.form,
                      shared=self.shared)


@dataclass(frozen=True)
class Layout:
    """Where each parameter of ModelParameters' flat vector goes.

    linear:    k_0..k_P, a_1..a_N, r_11..r_CM  (columns of the design matrix, in this order)
    nonlinear: alpha_1 (re, im), ..., alpha_N, beta_11..beta_CM (shared: beta_1..beta_M, each
               the order of its term in every cycle)
    """

    P: int
    N: int
    M: int
    C: int  # cycles with their own residual terms
    form: str = "causal"  # what the residual columns are (RESIDUAL_FORMS)
    shared: bool = False  # one order per residual term for all cycles (amplitudes per cycle)

    @property
    def n_linear(self) -> int:
        return self.P + 1 + self.N + self.C * self.M

    @property
    def n_betas(self) -> int:
        return self.M if self.shared else self.C * self.M

    @property
    def n_nonlinear(self) -> int:
        return 2 * self.N + self.n_betas

    @property
    def n_params(self) -> int:
        return self.n_linear + self.n_nonlinear

    @property
    def n_flat(self) -> int:
        """Length of ModelParameters' flat vector (every cycle's orders, shared or not)."""
        return self.P + 1 + 3 * self.N + 2 * self.C * self.M

    @property
    def orders(self) -> Orders:
        return Orders(N=self.N, M=self.M, P=self.P, C=self.C, form=self.form, shared=self.shared)

    def same_columns(self, other: "Layout") -> bool:
        """Are the columns of one a basis of the other's (the same cycles, elastic order and
        residual form; the orders N, M and their sharing may differ)?"""
        return (self.C, self.P, self.form) == (other.C, other.P, other.form)

    def betas(self, nonlinear: np.ndarray) -> np.ndarray:
        """(C, M): the order of each cycle's terms."""
        beta = np.asarray(nonlinear[2 * self.N:], float)
        return np.tile(beta, (self.C, 1)) if self.shared else beta.reshape(self.C, self.M)

    @cached_property
    def derivative_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(nonlinear parameter, design column) of each derivative column a basis gives
        (ModelBasis.design_derivatives): one per damping parameter and one per cycle and term,
        so a shared order moves the columns of its term in every cycle."""
        damping = np.arange(2 * self.N)
        c, m = np.divmod(np.arange(self.C * self.M), self.M)
        beta = 2 * self.N + (m if self.shared else c * self.M + m)
        parameter = np.concatenate([damping, beta]).astype(int)
        column = np.concatenate([self.P + 1 + damping // 2, self.P + 1 + self.N + c * self.M + m]).astype(int)
        return parameter, column

    def combine(self, per_pair: np.ndarray) -> np.ndarray:
        """(rows, pairs) -> (rows, n_nonlinear): each parameter's derivative columns summed."""
        if not self.shared:
            return per_pair
        rows = per_pair.shape[0]
        out = np.empty((rows, self.n_nonlinear))
        out[:, :2 * self.N] = per_pair[:, :2 * self.N]
        out[:, 2 * self.N:] = per_pair[:, 2 * self.N:].reshape(rows, self.C, self.M).sum(axis=1)
        return out

    def column_of_nonlinear(self, j: int) -> int:
        """Design-matrix column that nonlinear parameter j acts on (a shared order: its term's
        column in the first cycle; derivative_pairs has them all)."""
        if j < 2 * self.N:
            return self.P + 1 + j // 2
        return self.P + 1 + self.N + (j - 2 * self.N)

    def to_flat(self, linear: np.ndarray, nonlinear: np.ndarray) -> np.ndarray:
        """ModelParameters.to_vector() order from (linear, nonlinear)."""
        p1, N, C, M = self.P + 1, self.N, self.C, self.M
        k = linear[:p1]
        a = linear[p1:p1 + N]
        r = linear[p1 + N:].reshape(C, M)
        al = nonlinear[:2 * N].reshape(N, 2)
        beta = self.betas(nonlinear)
        damping = np.column_stack([a, al[:, 0], al[:, 1]]).ravel()
        residual = np.stack([r, beta], axis=-1).ravel()
        return np.concatenate([k, damping, residual])

    def from_flat(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(linear, nonlinear) of a flat vector (shared: the first cycle's orders)."""
        p1, N, C, M = self.P + 1, self.N, self.C, self.M
        flat = np.asarray(flat, float)
        d = flat[p1:p1 + 3 * N].reshape(N, 3)
        res = flat[p1 + 3 * N:].reshape(C, M, 2)
        linear = np.concatenate([flat[:p1], d[:, 0], res[:, :, 0].ravel()])
        beta = res[0, :, 1] if self.shared else res[:, :, 1].ravel()
        nonlinear = np.concatenate([d[:, 1:].ravel(), beta])
        return linear, nonlinear

    def canonical_permutation(self, linear: np.ndarray, nonlinear: np.ndarray) -> np.ndarray:
        """Index into [linear, nonlinear] that puts damping modes in order of decay rate
        (then frequency) and each cycle's residual terms in order of beta: one name per
        mode/term whatever order the optimiser found them in."""
        p1, N, C, M = self.P + 1, self.N, self.C, self.M
        L = self.n_linear
        lin_perm = np.arange(L)
        nl_perm = np.arange(self.n_nonlinear)
        al = np.asarray(nonlinear[:2 * N], float).reshape(N, 2)
        order = np.lexsort((al[:, 1], al[:, 0]))
        lin_perm[p1:p1 + N] = p1 + order
        nl_perm[:2 * N] = (2 * order[:, None] + np.arange(2)).ravel()
        beta = self.betas(nonlinear)
        for c in range(C):
            o = np.argsort(beta[c], kind="stable")
            lin_perm[p1 + N + c * M:p1 + N + (c + 1) * M] = p1 + N + c * M + o
            if not self.shared or c == 0:
                nl_perm[2 * N + c * M:2 * N + (c + 1) * M] = 2 * N + c * M + o
        return np.concatenate([lin_perm, L + nl_perm])

    def flat_index_of_linear(self) -> np.ndarray:
        """Index in the flat vector of each linear parameter (design-column order)."""
        flat = np.arange(self.n_flat, dtype=float)
        lin, _ = self.from_flat(flat)
        return lin.astype(int)

    def flat_index_of_nonlinear(self) -> np.ndarray:
        """Index in the flat vector of each nonlinear parameter (shared: the first cycle's beta)."""
        flat = np.arange(self.n_flat, dtype=float)
        _, nl = self.from_flat(flat)
        return nl.astype(int)

    def tied(self) -> dict[int, int]:
        """Flat index of each order a shared one stands for (later cycles' beta) -> the flat index
        of the parameter it equals (the first cycle's)."""
        if not self.shared:
            return {}
        first = self.flat_index_of_nonlinear()[2 * self.N:]
        p1, N, M = self.P + 1, self.N, self.M
        return {p1 + 3 * N + 2 * (c * M + m) + 1: int(first[m]) for c in range(1, self.C) for m in range(M)}


def nonlinear_bounds(orders: Orders, n_cycles: int, loading_time_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of (alpha_re, alpha_im) x N and beta x (C M) (shared: x M), from the loading time."""
    lo_a, hi_a = ALPHA_LO / loading_time_s, ALPHA_HI / loading_time_s
    betas = orders.M if orders.shared else n_cycles * orders.M
    lower = [lo_a, 0.0] * orders.N + [BETA_LO] * betas
    upper = [hi_a, hi_a] * orders.N + [BETA_HI] * betas
    return np.asarray(lower, float), np.asarray(upper, float)
