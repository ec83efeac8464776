"""An independent generator of compression runs with known truth (the combined model).

Why independent: this module does not import or call any of foamlab's model code
(``foamlab.model``, ``foamlab.identification``, ``foamlab.diagnosis``, ``simulator``).
It writes the model of docs/model.md again, from the paper's equations, in a different
form: closed forms on the ideal triangular history, evaluated on integer sample indices.
(``foamlab.rundata.RunData`` is imported lazily, only to hand a run over.)
``tests/test_independent_model.py`` checks these closed forms against brute-force
quadratures written here too (Grünwald-Letnikov sums, adaptive quadrature), and
against foamlab's own model on the same parameters.

History (Eq. 7, the paper's protocol): ``n`` triangular cycles at constant crosshead
rate v to the stroke A (a fraction of the specimen height) and back to 0, no dwell,
sampled at 16 Hz, in continuous time: the motion starts at t0 (``start_s``, a phase
within the first sample step drawn from the seed unless given) and turns at
t0 + j A/v, which in general lies BETWEEN samples, as on a real machine. Cycle k
(0-based) starts at t_k = t0 + k T, T = 2 A / v, and peaks at t_k + T/2; it is loading
for t_k <= t <= t_k + T/2 (an instant at the peak is loading) and unloading after, up
to the next start; x = 0 before t0 and after t0 + n T. The ``*_GRID`` regimes put the
turning points on samples (t0 = 0, A / v * fs an integer).

Components (x in mm, t in s, F in N):

* Elastic, Eq. 12 in the scaled variable: E(x) = sum_{i=0..7} k_i (x / A)^i.
  The truth's k_i are the least-squares degree-7 polynomial (k_0 = 0) of a foam
  stress-strain law sigma(eps) = sp tanh(E0 eps / sp) + sd (eps / 0.8)^m times the area
  (linear region, plateau, densification); the polynomial *is* the truth.
* Damping, Eq. 9 (the kernel on the displacement, docs/model.md inconsistency 1), on
  loading samples only, from the cycle's start (x(t_k) = 0 on this history):
  V_D(t) = Re sum_i a_i int_0^u exp(-alpha_i s) (x(t - s) - x(t_k)) ds,  u = t - t_k.
  For the ramp x(t - s) = v (u - s) this is v sum_i a_i [u M0_i(u) - M1_i(u)] with the
  kernel's moments M0 = int_0^u e^{-alpha s} ds = (1 - e^{-alpha u})/alpha and
  M1 = int_0^u s e^{-alpha s} ds = (1 - (1 + alpha u) e^{-alpha u})/alpha^2.
  A complex alpha is a conjugate pair with a/2 each: the real part (inconsistency 2).
* Residual, Eq. 10, causal: from the first unloading sample of cycle k on, to the end
  of the run, V_Rk(t) = sum_i r_ki D^{beta_ki} [x - x(t_k)](t), Riemann-Liouville with
  lower terminal t_k (the start of cycle k's loading). y = x - x(t_k) is piecewise
  linear, y = sum_j ds_j (t - c_j)_+ with corners c_0 = t_k (+v), c_j = t_k + j T/2
  (-2v at peaks, +2v at later starts, +v at the run's end t = nT where x stays 0), and
  D^beta (t - c)_+ = (t - c)_+^{1-beta} / Gamma(2 - beta) (any beta < 1; beta < 0 is the
  fractional integral), so V_Rk = sum_i r_ki sum_j ds_j (t - c_j)_+^{1-beta_ki} / Gamma(2 - beta_ki).
  In cycle k's own unloading this is Eq. 11; in later half-cycles it is the causal
  continuation (docs/model.md inconsistency 5), not the paper's Eq. 20c-f reading.
  Cycles beyond the rows of r/beta reuse the last row.
  ``form="paper"`` (Eqs. 20b-f as printed): V_Rk is the same function of x in every
  half-cycle after cycle k's peak: the value cycle k's own unloading has at that x. Written
  here as the corner sum of cycle k's own triangle alone (corners t_k: +v, t_k + T/2: -2v)
  at the instant tau(x) = t_k + T - x/v of its unloading where it passes x - not as Eq. 11's
  closed form in x.
* Total, Eq. 20a-f: F = E + V_D [loading] + sum_{k: past its peak} V_Rk.
* Load cell: reads max(F, 0) (contact loss: the plate cannot pull the foam), plus a
  constant zero offset and Gaussian noise sigma (0.15 N); the displacement is exact,
  quantised to 1 um (the encoder's resolution).

Regimes (``REGIMES``; neither is the default specimen of configs/specimens/default.toml,
whose orders are (-0.1, 0.4, 0.8), damping 1/30 s^-1 and 0.15 +- 0.25j, 58 mm at 23.6 mm/min):

* A: 100x100x62 mm soft foam (E0 80 kPa, plateau 5 kPa, densification 20 kPa (eps/0.8)^4),
  80 % = 49.6 mm at 60 mm/min (793.6 samples a half-cycle); damping: two real decaying
  modes a = (0.042, 0.11) N/(mm s), alpha = (0.05, 0.5) 1/s (35 N at the peak); residual
  orders (0.9, 0.7, -0.35), (0.88, 0.68, -0.33), (0.86, 0.66, -0.30) for cycles 1..3 with
  r = (5, 2, -0.15), then 10 % and 5 % of it; zero offset +0.3 N. Peaks 286/269/263 N,
  contact lost 2.3/3.6/5.1 mm before the end of the unloadings, regained at 0.9/1.3 mm.
* B: 100x100x76 mm foam with a stiffer densification (E0 120 kPa, plateau 8 kPa,
  densification 34 kPa (eps/0.8)^6), 80 % = 60.8 mm at 90 mm/min (648.53 samples a half);
  damping: a real mode (a 0.03, alpha 0.04) and a decaying complex pair (a 0.06,
  alpha 0.25 +- 0.4j); residual orders (0.8, 0.45, -0.4), (0.78, 0.4, -0.35),
  (0.75, 0.35, -0.3), r = (3, 1.5, -0.15) then 10 % and 5 %; zero offset -0.2 N.
  Peaks 446/428/419 N, contact lost at 2.7/4.3/6.0 mm, regained at 1.6/2.3 mm.

Both: Gaussian load-cell noise 0.15 N, displacement quantised to 1 um, elastic scale
x_s = A (what ``foamlab fit`` uses by default: the run's largest compression).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SAMPLING_HZ = 16.0
NOISE_N = 0.15
QUANTUM_MM = 0.001
#: Instants closer than this are the same (a sample at a turning point computed in floating point).
EPS_S = 1e-9


def foam_law_polynomial(*, E0_kPa: float, plateau_kPa: float, densification_kPa: float,
                        densification_power: float, area_mm2: float, height_mm: float,
                        stroke_mm: float, order: int = 7) -> tuple[float, ...]:
    """k_0..k_order [N] of sum k_i (x/A)^i, least squares (k_0 = 0) to the foam law."""
    s = np.linspace(0.0, 1.0, 400)                     # x / A
    eps = s * stroke_mm / height_mm
    sigma_kPa = plateau_kPa * np.tanh(E0_kPa * eps / plateau_kPa) + densification_kPa * (eps / 0.8) ** densification_power
    force = sigma_kPa * 1e3 * area_mm2 * 1e-6           # kPa * mm^2 -> N
    basis = np.vander(s, order + 1, increasing=True)[:, 1:]
    k, *_ = np.linalg.lstsq(basis, force, rcond=None)
    return (0.0,) + tuple(float(c) for c in k)


@dataclass(frozen=True)
class Regime:
    name: str
    height_mm: float
    strain: float
    speed_mm_min: float
    k: tuple[float, ...]                     # N, coefficient of (x / stroke)^i
    a: tuple[float, ...]                     # N / (mm s)
    alpha: tuple[complex, ...]               # 1/s (complex = conjugate pair)
    r: tuple[tuple[float, ...], ...]         # per cycle, N s^beta / mm
    beta: tuple[tuple[float, ...], ...]      # per cycle
    cycles: int = 3
    noise_N: float = NOISE_N
    zero_offset_N: float = 0.0
    quantum_mm: float = QUANTUM_MM
    sampling_hz: float = SAMPLING_HZ
    width_mm: float = 100.0
    depth_mm: float = 100.0
    start_s: float | None = None             # motion starts this long after the first sample
                                             # (None: a phase in [0, 1/fs) drawn from the seed)
    form: str = "causal"                     # the residual: "causal" (Eq. 10) or "paper" (Eq. 20b-f)

    @property
    def stroke_mm(self) -> float:
        return self.strain * self.height_mm

    @property
    def rate_mm_s(self) -> float:
        return self.speed_mm_min / 60.0

    @property
    def half_s(self) -> float:
        return self.stroke_mm / self.rate_mm_s

    @property
    def on_grid(self) -> bool:
        """Turning points on samples (with start_s = 0): A / v * fs is an integer."""
        n = self.half_s * self.sampling_hz
        return abs(n - round(n)) < 1e-9

    def residual_row(self, cycle: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(r, beta) of a 0-based cycle; cycles beyond the rows reuse the last."""
        c = min(cycle, len(self.r) - 1)
        return self.r[c], self.beta[c]

    def with_(self, **changes) -> Regime:
        from dataclasses import replace
        return replace(self, **changes)

    def parameter_dict(self) -> dict[str, float]:
        """The truth under foamlab's flat names (k0.., a1, alpha1_re, alpha1_im, r1_1, beta1_1, ..)."""
        d = {"x_scale_mm": self.stroke_mm}
        d.update({f"k{i}": float(v) for i, v in enumerate(self.k)})
        for i, (a, al) in enumerate(zip(self.a, self.alpha), 1):
            d.update({f"a{i}": a, f"alpha{i}_re": complex(al).real, f"alpha{i}_im": complex(al).imag})
        for c, (rs, bs) in enumerate(zip(self.r, self.beta), 1):
            for i, (r, b) in enumerate(zip(rs, bs), 1):
                d.update({f"r{c}_{i}": r, f"beta{c}_{i}": b})
        return d


