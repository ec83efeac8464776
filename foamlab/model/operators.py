"""Causal memory operators with O(1) cost per sample.

Both operators act on a displacement history x(t) sampled at t_n and taken as
piecewise LINEAR between samples (what a crosshead does between two readings).
Each is a bank of first-order modes with an exact per-step update, so the batch
evaluation (scipy.signal.lfilter on a uniform grid) and the online stepper (one
update per sample, any step) are the same discretisation.

- HereditaryOperator:  z(t) = int_{t0}^t sum_i a_i exp(-alpha_i (t - tau)) x(tau) dtau
  (paper Eq. 9: the kernel acts on the displacement). Complex alpha_i stand for a
  conjugate pair with weight a_i/2 each, so the result is Re(sum a_i z_i): real.
- FractionalOperator:  y(t) = D^beta x(t), Riemann-Liouville with lower terminal t0
  (paper Eq. 10), for x(t0) = 0, written as I^nu xdot with nu = 1 - beta > 0 and
  nu = m + f (m integer, 0 < f <= 1): y = I^m (I^f xdot). I^f has the power kernel
  s^(f-1)/Gamma(f); its last step is integrated exactly and its history by a
  sum of exponentials (SOE). Why by hand: no maintained library offers a streaming
  fractional integral; the SOE is the standard "fast convolution" (trapezoidal rule
  on the Laplace representation s^-g = 1/Gamma(g) int_0^inf u^(g-1) e^(-us) du in
  log u, with the slowest modes lumped into one exact integrator).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.signal import lfilter
from scipy.special import gamma

# Relative accuracy targets of the SOE (see docs/model.md for the measured error).
SOE_STEP = 0.6          # trapezoid step in log(u): discretisation error ~ exp(-pi^2/step) ~ 7e-8
SOE_TAIL = 1e-5         # lumped slow modes: relative error ~ SOE_TAIL^(2-f)
SOE_FAST = 40.0         # fastest mode: exp(-SOE_FAST) negligible after one step

# A clock is treated as uniform (each sample used as is, step = median) when every step
# is within this fraction of the median: acquisition jitter of a few ms at 16 Hz then
# costs ~jitter x rate (um), whereas resampling would cut the turning-point corners.
UNIFORM_RTOL = 0.1


def step_weights(lam: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact step coefficients of z' = -lam z + x for x linear over a step h.

    Returns (E, w_prev, w_new): z_n = E z_{n-1} + w_prev x_{n-1} + w_new x_n.
    Series for small |lam h| avoid the cancellation in 1 - exp(-lam h) (computed only
    where needed: this runs once per simulator step, so numpy calls are counted).
    """
    lam = np.asarray(lam)
    lh = lam * h
    E = np.exp(-lh)
    small = np.abs(lh) < 1e-4
    if small.any():
        safe = np.where(small, 1.0, lam)
        phi0 = np.where(small, h * (1 - lh / 2 + lh**2 / 6), -np.expm1(-lh) / safe)
        phi1_h = np.where(small, h * (0.5 - lh / 6 + lh**2 / 24), (1.0 - phi0 / h) / safe)
    else:
        phi0 = -np.expm1(-lh) / lam
        phi1_h = (1.0 - phi0 / h) / lam
    return E, phi0 - phi1_h, phi1_h


def is_uniform(t: np.ndarray) -> bool:
    if len(t) < 3:
        return True
    d = np.diff(t)
    med = float(np.median(d))
    return med > 0 and bool(np.all(np.abs(d - med) <= UNIFORM_RTOL * med))


class HereditaryOperator:
    """Eq. 9 damping memory: Re sum_i a_i int exp(-alpha_i (t - tau)) x(tau) dtau."""

    def __init__(self, a, alpha):
        self.a = np.asarray(a, dtype=float)
        self.alpha = np.asarray(alpha, dtype=complex)
        self.reset()

    def reset(self) -> None:
        self._z = np.zeros(len(self.a), dtype=complex)
        self._x_prev = 0.0
        self._coef_h, self._coef = None, None

    def step(self, h: float, x: float) -> float:
        """Advance by h seconds to displacement x (relative to the operator's start)."""
        if h > 0:
            if h != self._coef_h:  # a simulator steps with a fixed h: compute once
                self._coef_h, self._coef = h, step_weights(self.alpha, h)
            E, wp, wn = self._coef
            self._z = E * self._z + wp * self._x_prev + wn * x
        self._x_prev = x
        return float(np.real(np.dot(self.a, self._z)))

    def batch(self, h: float, x: np.ndarray) -> np.ndarray:
        """Uniform step h, x[0] at the operator's start (state zero there)."""
        out = np.zeros(len(x))
        if len(x) < 2:
            return out
        for a_i, al in zip(self.a, self.alpha):
            E, wp, wn = step_weights(np.array([al]), h)
            z = lfilter([wn[0], wp[0]], [1.0, -E[0]], x)
            z -= z[0]  # state is zero at the start, whatever x[0] is (x[0] is 0 in use)
            out += np.real(a_i * z)
        return out


