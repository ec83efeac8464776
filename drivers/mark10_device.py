"""The Mark-10 ESM303 + Series 5 device file (configs/devices/mark10-esm303.toml), read and checked.

The driver (drivers.ascii) and the simulator (simulator.serial_server) take every byte they
exchange from here: command letters, fixed-width argument formats, reply line templates,
terminators, the pass-through, units, status codes and error codes. Each entry keeps its
`source`, and `unconfirmed()` lists what the manuals do not settle with what would settle it.
"""

from __future__ import annotations

import math
import re
import string
from dataclasses import dataclass, field

from .device_file import Entry, FileReader

#: Stand commands the driver sends, and gauge commands it sends through the pass-through.
STAND_COMMANDS = ("move_down", "move_up", "stop", "zero_travel", "read_travel", "read_sample", "status",
                  "read_speed", "set_speed", "set_lower_limit", "set_upper_limit", "limit_mode",
                  "read_upper_limit", "read_lower_limit")
GAUGE_COMMANDS = ("read_current", "zero", "full", "list", "read_name", "read_model", "read_firmware",
                  "read_serial")
#: Reply line fields that carry a number, and the unit field that may follow each.
NUMBER_FIELDS = {"force": "force_unit", "travel": "travel_unit", "limit": "travel_unit", "speed": "speed_unit"}
TEXT_FIELDS = ("status", "text", "settings")


@dataclass(frozen=True)
class FixedWidth:
    """A vendor argument format: minus only if negative, zero-padded integer digits, fixed decimals."""

    integer_digits: int
    decimals: int

    def format(self, value: float) -> str:
        """`eXXXX.X`-style text for value; ValueError when it does not fit the width."""
        if not math.isfinite(value):
            raise ValueError(f"{value!r} is not a finite number")
        text = f"{abs(value):0{self.integer_digits + 1 + self.decimals}.{self.decimals}f}"
        if len(text) > self.integer_digits + 1 + self.decimals:
            raise ValueError(f"{value:g} does not fit {self.integer_digits} integer digits")
        return ("-" if value < 0 and float(text) != 0 else "") + text

    @property
    def resolution(self) -> float:
        return 10.0 ** -self.decimals

    def pattern(self, signed: bool) -> str:
        return ("-?" if signed else "") + rf"\d{{{self.integer_digits}}}\.\d{{{self.decimals}}}"


@dataclass(frozen=True)
class Command:
    name: str
    send: str                          # template: "e{speed}", "g{limit}", "?C"
    reply: tuple[str, ...]             # one template per reply line; () = answers nothing
    entry: Entry

    def text(self, **values) -> str:
        return self.send.format(**values)

    @property
    def prefix(self) -> str:
        return self.send.split("{", 1)[0]


@dataclass(frozen=True)
class StandUnit:
    name: str                          # "mm" / "in"
    command: str                       # the stand command selecting it (`i` / `b`)
    reply: str                         # how replies spell it
    speed_unit: str
    to_mm: float
    speed: FixedWidth
    limit: FixedWidth
    reading_decimals: int

    @property
    def reading_resolution_mm(self) -> float:
        """The travel a reading's last digit stands for: 10^-decimals in this unit, in mm."""
        return 10.0 ** -self.reading_decimals * self.to_mm


@dataclass(frozen=True)
class GaugeUnit:
    name: str
    command: str                       # GCL2 command selecting it
    reply: str                         # how a reading spells it
    to_newton: float


def reply_fields(template: str) -> tuple[str, ...]:
    """The field names of one reply line template, in order: "{force} {force_unit}" -> (force, force_unit)."""
    return tuple(name for _, name, _, _ in string.Formatter().parse(template) if name)


