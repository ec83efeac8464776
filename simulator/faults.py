"""Fault plan of the simulated machine: what goes wrong, and when (virtual time).

Spec grammar (one fault per spec; several specs may be given, or joined by commas
or spaces in one string):

    NAME@T        one event at virtual time T seconds
    NAME@T+D      a window: in effect from T for D seconds
    NAME:p=P      at random, with probability P per opportunity (seeded)

Names:
    transport  drop       close the connection
               timeout    do not reply
               crc        corrupt the frame (bad CRC / checksum)
               exception  Modbus exception reply (`*10`-style error on ASCII)
               garbage    write garbage bytes on the serial line
    physics    stall      the crosshead jams: commanded motion, position frozen, fault 1
               overload   the load cell reads beyond its capacity (over-range)

Queries (always at the plan's clock, i.e. virtual time):
- ``should_fire(name)``: does this opportunity carry the fault? One opportunity is
  one request for transport faults. A single event (``@T``) answers True exactly
  once, at the first query at or after T; a window (``@T+D``) answers True for
  every query inside it; a random fault draws once per query.
- ``fires_during(name, t0, t1)``: the same question for an interval of virtual time
  (physics faults; the machine asks once per physics step). Random faults then
  read P as a probability per virtual second, so the answer does not depend on the
  step size.
- ``active(name)``: is a scheduled fault in effect now? ``@T`` is in effect from T
  on, ``@T+D`` inside its window; random faults are never "active" (no draw).
"""

from __future__ import annotations

import collections
import math
import re
import threading
import zlib
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

TRANSPORT_FAULTS = ("drop", "timeout", "crc", "exception", "garbage")
PHYSICS_FAULTS = ("stall", "overload")
FAULT_NAMES = TRANSPORT_FAULTS + PHYSICS_FAULTS

_NUMBER = r"[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?"
_SCHEDULED = re.compile(rf"^(?P<name>[a-z_]+)@(?P<t>{_NUMBER})(?:\+(?P<d>{_NUMBER}))?$")
_RANDOM = re.compile(rf"^(?P<name>[a-z_]+):p=(?P<p>{_NUMBER})$")


@dataclass
class FaultSpec:
    name: str
    at_s: float | None = None          # scheduled start (virtual s)
    duration_s: float | None = None    # window length; None = single event / from T on
    probability: float | None = None   # random faults
    text: str = ""
    consumed: bool = field(default=False, repr=False)  # single event already fired

    @property
    def is_random(self) -> bool:
        return self.probability is not None

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        s = text.strip().lower()
        m = _SCHEDULED.match(s)
        if m:
            name, at = m["name"], float(m["t"])
            dur = float(m["d"]) if m["d"] is not None else None
            if dur is not None and dur <= 0:
                raise ValueError(f"fault {text!r}: the duration after '+' must be positive")
            spec = cls(name, at_s=at, duration_s=dur, text=text.strip())
        else:
            m = _RANDOM.match(s)
            if not m:
                raise ValueError(
                    f"fault {text!r}: expected NAME@SECONDS, NAME@SECONDS+DURATION or NAME:p=PROBABILITY"
                )
            name, p = m["name"], float(m["p"])
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"fault {text!r}: probability must be between 0 and 1")
            spec = cls(name, probability=p, text=text.strip())
        if name not in FAULT_NAMES:
            raise ValueError(f"fault {text!r}: unknown fault {name!r} (known: {', '.join(FAULT_NAMES)})")
        return spec


