"""The combined model as a linear combination of columns (variable projection).

F(t) = sum_i k_i (x/x_s)^i + sum_i a_i Re z_i(t; alpha_i) + sum_{c,m} r_cm y_cm(t; beta_cm)

is LINEAR in k, a and r; only alpha (damping) and beta (residual) enter nonlinearly,
and each column depends on one alpha or one beta. So for given (alpha, beta) the
best (k, a, r) is one linear least-squares solve, and a column's derivative with
respect to its own nonlinear parameter is all the Jacobian needs.

The columns are the model's own components (foamlab.model), evaluated as
``evaluate`` does: each cycle's memory runs on a uniform grid from the cycle's
start (x relative to x at that start), damping is switched on over the cycle's
loading, and the residual of cycle c from its peak on (cycles beyond the
identified ones reuse the last cycle's terms). The damping column is the model's
HereditaryOperator recursion (its step coefficients imported, not copied), run
with a complex state so that its derivative in alpha comes with it. The fractional column is the exact Riemann-Liouville
derivative of the piecewise-linear displacement (the same quantity as the
model's FractionalOperator, which approximates it by a sum of exponentials):
sum_j ds_j (t - t_j)^nu / Gamma(nu + 1), a convolution done by FFT, with the
FFT of the slope changes cached per cycle - about 20x cheaper than the SOE
operator and with an analytic derivative in beta. tests/test_identification.py
checks that the columns times the parameters reproduce ``evaluate``.

A coarser step than the run's (``step_s``) gives the same model on a decimated
grid (the operators are continuous in time): the fit runs there and is polished
at full resolution.
"""

from __future__ import annotations

import copy
from functools import partial

import numpy as np
from scipy import fft as sfft
from scipy.signal import lfilter
from scipy.special import digamma, gammaln

from foamlab.model.components import residual_static
from foamlab.model.history import HistoryLabels
from foamlab.model.layout import Layout
from foamlab.model.operators import (
    step_weights,  # the model's exact step coefficients (one definition)
)

#: Relative step for the derivative of the damping step coefficients in alpha.
ALPHA_FD_STEP = 1e-6
#: Samples on each side of a corner of x kept as exact nodes of the fractional operator.
CORNER_SAMPLES = 1
#: Samples between the operators' grid nodes: what a line between the nodes misses of the
#: sources this many grid nodes before them is added exactly (the memory's cusp after a corner).
NEAR_STEPS = 16
#: ...and of the turning points this many grid steps before them: a turn's slope change is
#: large, and what the line misses of it decays slowly for orders near 1 (the kernel's
#: curvature as lag^(nu - 2)); few turns lie within this reach, so it costs little.
TURN_REACH_STEPS = 256
#: Nodes this close after a grid node (a share of the step) are exact nodes (_just_after_nodes).
JUST_AFTER_STEPS = 0.02
#: Turning points x grid nodes up to which every turning point's term is exact at every node
#: (a 3-cycle run with turns between samples: 6 x 14 000; 20 cycles: 40 x 23 000).
EXACT_SOURCE_NODES = 200_000
#: Where it runs on the path's nodes (_Damping: a stop before a turn), the damping recursion takes
#: the steps as stretches of steps equal within EQUAL_STEP_RTOL (lfilter each: a Python step per
#: stretch) when there are fewer than MAX_STRETCHES, else every step its own factor (_recursion).
EQUAL_STEP_RTOL = 1e-6
MAX_STRETCHES = 64
#: A varying-step recursion is solved in chunks of at most this much decay of its memory (e^-30:
#: 1 / P stays far from overflow), each step's factor at least TINY_DECAY (exp underflows to 0).
CHUNK_DECAY = 30.0
TINY_DECAY = 1e-250
#: Cached operator outputs are cleared beyond this many entries or bytes (a long run's
#: full-resolution columns are ~1 MB each: a count alone let a 20-cycle fit hold ~0.5 GB).
CACHE_LIMIT = 512
CACHE_BYTES = 32 * 2 ** 20


class _Interp:
    """Linear interpolation from a uniform grid (start t0, step h) to fixed times."""

    def __init__(self, t0: float, h: float, times: np.ndarray, n_grid: int):
        pos = (times - t0) / h
        pos = np.clip(pos, 0.0, n_grid - 1)
        i0 = np.minimum(np.floor(pos + 1e-9).astype(int), max(n_grid - 2, 0))
        self.i0 = i0
        self.w = np.clip(pos - i0, 0.0, 1.0)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """y: (n_grid,) or (n_grid, K)."""
        if len(y) == 1:
            return np.repeat(y[:1], len(self.i0), axis=0)
        w = self.w if y.ndim == 1 else self.w[:, None]
        return (1.0 - w) * y[self.i0] + w * y[self.i0 + 1]


