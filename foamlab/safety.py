"""Checks that keep the machine's references honest, in one place for the window and the engine.

A tare (or a force zero) taken with the plate pressing on a specimen makes every later
force wrong by that load: issue 18's e-stop at 43 mm (~56 N), reset and Start tared on
the squeezed block, and the free crosshead then read -51 N. So a tare is refused, with
the reason in words, when

- the load cell does not read its unloaded level: |net force| above UNLOADED_FRACTION
  of the cell's capacity (the net force is relative to the last tare, taken in air), or
- the crosshead stands below (positions grow downwards) the point where the plate last
  touched a specimen on this machine, when that point is known (remember_contact()).

The contact points are kept per machine object (weakly: a closed machine is forgotten);
the window records them from each run's result, so the engine's own tare at the start of
the next run is checked against them too.
"""

from __future__ import annotations

import weakref

from drivers.base import Machine
from foamlab import FoamlabError

#: "Unloaded" means within this fraction of the load cell's capacity (5 N on a 500 N cell):
#: well above the noise and drift of an indicator, well below a specimen pressed a few %.
UNLOADED_FRACTION = 0.01

_contacts: "weakref.WeakKeyDictionary[Machine, float]" = weakref.WeakKeyDictionary()


def remember_contact(machine: Machine, position_mm: float | None) -> None:
    """Where the plate touched the specimen in the last run (machine coordinates, mm)."""
    if position_mm is not None:
        _contacts[machine] = float(position_mm)


def last_contact(machine: Machine) -> float | None:
    return _contacts.get(machine)


def shift_contact(machine: Machine, by_mm: float) -> None:
    """The machine's position zero moved by `by_mm` (set_zero at position p: by = -p)."""
    if machine in _contacts:
        _contacts[machine] += by_mm


def unloaded_tolerance_N(machine: Machine) -> float:
    return UNLOADED_FRACTION * float(machine.load_cell.capacity_N)


def check_safe_to_tare(machine: Machine, action: str = "tare") -> None:
    """Raise FoamlabError (one plain line) unless the load cell may be tared/zeroed now.

    Reads one sample from the machine: call it on the thread that owns the machine."""
    sample = machine.read_sample()
    tolerance = unloaded_tolerance_N(machine)
    if abs(sample.force_N) > tolerance:
        raise FoamlabError(
            f"{action} refused: the load cell reads {sample.force_N:.1f} N, not its unloaded level "
            f"(within ±{tolerance:.3g} N); unload the specimen (jog up) before the {action}")
    contact = _contacts.get(machine)
    if contact is not None and sample.position_mm > contact:
        raise FoamlabError(
            f"{action} refused: the crosshead is at {sample.position_mm:.2f} mm, below the point where the "
            f"plate last touched the specimen ({contact:.2f} mm); jog up above it before the {action}")


def check_run_fits(method, specimen, limits, position_mm: float | None) -> None:
    """Raise FoamlabError, in the operator's words, when the method's deepest point on this
    specimen lies beyond the lower travel limit, counted from where the crosshead stands
    (the contact search starts there and only goes down). `position_mm` None: unknown,
    counted from the upper travel limit. (method: foamlab.methods.Method, specimen:
    foamlab.rundata.Specimen, limits: foamlab.acquisition.Limits.)"""
    stroke = method.max_strain * specimen.height_mm
    start = limits.travel_upper_mm if position_mm is None else position_mm
    room = limits.travel_lower_mm - start
    if stroke > room:
        raise FoamlabError(
            f"{specimen.height_mm:g} mm specimen, {method.max_strain:.0%} stroke: needs {stroke:.3g} mm of travel; "
            f"the lower travel limit ({limits.travel_lower_mm:g} mm) allows {max(room, 0):.3g} mm below the "
            f"crosshead at {start:.1f} mm")
