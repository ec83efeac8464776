"""Machine profiles: load a profile TOML, merge its wire contract, validate, open the machine.

A profile (configs/machines/<name>.toml) names the protocol, the connection, the
devices' settings and the safety limits; it references the wire contract by file
name (`command_set = "_mark10_commands.toml"`); a Modbus profile names its two devices
(`[load_cell] device = "flintec-dad141"`, `[crosshead] device = "leadshine-cs2rs"`), whose
device files (configs/devices/<id>.toml) are the registers as the manuals document them.

`load_profile()` returns the profile as a plain dict, exactly as in the TOML, plus:
  - "wire":   the referenced command set, loaded (a dict); for Modbus {"load_cell": ...,
              "crosshead": ...}, the two device files, loaded;
  - "source": the path of the profile file (str).
The original `command_set` / `device` keys keep their names.

Errors in a profile raise ProfileError (a ValueError) with a one-line message naming
the file and the key; `drivers` knows nothing of `foamlab`, the caller turns it into
its own user error.
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any

from .ascii import AsciiMachine, CommandSet, profile_units
from .base import Machine
from .cs2rs import motor_rpm, ramp_ms
from .device_file import FileReader
from .modbus import DRIVERS, ModbusMachine, device_map
from .registers import UNIT_N

#: The repository's machine profiles (used when no directory is given).
MACHINES_DIR = Path(__file__).resolve().parent.parent / "configs" / "machines"
#: The repository's device files (a profile's own configs folder may hold its own `devices/`).
DEVICES_DIR = MACHINES_DIR.parent / "devices"

PROTOCOLS = ("modbus", "ascii")
TRANSPORTS = ("tcp", "rtu")
PARITIES = ("N", "E", "O", "M", "S")

#: Connection keys `open_machine(**overrides)` accepts, with their expected type.
CONNECTION_OVERRIDES = {
    "host": str, "port": int, "port_url": str, "transport": str, "baudrate": int,
    "parity": str, "stopbits": int, "timeout_s": float, "retries": int,
}
#: Top-level profile keys `open_machine(**overrides)` accepts.
PROFILE_OVERRIDES: dict[str, type] = {}


class ProfileError(ValueError):
    """A machine profile (or its register map / command set) is missing or invalid."""


# --------------------------------------------------------------------------- loading

def _machines_dir(configs_dir: str | Path | None) -> Path:
    if configs_dir is None:
        return MACHINES_DIR
    configs_dir = Path(configs_dir)
    return configs_dir / "machines" if (configs_dir / "machines").is_dir() else configs_dir


def available_profiles(configs_dir: str | Path | None = None) -> list[str]:
    """Profile names in the machines directory (files starting with `_` are wire contracts)."""
    folder = _machines_dir(configs_dir)
    return sorted(p.stem for p in folder.glob("*.toml") if not p.name.startswith("_"))


def _resolve(name_or_path: str | Path, configs_dir: str | Path | None) -> Path:
    candidate = Path(name_or_path)
    looks_like_path = isinstance(name_or_path, Path) or candidate.suffix == ".toml" or len(candidate.parts) > 1
    if looks_like_path:
        if candidate.is_file():
            return candidate
        folder_candidate = _machines_dir(configs_dir) / candidate.name
        if len(candidate.parts) == 1 and folder_candidate.is_file():
            return folder_candidate
        raise ProfileError(f"machine profile file not found: {candidate}")
    named = _machines_dir(configs_dir) / f"{name_or_path}.toml"
    if named.is_file():
        return named
    names = ", ".join(available_profiles(configs_dir)) or "none"
    raise ProfileError(f"unknown machine profile {name_or_path!r} (available: {names})")


def _read_toml(path: Path) -> dict:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except OSError as exc:
        raise ProfileError(f"cannot read {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path.name}: not valid TOML: {exc}") from None


def load_profile(name_or_path: str | Path, configs_dir: str | Path | None = None) -> dict:
    """Load, merge and validate a machine profile.

    `name_or_path` is a bare profile name ("sim-modbus-tcp", looked up in
    `configs_dir` — a configs folder holding `machines/`, or the machines folder
    itself — default the repository's configs/machines) or a path to a .toml file.
    """
    path = _resolve(name_or_path, configs_dir)
    profile = _read_toml(path)
    profile.setdefault("name", path.stem)
    profile["source"] = str(path)
    protocol = profile.get("protocol")
    if protocol not in PROTOCOLS:
        raise ProfileError(f"{path.name}: protocol must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    if protocol == "modbus":      # two devices, each named by its [load_cell] / [crosshead] `device`
        profile["wire"] = {role: _read_toml(_device_file(profile, role, path)) for role in ("load_cell", "crosshead")}
        validate_profile(profile)
        return profile
    wire_key = "command_set"
    wire_name = profile.get(wire_key)
    if not isinstance(wire_name, str) or not wire_name:
        raise ProfileError(f"{path.name}: protocol {protocol!r} needs `{wire_key} = \"FILE.toml\"`")
    wire_path = Path(wire_name)
    if not wire_path.is_absolute():
        wire_path = path.parent / wire_path
    if not wire_path.is_file():
        raise ProfileError(f"{path.name}: {wire_key} file not found: {wire_path}")
    profile["wire"] = _read_toml(wire_path)
    validate_profile(profile)
    return profile


def _device_file(profile: dict, role: str, profile_path: Path) -> Path:
    """`device = "ID"` -> devices/ID.toml beside the profile's machines folder, else the repository's;
    `device = "FILE.toml"` -> that file (relative to the profile)."""
    name = profile.get(role, {}).get("device") if isinstance(profile.get(role), dict) else None
    if not isinstance(name, str) or not name:
        raise ProfileError(f"{profile_path.name}: [{role}] needs `device = \"ID\"` (a file in configs/devices)")
    if name.endswith(".toml"):
        candidates = [profile_path.parent / name]
    else:
        candidates = [profile_path.parent.parent / "devices" / f"{name}.toml", DEVICES_DIR / f"{name}.toml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ProfileError(f"{profile_path.name}: [{role}] device file not found: {candidates[0]}")


# --------------------------------------------------------------------------- validation

class _Checker(FileReader):
    """Small helper so every message names the file and the key."""

    def __init__(self, profile: dict):
        super().__init__(Path(profile.get("source", "<profile>")).name, ProfileError)

    def number(self, table: dict, key: str, where: str, *, positive=False, optional=False, integer=False):
        value = table.get(key)
        if value is None and optional:
            return None
        ok_type = isinstance(value, int) if integer else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok_type or not math.isfinite(value):
            kind = "an integer" if integer else "a number"
            self.fail(where, f"`{key}` must be {kind}, got {value!r}")
        if positive and value <= 0:
            self.fail(where, f"`{key}` must be > 0, got {value!r}")
        return value

    def choice(self, table: dict, key: str, where: str, choices) -> str:
        value = table.get(key)
        if value not in choices:
            self.fail(where, f"`{key}` must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value


def validate_profile(profile: dict) -> None:
    """Raise ProfileError on the first problem; return None when the profile is usable."""
    c = _Checker(profile)
    connection = c.table(profile, "connection", "")
    c.number(connection, "timeout_s", "[connection]", positive=True)
    retries = c.number(connection, "retries", "[connection]", integer=True)
    if retries < 0:
        c.fail("[connection]", f"`retries` must be >= 0, got {retries}")
    load_cell = c.table(profile, "load_cell", "")
    capacity = c.number(load_cell, "capacity_N", "[load_cell]", positive=True)
    sign = load_cell.get("force_sign", 1)
    if sign not in (1, -1):
        c.fail("[load_cell]", f"`force_sign` must be 1 or -1, got {sign!r}")
    crosshead = c.table(profile, "crosshead", "")
    c.number(crosshead, "max_speed_mm_min", "[crosshead]", positive=True)
    c.number(crosshead, "acceleration_mm_s2", "[crosshead]", positive=True, optional=True)
    limits = c.table(profile, "limits", "")
    force_limit = c.number(limits, "force_N", "[limits]", positive=True)
    if force_limit > capacity:
        c.fail("[limits]", f"`force_N` ({force_limit}) exceeds the load-cell capacity ({capacity})")
    upper = c.number(limits, "travel_upper_mm", "[limits]")
    lower = c.number(limits, "travel_lower_mm", "[limits]")
    if not upper < lower:
        c.fail("[limits]", f"`travel_upper_mm` ({upper}) must be smaller than `travel_lower_mm` ({lower}); positions grow downward")
    c.number(limits, "max_speed_mm_min", "[limits]", positive=True)

    if profile["protocol"] == "modbus":
        _validate_modbus(profile, c)
    else:
        _validate_ascii(profile, c)


def _validate_modbus(profile: dict, c: _Checker) -> None:
    for key, why in (("word_order", "is the device's ([device.word_order] in its device file)"),
                     ("register_map", "is gone: name the devices (`[load_cell] device`, `[crosshead] device`)")):
        if key in profile:
            c.fail("", f"`{key}` {why}")
    connection = profile["connection"]
    transport = c.choice(connection, "transport", "[connection]", TRANSPORTS)
    if transport == "tcp":
        if not isinstance(connection.get("host"), str) or not connection["host"]:
            c.fail("[connection]", "`host` must be a host name or address")
        port = c.number(connection, "port", "[connection]", integer=True)
        if not 0 < port < 65536:
            c.fail("[connection]", f"`port` must be 1..65535, got {port}")
    else:
        if not isinstance(connection.get("port_url"), str) or not connection["port_url"]:
            c.fail("[connection]", "`port_url` must be a pyserial URL or device path")
        c.number(connection, "baudrate", "[connection]", integer=True, positive=True)
        if connection.get("parity", "N") not in PARITIES:
            c.fail("[connection]", f"`parity` must be one of {', '.join(PARITIES)}")
        if connection.get("stopbits", 1) not in (1, 2):
            c.fail("[connection]", "`stopbits` must be 1 or 2")
    units = [c.number(profile[role], "unit_id", f"[{role}]", integer=True) for role in ("load_cell", "crosshead")]
    for role, unit in zip(("load_cell", "crosshead"), units):
        if not 1 <= unit <= 247:
            c.fail(f"[{role}]", f"`unit_id` must be 1..247, got {unit}")
    if units[0] == units[1]:
        c.fail("[crosshead]", f"`unit_id` {units[1]} is the load cell's too: two devices on one link need two ids")
    devices = {}
    for role in ("load_cell", "crosshead"):    # building a device map checks every entry of its file
        try:
            devices[role] = device_map(profile, role)
        except ValueError as exc:
            raise ProfileError(str(exc)) from None
    if profile["load_cell"].get("unit", "N") not in UNIT_N:
        c.fail("[load_cell]", f"`unit` must be one of {', '.join(UNIT_N)} (what the indicator is calibrated in)")
    check_profile = getattr(DRIVERS["load_cell"][devices["load_cell"].id], "check_profile", None)
    if check_profile is not None:    # settings a driver needs beyond the common ones (the TLU's decimals)
        try:
            check_profile(profile["load_cell"])
        except ValueError as exc:
            c.fail("[load_cell]", str(exc))
    _validate_screw(profile["crosshead"], devices["crosshead"], c)


def _validate_screw(crosshead: dict, drive, c: _Checker) -> None:
    """The drive's scaling: screw lead, gear ratio, pulses per motor revolution, ramps in its units."""
    if "watchdog_ms" in crosshead:
        c.fail("[crosshead]", f"`watchdog_ms`: the {drive.name} has no documented host watchdog (its device file)")
    lead = c.number(crosshead, "lead_mm", "[crosshead]", positive=True)
    gear = c.number(crosshead, "gear_ratio", "[crosshead]", positive=True)
    ppr = c.number(crosshead, "pulses_per_rev", "[crosshead]", integer=True, positive=True)
    low, high = drive.registers["pulses_per_rev"].range or (1, 0xFFFF)
    if not low <= ppr <= high:
        c.fail("[crosshead]", f"`pulses_per_rev` must be {low}..{high} (the drive's Pr0.00), got {ppr}")
    acceleration = c.number(crosshead, "acceleration_mm_s2", "[crosshead]", positive=True)
    if not ramp_ms(acceleration, lead, gear) <= 0xFFFF:
        c.fail("[crosshead]", f"`acceleration_mm_s2` {acceleration} is slower than the drive's ramp register holds")
    top = motor_rpm(crosshead["max_speed_mm_min"], lead, gear)
    if top > 0xFFFF:
        c.fail("[crosshead]", f"`max_speed_mm_min` is {top:.0f} rpm at the motor: beyond the drive's speed register")


def _validate_ascii(profile: dict, c: _Checker) -> None:
    connection = profile["connection"]
    if not isinstance(connection.get("port_url"), str) or not connection["port_url"]:
        c.fail("[connection]", "`port_url` must be a pyserial URL or device path")
    c.number(connection, "baudrate", "[connection]", integer=True, positive=True)
    try:
        commands = CommandSet.from_toml(profile["wire"])
    except ValueError as exc:
        raise ProfileError(f"{profile['command_set']}: {exc}") from None
    try:   # the profile's units and travel sign, against what the device file offers
        profile_units(profile, commands)
    except ValueError as exc:
        c.fail("", str(exc))


# --------------------------------------------------------------------------- opening

def apply_overrides(profile: dict, **overrides: Any) -> dict:
    """A validated copy of `profile` with connection settings replaced (None values are ignored)."""
    result = copy.deepcopy(profile)
    for key, value in overrides.items():
        if value is None:
            continue
        if key in CONNECTION_OVERRIDES:
            kind = CONNECTION_OVERRIDES[key]
            try:
                value = kind(value)
            except (TypeError, ValueError):
                raise ProfileError(f"override {key}={value!r}: expected {kind.__name__}") from None
            result["connection"][key] = value
        elif key in PROFILE_OVERRIDES:
            result[key] = value
        else:
            known = ", ".join(sorted({*CONNECTION_OVERRIDES, *PROFILE_OVERRIDES}))
            raise ProfileError(f"unknown machine override {key!r} (known: {known})")
    validate_profile(result)
    return result


def open_machine(profile: dict | str | Path, *, connect: bool = True, **overrides: Any) -> Machine:
    """Build the machine a profile describes and (by default) connect it.

    `profile` is a loaded profile, or a name / path for load_profile().
    `overrides` replace connection settings: host, port, port_url, transport,
    baudrate, parity, stopbits, timeout_s and retries. Use it as a
    context manager to be sure it is closed: `with open_machine(p) as m: ...`
    (connect() is idempotent).
    """
    if not isinstance(profile, dict):
        profile = load_profile(profile)
    profile = apply_overrides(profile, **overrides)
    if profile["protocol"] == "modbus":
        machine: Machine = ModbusMachine(profile)
    else:
        machine = AsciiMachine(profile)
    if connect:
        machine.connect()
    return machine
