"""`foamlab diagnose --suggest`: the next test that would settle a close call.

When the data leave two explanations close (the two best candidates of the first round
within CLOSE_DELTA_BIC of each other, or two partial ones), or a cause needs a run this
diagnosis does not have (rate_dependence: runs at two or more speeds), each contender's
extended model - the fitted one: the base parameters and effects of its fit, evaluated by
foamlab.model on a new displacement history - is simulated under a few protocols foamlab can
run (other speeds, a dwell at the peak, a smaller stroke, more cycles), built as foamlab
Method objects from the reference run's own protocol, and each is given the predicted RMS
difference of the two models' forces over the noise level. The best is written as a method
file `foamlab run --method FILE` accepts (docs/analysis.md, "The next test").

Which is best: a protocol decides when its predicted evidence - the likelihood ratio the two
models' difference would give on the samples the protocol takes, sum of (difference / noise)^2 -
reaches DECISIVE_EVIDENCE; the shortest protocol that decides is proposed (ranked by the difference
alone, a 59-min run was proposed where a 3.7-min one would do: issue 27), the one with the
most evidence when none does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foamlab.diagnosis.result import Candidate, Diagnosis
from foamlab.methods import (
    DEFAULT_METHOD,
    MAX_SAMPLING_HZ,
    Method,
    Step,
    load_method,
    method_toml,
)
from foamlab.model import ModelParameters, label_history
from foamlab.model.effects import Effect, EffectChain, RateDependence

#: Two candidates whose Delta BIC (against the same model) differ by less than this are a close call:
#: the data favour one by less than "very strong" evidence (the margin a finding needs).
CLOSE_DELTA_BIC = 10.0
#: The rate exponent a run at another speed is sized for when rate_dependence was not testable
#: (RateDependence's m: the damping scales as (v / v_ref)^m).
RATE_PROBE_M = 0.2
#: Speed factors, dwell (s), stroke factor and cycle factor of the protocols tried.
SPEED_FACTORS = (4.0, 0.25)
DWELL_S = 60.0
STROKE_FACTOR = 0.5
CYCLE_FACTOR = 2
#: Predicted evidence (-2 ln likelihood ratio of the two contenders on the protocol's samples) at
#: which a protocol decides: ten times the close call's margin, for what the parameters both runs
#: share absorb of the difference when the runs are fitted together (the prediction keeps them
#: at the first run's values).
DECISIVE_EVIDENCE = 10 * CLOSE_DELTA_BIC
#: Protocols longer than this are not proposed (s).
MAX_DURATION_S = 3600.0
#: Crosshead speeds a protocol may use (mm/min).
SPEED_RANGE_MM_MIN = (1.0, 500.0)
#: The predictions are simulated on at most about this many samples (the ranking does not need more).
PREDICT_SAMPLES = 4000
#: Strain assumed at the peak of a run whose file does not give the specimen height (the paper's).
ASSUMED_PEAK_STRAIN = 0.8


@dataclass(frozen=True)
class Contender:
    """One model the next test should tell from the other: a candidate's fitted extension."""

    name: str                      # the cause, or 'no rate_dependence'
    params: ModelParameters
    effects: tuple[Effect, ...]
    delta_bic: float               # its evidence on the runs diagnosed (nan: not fitted)

    def force(self, t: np.ndarray, x: np.ndarray) -> np.ndarray:
        """What the load cell would read under the history x(t) (the model's force through
        the effects, as the simulator computes it; no noise, no zero offset)."""
        return EffectChain(self.effects).measured_force(self.params, t, x, labels=label_history(x))


@dataclass(frozen=True)
class Protocol:
    key: str                       # faster | slower | dwell | smaller_stroke | more_cycles
    description: str
    method: Method
    height_mm: float


@dataclass(frozen=True)
class Prediction:
    protocol: Protocol
    rms_difference_N: float        # of the two contenders' predicted forces
    over_noise: float              # rms_difference_N / the noise level
    duration_s: float
    evidence: float                # sum of (difference / noise)^2 over the samples the protocol takes

    @property
    def decides(self) -> bool:
        return self.evidence >= DECISIVE_EVIDENCE


