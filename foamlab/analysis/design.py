"""The base model as a linear design, extended by the catalogue's effects.

For fixed nonlinear parameters phi (damping exponents alpha_i, fractional orders
beta) the paper's force is linear in its other parameters: elastic k_i, damping
a_i and residual r_ci. Identification's ModelBasis gives that design matrix and
each column's derivative in its own phi (foamlab.analysis.basis). The
effects of foamlab.model.effects act on it as follows:

- memory (memory_lag): each effect's own ``memory_batch`` (a response in time, linear)
  applied to the damping and residual columns and to their derivatives;
- specimen stage (cycle_softening, damping_cycle_change, rate_dependence,
  direction_friction): each effect's own ``modify``, probed with unit components,
  gives a per-sample gain of the elastic, damping and residual components and an
  added force (they are elementwise affine maps: checked on every use);
- contact: the plate cannot pull -- the force is max(total, 0) where the specimen is
  compressed. Handled as an active set: the columns are zeroed where the current
  solution is out of contact, and the set is updated until it is consistent;
- sensor stage (channel_lag, force_zero_drift): each effect's own ``sensor_batch``
  applied to each masked column (affine in the force);
- input stage (machine_compliance): the specimen sees x_s = x - C G, G the force
  the frame deflects under (effects.frame_force of the measured force). Elastic
  columns are evaluated at x_s; the memory operators are linear in the
  displacement history, so their columns at x_s are those of x minus C times
  those of G (exact except where the effect keeps x_s monotone after a turning
  point: a few samples, see tests/test_diagnosis.py).
- the load cell's zero offset (its unloaded reading) is one more linear column per run: each run
  its own zero (another day, another tare), the specimen's parameters shared.

Given the nonlinear vector nu = [phi (when the base is free), effect parameters],
the linear parameters are solved by least squares (variable projection); the
Jacobian in nu is Kaufman's, -(I - P) d(design theta)/d nu, with the phi
columns from ModelBasis' analytic derivatives pushed through the same effects.
The prediction equals ``EffectChain(effects).measured_force`` of the model with
those parameters (tests/test_diagnosis.py checks every effect).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from foamlab.analysis.basis import ModelBasis
from foamlab.analysis.path import PathNodes
from foamlab.model import ModelParameters
from foamlab.model.effects import (
    Components,
    Effect,
    EffectChain,
    frame_force,
    specimen_displacement,
)
from foamlab.model.history import HistoryLabels
from foamlab.model.layout import Layout
from foamlab.model.turns import respond_with, times_after, turn_instants, with_times

#: The active (contact) set is iterated at most this many times per solve.
MAX_CONTACT_ITERATIONS = 12
#: A decimated series keeps every sample within this fraction of a half-cycle after each
#: turning point.
AFTER_TURN_HALF_CYCLE = 0.02
#: Relative eigenvalue cut-off of the (column-scaled) normal equations.
RCOND = 1e-13


# ----------------------------------------------------------------------------- linear algebra

class NormalSolve:
    """min |a theta - b| for a tall, narrow design, by the column-scaled normal equations.

    Why not np.linalg.lstsq: LAPACK's QR/SVD of a tall-skinny matrix runs many times
    slower than A^T A on a busy 2-core machine; with column scaling the normal
    equations keep ~1e-6 relative accuracy in theta, far below the noise in the
    prediction. Zero and redundant columns get the minimum-norm answer. Also gives
    the projection on the design's range (Kaufman's Jacobian).
    """

    def __init__(self, a: np.ndarray):
        scale = np.sqrt(np.einsum("ij,ij->j", a, a))
        scale[scale == 0] = 1.0
        self.scale = scale
        self.a_s = a / scale
        w, v = np.linalg.eigh(self.a_s.T @ self.a_s)
        keep = w > w.max() * RCOND if w.max() > 0 else np.zeros_like(w, dtype=bool)
        self.v = v[:, keep]
        self.w = w[keep]

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, float)
        col = b.ndim > 1
        coef = self.v @ ((self.v.T @ (self.a_s.T @ b)) / (self.w[:, None] if col else self.w))
        return coef / (self.scale[:, None] if col else self.scale)

    def residual_of(self, vectors: np.ndarray) -> np.ndarray:
        """(I - P) vectors, P the orthogonal projection on the design's range."""
        coef = self.v @ ((self.v.T @ (self.a_s.T @ vectors)) / self.w[:, None])
        return vectors - self.a_s @ coef