class _Damping:
    """Cycle k's loading, from its start to its peak, on a uniform grid from the start with the
    peak on it (the step shortened to a whole number of steps), interpolated to the samples: at
    the run's own step that is the model's exact step at every sample to ~2e-7 of the peak
    (tests/test_fit_reproduces.py) - except where the crosshead stops before it turns (a corner
    of the path inside the loading), which the grid cuts (2e-4 N on the real Bluehill file).
    There, at the run's own step, the recursion runs on the path's nodes themselves, each step
    its own length: what SpecimenState, the simulator's specimen, computes."""

    def __init__(self, t, x, start: int, peak: int, obs: np.ndarray, h: float, corners=()):
        self.rows = np.flatnonzero((obs >= start) & (obs <= peak))
        own_step = len(t) > 1 and h <= (1.0 + EQUAL_STEP_RTOL) * float(np.median(np.diff(t)))
        if own_step and any(start < c < peak for c in corners):
            steps = np.diff(t[start:peak + 1])
            # a regular clock: stretches of equal steps (lfilter); a jittery one: every step its own
            self.stretches = _equal_stretches(steps) or [(0, len(steps), steps)]
            self.xk = x[start:peak + 1] - x[start]
            # the samples are nodes: no interpolation (a partial, not a lambda: bases are pickled)
            self.interp = partial(np.take, indices=obs[self.rows] - start, axis=0)
            return
        duration = float(t[peak] - t[start])
        n = max(int(np.ceil(duration / h - 1e-9)), 1)
        step = duration / n if duration > 0 else h
        grid_t = t[start] + step * np.arange(n + 1)
        grid_t[-1] = t[peak]
        self.stretches = [(0, n, step)]
        self.xk = np.interp(grid_t, t, x) - x[start]
        self.interp = _Interp(float(t[start]), step, t[obs[self.rows]], len(grid_t))

    def columns(self, alpha: complex, derivative: bool):
        """Re z for a unit a (Eq. 9 kernel on the displacement, the model's exact step
        for piecewise-linear x: z_n = E z_n-1 + w_p x_n-1 + w_n x_n, as in
        HereditaryOperator) and, with derivative, d/d(alpha_re), d/d(alpha_im)
        by differentiating that recursion (z is analytic in alpha)."""
        eps = ALPHA_FD_STEP * max(abs(alpha), 1e-3)
        at = np.array([alpha, alpha + eps, alpha - eps] if derivative else [alpha], dtype=complex)
        xk = self.xk
        if len(self.stretches) == 1 and np.ndim(self.stretches[0][2]) == 0:   # one step: as batch()
            E_all, wp_all, wn_all = step_weights(at, self.stretches[0][2])
            z = lfilter([wn_all[0], wp_all[0]], [1.0, -E_all[0]], xk)
            dz = None
            if derivative:
                dE, dwp, dwn = ((c[1] - c[2]) / (2 * eps) for c in (E_all, wp_all, wn_all))
                u = np.zeros(len(z), dtype=complex)
                u[1:] = dE * z[:-1] + dwp * xk[:-1] + dwn * xk[1:]
                dz = lfilter([1.0], [1.0, -E_all[0]], u)
        else:
            z, dz = self._stretched(at, eps, derivative)
        col = self.interp(z.real)
        if not derivative:
            return col, None, None
        return col, self.interp(dz.real), self.interp(-dz.imag)

    def _stretched(self, at: np.ndarray, eps: float, derivative: bool):
        """The recursion and its derivative over stretches of steps (an array: each its own)."""
        xk = self.xk
        z = np.zeros(len(xk), dtype=complex)
        dz = np.zeros(len(xk), dtype=complex) if derivative else None
        for lo, hi, h in self.stretches:             # steps lo..hi-1: nodes lo -> hi
            E_all, wp_all, wn_all = step_weights(at[:, None] if np.ndim(h) else at, h)
            E, wp, wn = E_all[0], wp_all[0], wn_all[0]
            z[lo + 1:hi + 1] = _recursion(E, wp * xk[lo:hi] + wn * xk[lo + 1:hi + 1], z[lo])
            if derivative:
                dE, dwp, dwn = ((c[1] - c[2]) / (2 * eps) for c in (E_all, wp_all, wn_all))
                u = dE * z[lo:hi] + dwp * xk[lo:hi] + dwn * xk[lo + 1:hi + 1]
                dz[lo + 1:hi + 1] = _recursion(E, u, dz[lo])
        return z, dz


