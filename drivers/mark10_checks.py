"""Commissioning checks of an ESM303 + Series 5 against the device file (`foamlab probe`).

Each reply the manuals leave open is fetched raw and compared byte for byte with the
device file's assumption (configs/devices/mark10-esm303.toml): a match confirms it; a
reply that differs but that the driver still reads passes with a note saying what to
correct in the device file; a reply the driver cannot read fails. Nothing here moves
the crosshead.
"""

from __future__ import annotations

import re
import string

from .base import DeviceError

_NUMBER = r"[-+]?\d+(?:\.\d+)?"


def _expected_pattern(template: str, machine, terminator: bytes) -> re.Pattern:
    """The exact reply line a template describes, e.g. "{travel} {travel_unit}" -> `<number> mm` CR LF."""
    link = machine.link
    units = {"force_unit": link.gauge_unit.reply, "travel_unit": link.stand_unit.reply,
             "speed_unit": link.stand_unit.speed_unit}
    codes = "|".join(sorted((re.escape(c) for c in machine.commands.status_codes), key=len, reverse=True))
    parts = {"status": rf"(?:{codes})(?: (?:{codes}))*", "text": r"[ -~]+", "settings": r"[ -~]+"}
    pattern = ""
    for literal, name, _, _ in string.Formatter().parse(template):
        pattern += re.escape(literal)
        if name:
            pattern += re.escape(units[name]) if name in units else parts.get(name, _NUMBER)
    return re.compile(pattern.encode("ascii") + re.escape(terminator))


def _check(machine, label: str, text: str, templates: tuple[str, ...], *, gauge: bool):
    terminator = machine.commands.gauge_reply_terminator if gauge else machine.commands.stand_reply_terminator
    name = f"{label} ({text!r}{' through the pass-through' if gauge else ''})"
    try:
        raws = machine.link.capture(text, len(templates), gauge=gauge)
    except DeviceError as exc:
        return name, False, str(exc)
    shown = b"".join(raws)
    if all(_expected_pattern(t, machine, terminator).fullmatch(raw) for t, raw in zip(templates, raws)):
        return name, True, f"{shown!r}: as the device file assumes"
    try:   # does the driver still read it? (its tolerance: bare numbers, LF only, skipped lines)
        values = machine.link.parse_captured(text, templates, raws)
    except DeviceError as exc:
        return name, False, f"{shown!r}: the driver cannot read it ({exc})"
    fields = ", ".join(f"{k}={v}" for k, v in values.items())
    return name, True, (f"{shown!r}: read as {fields}, but it differs from the device file's assumption "
                        f"{' / '.join(templates)}: correct configs/devices/mark10-esm303.toml")


def self_checks(machine) -> list[tuple[str, bool, str]]:
    stand, gauge = machine.commands.stand, machine.commands.gauge
    checks = [_check(machine, label, stand[name].send, stand[name].reply, gauge=False)
              for label, name in (("travel reply", "read_travel"), ("sample reply", "read_sample"),
                                  ("status reply", "status"), ("speed reply", "read_speed"),
                                  ("upper limit reply", "read_upper_limit"), ("lower limit reply", "read_lower_limit"))]
    checks.append(_check(machine, "gauge reading", gauge["read_current"].send, gauge["read_current"].reply, gauge=True))
    checks.append(_settings_check(machine))
    return checks


def _settings_check(machine) -> tuple[str, bool, str]:
    """The gauge's LIST shows the profile's unit and FULL (units sent with readings)."""
    name = "gauge settings (LIST)"
    try:
        settings = machine.link.gauge_ask("list")["settings"]
    except DeviceError as exc:
        return name, False, str(exc)
    tokens = settings.upper().split(";")
    unit = machine.link.gauge_unit
    missing = [t for t in (unit.reply.upper(), machine.commands.gauge["full"].send) if t not in tokens]
    if missing:
        return name, False, f"{settings!r} lacks {', '.join(missing)} (unit or data format not as connect() set them)"
    return name, True, f"{settings!r}: unit {unit.reply}, readings with units"