_AREA = 100.0 * 100.0

REGIME_A = Regime(
    name="A",
    height_mm=62.0, strain=0.8, speed_mm_min=60.0,
    k=foam_law_polynomial(E0_kPa=80.0, plateau_kPa=5.0, densification_kPa=20.0, densification_power=4,
                          area_mm2=_AREA, height_mm=62.0, stroke_mm=49.6),
    a=(0.042, 0.11),
    alpha=(0.05 + 0j, 0.5 + 0j),
    r=((5.0, 2.0, -0.15), (0.5, 0.2, -0.015), (0.25, 0.1, -0.0075)),
    beta=((0.9, 0.7, -0.35), (0.88, 0.68, -0.33), (0.86, 0.66, -0.30)),
    zero_offset_N=0.3,
)

REGIME_B = Regime(
    name="B",
    height_mm=76.0, strain=0.8, speed_mm_min=90.0,
    k=foam_law_polynomial(E0_kPa=120.0, plateau_kPa=8.0, densification_kPa=34.0, densification_power=6,
                          area_mm2=_AREA, height_mm=76.0, stroke_mm=60.8),
    a=(0.03, 0.06),
    alpha=(0.04 + 0j, 0.25 + 0.4j),
    r=((3.0, 1.5, -0.15), (0.3, 0.15, -0.015), (0.15, 0.075, -0.0075)),
    beta=((0.8, 0.45, -0.4), (0.78, 0.4, -0.35), (0.75, 0.35, -0.3)),
    zero_offset_N=-0.2,
)

