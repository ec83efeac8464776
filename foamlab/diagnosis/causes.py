"""Candidate causes: how diagnosis tests each effect of foamlab.model.effects.

The effect is the one definition of a cause: its physics, its name, what it means and
how it shows (Effect.name / meaning / signature). A cause adds only the diagnosis'
strategy: when it can be tested, on what scale its parameter lives for this data (the
starting grid of the fit), and how to say the fitted value in words. A new cause is an
Effect subclass in foamlab.model.effects (listed in EFFECTS) plus one class here.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from foamlab.analysis.design import Series
from foamlab.model import effects as fx

CAUSES: dict[str, type["Cause"]] = {}

#: Multiples of a cause's scale tried before the local fit (both signs unless bounded).
SCAN_MULTIPLES = (0.003, 0.03, 0.3, 1.0)


def register(cls: type["Cause"]) -> type["Cause"]:
    """A cause for one of the model's effects (foamlab.model.effects.EFFECTS), by its name."""
    if fx.EFFECTS.get(cls.name) is not cls.effect:
        raise ValueError(f"cause {cls.__name__}: its effect {cls.name!r} is not in foamlab.model.effects.EFFECTS")
    CAUSES[cls.name] = cls
    return cls


class Cause:
    """How diagnosis tests one effect of foamlab.model.effects: its name, its meaning and its
    signature are the effect's own (one definition); the cause adds when it can be tested,
    the scale of its parameter on these runs and how to say its fitted value in words."""

    effect: ClassVar[type[fx.Effect]]
    name: ClassVar[str]                   # the effect's
    meaning: ClassVar[str]                # the effect's: what it is, physically (one line)
    signature: ClassVar[str]              # the effect's: how it shows in the base model's residuals
    min_speeds: ClassVar[int] = 1         # runs at this many distinct speeds are needed
    #: Identification's staged fit (the paper's method) takes this effect into the base
    #: model's own terms, so an extension fitted from that base stays near zero: its fit is
    #: also restarted from identification on the data with the effect taken out.
    absorbed_by_identification: ClassVar[bool] = False
    #: The base model imitates this effect by bending several of its own parameters at once
    #: (alpha/beta with the linear ones), so a short joint probe from the base stays near zero:
    #: it is always fitted jointly to convergence in the search, however its probe ranked.
    imitated_by_base: ClassVar[bool] = False
    #: Sizes (the first fitted parameter's, each sign it can take) the search walks the effect out
    #: to from zero, each fit continued from the last (extend.walk); () none.
    walk_sizes: ClassVar[tuple[float, ...]] = ()
    #: Multiples of its scale such an effect is started from (extend.multistart); None: MULTISTART_SIZES.
    multistart_sizes: ClassVar[tuple[float, ...] | None] = None
    #: The base holds this effect in its own terms from the base's start at any size the search
    #: gives it (a lag of under one sample: the damping modes take it): in the first round it is
    #: always fitted from several starts on the finer samples (Procedure._imitated), whatever the
    #: search's fit showed.
    always_multistart: ClassVar[bool] = False
    #: The effect grows faster than its size near zero (its slope there promises too little): its
    #: detection limit is found with the effect at each size (limits._sized), not its slope.
    nonlinear_in_size: ClassVar[bool] = False
    #: The effect is the whole reading late (its parameter the delay, in s): the detection limit's
    #: check injects the force that late along the path (limits, analysis.prepared.force_late), not
    #: the effect's batch form, which interpolates the sampled force across a turn.
    reads_late: ClassVar[bool] = False

    @classmethod
    def held_by_base(cls) -> bool:
        """The base can take this effect into the model's own terms (identification absorbs it, the
        base imitates it, or holds it from its start), or its limit is found from its own effect with
        the base linearised (nonlinear_in_size: what the base's refit takes of it is not in that): its
        detection limit is checked by injection."""
        return cls.absorbed_by_identification or cls.imitated_by_base or cls.always_multistart or cls.nonlinear_in_size

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.name, cls.meaning, cls.signature = cls.effect.name, cls.effect.meaning, cls.effect.signature

    @classmethod
    def applicable(cls, series: list[Series]) -> str | None:
        """None if the cause can be tested on these runs, else why not."""
        speeds = distinct_speeds(series)
        if len(speeds) < cls.min_speeds:
            return f"needs runs at {cls.min_speeds} or more distinct speeds (got {len(speeds)})"
        return None

    @classmethod
    def bounds(cls) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the fitted parameters: the effect's own unless physics narrows them."""
        return cls.effect.bounds()

    @classmethod
    def settings(cls, series: list[Series]) -> dict[str, float]:
        """Fixed (not fitted) values of the effect for these runs."""
        return {}

    @classmethod
    def scale(cls, series: list[Series]) -> float:
        """A size of the parameter that changes the force by a visible amount on these runs."""
        raise NotImplementedError

    @classmethod
    def starts(cls, series: list[Series]) -> np.ndarray:
        """Starting values of the fitted parameter (one per row), inside the bounds."""
        lo, hi = cls.bounds()
        scale = cls.scale(series)
        vals = [0.0] + [s * m * scale for m in SCAN_MULTIPLES for s in (1.0, -1.0)]
        vals = sorted({float(np.clip(v, lo[0], hi[0])) for v in vals})
        return np.array(vals)[:, None]

    @classmethod
    def joint_start(cls, series: list[Series]) -> float:
        """Where the joint fit starts when the screening saw nothing: a visible size."""
        lo, hi = cls.bounds()
        return float(np.clip(0.3 * cls.scale(series), lo[0], hi[0]))

    @classmethod
    def signs(cls) -> tuple[float, ...]:
        """The signs its effect can take (its bounds): 1, or 1 and -1 (a damping rise or drop)."""
        return (1.0, -1.0) if float(cls.bounds()[0][0]) < 0 else (1.0,)

    @classmethod
    def limit_text(cls, limit: float, below: float | None = None) -> str:
        """The smallest size this run would name, in words and physical units. below: a drop's own
        limit where a cause of either sign has one (limits.checked; its overrides say it)."""
        p = cls.effect.fitted_parameters()[0]
        return f"no {cls.name} above {limit:.2g} {p.unit}"

    @classmethod
    def describe(cls, values: dict[str, float], stderr: dict[str, float]) -> str:
        p = cls.effect.parameters[0]
        v, se = values[p.name], stderr.get(p.name, float("nan"))
        return f"{p.name} = {v:.4g} ± {se:.2g} {p.unit}"