# ----------------------------------------------------------------------------- runs

@dataclass(eq=False)
class Series:
    """One run as diagnosis sees it: samples, half-cycle labels, crosshead velocity.

    A decimated series (``decimated``) holds every k-th sample (and every turning
    point) of its full series; its model columns are the full model's at those
    samples (operators on a k-times coarser grid), its sensor stage runs on its own
    samples: a cheaper, slightly approximate copy for the parameter search.
    """

    name: str
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray                    # measured force
    labels: HistoryLabels            # of the full series
    velocity: np.ndarray             # crosshead, mm/s, positive compressing
    rate: np.ndarray                 # mean crosshead speed since the cycle started, mm/s
    speed_mm_min: float              # typical crosshead speed while moving
    full: "Series | None" = None     # the full series if this one is decimated
    obs: np.ndarray | None = None    # its samples in the full series
    nodes: PathNodes | None = None   # identification's displacement path with its corner nodes
    x_measured: np.ndarray | None = None   # the displacement as recorded (x: the path; default x)
    y_path: np.ndarray | None = None       # the force smoothed as the path (path.force_path; default y)
    evidence: np.ndarray | None = None     # samples the model is judged on (None: all; see data.py)
    no_contact: np.ndarray | None = None   # measured off the specimen (the unloaded reading)
    _bases: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.t)

    def __getstate__(self) -> dict:
        # its columns stay behind (tens of MB): a copy computes its own (analysis.parallel)
        return {**self.__dict__, "_bases": {}}

    @property
    def source(self) -> "Series":
        return self.full if self.full is not None else self

    @property
    def samples(self) -> np.ndarray:
        return self.obs if self.obs is not None else np.arange(len(self.t))

    @property
    def used(self) -> np.ndarray:
        """The samples fits and statistics use: where the measured displacement determines the
        model's force (all but the few samples around each turning point, see data.py)."""
        return np.ones(len(self.t), dtype=bool) if self.evidence is None else self.evidence

    @property
    def cycle(self) -> np.ndarray:
        return self.source.labels.cycle[self.samples]

    @property
    def direction(self) -> np.ndarray:
        return self.source.labels.direction[self.samples]

    @property
    def step_s(self) -> float:
        return float(np.median(np.diff(self.t))) if len(self.t) > 1 else 1.0

    def frame_force(self, frame_tau_s: float) -> np.ndarray:
        """The force the frame deflects under (machine_compliance), on the full series: at once
        (frame_tau_s = 0), the measured force smoothed as the displacement's path is."""
        key = ("frame", frame_tau_s)
        if key not in self._bases:
            f = self.source
            y = f.y if f.y_path is None or frame_tau_s > 0 else f.y_path
            self._bases[key] = frame_force(f.t, y, frame_tau_s)
        return self._bases[key]

    def basis(self, layout: Layout, x_scale_mm: float, frame_tau_s: float | None = None) -> ModelBasis:
        """Design of the displacement history, or (frame_tau_s given) of the force the frame
        deflects under (machine_compliance subtracts C times its memory columns)."""
        key = (layout, x_scale_mm, frame_tau_s)
        kin = next((v for k, v in self._bases.items() if isinstance(v, ModelBasis) and k[1:] == key[1:]
                    and k[0].same_columns(layout)), None)
        if key not in self._bases and kin is not None:     # another structure of the same cycles
            self._bases[key] = kin.with_layout(layout)
        if key not in self._bases:
            f = self.source
            src = None if frame_tau_s is None else f.frame_force(frame_tau_s)
            if f.nodes is not None:      # identification's path: the base model is identification's
                self._bases[key] = f.nodes.basis(self.samples, layout, x_scale_mm, self.step_s, source=src)
            else:                        # an exact history (tests): the samples are the path
                self._bases[key] = ModelBasis(f.t, f.x if src is None else src, f.labels, self.samples,
                                              layout, x_scale_mm, self.step_s)
        return self._bases[key]

    def turn_basis(self, layout: Layout, x_scale_mm: float, frame_tau_s: float | None = None
                   ) -> tuple[np.ndarray, ModelBasis]:
        """(times, the design there) at finer times than the samples after each turn (model.turns):
        what the memory stage (memory_lag) reads the model's jump at a turn from. As ``basis``: of
        the displacement's path with its nodes, or of the force the frame deflects under."""
        key = ("turns", layout, x_scale_mm, frame_tau_s)
        if key not in self._bases:
            f = self.source
            # the frame's force where frame_tau_s is given, piecewise linear between samples
            src = None if frame_tau_s is None else f.frame_force(frame_tau_s)
            t, x, labels, corners = ((f.nodes.t, f.nodes.along(src), f.nodes.labels, f.nodes.corners)
                                     if f.nodes is not None else (f.t, f.x if src is None else src, f.labels, ()))
            extra = times_after(turn_instants(t, labels), f.step_s, float(self.t[0]), float(self.t[-1]))
            path = with_times(t, x, labels, extra, corners)
            self._bases[key] = (extra, ModelBasis(path.t, path.x, path.labels, path.extra_rows, layout, x_scale_mm,
                                                  self.step_s, path.corners))
        return self._bases[key]

    def specimen_x(self, compliance: float, frame_tau_s: float) -> np.ndarray:
        """machine_compliance's specimen displacement (computed on the full series)."""
        f = self.source
        return specimen_displacement(f.x, f.y, compliance, f.t, frame_tau_s,
                                     frame=f.frame_force(frame_tau_s))[self.samples]

    def decimated(self, k: int) -> "Series":
        """Every k-th sample plus the turning points and every sample in the first
        AFTER_TURN_HALF_CYCLE of a half-cycle after each (k <= 1: self): there the memory
        operators change fastest (the residual switches on with a near-derivative response,
        memory_lag releases the force), and a k-times coarser grid would cut it."""
        if k <= 1 or self.full is not None:
            return self
        if ("decimated", k) in self._bases:     # one copy: its columns are cached with it
            return self._bases[("decimated", k)]
        n = len(self.t)
        turning = np.concatenate([np.asarray(self.labels.starts, int), np.asarray(self.labels.peaks, int)])
        halves = np.diff(np.sort(turning))
        dense = max(1, int(AFTER_TURN_HALF_CYCLE * float(np.median(halves)))) if len(halves) else 1
        after = (turning[:, None] + np.arange(dense + 1)[None, :]).ravel()
        keep = np.unique(np.concatenate([np.arange(0, n, k), turning, after, [n - 1]]))
        keep = keep[(keep >= 0) & (keep < n)]
        out = Series(self.name, self.t[keep], self.x[keep], self.y[keep], self.labels,
                     self.velocity[keep], self.rate[keep], self.speed_mm_min, full=self, obs=keep,
                     evidence=self.used[keep],
                     no_contact=None if self.no_contact is None else self.no_contact[keep])
        self._bases[("decimated", k)] = out
        return out