def _text(value, where: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{where} must be a string, got {value!r}")
    return value


def _entry(name: str, table: dict) -> Entry:
    """An entry's provenance (drivers.device_file); an unconfirmed one states its assumption too."""
    return FileReader("").entry(table, f"[{name}]", assumption=True)


def _commands(tables: dict, where: str, required: tuple[str, ...]) -> dict[str, Command]:
    if not isinstance(tables, dict):
        raise ValueError(f"needs a [{where}] table")
    missing = [name for name in required if name not in tables]
    if missing:
        raise ValueError(f"[{where}] lacks {', '.join(missing)}")
    commands = {}
    for name, table in tables.items():
        key = f"{where}.{name}"
        reply = table.get("reply", [])
        if not isinstance(reply, list) or not all(isinstance(r, str) for r in reply):
            raise ValueError(f"[{key}] reply must be a list of line templates")
        for template in reply:
            unknown = [f for f in reply_fields(template)
                       if f not in NUMBER_FIELDS and f not in NUMBER_FIELDS.values() and f not in TEXT_FIELDS]
            if unknown:
                raise ValueError(f"[{key}] reply field {unknown[0]!r} unknown")
        commands[name] = Command(name, _text(table.get("send"), f"[{key}] send"), tuple(reply), _entry(key, table))
    return commands


def _setting(table: dict, key: str):
    """A `[x.y] value = ...` setting with its provenance, or a plain value."""
    return table["value"] if isinstance(table, dict) and "value" in table else table


@dataclass(frozen=True)
class CommandSet:
    """The device file, checked. `from_toml` raises ValueError naming the key."""

    name: str
    stand: dict[str, Command]
    gauge: dict[str, Command]
    stand_units: dict[str, StandUnit]
    gauge_units: dict[str, GaugeUnit]
    status_codes: dict[str, str]
    errors: dict[str, str]              # "*10" -> "illegal command"
    stand_terminator: bytes
    stand_reply_terminator: bytes
    passthrough_open: bytes
    passthrough_close: bytes
    passthrough_pause_s: float
    gauge_terminator: bytes
    gauge_reply_terminator: bytes
    setter_window_s: float
    force_decimals: int
    serial: dict                        # data_bits, parity, stop_bits, baudrate
    absent: tuple[str, ...]
    entries: tuple[Entry, ...] = field(default=(), repr=False)

    @classmethod
    def from_toml(cls, wire: dict) -> "CommandSet":
        try:
            return cls._build(wire)
        except KeyError as exc:
            raise ValueError(f"lacks {exc.args[0]!r}") from None
        except (TypeError, AttributeError) as exc:
            raise ValueError(f"malformed: {exc}") from None

    @classmethod
    def _build(cls, wire: dict) -> "CommandSet":
        stand, gauge = wire["stand"], wire["gauge"]
        stand_commands = _commands(stand.get("commands"), "stand.commands", STAND_COMMANDS)
        gauge_commands = _commands(gauge.get("commands"), "gauge.commands", GAUGE_COMMANDS)
        entries = [c.entry for c in (*stand_commands.values(), *gauge_commands.values())]
        for key, table in (("serial", wire["serial"]), ("serial.baudrate", wire["serial"]["baudrate"]),
                           ("serial.gauge_baudrate", wire["serial"]["gauge_baudrate"]),
                           ("stand.framing", stand["framing"]), ("stand.reply_framing", stand["reply_framing"]),
                           ("stand.acknowledge", stand["acknowledge"]), ("stand.status_codes", stand["status_codes"]),
                           ("gauge.passthrough", gauge["passthrough"]),
                           ("gauge.passthrough.pause_s", gauge["passthrough"]["pause_s"]),
                           ("gauge.framing", gauge["framing"]), ("gauge.setter_reply", gauge["setter_reply"]),
                           ("gauge.units_source", gauge["units_source"]), ("gauge.errors_source", gauge["errors_source"])):
            entries.append(_entry(key, table))
        stand_units = {}
        for name, u in stand["units"].items():
            entries.append(_entry(f"stand.units.{name}", u))
            stand_units[name] = StandUnit(name, u["command"], u["reply"], u["speed_unit"], float(u["to_mm"]),
                                          FixedWidth(**u["speed"]), FixedWidth(**u["limit"]), int(u["reading_decimals"]))
        gauge_units = {name: GaugeUnit(name, u["command"], u["reply"], float(u["to_newton"]))
                       for name, u in gauge["units"].items()}
        errors = dict(gauge["errors"])
        for code, meaning in errors.items():
            if not re.fullmatch(r"\*\d\d", code) or not isinstance(meaning, str):
                raise ValueError(f"[gauge.errors] {code!r} must look like \"*10\" = \"meaning\"")
        codes = {k: v for k, v in stand["status_codes"].items() if k not in ("source", "confirmed", "assumption", "settle")}
        serial = wire["serial"]
        return cls(
            name=_text(wire["name"], "name"), stand=stand_commands, gauge=gauge_commands,
            stand_units=stand_units, gauge_units=gauge_units, status_codes=codes, errors=errors,
            stand_terminator=_text(stand["framing"]["command_terminator"], "command_terminator").encode("ascii"),
            stand_reply_terminator=_text(stand["reply_framing"]["reply_terminator"], "reply_terminator").encode("ascii"),
            passthrough_open=_text(gauge["passthrough"]["open"], "passthrough open").encode("ascii"),
            passthrough_close=_text(gauge["passthrough"]["close"], "passthrough close").encode("ascii"),
            passthrough_pause_s=float(_setting(gauge["passthrough"]["pause_s"], "pause_s")),
            gauge_terminator=_text(gauge["framing"]["command_terminator"], "gauge terminator").encode("ascii"),
            gauge_reply_terminator=_text(gauge["framing"]["reply_terminator"], "gauge reply").encode("ascii"),
            setter_window_s=float(gauge["setter_reply"]["window_s"]),
            force_decimals=int(gauge["framing"]["force_decimals"]),
            serial={"data_bits": int(serial["data_bits"]), "parity": str(serial["parity"]),
                    "stop_bits": int(serial["stop_bits"]), "baudrate": int(_setting(serial["baudrate"], "baudrate"))},
            absent=tuple(wire.get("absent", ())), entries=tuple(entries))

    def unconfirmed(self) -> list[Entry]:
        """Every entry the manuals do not settle (its assumption and what would settle it)."""
        return [e for e in self.entries if not e.confirmed]

    def stand_unit_of_reply(self, token: str) -> StandUnit | None:
        return next((u for u in self.stand_units.values() if u.reply == token), None)

    def gauge_unit_of_reply(self, token: str) -> GaugeUnit | None:
        return next((u for u in self.gauge_units.values() if u.reply == token), None)