class FaultPlan:
    """Parsed fault specs plus one seeded random stream per fault name (thread-safe)."""

    def __init__(self, specs: Iterable[str] | str | None = None, seed: int = 0,
                 clock: Callable[[], float] | None = None) -> None:
        if specs is None:
            specs = []
        if isinstance(specs, str):
            specs = [specs]
        texts = [piece for s in specs for piece in re.split(r"[,\s]+", s) if piece]
        self.specs: list[FaultSpec] = [FaultSpec.parse(t) for t in texts]
        self.seed = int(seed)
        self.clock = clock
        # (virtual time, name) of the faults that fired, most recent last
        self.fired: collections.deque[tuple[float, str]] = collections.deque(maxlen=1000)
        self._lock = threading.Lock()
        # One stream per name: the draws of one fault do not depend on how often others are asked.
        self._rng = {n: np.random.default_rng([self.seed, zlib.crc32(n.encode())]) for n in FAULT_NAMES}

    def __bool__(self) -> bool:
        return bool(self.specs)

    def __repr__(self) -> str:
        return f"FaultPlan({[s.text for s in self.specs]!r}, seed={self.seed})"

    def names(self) -> set[str]:
        return {s.name for s in self.specs}

    def _now(self, now: float | None) -> float:
        if now is not None:
            return now
        if self.clock is None:
            raise RuntimeError("FaultPlan has no clock: bind one (plan.clock = machine.clock.now)")
        return self.clock()

    def _check(self, name: str) -> None:
        if name not in FAULT_NAMES:
            raise ValueError(f"unknown fault {name!r} (known: {', '.join(FAULT_NAMES)})")

    def active(self, name: str, now: float | None = None) -> bool:
        self._check(name)
        t = self._now(now)
        with self._lock:
            for s in self.specs:
                if s.name != name or s.is_random:
                    continue
                if s.duration_s is None and t >= s.at_s:
                    return True
                if s.duration_s is not None and s.at_s <= t < s.at_s + s.duration_s:
                    return True
        return False

    def should_fire(self, name: str, now: float | None = None) -> bool:
        self._check(name)
        t = self._now(now)
        fire = False
        with self._lock:
            for s in self.specs:
                if s.name != name:
                    continue
                if s.is_random:
                    fire |= bool(self._rng[name].random() < s.probability)
                elif s.duration_s is None:
                    if t >= s.at_s and not s.consumed:
                        s.consumed = True
                        fire = True
                elif s.at_s <= t < s.at_s + s.duration_s:
                    fire = True
            if fire:
                self.fired.append((t, name))
        return fire

    def in_window(self, name: str, now: float | None = None) -> bool:
        """Is a windowed spec (``@T+D``) of this fault in effect now?"""
        self._check(name)
        t = self._now(now)
        with self._lock:
            return any(s.name == name and s.duration_s is not None and s.at_s <= t < s.at_s + s.duration_s
                       for s in self.specs)

    def scheduled_times(self, names: Iterable[str] = FAULT_NAMES) -> list[float]:
        """Start and end times of the scheduled specs of these faults (physics breakpoints)."""
        names = set(names)
        out = []
        for s in self.specs:
            if s.name in names and not s.is_random:
                out.append(s.at_s)
                if s.duration_s is not None:
                    out.append(s.at_s + s.duration_s)
        return sorted(out)

    def fires_during(self, name: str, t0: float, t1: float, windows: bool = True) -> bool:
        """Does the fault fire in the virtual interval (t0, t1]? Random: P per virtual second.

        windows=False ignores ``@T+D`` specs (a caller that asks ``in_window`` for those)."""
        self._check(name)
        fire = False
        with self._lock:
            for s in self.specs:
                if s.name != name or (not windows and s.duration_s is not None):
                    continue
                if s.is_random:
                    dt = max(t1 - t0, 0.0)
                    p_interval = 1.0 - math.pow(1.0 - s.probability, dt) if s.probability < 1 else 1.0
                    fire |= bool(dt > 0 and self._rng[name].random() < p_interval)
                elif s.duration_s is None:
                    if t1 >= s.at_s and not s.consumed:
                        s.consumed = True
                        fire = True
                elif s.at_s < t1 and t0 < s.at_s + s.duration_s:
                    fire = True
            if fire:
                self.fired.append((t1, name))
        return fire
