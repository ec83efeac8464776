"""The fourth device, Laumas TLU (configs/devices/laumas-tlu.toml): described from its manual, no driver.

L1 = Laumas "Installation and User Manual, TLU - TLUANA" v1.04 p.30: registers 40001-40019 in
Modicon numbering (PDU address = number - 40001), 32-bit weights high word first, functions 03
and 16 only. What the manuals leave open is unconfirmed in the file; a profile naming it is refused.
"""

from __future__ import annotations

import copy
import tomllib

import pytest

from drivers.modbus import device_map
from drivers.profile import DEVICES_DIR, ProfileError, load_profile, validate_profile
from drivers.registers import DeviceMap

pytestmark = pytest.mark.timeout(30)


@pytest.fixture(scope="module")
def tlu() -> DeviceMap:
    with (DEVICES_DIR / "laumas-tlu.toml").open("rb") as f:
        return DeviceMap.from_toml(tomllib.load(f), "laumas-tlu.toml")


def test_the_documented_registers_at_their_pdu_addresses(tlu):
    # 40006 command, 40007 status, 40008/40010/40012 gross/net/peak high words (L1 p.30)
    assert {n: r.address for n, r in tlu.registers.items() if n in ("command", "status", "gross", "net", "peak")} \
        == {"command": 0x0005, "status": 0x0006, "gross": 0x0007, "net": 0x0009, "peak": 0x000B}
    assert tlu.functions == {3, 16} and tlu.word_order == "big"
    assert all(r.type != "float32" for r in tlu.registers.values())            # no floats documented
    assert tlu.blocks["sample"].count == 7 and not tlu.blocks["sample"].is_copy
    assert tlu.exceptions == {1: "illegal function", 2: "illegal data address", 3: "illegal data value"}


def test_what_only_third_party_code_says_is_unconfirmed(tlu):
    assert tlu.value("command", "save_eeprom") == 99 and tlu.provenance["[values.command] save_eeprom"].confirmed
    for name in ("semi_auto_zero", "tare"):
        where = tlu.provenance[f"[values.command] {name}"]
        assert not where.confirmed and where.source.startswith("T1") and where.settle
    assert all(not tlu.provenance[f"[bits.status] {name}"].confirmed for name in tlu.bits["status"])
    assert all(p.source for p in tlu.provenance.values())


def test_a_profile_naming_it_is_refused_until_it_has_a_driver():
    profile = copy.deepcopy(load_profile("sim-modbus-rtu"))
    profile["load_cell"]["device"] = "laumas-tlu"
    with (DEVICES_DIR / "laumas-tlu.toml").open("rb") as f:
        profile["wire"]["load_cell"] = tomllib.load(f)
    with pytest.raises(ValueError, match=r"laumas-tlu.toml: no load_cell driver for laumas-tlu"):
        device_map(profile, "load_cell")
    with pytest.raises(ProfileError, match=r"no load_cell driver for laumas-tlu"):
        validate_profile(profile)
