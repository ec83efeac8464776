"""A Modbus device as its manual documents it: the device file (configs/devices/<id>.toml), read once.

A device file lists the device's registers, blocks, status bits and command / code values,
each with the `source` that documents it (manual short name + section/page) and, where the
manual does not settle it, `confirmed = false` with `settle` (what would). What the manual
does not document is not in the file. `DeviceMap.from_toml()` checks all of that and gives
the drivers and the simulator one typed description (PyMeasure-style: data, not code):

    [registers.net]
    address = 0x2002
    type = "float32"
    access = "r"
    unit = "calibration unit"
    source = "S1 p.3 (Index 2002 Net Weight, Float)"

`drivers` knows nothing of `foamlab`: errors are ValueError with one line naming the entry.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Sequence

from .device_file import Entry, FileReader

#: Register types a device file may use -> struct format (big-endian bytes inside a register).
TYPES = {"uint16": "H", "int16": "h", "uint32": "I", "int32": "i", "float32": "f"}
#: Order of the two registers of a 32-bit value: "big" = high word first (ABCD).
WORD_ORDERS = ("big", "little")
ACCESS = ("r", "w", "rw")
KINDS = ("load_cell", "crosshead")
#: Units an indicator may be calibrated in (a profile's `[load_cell] unit`) -> N per unit;
#: "kg" is a cell calibrated with masses (kilogram-force).
UNIT_N = {"N": 1.0, "kN": 1000.0, "kg": 9.80665, "g": 0.00980665, "lbf": 4.4482216152605}


@dataclass(frozen=True)
class Register:
    """One value: a 16-bit register, or a 32-bit value over two registers."""

    name: str
    address: int
    type: str
    access: str = "r"
    unit: str = ""
    range: tuple[int, int] | None = None     # documented limits of a setting, when given

    @property
    def count(self) -> int:
        return 2 if self.type.endswith("32") else 1

    @property
    def span(self) -> range:
        return range(self.address, self.address + self.count)

    def decode(self, words: Sequence[int], word_order: str) -> int | float:
        words = list(words)[::-1] if word_order == "little" else list(words)
        return struct.unpack(">" + TYPES[self.type], b"".join(w.to_bytes(2, "big") for w in words))[0]

    def encode(self, value: int | float, word_order: str) -> list[int]:
        fmt = TYPES[self.type]
        if fmt != "f":
            value = int(value)
            bits = 16 * self.count
            low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if fmt.islower() else (0, (1 << bits) - 1)
            if not low <= value <= high:
                raise ValueError(f"{value} does not fit register {self.label()} ({self.type})")
        raw = struct.pack(">" + fmt, value)
        words = [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]
        return words[::-1] if word_order == "little" else words

    def label(self) -> str:
        return f"{self.name} (0x{self.address:04X})"


@dataclass(frozen=True)
class Block:
    """Consecutive registers read or written in one request.

    A block at its first register's own address groups those registers (the drive's PR0
    path); a block elsewhere is a copy the device keeps for one read (the indicator's 0x3500).
    """

    name: str
    address: int
    count: int
    layout: tuple[Register, ...]

    @property
    def is_copy(self) -> bool:
        return self.address != self.layout[0].address

    def decode(self, words: Sequence[int], word_order: str) -> dict[str, int | float]:
        values, offset = {}, 0
        for register in self.layout:
            values[register.name] = register.decode(words[offset:offset + register.count], word_order)
            offset += register.count
        return values

    def encode(self, values: dict[str, int | float], word_order: str) -> list[int]:
        return [w for register in self.layout for w in register.encode(values[register.name], word_order)]

    def label(self) -> str:
        return f"{self.name} (0x{self.address:04X}, {self.count} registers)"


@dataclass(frozen=True)
class DeviceMap:
    """One device file, typed. `bits[register][name]` = bit number; `values[register][name]` =
    a command or code value of that register; `meanings[register][value]` = its words."""

    id: str
    name: str
    kind: str
    word_order: str
    functions: frozenset[int]
    registers: dict[str, Register]
    blocks: dict[str, Block]
    bits: dict[str, dict[str, int]]
    values: dict[str, dict[str, int]]
    meanings: dict[str, dict[int, str]]
    exceptions: dict[int, str]
    provenance: dict[str, Entry] = field(default_factory=dict, compare=False)
    file: str = field(default="", compare=False)     # where it was read from, for messages

    # ------------------------------------------------------------------ reading a device file
    @classmethod
    def from_toml(cls, data: dict, where: str = "device file") -> "DeviceMap":
        """Build and check the description; ValueError (one line, naming the entry) when wrong."""
        reader = _Reader(where)
        device = reader.table(data, "device", "")
        ident = reader.text(device, "id", "[device]")
        kind = reader.text(device, "kind", "[device]")
        if kind not in KINDS:
            reader.fail("[device]", f"`kind` must be one of {', '.join(KINDS)}, got {kind!r}")
        word_order = reader.documented(device, "word_order", "[device]")
        if word_order not in WORD_ORDERS:
            reader.fail("[device] word_order", f"must be one of {', '.join(WORD_ORDERS)}, got {word_order!r}")
        for key, item in device.items():    # every documented property of the device
            if isinstance(item, dict):
                reader.provenance(item, f"[device.{key}]")
        functions = reader.documented(device, "functions", "[device]")
        if not isinstance(functions, list) or not all(isinstance(f, int) and 0 < f < 128 for f in functions):
            reader.fail("[device] functions", "must be a list of Modbus function codes")

        registers = {name: reader.register(name, entry)
                     for name, entry in reader.table(data, "registers", "").items()}
        blocks = {name: reader.block(name, entry, registers)
                  for name, entry in data.get("blocks", {}).items()}
        bits = {reg: {name: reader.number(entry, "bit", f"[bits.{reg}] {name}", 0, 15)
                      for name, entry in reader.entries(data, "bits", reg, registers).items()}
                for reg in data.get("bits", {})}
        values, meanings = {}, {}
        for reg in data.get("values", {}):
            entries = reader.entries(data, "values", reg, registers)
            values[reg] = {name: reader.number(entry, "value", f"[values.{reg}] {name}", 0, 0xFFFF)
                           for name, entry in entries.items()}
            meanings[reg] = {values[reg][name]: str(entry.get("meaning", name.replace("_", " ")))
                             for name, entry in entries.items()}
        exceptions = {}
        for name, entry in data.get("exceptions", {}).items():
            reader.provenance(entry, f"[exceptions] {name}")
            exceptions[reader.number(entry, "code", f"[exceptions] {name}", 1, 0x7F)] = str(entry.get("meaning", name))
        return cls(ident, str(device.get("name", ident)), kind, word_order, frozenset(functions), registers, blocks,
                   bits, values, meanings, exceptions, reader.seen, where)

    # ------------------------------------------------------------------ what a driver uses
    def require(self, registers: Sequence[str] = (), blocks: Sequence[str] = (),
                bits: dict[str, Sequence[str]] | None = None,
                values: dict[str, Sequence[str]] | None = None) -> "DeviceMap":
        """Check that the names a driver uses exist; ValueError naming the first missing one."""
        for name in registers:
            if name not in self.registers:
                raise ValueError(f"{self.file or self.id}: lacks register {name!r}")
        for name in blocks:
            if name not in self.blocks:
                raise ValueError(f"{self.file or self.id}: lacks block {name!r}")
        for table, wanted in (("bits", bits or {}), ("values", values or {})):
            for register, names in wanted.items():
                for name in names:
                    if name not in getattr(self, table).get(register, {}):
                        raise ValueError(f"{self.file or self.id}: [{table}.{register}] lacks {name!r}")
        return self

    def decode_bits(self, register: str, word: int) -> dict[str, bool]:
        return {name: bool(word >> bit & 1) for name, bit in self.bits[register].items()}

    def value(self, register: str, name: str) -> int:
        return self.values[register][name]

    def meaning(self, register: str, value: int) -> str | None:
        return self.meanings.get(register, {}).get(value)


def profile_device(profile: dict, role: str) -> DeviceMap:
    """The device a loaded machine profile names for `role` ("load_cell" / "crosshead"), as its
    device file describes it (drivers.profile loads the file into profile["wire"][role])."""
    name = profile[role]["device"]
    device = DeviceMap.from_toml(profile["wire"][role], name if name.endswith(".toml") else f"{name}.toml")
    if device.kind != role:
        raise ValueError(f"{device.file}: a {device.kind} device cannot be the {role}")
    return device


class _Reader(FileReader):
    """Reads a Modbus device file's entries, keeping each one's provenance."""

    def __init__(self, where: str):
        super().__init__(where)
        self.seen: dict[str, Entry] = {}

    def text(self, table: dict, key: str, entry: str) -> str:
        value = table.get(key)
        if not isinstance(value, str) or not value:
            self.fail(entry, f"`{key}` must be a non-empty string")
        return value

    def number(self, table: dict, key: str, entry: str, low: int, high: int) -> int:
        value = table.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            self.fail(entry, f"`{key}` must be an integer {low}..{high}, got {value!r}")
        return value

    def provenance(self, entry: dict, name: str) -> Entry:
        self.seen[name] = self.entry(entry, name)
        return self.seen[name]

    def documented(self, device: dict, key: str, entry: str):
        """A device property given as { value = ..., source = ... } (its source is checked with the rest)."""
        item = device.get(key)
        if not isinstance(item, dict):
            self.fail(f"{entry} {key}", "must be a table with `value` and `source`")
        return item.get("value")

    def register(self, name: str, entry: dict) -> Register:
        where = f"[registers.{name}]"
        self.provenance(entry, where)
        address = self.number(entry, "address", where, 0, 0xFFFF)
        kind = entry.get("type")
        if kind not in TYPES:
            self.fail(where, f"`type` must be one of {', '.join(TYPES)}, got {kind!r}")
        access = entry.get("access", "r")
        if access not in ACCESS:
            self.fail(where, f"`access` must be one of {', '.join(ACCESS)}, got {access!r}")
        limits = entry.get("range")
        if limits is not None and not (isinstance(limits, list) and len(limits) == 2
                                       and all(isinstance(v, int) for v in limits) and limits[0] <= limits[1]):
            self.fail(where, "`range` must be [low, high]")
        return Register(name, address, kind, access, str(entry.get("unit", "")), tuple(limits) if limits else None)

    def block(self, name: str, entry: dict, registers: dict[str, Register]) -> Block:
        where = f"[blocks.{name}]"
        self.provenance(entry, where)
        address = self.number(entry, "address", where, 0, 0xFFFF)
        try:
            layout = tuple(registers[r] for r in entry.get("layout", ()))
        except KeyError as exc:
            self.fail(where, f"layout names unknown register {exc.args[0]!r}")
        if not layout:
            self.fail(where, "needs a `layout` of register names")
        count = entry.get("count")
        if count != sum(r.count for r in layout):
            self.fail(where, f"count {count!r} does not match its layout ({sum(r.count for r in layout)} registers)")
        block = Block(name, address, count, layout)
        if not block.is_copy and any(a.address + a.count != b.address for a, b in zip(layout, layout[1:])):
            self.fail(where, "groups registers that are not consecutive")
        return block

    def entries(self, data: dict, table: str, register: str, registers: dict[str, Register]) -> dict:
        if register not in registers:
            self.fail(f"[{table}.{register}]", "names no register of this device")
        entries = data[table][register]
        for name, entry in entries.items():
            self.provenance(entry, f"[{table}.{register}] {name}")
        return entries