def _recursion(E, u: np.ndarray, z0: complex) -> np.ndarray:
    """z_n = E_n z_n-1 + u_n for n = 1..len(u) from z0. One E: lfilter. An E per step (steps
    of unequal length): in chunks over which the product P of the E falls by at most
    e^-CHUNK_DECAY, z_n = P_n (z0 + sum_k u_k / P_k) (no loop over steps; the chunks keep 1 / P
    finite)."""
    if not len(u):
        return np.zeros(0, dtype=complex)
    if np.ndim(E) == 0:
        # lfilter's state of y_n = u_n + E y_n-1 after the node before: E y_0
        return lfilter([1.0], [1.0, -E], u, zi=[E * z0])[0]
    E = np.where(np.abs(E) < TINY_DECAY, TINY_DECAY, E)
    decay = np.cumsum(-np.log(np.abs(E)))
    out = np.empty(len(u), dtype=complex)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(np.floor(decay / CHUNK_DECAY))) + 1, [len(u)]])
    for a, b in zip(bounds[:-1], bounds[1:]):
        P = np.cumprod(E[a:b])
        out[a:b] = P * (z0 + np.cumsum(u[a:b] / P))
        z0 = out[b - 1]
    return out


def _equal_stretches(steps: np.ndarray) -> list[tuple[int, int, float]] | None:
    """The steps as stretches of equal steps (first step, end, step) when they fall into at most
    MAX_STRETCHES (a regular clock, a few missed samples, a few steps at a stop); else None."""
    if not len(steps) or not steps.min() > 0:
        return None
    new = np.flatnonzero(np.abs(np.diff(steps)) > EQUAL_STEP_RTOL * steps[1:]) + 1
    if len(new) >= MAX_STRETCHES:
        return None
    bounds = np.concatenate([[0], new, [len(steps)]])
    return [(int(a), int(b), float(np.mean(steps[a:b]))) for a, b in zip(bounds[:-1], bounds[1:])]


def _slope_changes(t, x, start: int, grid_t: np.ndarray, grid_x: np.ndarray, j0: int, turning,
                   later_starts, tol: float):
    """The memory's nodes from the start on (grid nodes from j0, and the turning points that
    are not grid nodes) and each node's slope change ds, summed over the memories begun."""
    tk, h = float(t[start]), grid_t[1] - grid_t[0]
    # turning points at or after the start that are not grid nodes
    # (a node after the grid's end reaches no row: rows lie on the grid's span)
    tp = np.asarray([i for i in turning if tk - tol <= t[i] <= grid_t[-1] + tol], dtype=int)
    tp_t = t[tp]
    off = np.abs((tp_t - grid_t[0]) / h - np.round((tp_t - grid_t[0]) / h)) * h > tol
    off |= tp_t <= tk + tol            # the start is always its own node
    tp, tp_t = tp[off], tp_t[off]
    node_t = np.concatenate([grid_t[j0:], tp_t])
    node_u = np.concatenate([grid_x[j0:], x[tp]]) - x[start]
    is_grid = np.concatenate([np.ones(len(grid_t) - j0, bool), np.zeros(len(tp), bool)])
    grid_idx = np.concatenate([np.arange(j0, len(grid_t)), np.full(len(tp), -1)])
    order = np.argsort(node_t, kind="stable")
    node_t, node_u, is_grid, grid_idx = node_t[order], node_u[order], is_grid[order], grid_idx[order]
    slopes = np.diff(node_u) / np.diff(node_t)
    ds = np.zeros(len(node_t))
    if len(slopes):
        ds[0] = slopes[0]
        ds[1:len(slopes)] = np.diff(slopes)
    if len(later_starts) and len(slopes):
        # memory k adds its initial slope at its start and every slope change after it
        at = np.searchsorted(node_t, t[np.asarray(later_starts, int)] - tol)
        begun = 1 + np.searchsorted(np.sort(at), np.arange(len(node_t)), side="left")
        ds[1:] *= begun[1:]
        np.add.at(ds, at[at < len(slopes)], slopes[at[at < len(slopes)]])
    return node_t, ds, is_grid, grid_idx