def specimen_gains(chain: EffectChain, cycle, velocity, rate) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """Per-sample gains of the elastic, damping and residual components and the added force.

    The specimen-stage effects are elementwise affine in the components (each scales a
    component or adds a force), so probing their own ``modify`` with unit components
    gives the whole map; a random probe checks the affinity (a new effect that mixes
    samples or components in another way is refused instead of silently mis-fitted).
    """
    n = len(cycle)
    effects = chain.specimen_effects
    if not effects:
        one = np.ones(n)
        return (one, one, one), np.zeros(n)

    def total(e, d, r):
        c = Components(np.broadcast_to(e, n).astype(float), np.broadcast_to(d, n).astype(float),
                       np.broadcast_to(r, n).astype(float), np.zeros(n), cycle, velocity, rate)
        for eff in effects:
            c = eff.modify(c)
        return np.broadcast_to(c.total, n)

    offset = total(0.0, 0.0, 0.0).copy()
    gains = tuple(total(*unit) - offset for unit in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    kinds = tuple(type(e) for e in effects)
    if kinds not in _AFFINE_CHECKED:
        probe = np.random.default_rng(0).normal(size=(3, n))
        expected = offset + sum(g * p for g, p in zip(gains, probe))
        if not np.allclose(total(*probe), expected, rtol=1e-9, atol=1e-9 * (1 + np.abs(expected).max())):
            raise ValueError("a specimen-stage effect is not an elementwise affine map of the model's "
                             "components; diagnosis cannot project it")
        _AFFINE_CHECKED.add(kinds)
    return gains, offset


#: Chains of specimen-effect classes already checked to be elementwise affine.
_AFFINE_CHECKED: set[tuple[type, ...]] = set()


# ----------------------------------------------------------------------------- the model

@dataclass
class Solution:
    theta: np.ndarray                  # model linear parameters + each run's zero offset
    predictions: list[np.ndarray]      # per series, every sample
    residuals: list[np.ndarray]        # measured - predicted, per series, every sample
    masks: list[np.ndarray]            # contact set per series
    used: list[np.ndarray]             # the samples the model is judged on, per series (Series.used)
    designs: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list, repr=False)
    normal: NormalSolve | None = field(default=None, repr=False)

    @property
    def used_residuals(self) -> list[np.ndarray]:
        """Residuals at the used samples, per series (what every statistic is computed on)."""
        return [r[u] for r, u in zip(self.residuals, self.used)]

    @property
    def residual(self) -> np.ndarray:
        """Residuals at the used samples of every series, concatenated."""
        return np.concatenate(self.used_residuals)

    def rss(self, keep: np.ndarray | None = None) -> float:
        """Sum of squares over the used samples (keep: an index into every sample instead)."""
        r = self.residual if keep is None else np.concatenate(self.residuals)[keep]
        return float(r @ r)


