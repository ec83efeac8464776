"""Motion planning of the simulated crosshead: time-optimal trapezoidal profiles, exact at every instant.

A plan is a list of constant-acceleration segments, computed analytically when a command
arrives, so positions are exact whatever the physics step; its corners and its crossings of
a level (the specimen's top, a travel limit) are where the machine cuts its steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

MIN_STEP_S = 1e-6               # shorter steps would differentiate rounding errors (rates ~ dx/h)


@dataclass(frozen=True)
class Segment:
    """Constant acceleration from (t0, p0, v0) for dur seconds."""

    t0: float
    p0: float
    v0: float
    a: float
    dur: float

    @property
    def t1(self) -> float:
        return self.t0 + self.dur

    def at(self, t: float) -> tuple[float, float]:
        tau = min(max(t - self.t0, 0.0), self.dur)
        return self.p0 + self.v0 * tau + 0.5 * self.a * tau * tau, self.v0 + self.a * tau

    def crossing(self, level: float) -> list[float]:
        """Times within the segment where the position equals `level`."""
        c = self.p0 - level
        if self.a == 0.0:
            roots = [-c / self.v0] if self.v0 != 0 else []
        else:
            disc = self.v0 * self.v0 - 2.0 * self.a * c
            if disc < 0:
                return []
            sq = math.sqrt(disc)
            roots = [(-self.v0 - sq) / self.a, (-self.v0 + sq) / self.a]
        return [self.t0 + r for r in roots if 0.0 < r < self.dur]


@dataclass
class Motion:
    kind: str                      # "move" | "stop"
    segments: list[Segment]
    target: float                  # physical mm (final position of the plan)
    speed: float                   # mm/s (cruise), to replan after a jam
    end: float = field(init=False)

    def __post_init__(self):
        self.end = self.segments[-1].t1 if self.segments else -math.inf

    def at(self, t: float) -> tuple[float, float]:
        for seg in self.segments:
            if t <= seg.t1:
                return seg.at(t)
        return self.target, 0.0


def plan_move(t0: float, p: float, v: float, target: float, v_max: float, acc: float) -> list[Segment]:
    """Time-optimal trapezoidal (or triangular) profile from (p, v) to rest at target.

    Hand-written because it must start from any state (moving, even away from the
    target) and be exact at every instant; ~20 lines of kinematics.
    """
    segs: list[Segment] = []
    state = [t0, p, v]

    def add(a: float, dur: float) -> None:
        if dur <= 0:
            return
        t, p_, v_ = state
        segs.append(Segment(t, p_, v_, a, dur))
        state[:] = [t + dur, p_ + v_ * dur + 0.5 * a * dur * dur, v_ + a * dur]

    d = target - p
    if v != 0.0 and (v * d <= 0 or v * v / (2 * acc) > abs(d) + 1e-12):
        add(-math.copysign(acc, v), abs(v) / acc)        # brake to rest first
        state[2] = 0.0
        d = target - state[1]
    if abs(d) <= 1e-12:
        return segs
    s = math.copysign(1.0, d)
    u, D = abs(state[2]), abs(d)
    vp = v_max if u > v_max else min(v_max, math.sqrt(acc * D + 0.5 * u * u))
    t_a = abs(vp - u) / acc
    d_a = 0.5 * (vp + u) * t_a
    d_d = vp * vp / (2 * acc)
    add(s * math.copysign(acc, vp - u), t_a)
    add(0.0, max(D - d_a - d_d, 0.0) / vp)
    add(-s * acc, vp / acc)
    return segs


def plan_stop(t0: float, p: float, v: float, acc: float) -> list[Segment]:
    return [Segment(t0, p, v, -math.copysign(acc, v), abs(v) / acc)] if v != 0 else []