@dataclass
class Suggestion:
    """The close call, the protocols ranked (best first) and where the best was written."""

    why: str                                   # the close call, or why there is none
    contenders: tuple[Contender, Contender] | None
    ranking: list[Prediction] = field(default_factory=list)
    noise_sigma: float = float("nan")
    height_note: str = ""                      # how the specimen height was set
    path: Path | None = None                   # the method file written

    @property
    def made(self) -> bool:
        return bool(self.ranking)

    @property
    def best(self) -> Prediction | None:
        return self.ranking[0] if self.ranking else None

    def method_text(self) -> str:
        best = self.best
        a, b = self.contenders
        comment = (f"foamlab diagnose --suggest: the test that best tells {a.name} from {b.name}\n"
                   f"({self.why}).\n{best.protocol.description}: predicted RMS difference "
                   f"{best.rms_difference_N:.3g} N = {best.over_noise:.3g} x the noise, evidence "
                   f"{best.evidence:.3g} ({'decides' if best.decides else 'the most of any protocol'}).\n"
                   f"Strains are for a specimen {best.protocol.height_mm:.4g} mm high{self.height_note}.\n"
                   "Run it on the same specimen, then diagnose both runs together, the first run first.")
        return method_toml(best.protocol.method, comment)

    def write(self, path: str | Path) -> Path:
        out = Path(path)
        out.write_text(self.method_text(), encoding="utf-8")
        self.path = out
        return out

    def lines(self) -> list[str]:
        if not self.made:
            return [f"suggest: nothing to suggest ({self.why})"]
        a, b = self.contenders
        out = [f"suggest: {a.name} or {b.name}? ({self.why})",
               f"  predicted difference of the two fitted models (noise {self.noise_sigma:.3g} N):",
               f"  {'protocol':<64}{'RMS diff N':>11}{'x noise':>9}{'evidence':>10}{'min':>7}"]
        out += [f"  {p.protocol.description:<64}{p.rms_difference_N:>11.3g}{p.over_noise:>9.3g}"
                f"{p.evidence:>10.3g}{p.duration_s / 60:>7.1f}" for p in self.ranking]
        out.append(f"  decides: predicted evidence >= {DECISIVE_EVIDENCE:g}; the shortest that decides is first")
        if self.path is not None:
            out.append(f"  best: {self.best.protocol.description}; method written to {self.path}")
            out.append(f"  run it: foamlab run --method {self.path}; then foamlab diagnose FIRST NEW")
        return out

    def to_dict(self) -> dict:
        if not self.made:
            return {"made": False, "why": self.why}
        return {"made": True, "why": self.why, "contenders": [c.name for c in self.contenders],
                "noise_sigma": self.noise_sigma, "method_file": str(self.path) if self.path else None,
                "best": self.best.protocol.key,
                "ranking": [{"protocol": p.protocol.key, "description": p.protocol.description,
                             "method": p.protocol.method.name, "rms_difference_N": p.rms_difference_N,
                             "over_noise": p.over_noise, "duration_s": p.duration_s,
                             "evidence": p.evidence, "decides": p.decides} for p in self.ranking]}


def suggest(d: Diagnosis, height_mm: float | None = None) -> Suggestion:
    """The next test for diagnosis d (height_mm: the reference run's specimen, if known)."""
    call = close_call(d)
    if call is None:
        return Suggestion(f"no two candidates within {CLOSE_DELTA_BIC:g} of Delta BIC with evidence, no "
                          "cause waiting for another run", None, noise_sigma=d.noise_sigma)
    why, pair = call
    shape = RunShape.of(d)
    height, note = shape.height(height_mm)
    ranking = sorted((predict(pair, p, d.noise_sigma) for p in protocols(shape, height)), key=_rank)
    return Suggestion(why, pair, ranking, d.noise_sigma, note)