class _Fractional:
    """D^beta of (x - x(t_k)) from cycle k's start t_k, at the observed samples after its peak.

    x is taken piecewise linear on the nodes: a uniform grid (step h, shared by all
    cycles) plus the turning points at their exact times (a corner between grid
    nodes would otherwise be cut, and the residual is switched on right at one). Then
    D^beta x(t) = sum_n ds_n (t - t_n)_+^nu / Gamma(nu + 1) over the nodes' slope
    changes ds_n (the cycle's start is a node: x - x(t_k) is zero before it). Grid
    sources by FFT convolution, turning-point sources directly; samples between grid nodes
    from the line through their nodes, corrected by what it misses of the near sources.
    """

    def __init__(self, t, x, start: int, peak: int, obs: np.ndarray, grid_t: np.ndarray,
                 grid_x: np.ndarray, turning: np.ndarray, later_starts=(), rows: np.ndarray | None = None):
        """later_starts: starts of later cycles whose memories share this one's terms: the sum
        of their D^beta, each from its own start, is one convolution (the slope changes
        counted once per memory that has begun). rows: observed rows to evaluate (default:
        those after the peak)."""
        h = grid_t[1] - grid_t[0]
        tol = 1e-6 * h
        tk = float(t[start])
        self.rows = np.flatnonzero(obs > peak) if rows is None else np.asarray(rows, int)
        obs_t = t[obs[self.rows]]
        on_grid = grid_t > tk + tol
        j0 = int(np.argmax(on_grid)) if on_grid.any() else len(grid_t)
        node_t, ds, is_grid, grid_idx = _slope_changes(t, x, start, grid_t, grid_x, j0, turning,
                                                       later_starts, tol)
        n = len(grid_t)
        self.h, self.n = h, n
        self.d_grid = np.zeros(n)
        self.d_grid[grid_idx[is_grid]] = ds[is_grid]
        self.src_t, self.src_ds = node_t[~is_grid], ds[~is_grid]
        self.log_m_h = np.log(h * np.arange(1, n))
        self.nfft = sfft.next_fast_len(2 * n - 1, real=True)
        # where each observed sample's value comes from: a grid node, or between two nodes their
        # line, corrected by what it misses of the sources near before the sample (all the
        # turning points, the last NEAR_STEPS grid nodes): after a corner the memory has a cusp,
        # (t - t_c)^nu, that a line through the nodes cuts (10 x the noise on a 20-cycle run
        # decimated 8-fold, whose samples right after each turn are kept); sources further back
        # are smooth over a step
        pos = (obs_t - grid_t[0]) / h
        near = np.round(pos).astype(int)
        exact = np.abs(pos - near) * h <= tol
        self.at_grid = np.flatnonzero(exact)
        self.at_grid_idx = np.clip(near[exact], 0, n - 1)
        self.between = np.flatnonzero(~exact)
        bt = obs_t[~exact]
        self.interp = _Interp(float(grid_t[0]), h, bt, n)
        i0 = self.interp.i0
        window = i0[:, None] - np.arange(NEAR_STEPS)[None, :]
        self.near_grid = np.clip(window, 0, n - 1)
        self.near_valid = window >= 0
        a, b = grid_t[i0], grid_t[np.minimum(i0 + 1, n - 1)]
        src_tau, src_ds = _near_sources(self.src_t, self.src_ds, bt, b, TURN_REACH_STEPS * h)
        tau = np.hstack([grid_t[self.near_grid], src_tau])
        self.missed = _Missed(bt, a, b, self.interp.w, tau)
        # each near source's slope change (the grid's in the window, the turning points' in it)
        self.near_ds = np.hstack([self.d_grid[self.near_grid] * self.near_valid, src_ds])
        # grid nodes whose value is used, and the turning points' terms there
        used = np.union1d(self.at_grid_idx, np.concatenate([i0, i0 + 1]))
        self.used = np.clip(used, 0, n - 1).astype(int)
        # each turning point's term exact at every node after it where that is affordable (every
        # run of a few cycles: what the identification and diagnosis tests were tuned on; their edge
        # cases moved with the split's 1e-5 N). Beyond, a turning point's term far after it is
        # smooth over a grid step: there it is its two neighbouring nodes' (shares 1 - w, w), in the
        # convolution; within TURN_REACH_STEPS after it the nodes get the exact term (_NearNodes).
        # Every turning point at every node grew with cycles x samples (50 cycles: 3.6 of 18 s)
        self.exact = len(self.src_t) * len(self.used) <= EXACT_SOURCE_NODES
        split = 0.0
        if self.exact:
            self.lag_src_grid = _Lags(grid_t[None, self.used] - self.src_t[:, None])
        else:
            split, self.near_nodes = _NearNodes.of(grid_t, self.src_t, self.src_ds, TURN_REACH_STEPS)
        self.d_hat = sfft.rfft((self.d_grid + split)[:-1], self.nfft)

    def columns(self, betas: np.ndarray, derivative: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """D^beta on the observed rows for each beta (rows x M) and, with derivative,
        d/dbeta of each. All kernels go through one batched FFT."""
        nu = 1.0 - np.asarray(betas, float)
        m = len(nu)
        lg = gammaln(nu + 1.0)
        kern = np.exp(nu[:, None] * self.log_m_h[None, :] - lg[:, None])   # (m h)^nu / Gamma(nu+1)
        psi = None
        if derivative:
            # d/dbeta of lag^nu / Gamma(nu + 1) = -(log lag - psi(nu + 1)) * value
            psi = digamma(nu + 1.0)
            kern = np.vstack([kern, -kern * (self.log_m_h[None, :] - psi[:, None])])
        missed = self.missed.values(nu, lg, psi)
        if self.exact:
            near = self.lag_src_grid.power(nu, lg)
            if derivative:
                near = np.concatenate([near, self.lag_src_grid.dbeta(near, psi)])
        else:
            near = self.near_nodes.values(nu, lg, psi)
        out = self._assemble(kern, near, missed)
        return (out[:, :m], out[:, m:]) if derivative else (out, None)

    def _assemble(self, kern, near, missed) -> np.ndarray:
        K = kern.shape[0]
        y = np.zeros((K, self.n))
        spec = self.d_hat[None, :] * sfft.rfft(kern, self.nfft, axis=1)
        y[:, 1:] = sfft.irfft(spec, self.nfft, axis=1)[:, :self.n - 1]
        if self.exact:
            if len(self.src_t):
                y[:, self.used] += np.einsum("ksu,s->ku", near, self.src_ds)
        else:
            for k in range(K):
                y[k] += self.near_nodes.at_nodes(near[k], self.n)
        out = np.empty((len(self.rows), K))
        out[self.at_grid] = y[:, self.at_grid_idx].T
        if len(self.between):
            out[self.between] = self.interp(y.T) + np.einsum("krs,rs->rk", missed, self.near_ds)
        return out


def _near_sources(src_t: np.ndarray, src_ds: np.ndarray, t: np.ndarray, b: np.ndarray,
                  reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The turning points near before each sample (before its next grid node b, at most reach
    before t), padded to one width: (rows, S) times and slope changes. Sources further back are
    smooth over a grid step, as the grid's own beyond NEAR_STEPS; taking every turning point for
    every sample made a 20-cycle run's columns grow with the square of its cycles. Padding sits
    after b (every lag negative: no term) with no slope change."""
    if not len(src_t):
        return np.zeros((len(t), 0)), np.zeros((len(t), 0))
    lo = np.searchsorted(src_t, t - reach, side="left")
    count = np.maximum(np.searchsorted(src_t, b, side="left") - lo, 0)
    width = int(count.max()) if len(count) else 0
    valid = np.arange(width)[None, :] < count[:, None]
    idx = np.clip(lo[:, None] + np.arange(width)[None, :], 0, len(src_t) - 1)
    tau = np.where(valid, src_t[idx], (b + 1.0)[:, None])
    return tau, np.where(valid, src_ds[idx], 0.0)


class _NearNodes:
    """The turning points' exact terms at the grid nodes within reach after each, less the share
    of their neighbouring nodes the convolution gives them there (pairs of a source and a node)."""

    def __init__(self, node: np.ndarray, ds: np.ndarray, missed: _Missed):
        self.node, self.ds, self.missed = node, ds, missed

    @classmethod
    def of(cls, grid_t: np.ndarray, src_t: np.ndarray, src_ds: np.ndarray, reach: int
           ) -> tuple[np.ndarray, _NearNodes]:
        """(each source's slope change split onto its two neighbouring nodes, the near pairs)."""
        n, h = len(grid_t), grid_t[1] - grid_t[0]
        split = np.zeros(n)
        j = np.clip(np.floor((src_t - grid_t[0]) / h).astype(int), 0, max(n - 2, 0))
        w = np.clip((src_t - grid_t[j]) / h, 0.0, 1.0)
        np.add.at(split, j, (1.0 - w) * src_ds)
        np.add.at(split, np.minimum(j + 1, n - 1), w * src_ds)
        # the pairs: every node from the source's right neighbour to reach steps after it
        k = (j[:, None] + 1 + np.arange(reach)[None, :]).ravel()
        s = np.repeat(np.arange(len(src_t)), reach)
        keep = k < n
        k, s = k[keep], s[keep]
        # K(node - source) - (1 - w) K(node - left) - w K(node - right), as _Missed at the node
        lags = np.stack([grid_t[k] - src_t[s], grid_t[k] - grid_t[j[s]], grid_t[k] - grid_t[np.minimum(j[s] + 1, n - 1)]])
        weights = np.stack([np.ones(len(k)), -(1.0 - w[s]), -w[s]])
        return split, cls(k, src_ds[s], _Missed.of_lags(lags[:, :, None], weights[:, :, None]))

    def values(self, nu: np.ndarray, log_gamma: np.ndarray, psi: np.ndarray | None = None) -> np.ndarray:
        """(len(nu), pairs), then as many again for d/dbeta when psi is given; times the slope changes."""
        return self.missed.values(nu, log_gamma, psi)[:, :, 0] * self.ds[None, :]

    def at_nodes(self, values: np.ndarray, n: int) -> np.ndarray:
        return np.bincount(self.node, weights=values, minlength=n)


class _Missed:
    """For samples at t between grid nodes a and b (t = a + w h) and sources at tau: what the line
    between the nodes misses of each source's term, K(t - tau) - (1 - w) K(a - tau) - w K(b - tau),
    K(u) = u_+^nu / Gamma(nu + 1), and its derivative in beta (the three lags in one array)."""

    def __init__(self, t: np.ndarray, a: np.ndarray, b: np.ndarray, w: np.ndarray, tau: np.ndarray):
        self.lags = _Lags(np.stack([u[:, None] - tau for u in (t, a, b)]))       # (3, rows, sources)
        self.weights = np.stack([np.ones_like(w), -(1.0 - w), -w])[:, :, None]    # (3, rows, 1)

    @classmethod
    def of_lags(cls, lags: np.ndarray, weights: np.ndarray) -> _Missed:
        """From its three lags (3, rows, sources) and their weights (3, rows, 1) directly."""
        out = cls.__new__(cls)
        out.lags, out.weights = _Lags(lags), weights
        return out

    def values(self, nu: np.ndarray, log_gamma: np.ndarray, psi: np.ndarray | None = None) -> np.ndarray:
        """(len(nu), rows, sources), then as many again for d/dbeta when psi is given."""
        power = np.exp(nu[:, None, None, None] * self.lags.log[None] - log_gamma[:, None, None, None]) * self.lags.mask
        out = np.einsum("kirs,irs->krs", power, np.broadcast_to(self.weights, power.shape[1:]))
        if psi is None:
            return out
        dpower = -power * (self.lags.log[None] - psi[:, None, None, None])
        return np.concatenate([out, np.einsum("kirs,irs->krs", dpower, np.broadcast_to(self.weights, power.shape[1:]))])


class _Static:
    """The paper form's residual of cycle k (Eq. 11 in x, model.components.residual_static)
    at the observed samples after its peak: no memory, so no grid and no convolution."""

    def __init__(self, t, x, start: int, peak: int, obs: np.ndarray):
        self.rows = np.flatnonzero(obs > peak)
        self.x_rel = x[obs[self.rows]] - x[start]
        self.stroke, self.period = float(x[peak] - x[start]), 2.0 * float(t[peak] - t[start])

    def columns(self, betas: np.ndarray, derivative: bool) -> tuple[np.ndarray, np.ndarray | None]:
        return residual_static(self.x_rel, self.stroke, self.period, betas, derivative)


class _Lags:
    """Positive time lags (others contribute nothing) as logs, for lag^nu terms."""

    def __init__(self, lag: np.ndarray):
        self.mask = lag > 0
        self.log = np.log(np.where(self.mask, lag, 1.0))

    def power(self, nu: np.ndarray, log_gamma: np.ndarray) -> np.ndarray:
        """(len(nu), *lag.shape): lag^nu / Gamma(nu + 1)."""
        return np.exp(nu[:, None, None] * self.log[None] - log_gamma[:, None, None]) * self.mask

    def dbeta(self, power: np.ndarray, psi: np.ndarray) -> np.ndarray:
        return -power * (self.log[None] - psi[:, None, None])


class _ColumnCache(dict):
    """Columns by (kind, rate/order): bounded in entries and bytes (a long run's columns are big)."""

    nbytes = 0

    def store(self, key, value) -> None:
        size = sum(v.nbytes for v in value if v is not None)
        if len(self) >= CACHE_LIMIT or self.nbytes + size > CACHE_BYTES:
            self.clear()
            self.nbytes = 0
        self[key] = value
        self.nbytes += size


def _just_after_nodes(t: np.ndarray, t0: float, step_s: float) -> np.ndarray:
    """Nodes a jittered clock put just after a grid node (by at most JUST_AFTER_STEPS of a step):
    the line between grid nodes would move the path's corner there onto the grid node, whose
    memory at the sample, a lag of microseconds later, is a cusp (lag^nu): 1.7e-6 of the peak
    on the real Bluehill file, whose clock is 10-30 us off its 50 Hz. Few on any clock that
    keeps its rate; each is an exact node."""
    phase = (t - t0) / step_s
    after = (phase - np.floor(phase + 1e-6)) * step_s
    return np.flatnonzero((after > 1e-6 * step_s) & (after <= JUST_AFTER_STEPS * step_s) & (t > t0))


class ModelBasis:
    """Design matrix of the model at the observed samples ``obs`` of a run.

    step_s: the operators' grid step (the run's own step for full resolution, a
    multiple of it for the decimated fit). corners: sample indices where x has a
    corner other than the labels' turning points (the start of a dwell).
    """

    def __init__(self, t: np.ndarray, x: np.ndarray, labels: HistoryLabels, obs: np.ndarray,
                 layout: Layout, x_scale_mm: float, step_s: float, corners=()):
        self.t = np.asarray(t, float)
        self.x = np.asarray(x, float)
        self.obs = np.asarray(obs, dtype=int)
        self.layout = layout
        self.x_scale_mm = float(x_scale_mm)
        self.n_obs = len(self.obs)
        starts, peaks = list(labels.starts), list(labels.peaks)
        t_end = float(self.t[self.obs].max()) if self.n_obs else float(self.t[-1])
        t0 = float(self.t[starts[0]]) if starts else float(self.t[0])
        n_grid = int(np.ceil((t_end - t0) / step_s - 1e-9)) + 1
        grid_t = t0 + step_s * np.arange(max(n_grid, 2))
        grid_x = np.interp(grid_t, self.t, self.x)
        # the samples around each corner of x (turning points, and where a dwell
        # begins) are nodes too: the fractional derivative near a corner depends on
        # how the samples there cut it
        turning = np.unique(np.concatenate(
            [np.arange(i - CORNER_SAMPLES, i + CORNER_SAMPLES + 1) for i in starts + peaks + list(corners)]
            or [np.zeros(0, int)]))
        turning = turning[(turning >= 0) & (turning < len(self.t))]
        turning = np.union1d(turning, _just_after_nodes(self.t, t0, step_s))
        self.damping_parts = [_Damping(self.t, self.x, s, p, self.obs, step_s, corners)
                              for s, p in zip(starts, peaks)]
        self.residual_parts = self._residual_parts(starts, peaks, grid_t, grid_x, turning)
        xs = self.x[self.obs] / self.x_scale_mm
        self.elastic = np.vander(xs, layout.P + 1, increasing=True)
        self._cache = _ColumnCache()

    def with_layout(self, layout: Layout) -> ModelBasis:
        """The same basis for another layout of the same columns (Layout.same_columns: other
        orders N, M, shared or not): the operators and their cached columns are shared, so the
        structures a selection tries cost their solves, not their columns again."""
        if not layout.same_columns(self.layout):
            raise ValueError("another layout of a basis must keep its cycles, elastic order and form")
        other = copy.copy(self)
        other.layout = layout
        return other

    def _residual_parts(self, starts, peaks, grid_t, grid_x, turning) -> list[tuple[int, float, _Fractional]]:
        """(layout cycle, sign, part) of each residual memory (paper form: of each cycle's Eq. 11,
        later cycles on the last one's terms). Cycles up to the layout's last
        have a part each; the last and every later cycle share its terms, so their memories
        are one convolution from the last's start (each later one's own start and slope
        changes counted as they begin) minus, on each later cycle's loading, that cycle's own
        memory (not yet switched on there): the cost stays linear in the cycles."""
        last = self.layout.C - 1
        if self.layout.form == "paper":
            return [(min(k, last), 1.0, _Static(self.t, self.x, s, p, self.obs)) for k, (s, p) in enumerate(zip(starts, peaks))]
        parts = [(k, 1.0, _Fractional(self.t, self.x, s, p, self.obs, grid_t, grid_x, turning))
                 for k, (s, p) in enumerate(zip(starts[:last], peaks[:last]))]
        if len(starts) <= last:
            return parts
        later = list(zip(starts[last + 1:], peaks[last + 1:]))
        parts.append((last, 1.0, _Fractional(self.t, self.x, starts[last], peaks[last], self.obs, grid_t,
                                             grid_x, turning, later_starts=[s for s, _ in later])))
        for s, p in later:
            loading = np.flatnonzero((self.obs >= s) & (self.obs <= p))
            if not len(loading):
                continue
            # its memory on the grid from its own start to its peak (a grid from the run's start
            # would make the later cycles cost cycles^2)
            h = grid_t[1] - grid_t[0]
            first = max(int(np.searchsorted(grid_t, self.t[s], side="right")) - 1, 0)
            end = max(int(np.searchsorted(grid_t, self.t[p] + h, side="right")), first + 2)
            parts.append((last, -1.0, _Fractional(self.t, self.x, s, p, self.obs, grid_t[first:end],
                                                  grid_x[first:end], turning, rows=loading)))
        return parts

    # -- columns -----------------------------------------------------------------
    def damping_column(self, alpha: complex, derivative: bool = False):
        """Column of a_i (unit a) and, with derivative, d/d(alpha_re), d/d(alpha_im)."""
        key = ("d", complex(alpha))
        hit = self._cache.get(key)
        if hit is not None and (hit[1] is not None or not derivative):
            return hit
        col = np.zeros(self.n_obs)
        d_re = np.zeros(self.n_obs) if derivative else None
        d_im = np.zeros(self.n_obs) if derivative else None
        for part in self.damping_parts:
            if not len(part.rows):
                continue
            c, dr, di = part.columns(alpha, derivative)
            col[part.rows] = c
            if derivative:
                d_re[part.rows], d_im[part.rows] = dr, di
        out = (col, d_re, d_im)
        self._store(key, out)
        return out

    def residual_columns(self, c: int, betas, derivative: bool = False):
        """Columns of r_{c,1..M} (unit r, cycle c 0-based; later cycles beyond the
        identified ones add to the last) and, with derivative, each d/dbeta."""
        betas = np.atleast_1d(np.asarray(betas, float))
        key = ("r", c, betas.tobytes())
        hit = self._cache.get(key)
        if hit is not None and (hit[1] is not None or not derivative):
            return hit
        col = np.zeros((self.n_obs, len(betas)))
        dcol = np.zeros((self.n_obs, len(betas))) if derivative else None
        for k, sign, part in self.residual_parts:
            if k != c or not len(part.rows):
                continue
            y, dy = part.columns(betas, derivative)
            col[part.rows] += sign * y
            if derivative:
                dcol[part.rows] += sign * dy
        out = (col, dcol)
        self._store(key, out)
        return out

    def _store(self, key, value) -> None:
        self._cache.store(key, value)

    # -- design matrix -----------------------------------------------------------------
    def _alphas(self, nonlinear: np.ndarray) -> np.ndarray:
        N = self.layout.N
        al = np.asarray(nonlinear[:2 * N], float).reshape(N, 2)
        return al[:, 0] + 1j * al[:, 1]

    def design(self, nonlinear: np.ndarray) -> np.ndarray:
        lay = self.layout
        out = np.empty((self.n_obs, lay.n_linear))
        out[:, :lay.P + 1] = self.elastic
        j = lay.P + 1
        for al in self._alphas(nonlinear):
            out[:, j] = self.damping_column(al)[0]
            j += 1
        betas = lay.betas(nonlinear)
        for c in range(lay.C):
            out[:, j:j + lay.M] = self.residual_columns(c, betas[c])[0]
            j += lay.M
        return out

    def design_derivatives(self, nonlinear: np.ndarray) -> np.ndarray:
        """(n_obs, pairs): for each (parameter, column) of Layout.derivative_pairs, the column's
        derivative in its parameter (Layout.combine sums a shared order's over its cycles)."""
        lay = self.layout
        out = np.empty((self.n_obs, len(lay.derivative_pairs[0])))
        for i, al in enumerate(self._alphas(nonlinear)):
            _, d_re, d_im = self.damping_column(al, derivative=True)
            out[:, 2 * i], out[:, 2 * i + 1] = d_re, d_im
        betas = lay.betas(nonlinear)
        j = 2 * lay.N
        for c in range(lay.C):
            out[:, j:j + lay.M] = self.residual_columns(c, betas[c], derivative=True)[1]
            j += lay.M
        return out

    def force(self, linear: np.ndarray, nonlinear: np.ndarray) -> np.ndarray:
        return self.design(nonlinear) @ linear