def force_scale(series: list[Series]) -> float:
    return max(float(np.percentile(s.y, 99)) for s in series)


def distinct_speeds(series: list[Series], rel_tol: float = 0.1) -> list[float]:
    out: list[float] = []
    for v in sorted(s.speed_mm_min for s in series):
        if not out or v > out[-1] * (1 + rel_tol):
            out.append(v)
    return out


@register
class CycleSoftening(Cause):
    effect = fx.CycleSoftening
    # like a damping change: identification gives a later cycle's lower elastic force to the
    # residual terms of the earlier cycles, a base the joint fit cannot leave
    absorbed_by_identification = True

    @classmethod
    def applicable(cls, series):
        if max(int(s.cycle.max()) for s in series) < 2:
            return "needs two or more cycles"
        return None

    @classmethod
    def bounds(cls):
        # softening only (Mullins damage does not heal within a test): a 0.1 %/cycle hardening is
        # how a 1 000 N/mm frame reads (later, lower peaks stretch the frame less; regime A)
        lo, hi = cls.effect.bounds()
        return np.maximum(lo, 0.0), hi

    @classmethod
    def scale(cls, series):
        return 0.1

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no softening above {100 * limit:.2g} %/cycle"

    @classmethod
    def describe(cls, values, stderr):
        return (f"the elastic force drops {100 * values['s']:.3g} % ± {100 * stderr.get('s', np.nan):.2g} % "
                "per cycle")


@register
class DampingCycleChange(Cause):
    effect = fx.DampingCycleChange
    # identification takes the damping from the first loading and gives the later loadings'
    # change to the residual terms of the earlier cycles (docs/analysis.md, "Restarts")
    absorbed_by_identification = True
    # a change identification took up leaves a dip in the walked profile at its size (causal form:
    # 7 of 9 missed rises of 17-52 %/cycle; docs/analysis.md, "A walk")
    walk_sizes = tuple(round(0.05 * k, 2) for k in range(1, 11))

    @classmethod
    def applicable(cls, series):
        if max(int(s.cycle.max()) for s in series) < 2:
            return "needs two or more cycles"
        return None

    @classmethod
    def scale(cls, series):
        return 1.0

    @classmethod
    def limit_text(cls, limit, below=None):
        if below is None or not np.isfinite(below):
            return f"no damping change beyond ±{100 * limit:.2g} %/cycle"
        if np.isclose(below, limit, rtol=0.05):
            return f"no damping change beyond ±{100 * max(limit, below):.2g} %/cycle"
        # identification can take one sign into its own terms and not the other (limits.checked)
        return f"no damping rise above +{100 * limit:.2g} %/cycle, no drop below -{100 * below:.2g} %/cycle"

    @classmethod
    def describe(cls, values, stderr):
        return (f"the damping force changes {100 * values['d']:+.3g} % ± {100 * stderr.get('d', np.nan):.2g} % "
                "per cycle")