REGIMES = {"A": REGIME_A, "B": REGIME_B}

#: A third regime, fixed in session 39 before any diagnosis of it, that no foamlab setting was tuned
#: on: a small firm specimen at ISO 3386's 100 mm/min (turns between samples, 307.2 a half-cycle),
#: faster damping modes, a complex pair, flatter residual orders. Not in REGIMES (the tests' and
#: benchmarks' fixed cases stay as they were): what foamlab does on a specimen it never met.
REGIME_C = Regime(
    name="C",
    height_mm=40.0, strain=0.8, speed_mm_min=100.0,
    k=foam_law_polynomial(E0_kPa=250.0, plateau_kPa=20.0, densification_kPa=80.0, densification_power=5,
                          area_mm2=50.0 * 50.0, height_mm=40.0, stroke_mm=32.0),
    a=(0.05, 0.2),
    alpha=(0.1 + 0j, 1.0 + 0.6j),
    r=((2.0, 1.0, -0.1), (0.2, 0.1, -0.01), (0.1, 0.05, -0.005)),
    beta=((0.85, 0.5, -0.3), (0.83, 0.47, -0.28), (0.8, 0.45, -0.25)),
    zero_offset_N=0.1, width_mm=50.0, depth_mm=50.0,
)
OTHER_REGIMES = {"C": REGIME_C}
#: Every named regime, for looking one up by its name.
BY_NAME = {**REGIMES, **OTHER_REGIMES}

