"""Where the model misses: residuals by cycle, half-cycle, displacement and time.

A region's bias is its mean residual; its score is that mean in units of its
standard error under the data's own noise level (sigma / sqrt(samples), widened by
the residuals' lag-1 correlation), so |score| > ~4 is structure, not noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from foamlab.analysis.design import Series
from foamlab.analysis.noise import Whiteness, whiteness
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings



@dataclass
class Region:
    run: str
    cycle: int
    direction: int        # +1 loading, -1 unloading, 0 outside cycles
    x_lo: float
    x_hi: float
    n: int
    mean: float
    rms: float
    score: float

    @property
    def phase(self) -> str:
        return {1: "loading", -1: "unloading"}.get(self.direction, "outside cycles")

    def text(self) -> str:
        run = f"{self.run}: " if self.run else ""
        return (f"{run}cycle {self.cycle} {self.phase}, x {self.x_lo:.3g}-{self.x_hi:.3g} mm: "
                f"mean residual {self.mean:+.3g} N ({self.score:+.1f} se)")

    def to_dict(self) -> dict:
        return {"run": self.run, "cycle": self.cycle, "phase": self.phase,
                "x_mm": [round(self.x_lo, 4), round(self.x_hi, 4)], "samples": self.n,
                "mean_N": self.mean, "rms_N": self.rms, "score": self.score}


@dataclass
class Periodicity:
    period_s: float
    power_share: float     # share of the residual variance in the peak's neighbourhood

    def to_dict(self) -> dict:
        return {"period_s": self.period_s, "power_share": self.power_share}


@dataclass(frozen=True)
class Miss:
    """What the model misses, in one sentence: how large, where in the cycle, and how it changes
    with cycle number (the RMS per cycle and its change per cycle fitted by least squares)."""

    rmse_N: float
    noise_N: float
    where: str                         # the largest structure: turning points, or one region
    by_cycle_N: tuple[float, ...]      # RMS of the residual per cycle, cycle 1 first
    change_per_cycle: float            # relative change of that RMS per cycle (nan below 3 cycles)

    def sentence(self) -> str:
        size = f"{self.rmse_N:.3g} N RMS ({self.rmse_N / self.noise_N:.1f} x the noise)" if self.noise_N > 0 \
            else f"{self.rmse_N:.3g} N RMS"
        out = f"the model misses the measurement by {size}, most at {self.where}"
        if len(self.by_cycle_N) > 1:
            values = [f"{v:.3g}" for v in self.by_cycle_N]
            listed = " / ".join(values if len(values) <= 6 else values[:3] + ["..."] + values[-2:])
            out += f"; by cycle {listed} N RMS"
            if np.isfinite(self.change_per_cycle):
                out += f" ({self.change_per_cycle:+.0%} per cycle)"
        return out

    def to_dict(self) -> dict:
        return {"sentence": self.sentence(), "rmse": self.rmse_N, "where": self.where,
                "rmse_by_cycle": list(self.by_cycle_N),
                "change_per_cycle": self.change_per_cycle if np.isfinite(self.change_per_cycle) else None}


@dataclass
class ResidualAnalysis:
    rmse: float
    noise_sigma: float
    whiteness: Whiteness
    regions: list[Region]
    time_bins: list[tuple[str, float, float, float]]   # (run, t_mid, mean, score)
    periodicity: Periodicity | None
    by_half_cycle: list[tuple[str, int, int, float, float]] = field(default_factory=list)
    turning: tuple[float, float, float] = (0.0, 0.0, 0.0)   # (power share, sample share, window s)
    score_threshold: float = DEFAULT.score_threshold        # |score| above it: structure (settings)

    @property
    def excess_ratio(self) -> float:
        return self.rmse / self.noise_sigma if self.noise_sigma > 0 else float("inf")

    def structured_regions(self, limit: int = 5) -> list[Region]:
        hot = [r for r in self.regions if abs(r.score) > self.score_threshold]
        return sorted(hot, key=lambda r: -abs(r.score))[:limit]

    def where(self, limit: int = 5) -> list[str]:
        out = []
        power, samples, window = self.turning
        if power > 0.2 and power > 3 * samples:
            out.append(f"turning points: {power:.0%} of the residual power in the {window:.2g} s after "
                       f"each reversal ({samples:.1%} of the samples)")
        out += [r.text() for r in self.structured_regions(limit)]
        if self.periodicity is not None and self.periodicity.power_share > 0.25:
            out.append(f"periodic: {self.periodicity.power_share:.0%} of the residual power near "
                       f"a period of {self.periodicity.period_s:.3g} s")
        return out

    def miss(self) -> Miss:
        """The largest structure (turning points when they hold the most power per sample, else
        the region furthest from zero in standard errors) and the RMS per cycle."""
        power, samples, window = self.turning
        hot = self.structured_regions(1)
        if power > 0.2 and power > 3 * samples:
            where = (f"the turning points ({power:.0%} of the residual power in the {window:.2g} s after each "
                     f"reversal, {samples:.1%} of the samples)")
        elif hot:
            r = hot[0]
            where = (f"cycle {r.cycle} {r.phase}, x {r.x_lo:.3g}-{r.x_hi:.3g} mm (mean residual {r.mean:+.3g} N, "
                     f"{r.score:+.0f} standard errors)")
        else:
            where = "no region more than its noise (the residuals spread evenly)"
        sq: dict[int, list[float]] = {}
        for _, cycle, _, _, rms in self.by_half_cycle:       # half-cycles' RMS, weighted alike
            if cycle >= 1:
                sq.setdefault(cycle, []).append(rms ** 2)
        cycles = sorted(sq)
        by_cycle = tuple(float(np.sqrt(np.mean(sq[c]))) for c in cycles)
        change = float("nan")
        if len(by_cycle) >= 3 and np.mean(by_cycle) > 0:
            change = float(np.polyfit(cycles, by_cycle, 1)[0] / np.mean(by_cycle))
        return Miss(self.rmse, self.noise_sigma, where, by_cycle, change)

    def to_dict(self) -> dict:
        return {
            "miss": self.miss().to_dict(),
            "rmse": self.rmse,
            "noise_sigma": self.noise_sigma,
            "excess_ratio": self.excess_ratio,
            "whiteness": self.whiteness.to_dict(),
            "where": self.where(),
            "regions": [r.to_dict() for r in self.structured_regions(10)],
            "periodicity": self.periodicity.to_dict() if self.periodicity else None,
            "turning_points": {"power_share": self.turning[0], "sample_share": self.turning[1],
                               "window_s": self.turning[2]},
        }


@dataclass
class _UsedSamples:
    """A series' used samples (what analyse needs of it)."""

    name: str
    t: np.ndarray
    x: np.ndarray
    cycle: np.ndarray
    direction: np.ndarray
    source: Series

    @classmethod
    def of(cls, s: Series) -> "_UsedSamples":
        u = s.used
        return cls(s.name, s.t[u], s.x[u], s.cycle[u], s.direction[u], s.source)

    def __len__(self) -> int:
        return len(self.t)