@register
class ChannelLag(Cause):
    effect = fx.ChannelLag
    # a 50 ms lag at 16 Hz (0.8 of a sample): Delta BIC 36-72 from the true value on regime A's
    # every sample, < 0 from the search's joint fit (decimated or not: regime B; docs/analysis.md)
    always_multistart = True
    multistart_sizes = (0.025, 0.1)          # x 20 steps: half a step and two steps
    reads_late = True

    @classmethod
    def bounds(cls):
        # a delay: a filtered channel is late. An early force, fitted from several starts, took the
        # place of the base's own damping on a clean run (regime B seed 302: -17 ms, Delta BIC 11)
        lo, hi = cls.effect.bounds()
        return np.maximum(lo, 0.0), hi

    @classmethod
    def scale(cls, series):
        h = min(float(np.median(np.diff(s.t))) for s in series)
        return 20 * h

    @classmethod
    def starts(cls, series):
        h = min(float(np.median(np.diff(s.t))) for s in series)
        lo, hi = cls.bounds()
        vals = [0.0] + [sg * m * h for m in (0.3, 1.0, 3.0, 10.0, 30.0) for sg in (1.0, -1.0)]
        return np.array(sorted({float(np.clip(v, lo[0], hi[0])) for v in vals}))[:, None]

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no force channel lag above {1000 * limit:.2g} ms"

    @classmethod
    def describe(cls, values, stderr):
        tau = values["tau_s"]
        side = "late" if tau > 0 else "early"
        return f"the force channel is {side} by {1000 * abs(tau):.3g} ± {1000 * stderr.get('tau_s', np.nan):.2g} ms"


@register
class ForceZeroDrift(Cause):
    effect = fx.ForceZeroDrift

    @classmethod
    def scale(cls, series):
        duration = max(float(s.t[-1] - s.t[0]) for s in series)
        return 0.05 * force_scale(series) / max(duration, 1e-9)

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no force zero drift beyond ±{60 * limit:.2g} N/min"

    @classmethod
    def describe(cls, values, stderr):
        r = values["rate_N_per_s"]
        return f"the force zero drifts {60 * r:+.3g} ± {60 * stderr.get('rate_N_per_s', np.nan):.2g} N/min"


@register
class MachineCompliance(Cause):
    effect = fx.MachineCompliance
    # the elastic polynomial and the unloading's residual terms reshape to the specimen's curve
    imitated_by_base = True

    @classmethod
    def scale(cls, series):
        stroke = max(float(np.ptp(s.x)) for s in series)
        return 0.02 * stroke / force_scale(series)

    @classmethod
    def settings(cls, series):
        # a frame at once, the specimen's path taken from the displacement less C F: through
        # the simulator's 0.2 s it held half of an independent generator's frame, none of a
        # 1 000 N/mm one (docs/analysis.md, "The frame at once")
        return {"tau_frame_s": 0.0}

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no frame softer than {1 / limit:.3g} N/mm (compliance above {1000 * limit:.2g} um/N)"

    @classmethod
    def describe(cls, values, stderr):
        c = values["c_mm_per_N"]
        return (f"the machine deflects {1000 * c:.3g} ± {1000 * stderr.get('c_mm_per_N', np.nan):.2g} um/N "
                f"(stiffness {1 / c if c > 0 else float('inf'):.3g} N/mm)")


@register
class DirectionFriction(Cause):
    effect = fx.DirectionFriction
    # a constant force in contact is the elastic k0, and a constant loading-only force is two
    # damping modes of opposite sign: the base holds friction but for the loading's first 1/alpha
    imitated_by_base = True

    @classmethod
    def scale(cls, series):
        return 0.03 * force_scale(series)

    @classmethod
    def bounds(cls):
        # a force that opposes the motion: a negative one would drive it (not friction)
        lo, hi = cls.effect.bounds()
        return np.maximum(lo, 0.0), hi

    @classmethod
    def settings(cls, series):
        # reverse over ~1 % of the crosshead speed: sharp but smooth at the turning points
        return {"v_smooth_mm_s": 0.01 * min(s.speed_mm_min for s in series) / 60.0}

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no friction against the motion above {limit:.2g} N"

    @classmethod
    def describe(cls, values, stderr):
        return f"a friction force of {values['f_N']:.3g} ± {stderr.get('f_N', np.nan):.2g} N opposes the motion"


@register
class RateDependence(Cause):
    effect = fx.RateDependence
    min_speeds = 2

    @classmethod
    def settings(cls, series):
        return {"v_ref_mm_min": series[0].speed_mm_min}

    @classmethod
    def scale(cls, series):
        return 0.5

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no rate dependence of the damping beyond exponent ±{limit:.2g}"

    @classmethod
    def describe(cls, values, stderr):
        return (f"the damping scales as (v / {values['v_ref_mm_min']:.3g} mm/min)^{values['m']:.3g} "
                f"(± {stderr.get('m', np.nan):.2g})")


@register
class MemoryLag(Cause):
    effect = fx.MemoryLag
    nonlinear_in_size = True

    @classmethod
    def scale(cls, series):
        return 10 * min(float(np.median(np.diff(s.t))) for s in series)

    @classmethod
    def starts(cls, series):
        h = min(float(np.median(np.diff(s.t))) for s in series)
        lo, hi = cls.bounds()
        vals = [0.0] + [m * h for m in (0.3, 1.0, 3.0, 10.0, 30.0)]
        return np.array(sorted({float(np.clip(v, lo[0], hi[0])) for v in vals}))[:, None]

    @classmethod
    def limit_text(cls, limit, below=None):
        return f"no memory lag above {1000 * limit:.2g} ms"

    @classmethod
    def describe(cls, values, stderr):
        return (f"the damping and residual forces follow with a relaxation time of "
                f"{1000 * values['tau_s']:.3g} ± {1000 * stderr.get('tau_s', np.nan):.2g} ms")