#: The same regimes with their turning points on samples (stroke / rate * fs an integer, motion
#: from the first sample): the case foamlab's closed_form and the fit's switching handle exactly.
REGIME_A_GRID = REGIME_A.with_(name="A-grid", height_mm=60.0, start_s=0.0)      # 48 mm: 768 samples a half
REGIME_B_GRID = REGIME_B.with_(name="B-grid", height_mm=75.0, start_s=0.0)      # 60 mm: 640 samples a half
GRID_REGIMES = {"A-grid": REGIME_A_GRID, "B-grid": REGIME_B_GRID}


def start_phase(seed: int, sampling_hz: float = SAMPLING_HZ) -> float:
    """Where the motion starts within the first sample step, drawn from the seed."""
    return float(np.random.default_rng([seed, 7]).uniform(0.0, 1.0 / sampling_hz))


# -- the history ------------------------------------------------------------------------
@dataclass
class History:
    """The ideal triangle (continuous time) at the times t: motion starts at t0 = start_s."""

    t: np.ndarray          # s
    x: np.ndarray          # mm, exact
    cycle: np.ndarray      # 0-based cycle of each time (-1 before the motion starts)
    loading: np.ndarray    # bool: t_k <= t <= t_k + T/2 (the peak instant is loading)
    start_s: float         # t0
    half_s: float          # T/2 = A / v
    n_cycles: int
    rate: float            # mm/s

    @property
    def period_s(self) -> float:
        return 2.0 * self.half_s

    def start_time(self, k: int) -> float:
        return self.start_s + k * self.period_s

    def peak_time(self, k: int) -> float:
        return self.start_time(k) + self.half_s

    @property
    def end_s(self) -> float:
        return self.start_time(self.n_cycles)

    def corners(self, k: int) -> list[tuple[float, float]]:
        """Corners of y = x - x(t_k) from cycle k's start on: (time, slope change in mm/s)."""
        v, n = self.rate, self.n_cycles
        out = [(self.start_time(k), v)]
        for j in range(1, 2 * (n - k) + 1):
            ds = v if j == 2 * (n - k) else (-2 * v if j % 2 else 2 * v)   # the run's end: x stays 0
            out.append((self.start_time(k) + j * self.half_s, ds))
        return out

    def index_of(self, time_s: float) -> int:
        """The last sample at or before an instant."""
        return int(np.searchsorted(self.t, time_s + 1e-9, side="right")) - 1