def _rank(p: Prediction) -> tuple:
    """The protocols that decide first, shortest first; then the others, most evidence first."""
    return (0, p.duration_s, -p.evidence) if p.decides else (1, -p.evidence, p.duration_s)


def close_call(d: Diagnosis) -> tuple[str, tuple[Contender, Contender]] | None:
    """(why, the two contenders) - or None when the diagnosis leaves no close call."""
    first = d.tested[0] if d.tested else []
    named = {c.name for c in d.findings}
    # a candidate whose effect is not determined gains by moving the base, not by its effect: no
    # contender (a clean pair at two speeds: four such at Delta BIC 58-60, one BLAS thread)
    ranked = sorted((c for c in first if np.isfinite(c.delta_bic) and c.z_score >= d.settings.effect_z_min),
                    key=lambda c: -c.delta_bic)
    if ranked and ranked[0].delta_bic > d.settings.delta_bic_min:
        best = ranked[0]
        # rivals: fitted against the same model, not a second finding of this diagnosis
        rivals = [c for c in ranked[1:] if c.before is best.before and not {best.name, c.name} <= named]
        if rivals and rivals[0].delta_bic > 0 and best.delta_bic - rivals[0].delta_bic < CLOSE_DELTA_BIC:
            r = rivals[0]
            return (f"Delta BIC {best.delta_bic:.1f} vs {r.delta_bic:.1f}: within {CLOSE_DELTA_BIC:g}",
                    (_contender(best), _contender(r)))
    if len(d.partial) >= 2:
        a, b = sorted(d.partial, key=lambda c: -c.share)[:2]
        return (f"both partial: {a.share:.0%} and {b.share:.0%} of the structure", (_contender(a), _contender(b)))
    why = d.skipped.get(RateDependence.name, "")
    if why.startswith("needs runs at"):
        final = _fitted(d.final.params, d.final.model.effects(d.final.eta), "no rate_dependence", float("nan"))
        v_ref = d.series[0].speed_mm_min
        probe = final.effects + (RateDependence(RATE_PROBE_M, v_ref_mm_min=v_ref),)
        return (f"rate_dependence {why}; sized for an exponent m = {RATE_PROBE_M:g}",
                (final, _fitted(final.params, probe, RateDependence.name, float("nan"))))
    return None


def _contender(c: Candidate) -> Contender:
    return _fitted(c.fit.params, c.fit.model.effects(c.fit.eta), c.name, c.delta_bic)


def _fitted(params: ModelParameters, effects, name: str, delta_bic: float) -> Contender:
    return Contender(name, params, tuple(effects), float(delta_bic))


@dataclass(frozen=True)
class RunShape:
    """The reference run's protocol as diagnosis saw it."""

    peak_mm: float
    speed_mm_min: float
    cycles: int
    sampling_hz: float

    @classmethod
    def of(cls, d: Diagnosis) -> RunShape:
        s = d.series[0].source
        return cls(float(np.max(s.x)), float(s.speed_mm_min), max(len(s.labels.peaks), 1), 1.0 / s.step_s)

    def height(self, height_mm: float | None) -> tuple[float, str]:
        """The specimen height the method's strains are for, and a note when it is assumed."""
        if height_mm and self.peak_mm / height_mm <= ASSUMED_PEAK_STRAIN + 0.15:
            return float(height_mm), ""
        h = self.peak_mm / ASSUMED_PEAK_STRAIN
        return h, (f" (assumed: the run's file gives no usable height, so its peak {self.peak_mm:.4g} mm is "
                   f"taken as {ASSUMED_PEAK_STRAIN:.0%}; give the real one with --specimen-height)")