class ExtendedModel:
    """Base model + a chain of effect classes, on one or more runs.

    nu = [phi, eta]: phi the base model's nonlinear parameters (alpha, beta; only if
    ``free_base``, else fixed at ``params``), eta the effects' fitted parameters in
    chain order; ``settings`` holds the effects' fixed values (e.g. a reference speed).
    """

    def __init__(self, series: list[Series], params: ModelParameters,
                 effects: list[type[Effect]] = (), settings: dict[str, dict[str, float]] | None = None,
                 free_base: bool = False, base_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 effect_bounds: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                 masks: list[np.ndarray] | None = None):
        self.series = series
        self.params = params
        self.layout = params.layout
        self.linear0, self.phi0 = self.layout.from_flat(params.to_vector())
        self.effect_types = list(effects)
        self.settings = settings or {}
        self.free_base = free_base
        self.base_bounds = base_bounds
        self.effect_bounds = effect_bounds or {}   # narrower than the effect's own (physics)
        self.n_model = self.layout.n_linear
        self.n_linear = self.n_model + len(series)  # + each run's load-cell zero offset
        lay = self.layout
        self._component = np.array([0] * (lay.P + 1) + [1] * lay.N + [2] * (lay.C * lay.M))
        self._column_of = lay.derivative_pairs[1]      # design column of each derivative column
        # the contact set the first solve starts from (see solve): the set of the model this
        # one extends, when given; a start from the force's sign alone can end the active-set
        # iteration in a worse fixed point than that model had reached
        self._last_masks: list[np.ndarray | None] = list(masks) if masks is not None else [None] * len(series)
        self._cache: tuple | None = None

    # -- parameters
    @property
    def n_phi(self) -> int:
        return self.layout.n_nonlinear if self.free_base else 0

    @property
    def n_eta(self) -> int:
        return sum(len(e.fitted_parameters()) for e in self.effect_types)

    @property
    def n_nonlinear(self) -> int:
        return self.n_phi + self.n_eta

    def split(self, nu) -> tuple[np.ndarray, np.ndarray]:
        nu = np.atleast_1d(np.asarray(nu, float))
        if self.free_base:
            return nu[:self.n_phi], nu[self.n_phi:]
        return self.phi0, nu

    def start(self, eta=()) -> np.ndarray:
        return np.concatenate([self.phi0 if self.free_base else [], np.atleast_1d(eta)]).astype(float)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = [], []
        if self.free_base:
            if self.base_bounds is None:
                raise ValueError("a free base model needs bounds for its nonlinear parameters")
            lo += list(self.base_bounds[0])
            hi += list(self.base_bounds[1])
        for e in self.effect_types:
            b = self.effect_bounds.get(e.name) or e.bounds()
            lo += list(b[0])
            hi += list(b[1])
        return np.array(lo, float), np.array(hi, float)

    def effects(self, eta) -> list[Effect]:
        eta = np.atleast_1d(np.asarray(eta, float))
        out, i = [], 0
        for cls in self.effect_types:
            k = len(cls.fitted_parameters())
            e = cls(**self.settings.get(cls.name, {}))
            out.append(e.with_vector(eta[i:i + k]))
            i += k
        return out

    def parameters(self, nu, theta) -> ModelParameters:
        """The base model's parameters (effects aside) at a solution."""
        phi, _ = self.split(nu)
        flat = self.layout.to_flat(np.asarray(theta[:self.n_model], float), phi)
        return self.params.with_vector(flat)

    # -- columns for one series
    def _columns(self, s: Series, chain: EffectChain, phi, derivative: bool = False):
        """Pre-contact specimen force: design (n, L), offset (n,), specimen x, and with
        derivative the phi-derivative columns (n, D) (Layout.derivative_pairs: each of its own
        design column)."""
        lay, xs_mm = self.layout, self.params.x_scale_mm
        cols, deriv = self._design(lambda tau: s.basis(lay, xs_mm, tau), chain, phi, derivative)
        if chain.compliance:
            x_s = s.specimen_x(chain.compliance, chain.frame_tau_s)
            cols[:, :lay.P + 1] = np.vander(x_s / xs_mm, lay.P + 1, increasing=True)
        else:
            x_s = s.x
        if chain.has_memory:
            cols, deriv = self._memory(s, chain, phi, cols, deriv)
        gains, offset = specimen_gains(chain, s.cycle, s.velocity, s.rate)
        g = np.stack(gains, axis=1)                      # (n, 3)
        cols = cols * g[:, self._component]
        if derivative:
            deriv = deriv * g[:, self._component[self._column_of]]
        return cols, offset, x_s, deriv

    def _design(self, basis_of, chain: EffectChain, phi, derivative: bool):
        """The base's design and, with derivative, its phi-derivative columns from basis_of(None)
        (a basis of the displacement's path), less compliance times those of basis_of(frame_tau_s)
        (the frame's force) under machine_compliance."""
        basis = basis_of(None)
        frame = basis_of(chain.frame_tau_s) if chain.compliance else None
        if self.free_base and not derivative:
            # a free base's Jacobian follows almost every solve: computing the columns with
            # their derivatives fills identification's column cache for both at once
            for b in (basis, frame):
                if b is not None:
                    b.design_derivatives(phi)
        cols = basis.design(phi)
        deriv = basis.design_derivatives(phi) if derivative else None
        if frame is not None:
            cols = cols - chain.compliance * frame.design(phi)
            if derivative:
                deriv = deriv - chain.compliance * frame.design_derivatives(phi)
        return cols, deriv

    def _memory(self, s: Series, chain: EffectChain, phi, cols, deriv):
        """The specimen effects' responses in time (memory_lag) applied to the damping and
        residual columns and their derivatives: linear in each, so column by column, with the
        columns also at finer times after each turn (Series.turn_basis, model.turns)."""
        lay, xs_mm = self.layout, self.params.x_scale_mm
        extra, _ = s.turn_basis(lay, xs_mm)
        fine = lambda tau: s.turn_basis(lay, xs_mm, tau)[1]
        f_cols, f_deriv = self._design(fine, chain, phi, deriv is not None)
        damping, residual = self._component == 1, self._component == 2
        d, r = respond_with(s.t, (cols[:, damping], cols[:, residual]), extra,
                            (f_cols[:, damping], f_cols[:, residual]), chain.memory_batch)
        cols = cols.copy()
        cols[:, damping], cols[:, residual] = d, r
        if deriv is not None:
            comp = self._component[self._column_of]
            dd, dr = respond_with(s.t, (deriv[:, comp == 1], deriv[:, comp == 2]), extra,
                                  (f_deriv[:, comp == 1], f_deriv[:, comp == 2]), chain.memory_batch)
            deriv = deriv.copy()
            deriv[:, comp == 1], deriv[:, comp == 2] = dd, dr
        return cols, deriv

    @staticmethod
    def _sensor(chain: EffectChain, t, force):
        for e in chain.sensor_effects:
            force = e.sensor_batch(t, force)
        return force

    def _through_sensor(self, s: Series, chain: EffectChain, columns: np.ndarray) -> np.ndarray:
        """The sensor stage's linear part applied to each column."""
        if not chain.sensor_effects:
            return columns
        zero = self._sensor(chain, s.t, np.zeros(len(s)))
        out = np.empty_like(columns)
        for j in range(columns.shape[1]):
            out[:, j] = self._sensor(chain, s.t, columns[:, j]) - zero
        return out

    def _measured_design(self, k: int, s: Series, chain: EffectChain, cols, offset, mask):
        """Measured force = M theta + const for a fixed contact set of series k; M's last
        columns are each run's load-cell zero offset (its unloaded reading, there in and out of
        contact): 1 in series k's own."""
        n, p = cols.shape
        m = np.zeros((n, p + len(self.series)))
        m[:, :p] = self._through_sensor(s, chain, cols * mask[:, None])
        m[:, p + k] = 1.0
        const = self._sensor(chain, s.t, offset * mask) if chain.sensor_effects else offset * mask
        return m, const

    # -- solve
    def solve(self, nu=(), keep: list[np.ndarray] | None = None) -> Solution:
        """Linear parameters by least squares on the kept samples, for nonlinear parameters nu.

        The contact set (where the model pushes) is iterated to consistency.
        """
        phi, eta = self.split(nu)
        chain = EffectChain(self.effects(eta))
        columns = []
        for s in self.series:
            cols, offset, x_s, _ = self._columns(s, chain, phi)
            columns.append((s, cols, offset, x_s > 0))
        rows = self.rows(keep)
        keep_all = np.concatenate(rows)
        # the active set starts from the last full solve's (continuation: the set improves as
        # the parameters do), at first from the one this model was made with
        start = [(m if m is not None else compressed & (s.y > 0)) & compressed
                 for m, (s, _, _, compressed) in zip(self._last_masks, columns)]
        best = self._active_set(columns, chain, rows, keep_all, start)
        if keep is None:
            self._last_masks = [m.copy() for m in best.masks]
        return self._predict_unfitted(best, columns, rows, chain)

    def _active_set(self, columns, chain: EffectChain, rows, keep_all, start) -> Solution:
        """Least squares with the contact set iterated to consistency from ``start``, the best
        solution seen kept: after a step, the first iterate (the last solve's set) often fits better
        than the consistent one, and keeping it lets a fit's contact set lag its parameters - which
        restarts from far off need (docs/analysis.md, "The contact set its own solution pushes on")."""
        masks = list(start)
        best = None
        seen: list[list[np.ndarray]] = []
        for _ in range(MAX_CONTACT_ITERATIONS):
            designs = [self._measured_design(k, s, chain, cols, offset, mask)
                       for k, ((s, cols, offset, _), mask) in enumerate(zip(columns, masks))]
            a = np.vstack([m[rows[k]] for k, (m, _) in enumerate(designs)])
            b = np.concatenate([(s.y - c)[rows[k]] for k, ((s, *_), (_, c)) in enumerate(zip(columns, designs))])
            normal = NormalSolve(a)
            theta = normal.solve(b)
            preds = [m @ theta + c for m, c in designs]
            sol = Solution(theta, preds, [s.y - q for (s, *_), q in zip(columns, preds)],
                           list(masks), [s.used for s in self.series], designs, normal)
            if best is None or sol.rss(keep_all) < best.rss(keep_all):
                best = sol
            new_masks = [self._pushes(cols, offset, compressed, theta) for _, cols, offset, compressed in columns]
            # only the fitted rows' contact set shapes the fit: iterate on them alone
            fitted = [m[r] for m, r in zip(new_masks, rows)]
            old = [m[r] for m, r in zip(masks, rows)]
            if all(np.array_equal(a_, b_) for a_, b_ in zip(fitted, old)):
                break
            seen.append(old)
            if any(all(np.array_equal(a_, b_) for a_, b_ in zip(fitted, prev)) for prev in seen):
                break   # the active set cycles: keep the best solution seen
            masks = new_masks
        return best

    def _pushes(self, cols, offset, compressed, theta) -> np.ndarray:
        """Where the plate pushes (EffectChain._contact_force): the specimen's own force positive
        (the effects' added force, friction, acts only there) and the total with it too."""
        own = cols @ theta[:self.n_model]
        return compressed & (own > 0) & (own + offset > 0)

    def _predict_unfitted(self, sol: Solution, prepared, rows, chain: EffectChain) -> Solution:
        """The samples the fit did not use (held out, or not evidence) predicted by the solution:
        their contact set follows from it (the plate pushes where the model's force is
        positive), as in ``predict``, not from an earlier iteration's."""
        theta = sol.theta
        for i, ((s, cols, offset, compressed), r) in enumerate(zip(prepared, rows)):
            if r.all():
                continue
            mask = np.where(r, sol.masks[i], self._pushes(cols, offset, compressed, theta))
            if np.array_equal(mask, sol.masks[i]):
                continue
            m, c = self._measured_design(i, s, chain, cols, offset, mask)
            sol.masks[i], sol.designs[i] = mask, (m, c)
            sol.predictions[i] = m @ theta + c
            sol.residuals[i] = s.y - sol.predictions[i]
        return sol

    def rows(self, keep: list[np.ndarray] | None = None) -> list[np.ndarray]:
        """The least-squares rows per series: the used samples (Series.used), and of those
        the kept ones if ``keep`` is given."""
        used = [s.used for s in self.series]
        return used if keep is None else [u & k for u, k in zip(used, keep)]

    def residual_fn(self, keep: list[np.ndarray] | None = None):
        """(fun, jac) of nu for scipy.optimize.least_squares: residuals on the rows (used and
        kept samples) and Kaufman's variable-projection Jacobian."""
        keep_all = np.concatenate(self.rows(keep))

        def solved(nu):
            key = np.asarray(nu, float).tobytes()
            if self._cache is None or self._cache[0] != key or self._cache[1] is not keep:
                self._cache = (key, keep, self.solve(nu, keep))
            return self._cache[2]

        def fun(nu):
            return np.concatenate(solved(nu).residuals)[keep_all]

        def jac(nu):
            sol = solved(nu)
            d = self.prediction_derivatives(nu, sol)[keep_all]
            return -sol.normal.residual_of(d)

        return fun, jac

    def prediction_derivatives(self, nu, sol: Solution) -> np.ndarray:
        """d(prediction)/d nu at fixed linear parameters and contact set, all samples."""
        phi, eta = self.split(nu)
        chain = EffectChain(self.effects(eta))
        theta = sol.theta
        blocks = []
        for k, (s, mask, (m, const)) in enumerate(zip(self.series, sol.masks, sol.designs)):
            out = np.empty((len(s), self.n_nonlinear))
            if self.free_base:
                _, _, _, deriv = self._columns(s, chain, phi, derivative=True)
                out[:, :self.n_phi] = self._through_sensor(
                    s, chain, self.layout.combine(deriv * (mask[:, None] * theta[self._column_of][None, :])))
            base_pred = m @ theta + const
            for j in range(self.n_eta):
                step = np.zeros(self.n_eta)
                h = 1e-6 * max(abs(eta[j]), 1e-3)
                step[j] = h
                chain_j = EffectChain(self.effects(eta + step))
                cols, offset, _, _ = self._columns(s, chain_j, phi)
                mj, cj = self._measured_design(k, s, chain_j, cols, offset, mask)
                out[:, self.n_phi + j] = (mj @ theta + cj - base_pred) / h
            blocks.append(out)
        return np.vstack(blocks)

    def predict(self, theta, nu=()) -> list[np.ndarray]:
        """Measured force per series for given linear parameters (+ zero offset) and nu."""
        phi, eta = self.split(nu)
        chain = EffectChain(self.effects(eta))
        theta = np.asarray(theta, float)
        out = []
        for k, s in enumerate(self.series):
            cols, offset, x_s, _ = self._columns(s, chain, phi)
            mask = self._pushes(cols, offset, x_s > 0, theta)
            m, const = self._measured_design(k, s, chain, cols, offset, mask)
            out.append(m @ theta + const)
        return out

    def specimen_force(self, nu, theta) -> list[np.ndarray]:
        """The specimen's force per series before contact and sensor (the model's F of Eq. 20,
        evaluated exactly by the columns), for given linear parameters and nu."""
        phi, eta = self.split(nu)
        chain = EffectChain(self.effects(eta))
        theta = np.asarray(theta, float)
        return [cols @ theta[:self.n_model] + offset for s in self.series
                for cols, offset, _, _ in [self._columns(s, chain, phi)]]

    def linear_start(self) -> np.ndarray:
        """The given parameters' linear values, every run's zero offset 0."""
        return np.append(self.linear0, np.zeros(len(self.series)))
