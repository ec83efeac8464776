"""The Flintec DAD 141.1 indicator as a LoadCell (its registers: configs/devices/flintec-dad141.toml).

One block read per sample (0x3500: gross, net, qualifier); the net float is in the unit
the indicator was calibrated in (it has no unit register), converted to N with the
profile's `unit` and `force_sign` (compression positive). zero() is the indicator's
"set zero" and tare() its "set tare" (bit commands at 0x2061).
"""

from __future__ import annotations

from .base import DeviceRefused, ForceReading, LoadCell, LoadCellStatus
from .modbus_link import DeviceOnLink, ModbusLink
from .registers import UNIT_N, DeviceMap


class Dad141LoadCell(LoadCell):
    """Flintec DAD 141.1 load-cell indicator over Modbus RTU or TCP."""

    USES = dict(registers=("qualifier", "bit_commands"), blocks=("result",),
                bits={"qualifier": ("under_range", "over_range", "no_motion", "tare_set")},
                values={"bit_commands": ("set_zero", "set_tare")})

    @classmethod
    def check_device(cls, device: DeviceMap) -> DeviceMap:
        """The device file has what this driver uses (ValueError naming what is missing)."""
        device.require(**cls.USES)
        if not {"net", "qualifier"} <= {r.name for r in device.blocks["result"].layout}:
            raise ValueError(f"{device.file or device.id}: block 'result' must hold net and qualifier")
        return device

    def __init__(self, link: ModbusLink, device: DeviceMap, settings: dict):
        self.device = DeviceOnLink(link, self.check_device(device), int(settings["unit_id"]))
        self.capacity_N = float(settings["capacity_N"])      # from the cell's datasheet
        self.unit = settings.get("unit", "N")
        self._to_N = UNIT_N[self.unit] * int(settings.get("force_sign", 1))

    def _status(self, word: int) -> LoadCellStatus:
        bits = self.device.device.decode_bits("qualifier", word)
        return LoadCellStatus(under_range=bits["under_range"], over_range=bits["over_range"],
                              stable=bits["no_motion"], tare_set=bits["tare_set"])

    def read(self) -> ForceReading:
        values = self.device.read_block("result")
        return ForceReading(self._to_N * float(values["net"]), self._status(int(values["qualifier"])))

    def zero(self) -> None:
        self.device.command("bit_commands", "set_zero", repeatable=True)

    def tare(self) -> None:
        self.device.command("bit_commands", "set_tare", repeatable=True)
        # ST is disabled while the reading moves (S3 §10.5) and S1 does not say how Modbus
        # answers then: the qualifier's "tare set" bit says whether the tare was taken.
        word = int(self.device.read("qualifier"))
        if not self._status(word).tare_set:
            device = self.device.device
            command, qualifier = device.registers["bit_commands"], device.registers["qualifier"]
            raise DeviceRefused(
                f"{self.device.link.where}: unit {self.device.unit} did not take set_tare ({command.label()} = "
                f"0x{device.value('bit_commands', 'set_tare'):04X}): {qualifier.label()} reads 0x{word:04X}, "
                f"no tare bit (the reading was not stable)")

    # ------------------------------------------------------------------ commissioning (foamlab probe)
    def identify(self) -> str:
        firmware = int(self.device.read("firmware"))
        low = firmware & 0xFFFF
        return (f"{self.device.device.name}: device id {int(self.device.read('device_id'))}, "
                f"firmware {low & 0xFF}.{low >> 8:02d}")

    def self_checks(self) -> list[tuple[str, bool, str]]:
        """The reads that settle what S1 leaves open, on the unit as it is (docs: PROVENANCE.md).

        Separate reads are separate samples (noise): the float is compared with the Int32 within 20
        increments, and the block order is settled by a tare, which is exact inside one block read.
        """
        firmware = int(self.device.read("firmware"))
        checks = [("DAD 141.1 address base", firmware >> 16 == 0,
                   f"0x202E reads 0x{firmware:08X}: its high word must be 0 (S1 p.4)")]
        span = 0.01 * self.capacity_N / UNIT_N[self.unit]           # 1 % of the capacity, calibration unit
        gross, raw = float(self.device.read("gross")), int(self.device.read("gross_int"))
        # the Int32 counts increments (decimal point 0..5, S2 p.32): the float is one of raw / 10^k,
        # within 20 increments of noise between the two reads; the other word order is far off
        fits = any(abs(gross - raw / 10 ** k) <= 20 / 10 ** k for k in range(6))
        checks.append(("DAD 141.1 float word order", fits, f"0x2000 reads {gross:g} high word first, 0x2020 "
                                                          f"{raw} increments" + ("" if raw else " (no load: weak)")))
        net, block = float(self.device.read("net")), self.device.read_block("result")
        tare_in_block = block["gross"] - block["net"]           # exact: one sample
        if not self._status(int(block["qualifier"])).tare_set or abs(tare_in_block) < span:
            checks.append(("DAD 141.1 order of 0x3500", True, "not settled: tare a load (> 1 % of the capacity) "
                                                              "and probe again"))
        else:
            same = abs(tare_in_block - (gross - net)) < abs(tare_in_block + (gross - net))
            checks.append(("DAD 141.1 order of 0x3500", same, f"0x3500 holds {block['gross']:g}, {block['net']:g}; "
                                                              f"0x2000 gross {gross:g}, 0x2002 net {net:g}"))
        return checks