def analyse(series: list[Series], residuals: list[np.ndarray], noise_sigma: float,
            settings: DiagnosisSettings = DEFAULT) -> ResidualAnalysis:
    """residuals: per series, at every sample; only the used samples (Series.used) count."""
    residuals = [np.asarray(r)[s.used] for s, r in zip(series, residuals)]
    series = [_UsedSamples.of(s) for s in series]
    all_r = np.concatenate(residuals)
    white = whiteness(all_r)
    rho = min(max(white.lag1_correlation, 0.0), 0.99)
    inflation = np.sqrt((1 + rho) / (1 - rho))     # AR(1) variance of a mean
    regions: list[Region] = []
    halves: list[tuple[str, int, int, float, float]] = []
    time_bins = []
    multi = len(series) > 1
    for s, r in zip(series, residuals):
        name = s.name if multi else ""
        x_max = float(np.max(s.x)) if len(s.x) else 1.0
        x_min = float(np.min(s.x)) if len(s.x) else 0.0
        edges = np.linspace(x_min, x_max, settings.x_bins + 1)
        for cyc in np.unique(s.cycle):
            for d in (1, -1, 0):
                sel = (s.cycle == cyc) & (s.direction == d)
                if not np.any(sel):
                    continue
                rr = r[sel]
                halves.append((name, int(cyc), d, float(np.mean(rr)), float(np.sqrt(np.mean(rr ** 2)))))
                idx = np.clip(np.digitize(s.x[sel], edges) - 1, 0, settings.x_bins - 1)
                for b in range(settings.x_bins):
                    rb = rr[idx == b]
                    if len(rb) < 5:
                        continue
                    se = noise_sigma * inflation / np.sqrt(len(rb))
                    mean = float(np.mean(rb))
                    regions.append(Region(name, int(cyc), d, float(edges[b]), float(edges[b + 1]), len(rb),
                                          mean, float(np.sqrt(np.mean(rb ** 2))), mean / se if se > 0 else 0.0))
        tb = np.array_split(np.arange(len(r)), min(settings.time_bins, max(len(r) // 5, 1)))
        for ix in tb:
            if len(ix) == 0:
                continue
            se = noise_sigma * inflation / np.sqrt(len(ix))
            m = float(np.mean(r[ix]))
            time_bins.append((s.name, float(np.mean(s.t[ix])), m, m / se if se > 0 else 0.0))
    return ResidualAnalysis(
        turning=_turning_share(series, residuals),
        rmse=float(np.sqrt(np.mean(all_r ** 2))),
        noise_sigma=noise_sigma,
        whiteness=white,
        regions=regions,
        time_bins=time_bins,
        periodicity=_periodicity(series, residuals),
        by_half_cycle=halves,
        score_threshold=settings.score_threshold,
    )


def _periodicity(series: list[Series], residuals: list[np.ndarray]) -> Periodicity | None:
    """Strongest spectral line of the residuals (the longest run), if any.

    Periods longer than a quarter of the run are trends, not periodicity.
    """
    k = int(np.argmax([len(s) for s in series]))
    s, r = series[k], residuals[k]
    if len(r) < 64:
        return None
    h = float(np.median(np.diff(s.t)))
    f, p = signal.periodogram(r - np.mean(r), fs=1.0 / h, detrend="linear")
    total = float(np.sum(p[1:]))
    duration = float(s.t[-1] - s.t[0])
    usable = f > 4.0 / duration
    if total <= 0 or not np.any(usable):
        return None
    i = int(np.flatnonzero(usable)[np.argmax(p[usable])])
    df = f[1] - f[0]
    near = np.abs(f - f[i]) <= 3 * df
    return Periodicity(period_s=float(1.0 / f[i]), power_share=float(np.sum(p[near]) / total))


def _turning_share(series: list[Series], residuals: list[np.ndarray]) -> tuple[float, float, float]:
    """Share of the residual power just after the reversals (and the first loading's start),
    against their share of the samples: the model switches damping and residual terms
    there, so a specimen that relaxes or releases differently shows up here."""
    power = total = 0.0
    n_near = n = 0
    window = 0.0
    for s, r in zip(series, residuals):
        f = s.source
        half = np.median([f.t[p] - f.t[a] for a, p in zip(f.labels.starts, f.labels.peaks) if p > a] or [1.0])
        window = max(window, 0.01 * float(half))
        near = np.zeros(len(s), dtype=bool)
        for i in list(f.labels.peaks) + list(f.labels.starts[:1]):
            near |= (s.t >= f.t[i]) & (s.t <= f.t[i] + 0.01 * half)
        power += float(r[near] @ r[near])
        total += float(r @ r)
        n_near += int(near.sum())
        n += len(r)
    return (power / total if total > 0 else 0.0, n_near / max(n, 1), window)