def protocols(shape: RunShape, height_mm: float) -> list[Protocol]:
    """The protocols tried: the run's own, changed in one thing at a time."""
    v, n, strain = shape.speed_mm_min, shape.cycles, shape.peak_mm / height_mm
    lo, hi = SPEED_RANGE_MM_MIN
    out = [_protocol("faster" if k > 1 else "slower", f"{n} cycles at {v * k:.3g} mm/min ({k:g} x the speed)",
                     shape, height_mm, strain, v * k, n) for k in SPEED_FACTORS if lo <= v * k <= hi]
    out.append(_protocol("dwell", f"{n} cycles, {DWELL_S:g} s dwell at each peak", shape, height_mm, strain, v, n,
                         dwell_s=DWELL_S))
    out.append(_protocol("smaller_stroke", f"{n} cycles to {STROKE_FACTOR:g} x the stroke ({strain * STROKE_FACTOR:.0%})",
                         shape, height_mm, strain * STROKE_FACTOR, v, n))
    out.append(_protocol("more_cycles", f"{n * CYCLE_FACTOR} cycles", shape, height_mm, strain, v, n * CYCLE_FACTOR))
    return [p for p in out if p.method.duration_s(height_mm) <= MAX_DURATION_S]


def _protocol(key: str, description: str, shape: RunShape, height_mm: float, strain: float,
              speed: float, cycles: int, dwell_s: float = 0.0) -> Protocol:
    cycle = [Step("compress", 0, "cycle", strain=round(strain, 4), speed_mm_min=round(speed, 3))]
    if dwell_s:
        cycle.append(Step("dwell", 0, "cycle", duration_s=dwell_s))
    cycle.append(Step("return", 0, "cycle", speed_mm_min=round(speed, 3)))
    steps = tuple(Step(s.action, k + 1, s.label, s.strain, s.speed_mm_min, s.duration_s)
                  for k in range(cycles) for s in cycle)
    lab = load_method(DEFAULT_METHOD)           # the lab's contact search, park and sampling
    hz = sampling_hz(shape, lab)
    if hz != round(shape.sampling_hz, 3):       # said: the lab sets it up, and it is why the run decides
        description += f", sampled at {hz:g} Hz"
    method = Method(name=f"suggested-{key.replace('_', '-')}", title=f"Suggested next test: {description}",
                    sampling_hz=hz,
                    contact=lab.contact, park_speed_mm_min=lab.park_speed_mm_min, steps=steps,
                    per_cycle=("hysteresis_loss", "energy", "residual_strain"),
                    reference="foamlab diagnose --suggest (docs/analysis.md, 'The next test')")
    return Protocol(key, description, method, height_mm)


def sampling_hz(shape: RunShape, lab: Method) -> float:
    """A suggested run samples as finely as the lab's method does, or as the first run did where
    that is finer: an effect acting within one sampling interval of the turns is seen only on a
    finer grid (a 60 ms memory lag at 2 Hz is named friction, at 16 Hz memory_lag:
    docs/analysis.md, "Two runs"), and more samples never weaken the decision."""
    return min(max(round(shape.sampling_hz, 3), lab.sampling_hz), MAX_SAMPLING_HZ)


def predict(pair: tuple[Contender, Contender], protocol: Protocol, noise_sigma: float) -> Prediction:
    """The two contenders simulated under the protocol: RMS of the difference of their forces."""
    method = protocol.method
    duration = method.duration_s(protocol.height_mm)
    hz = min(method.sampling_hz, max(PREDICT_SAMPLES / max(duration, 1e-9), 1.0))
    t, x = method.history(protocol.height_mm, hz)
    diff = pair[0].force(t, x) - pair[1].force(t, x)
    rms = float(np.sqrt(np.mean(np.square(diff))))
    over = rms / noise_sigma if noise_sigma > 0 else float("inf")
    # the difference is simulated on a coarser grid; the evidence counts the samples the run takes
    return Prediction(protocol, rms, over, duration, over ** 2 * duration * method.sampling_hz)


def default_path(reference_name: str, folder: str | Path = ".") -> Path:
    """suggested-<run>.toml in folder, numbered when it exists (a suggestion never overwrites
    a file the user did not name)."""
    stem = Path(reference_name).stem.replace(" ", "_") or "run"
    base = Path(folder) / f"suggested-{stem}.toml"
    k, path = 2, base
    while path.exists():
        path, k = base.with_name(f"{base.stem}-{k}.toml"), k + 1
    return path