class _ModeSteps:
    """Exact step factors of the modes exp(-lam s) for the last step h (shared, see below).

    E = exp(-lam h), phi0 = int_0^h exp(-lam s) ds, phi1_h = the weight of the step's end
    for a linear input (see step_weights). Every order's SOE uses the same decay rates lam for
    given (h_min, t_max) - only the weights c depend on the order - so one computation
    per step serves all the operators of a specimen.
    """

    def __init__(self, lam: np.ndarray):
        self.lam = lam
        self._cached = (None, None)    # one reference: threads sharing it see a consistent pair

    def at(self, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cached = self._cached
        if cached[0] == h:
            return cached[1]
        E, w_prev, w_new = step_weights(self.lam, h)
        parts = (E, w_prev + w_new, w_new)      # (E, phi0, phi1_h)
        self._cached = (h, parts)
        return parts


@functools.lru_cache(maxsize=16)
def _mode_steps(lam: tuple[float, ...]) -> _ModeSteps:
    return _ModeSteps(np.array(lam))


class SumOfExponentials:
    """k(s) = s^(f-1)/Gamma(f) ~ sum_l c_l exp(-lam_l s) for h_min <= s <= t_max.

    Instances are shared (`shared`) by all operators of one order, and the decay rates
    by all orders (_ModeSteps): the step coefficients of a step h - the costly part of
    an online step - are computed once per step for all of a specimen's operators.
    """

    @classmethod
    @functools.lru_cache(maxsize=64)
    def shared(cls, f: float, h_min: float, t_max: float) -> "SumOfExponentials":
        return cls(f, h_min, t_max)

    def coefficients(self, h: float, linear_input: bool):
        """(E, w_prev or b, w_new or None, c*E, h^f) of a step h, cached for the last h."""
        key = (h, linear_input)
        cached = self._cached
        if cached[0] == key:
            return cached[1]
        E, phi0, phi1_h = self._steps.at(h)
        if linear_input:      # z_n = E z_{n-1} + (phi0 - phi1_h) x_{n-1} + phi1_h x_n
            coef = (E, phi0 - phi1_h, phi1_h, self.c * E, h**self.f)
        else:                 # s_n = E s_{n-1} + phi0 u_n (u constant over the step)
            coef = (E, phi0, None, self.c * E, h**self.f)
        self._cached = (key, coef)
        return coef

    def __init__(self, f: float, h_min: float, t_max: float):
        self.f = f
        self._cached = (None, None)
        if f >= 1.0:  # plain integral: a single exact integrator
            self.lam = np.array([0.0])
            self.c = np.array([1.0])
        else:
            g = 1.0 - f
            y_lo = math.log(SOE_TAIL / t_max)
            y_hi = math.log(SOE_FAST / h_min)
            y = np.arange(y_lo, y_hi + SOE_STEP, SOE_STEP)
            pref = math.sin(math.pi * f) / math.pi          # 1/(Gamma(f) Gamma(1-f))
            c = SOE_STEP * pref * np.exp(g * y)
            # the infinite trapezoid sum continues below y_lo with nodes whose modes never
            # decay within t_max: their geometric sum becomes one exact integrator.
            q = math.exp(-g * SOE_STEP)
            tail = SOE_STEP * pref * math.exp(g * y_lo) * q / (1.0 - q)
            self.lam = np.concatenate([[0.0], np.exp(y)])
            self.c = np.concatenate([[tail], c])
        self._steps = _mode_steps(tuple(self.lam))

    def kernel(self, s: np.ndarray) -> np.ndarray:
        return np.exp(-np.outer(s, self.lam)) @ self.c


class FractionalOperator:
    """D^beta x for x piecewise linear, x(t0) = 0 (Riemann-Liouville, lower terminal t0).

    nu = 1 - beta. For nu <= 1: y = I^nu xdot, xdot piecewise constant. For nu > 1:
    y = I^f w with w = I^j x (j plain integrals, exact by the trapezoid rule for the
    first one) and f = nu - j - 1 in (0, 1]; w is taken piecewise linear. Both I^f steps
    integrate the last interval exactly and the history with the SOE.
    """

    def __init__(self, beta: float, h_min: float = 1e-3, t_max: float = 1e4):
        if beta >= 1:
            raise ValueError("fractional order beta must be < 1")
        nu = 1.0 - beta
        if nu <= 1.0 + 1e-12:
            self.linear_input, self.j, f = False, 0, min(nu, 1.0)
        else:
            j = math.ceil(nu - 1.0 - 1e-12) - 1       # integer integrations of x before I^f
            self.linear_input, self.j, f = True, j, nu - 1.0 - j
        self.beta, self.f = beta, f
        self.soe = SumOfExponentials.shared(f, float(h_min), float(t_max))
        self.local = 1.0 / gamma(f + 1.0)
        # exact last-step weight of the linear part of a piecewise-linear input
        self.local_slope = 1.0 / ((f + 1.0) * gamma(f)) if f < 1.0 else 0.5
        self.reset()

    def reset(self) -> None:
        self._online = FractionalBank(self)

    def step(self, h: float, x: float) -> float:
        """Advance by h seconds to x (online; the same numbers as batch())."""
        return float(self._online.step(h, np.array([x]))[0])

    def batch(self, h: float, x: np.ndarray) -> np.ndarray:
        """Uniform step h; x[0] = 0 at the operator's start. Same numbers as step()."""
        return fractional_sum([(1.0, self)], h, x)

    def _input(self, h: float, x: np.ndarray) -> np.ndarray:
        """What I^f integrates: xdot, or w = I^j x (the same for every order of one j)."""
        if not self.linear_input:
            u = np.empty(len(x))
            u[0] = 0.0
            u[1:] = np.diff(x) / h
            return u
        w = np.asarray(x, float)
        for _ in range(self.j):
            w = np.concatenate([[0.0], np.cumsum(0.5 * h * (w[1:] + w[:-1]))])
        return w

    def _last_step(self, h: float, inp: np.ndarray) -> np.ndarray:
        """This order's exact integral of the last step, on its input (_input)."""
        hf = h**self.f
        if not self.linear_input:
            return inp * (self.local * hf)
        dw = np.concatenate([[inp[0]], np.diff(inp)])
        return hf * (inp * self.local - dw * self.local_slope)


def fractional_sum(terms: list[tuple[float, FractionalOperator]], h: float, x: np.ndarray) -> np.ndarray:
    """sum_i r_i D^beta_i x on a uniform step h (x[0] = 0 at the start). Orders that integrate
    the same input (all with nu <= 1; those with the same j above) share the SOE's decay rates,
    so each mode's recursion runs once for them all, weighted by sum_i r_i c_i: a cycle's
    residual terms cost one operator's recursions, not one each (a fit evaluates the model 4-6
    times; docs/benchmarks.md, "The residual form the data choose", session 21)."""
    n = len(x)
    y = np.zeros(n)
    if n < 2:
        return y
    groups: dict[tuple, list[tuple[float, FractionalOperator]]] = {}
    for r, op in terms:
        groups.setdefault((op.linear_input, op.j, op.soe.lam.tobytes()), []).append((r, op))
    for members in groups.values():
        first = members[0][1]
        inp = first._input(h, x)                       # one input for the whole group
        weights = np.zeros(len(first.soe.lam))
        for r, op in members:
            y += r * op._last_step(h, inp)
            weights += r * op.soe.c
        E, wp, wn = step_weights(first.soe.lam, h)
        if not first.linear_input:
            wn, wp = wp + wn, np.zeros_like(wp)        # constant input: the whole step's weight
        for E_l, wn_l, wp_l, c_l in zip(E, wn, wp, weights):
            s = lfilter([wn_l, wp_l], [1.0, -E_l], inp)        # s_n after step n
            y[1:] += c_l * E_l * s[:-1]
    return y


class FractionalBank:
    """Online stepping of several operators of one order D^beta at once (one row each).

    The simulator's specimen runs one operator per residual term of every cycle started,
    all with the same steps: one array update for all of them instead of a Python loop
    over operators (the step's cost is numpy calls, not arithmetic). Row r is an
    operator started at its own time (its input zero until then).
    """

    def __init__(self, order: FractionalOperator, rows: int = 1):
        self.order = order
        n_modes = len(order.soe.lam)
        self._s = np.zeros((rows, n_modes))
        self._x_prev = np.zeros(rows)
        self._ints = np.zeros((order.j, rows))   # running integrals I^1..I^j of x
        self._w_prev = np.zeros(rows)
        self._last = np.zeros(rows)

    @property
    def rows(self) -> int:
        return len(self._x_prev)

    def add_row(self) -> int:
        """A new operator (state zero); returns its row."""
        self._s = np.vstack([self._s, np.zeros((1, self._s.shape[1]))])
        self._x_prev, self._w_prev, self._last = (np.append(a, 0.0) for a in (self._x_prev, self._w_prev, self._last))
        self._ints = np.hstack([self._ints, np.zeros((self.order.j, 1))])
        return self.rows - 1

    def step(self, h: float, x: np.ndarray) -> np.ndarray:
        """Advance every row by h seconds to its input x[row]; returns D^beta x per row."""
        if h <= 0:
            return self._last
        op = self.order
        E, wp, wn, cE, hf = op.soe.coefficients(h, op.linear_input)
        if not op.linear_input:
            u = (x - self._x_prev) / h                 # xdot, constant over the step
            y = u * (op.local * hf) + self._s @ cE
            self._s = self._s * E + np.outer(u, wp)    # wp is b of the constant-input step
        else:
            inp_prev, inp_new = self._x_prev, x
            for i in range(op.j):                      # trapezoid: exact for piecewise-linear x
                old = self._ints[i].copy()
                self._ints[i] = old + 0.5 * h * (inp_prev + inp_new)
                inp_prev, inp_new = old, self._ints[i]
            w = inp_new.copy() if op.j else np.array(x, dtype=float)
            y = hf * (w * op.local - (w - self._w_prev) * op.local_slope) + self._s @ cE
            self._s = self._s * E + np.outer(self._w_prev, wp) + np.outer(w, wn)
            self._w_prev = w
        self._x_prev = np.array(x, dtype=float)
        self._last = y
        return y
