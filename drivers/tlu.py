"""The Laumas TLU weight transmitter as a LoadCell (its registers: configs/devices/laumas-tlu.toml).

One function-03 read per sample: the block at 0x0006 (40007-40013: status, gross, net, peak;
L1 p.30). The weights are 32-bit integers, high word first, holding the displayed value without
its decimal point (L1 p.30, L3 p.3): the profile's `decimals` (what the display shows; the
layout of 40014 that would say it is not documented) and `unit` scale them to N.

zero() and tare() are refused, and nothing is sent: the TLU's command values for them come only
from third-party code for a sibling (the device file's `confirmed = false`), and a guessed value
in the command register is a command the TLU may well have for something else.
"""

from __future__ import annotations

from .base import DeviceRefused, ForceReading, LoadCell, LoadCellStatus
from .modbus_link import DeviceOnLink, ModbusLink
from .registers import UNIT_N, DeviceMap

#: Status bits (40007, L3 p.3) that mean the weight is beyond what the transmitter measures.
OVER_RANGE_BITS = ("over_9_divisions", "over_110_percent", "gross_overflow", "net_overflow")
#: Status bits that mean there is no weight to read at all: the read fails with the device's words.
ERROR_BITS = ("load_cell_error", "adc_error")
#: Decimals a TLU display can show (L3 p.12: divisions 100 .. 0.0001).
MAX_DECIMALS = 4


class UnconfirmedCommand(DeviceRefused):
    """A command whose value the manuals do not document for this device: refused, never sent."""


class TluLoadCell(LoadCell):
    """Laumas TLU weight transmitter over Modbus RTU (functions 03 and 16 only)."""

    USES = dict(registers=("firmware", "instrument_type", "command", "status", "gross", "net"),
                blocks=("sample",),
                bits={"status": (*OVER_RANGE_BITS, *ERROR_BITS, "gross_negative", "net_negative",
                                 "net_mode", "stable")},
                values={"command": ("semi_auto_zero", "tare")})

    @classmethod
    def check_device(cls, device: DeviceMap) -> DeviceMap:
        device.require(**cls.USES)
        if not {"status", "gross", "net"} <= {r.name for r in device.blocks["sample"].layout}:
            raise ValueError(f"{device.file or device.id}: block 'sample' must hold status, gross and net")
        return device

    @classmethod
    def check_profile(cls, settings: dict) -> None:
        """The profile's [load_cell] settings this driver needs (ValueError, one line)."""
        decimals = settings.get("decimals")
        if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= MAX_DECIMALS:
            raise ValueError(f"`decimals` must be 0..{MAX_DECIMALS}: the decimals the TLU's display shows "
                             f"(its register 40014 does not document them), got {decimals!r}")

    def __init__(self, link: ModbusLink, device: DeviceMap, settings: dict):
        self.check_profile(settings)
        self.device = DeviceOnLink(link, self.check_device(device), int(settings["unit_id"]))
        self.capacity_N = float(settings["capacity_N"])      # from the cell's datasheet
        self.unit = settings.get("unit", "N")
        self.decimals = int(settings["decimals"])
        self._to_N = UNIT_N[self.unit] * int(settings.get("force_sign", 1)) / 10 ** self.decimals

    def _where(self) -> str:
        return f"{self.device.link.where}: unit {self.device.unit} ({self.device.device.name})"

    def _bits(self, word: int) -> dict[str, bool]:
        bits = self.device.device.decode_bits("status", word)
        errors = [name for name in ERROR_BITS if bits[name]]
        if errors:
            raise DeviceRefused(f"{self._where()}: status 0x{word:04X} reports {' and '.join(errors)}: "
                                f"no weight to read")
        return bits

    @staticmethod
    def signed(value: int, negative: bool) -> int:
        """L3 p.3 sends the magnitude with the sign in the status; a two's-complement reading (L4
        p.46 writes them so) is already negative: both read right until a unit settles which."""
        return -value if negative and value > 0 else value

    def read(self) -> ForceReading:
        values = self.device.read_block("sample")
        bits = self._bits(int(values["status"]))
        net = self.signed(int(values["net"]), bits["net_negative"])
        status = LoadCellStatus(over_range=any(bits[name] for name in OVER_RANGE_BITS),
                                stable=bits["stable"], tare_set=bits["net_mode"])
        return ForceReading(self._to_N * net, status)

    def _command(self, action: str, name: str) -> None:
        device = self.device.device
        where = device.provenance[f"[values.command] {name}"]
        if where.confirmed:     # a value the manual settles may be sent (none is, today)
            self.device.command("command", name)
            return
        raise UnconfirmedCommand(
            f"{self._where()}: {action} refused, nothing sent: its command value {device.value('command', name)} "
            f"is from {where.source}, not a TLU manual; would settle it: {where.settle}")

    def zero(self) -> None:
        self._command("zero", "semi_auto_zero")

    def tare(self) -> None:
        self._command("tare", "tare")

    # ------------------------------------------------------------------ commissioning (foamlab probe)
    def identify(self) -> str:
        return (f"{self.device.device.name}: instrument type {int(self.device.read('instrument_type'))}, "
                f"firmware 0x{int(self.device.read('firmware')):04X} (encodings not documented)")

    def self_checks(self) -> list[tuple[str, bool, str]]:
        """The reads that test what the manuals leave open (docs: PROVENANCE.md, Laumas TLU)."""
        values = self.device.read_block("sample")
        bits = self._bits(int(values["status"]))
        gross = self.signed(int(values["gross"]), bits["gross_negative"])
        net = self.signed(int(values["net"]), bits["net_negative"])
        # without a tare gross and net are one value: inside one block read they must agree exactly
        same = bits["net_mode"] or gross == net
        return [
            ("Laumas TLU status bits", same,
             f"40007 = 0x{int(values['status']):04X} (net mode {'on' if bits['net_mode'] else 'off'}), gross {gross}, "
             f"net {net}" + ("" if same else ": gross != net without net mode - the LCB's bit map (L3 p.3) is not "
                                             "the TLU's")),
            ("Laumas TLU decimals", True,
             f"not settled by a read: the force {self._to_N * net:g} N uses {self.decimals} decimals "
             f"(the profile's); the display must show {net / 10 ** self.decimals:.{self.decimals}f} {self.unit}"),
        ]