def triangle(regime: Regime, t=None, *, cycles: int | None = None, start_s: float = 0.0) -> History:
    """n cycles 0 -> A -> 0 at the rate v from t0 = start_s; x = 0 before and after.

    t: the times (default: the samples i / fs from 0 to the first sample at or after the end)."""
    n = regime.cycles if cycles is None else cycles
    v = regime.rate_mm_s
    half = regime.stroke_mm / v
    if t is None:
        dt = 1.0 / regime.sampling_hz
        t = np.arange(int(np.ceil((start_s + 2 * n * half) / dt - 1e-9)) + 1) * dt
    t = np.asarray(t, float)
    tau = t - start_s
    cyc = np.where(tau < -EPS_S, -1, np.clip(np.floor((tau + EPS_S) / (2 * half)), 0, n - 1)).astype(int)
    u = tau - np.maximum(cyc, 0) * 2 * half             # time since the cycle's start
    loading = (tau >= -EPS_S) & (u <= half + EPS_S)     # a sample at the peak instant is loading
    u = np.clip(u, 0.0, None)
    x = np.where(loading, v * u, np.clip(v * (2 * half - u), 0.0, None))
    x = np.where(tau < 0, 0.0, x)
    return History(t, x, cyc, loading, float(start_s), half, n, v)


# -- the components (closed forms) -------------------------------------------------------
def elastic(regime: Regime, x) -> np.ndarray:
    s = np.asarray(x, float) / regime.stroke_mm
    out = np.zeros_like(s)
    for c in reversed(regime.k):             # Horner
        out = out * s + c
    return out


def damping_ramp(a, alpha, u, rate: float) -> np.ndarray:
    """Eq. 9 on a ramp x(t_k + s) - x(t_k) = rate*s, at u = t - t_k >= 0: v sum a (u M0 - M1)."""
    u = np.asarray(u, float)
    total = np.zeros(u.shape)
    for a_i, al in zip(a, alpha):
        al = complex(al)
        e = np.exp(-al * u)
        m0 = (1.0 - e) / al
        m1 = (1.0 - (1.0 + al * u) * e) / al ** 2
        total += a_i * np.real(u * m0 - m1)
    return rate * total


def corner_sum(t, corners: list[tuple[float, float]], beta: float) -> np.ndarray:
    """RL D^beta of sum_j ds_j (t - c_j)_+ : sum_j ds_j (t - c_j)_+^{1-beta} / Gamma(2-beta)."""
    t = np.asarray(t, float)
    nu = 1.0 - beta
    out = np.zeros(t.shape)
    for c, ds in corners:
        lag = t - c
        out += ds * np.where(lag > EPS_S, lag, 0.0) ** nu      # a sample at a corner: lag 0, not 1e-14
    return out / math.gamma(1.0 + nu)


def residual_cycle(regime: Regime, hist: History, k: int) -> np.ndarray:
    """V_Rk at hist.t: zero up to cycle k's peak instant, then Eq. 10 (causal) or Eqs. 20b-f."""
    r, beta = regime.residual_row(k)
    corners = hist.corners(k)
    out = np.zeros(len(hist.t))
    on = hist.t > hist.peak_time(k) + EPS_S
    at = hist.t[on]
    if regime.form == "paper":      # cycle k's own triangle, where its unloading passes x
        corners = corners[:2]
        at = hist.start_time(k) + hist.period_s - hist.x[on] / hist.rate
    for r_i, b_i in zip(r, beta):
        out[on] += r_i * corner_sum(at, corners, b_i)
    return out


@dataclass
class Components:
    hist: History
    elastic: np.ndarray
    damping: np.ndarray
    residual: np.ndarray
    residual_by_cycle: list[np.ndarray] = field(default_factory=list)

    @property
    def force(self) -> np.ndarray:
        """The model force, unclipped (negative: the plate has lost contact)."""
        return self.elastic + self.damping + self.residual

    @property
    def contact(self) -> np.ndarray:
        return self.force > 0


def components(regime: Regime, t=None, *, cycles: int | None = None, start_s: float = 0.0) -> Components:
    """The model's three components (Eqs. 12, 9, 10) on the triangular history at the times t."""
    hist = triangle(regime, t, cycles=cycles, start_s=start_s)
    u = np.where(hist.loading, hist.t - hist.start_s - np.maximum(hist.cycle, 0) * hist.period_s, 0.0)
    damping = np.where(hist.loading, damping_ramp(regime.a, regime.alpha, u, regime.rate_mm_s), 0.0)
    by_cycle = [residual_cycle(regime, hist, k) for k in range(hist.n_cycles)]
    return Components(hist, elastic(regime, hist.x), damping, np.sum(by_cycle, axis=0), by_cycle)


