"""The Flintec DAD 141.1 indicator as a LoadCell (its registers: configs/devices/flintec-dad141.toml).

One block read per sample (0x3500: gross, net, qualifier); the net float is in the unit
the indicator was calibrated in (it has no unit register), converted to N with the
profile's `unit` and `force_sign` (compression positive). zero() is the indicator's
"set zero" and tare() its "set tare" (bit commands at 0x2061).
"""

from __future__ import annotations

from .base import DeviceRefused, ForceReading, LoadCell, LoadCellStatus
from .modbus_link import DeviceOnLink, ModbusLink
from .registers import DeviceMap

#: Units a DAD 141.1 may be calibrated in (the profile's `[load_cell] unit`) -> N per unit;
#: "kg" is a cell calibrated with masses (kilogram-force).
UNIT_N = {"N": 1.0, "kN": 1000.0, "kg": 9.80665, "g": 0.00980665, "lbf": 4.4482216152605}


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
        self.device.command("bit_commands", "set_zero")

    def tare(self) -> None:
        self.device.command("bit_commands", "set_tare")
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