def contact_loss_mm(comp: Components) -> list[float]:
    """Displacement at which contact is lost in each unloading (nan: never)."""
    h, out = comp.hist, []
    for k in range(h.n_cycles):
        span = np.flatnonzero((h.t > h.peak_time(k) + EPS_S) & (h.t <= h.start_time(k + 1) + EPS_S))
        off = span[~comp.contact[span]]
        out.append(float(h.x[off[0]]) if len(off) else float("nan"))
    return out


def contact_regain_mm(comp: Components) -> list[float]:
    """Displacement at which contact is regained in each later loading (nan: never lost)."""
    h, out = comp.hist, []
    for k in range(1, h.n_cycles):
        span = np.flatnonzero((h.t >= h.start_time(k) - EPS_S) & (h.t <= h.peak_time(k) + EPS_S))
        on = span[comp.contact[span]]
        out.append(float(h.x[on[0]]) if len(on) else float("nan"))
    return out


# -- a run -------------------------------------------------------------------------------
@dataclass
class SyntheticRun:
    regime: Regime
    seed: int
    time_s: np.ndarray
    displacement_mm: np.ndarray     # measured (quantised)
    force_N: np.ndarray             # measured: max(F, 0) + offset + noise
    true_force_N: np.ndarray        # max(F, 0) + offset (what a perfect fit reproduces)
    model: Components
    start_s: float = 0.0

    @property
    def sigma(self) -> float:
        return self.regime.noise_N

    def to_rundata(self):
        from foamlab.rundata import RunData, Specimen  # hand-over only, not model code
        spec = Specimen(label=f"independent-{self.regime.name}-{self.seed}", height_mm=self.regime.height_mm,
                        width_mm=self.regime.width_mm, depth_mm=self.regime.depth_mm)
        return RunData(self.time_s.copy(), self.displacement_mm.copy(), self.force_N.copy(), specimen=spec,
                       method="independent triangular", source=f"independent_model regime {self.regime.name}")

    def write_csv(self, path) -> None:
        r = self.regime
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(f"# tests/independent_model.py regime {r.name} seed {self.seed}: {r.cycles} cycles to "
                     f"{r.stroke_mm:g} mm at {r.speed_mm_min:g} mm/min, {r.sampling_hz:g} Hz, "
                     f"noise {r.noise_N:g} N, zero offset {r.zero_offset_N:g} N, motion from t = {self.start_s:.6f} s\n")
            fh.write("time_s,displacement_mm,force_N\n")
            np.savetxt(fh, np.column_stack([self.time_s, self.displacement_mm, self.force_N]),
                       fmt=["%.4f", "%.4f", "%.5f"], delimiter=",")


def generate(regime: Regime, seed: int, cycles: int | None = None, start_s: float | None = None) -> SyntheticRun:
    """One run of the regime: exact model force, load-cell clipping, offset, noise, 1 um encoder.

    start_s: when the motion starts after the first sample (default: the regime's)."""
    if cycles is not None and cycles != regime.cycles:
        regime = regime.with_(cycles=cycles)
    if start_s is None:
        start_s = regime.start_s if regime.start_s is not None else start_phase(seed, regime.sampling_hz)
    comp = components(regime, start_s=start_s)
    rng = np.random.default_rng(seed)
    clean = np.maximum(comp.force, 0.0) + regime.zero_offset_N
    force = clean + rng.normal(0.0, regime.noise_N, len(clean))
    x = comp.hist.x
    if regime.quantum_mm:
        x = np.round(x / regime.quantum_mm) * regime.quantum_mm
    return SyntheticRun(regime, seed, comp.hist.t.copy(), x, force, clean, comp, float(start_s))

