"""Machine profiles: lookup, merge of the wire contract, validation messages, overrides."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from drivers.ascii import AsciiMachine
from drivers.modbus import ModbusMachine, device_map
from drivers.profile import MACHINES_DIR, ProfileError, available_profiles, load_profile, open_machine

pytestmark = pytest.mark.timeout(30)

#: The ESM303's device file, as a path from the machines folder (profiles name it so).
MARK10 = "../devices/mark10-esm303.toml"
#: The Modbus profiles' device files (named by id: `device = "flintec-dad141"`).
DAD, CS2RS = "../devices/flintec-dad141.toml", "../devices/leadshine-cs2rs.toml"


@pytest.fixture
def machines(tmp_path: Path) -> Path:
    """A copy of the repository's machine profiles (and the device files they name) to break."""
    folder = tmp_path / "machines"
    shutil.copytree(MACHINES_DIR, folder)
    shutil.copytree(MACHINES_DIR.parent / "devices", tmp_path / "devices")
    return folder


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path.name}"
    path.write_text(text.replace(old, new, 1))


def test_repository_profiles_load_and_merge_their_wire_contract():
    assert {"sim-modbus-tcp", "sim-modbus-rtu", "sim-serial"} <= set(available_profiles())
    tcp = load_profile("sim-modbus-tcp")
    assert (tcp["load_cell"]["device"], tcp["crosshead"]["device"]) == ("flintec-dad141", "leadshine-cs2rs")
    assert tcp["wire"]["load_cell"]["blocks"]["result"]["address"] == 0x3500
    assert tcp["wire"]["crosshead"]["registers"]["motor_position"]["address"] == 0x602C
    assert tcp["source"].endswith("sim-modbus-tcp.toml")
    serial = load_profile("sim-serial")
    assert serial["wire"]["stand"]["commands"]["read_sample"]["send"] == "n"


def test_profile_by_path_and_by_configs_dir(machines: Path):
    assert load_profile(machines / "sim-serial.toml")["name"] == "sim-serial"
    assert load_profile(str(machines / "sim-serial.toml"))["name"] == "sim-serial"
    assert load_profile("sim-serial", configs_dir=machines.parent)["source"] == str(machines / "sim-serial.toml")
    assert load_profile("sim-serial", configs_dir=machines)["name"] == "sim-serial"


def test_unknown_name_lists_the_available_profiles():
    with pytest.raises(ProfileError, match=r"unknown machine profile 'nope' \(available: .*sim-modbus-tcp"):
        load_profile("nope")


def test_missing_file():
    with pytest.raises(ProfileError, match="not found"):
        load_profile("/nonexistent/x.toml")


@pytest.mark.parametrize("file,old,new,message", [
    ("sim-modbus-tcp.toml", 'protocol = "modbus"', 'protocol = "can"', r"protocol must be one of modbus, ascii, got 'can'"),
    ("sim-modbus-tcp.toml", "\n[connection]", 'word_order = "big"\n[connection]', r"`word_order` is the device's"),
    ("sim-modbus-tcp.toml", "port = 5020", "port = 70000", r"\[connection\] `port` must be 1..65535"),
    ("sim-modbus-tcp.toml", "timeout_s = 0.04", "timeout_s = 0", r"`timeout_s` must be > 0"),
    ("sim-modbus-tcp.toml", 'transport = "tcp"', 'transport = "udp"', r"`transport` must be one of tcp, rtu"),
    ("sim-modbus-tcp.toml", "unit_id = 2", "unit_id = 300", r"\[crosshead\] `unit_id` must be 1..247"),
    ("sim-modbus-tcp.toml", "force_N = 450.0", "force_N = 600.0", r"exceeds the load-cell capacity"),
    ("sim-modbus-tcp.toml", "travel_upper_mm = -20.0", "travel_upper_mm = 80.0", r"must be smaller than"),
    ("sim-modbus-tcp.toml", 'device = "leadshine-cs2rs"', 'device = "leadshine-cs3"',
     r"\[crosshead\] device file not found: .*leadshine-cs3.toml"),
    ("sim-modbus-tcp.toml", 'device = "flintec-dad141"', 'device = "leadshine-cs2rs"',
     r"leadshine-cs2rs.toml: a crosshead device cannot be the load_cell"),
    ("sim-modbus-tcp.toml", "unit_id = 2", "unit_id = 1", r"\[crosshead\] `unit_id` 1 is the load cell's too"),
    ("sim-modbus-tcp.toml", "acceleration_mm_s2 = 50.0", "acceleration_mm_s2 = 50.0\nwatchdog_ms = 2000",
     r"`watchdog_ms`: the Leadshine CS2RS has no documented host watchdog"),
    ("sim-modbus-tcp.toml", "pulses_per_rev = 10000", "pulses_per_rev = 100", r"`pulses_per_rev` must be 200..51200"),
    ("sim-modbus-tcp.toml", "lead_mm = 4.0", "lead = 4.0", r"\[crosshead\] `lead_mm` must be a number"),
    ("sim-modbus-tcp.toml", 'unit = "N"', 'unit = "stone"', r"\[load_cell\] `unit` must be one of N, kN, kg"),
    ("sim-modbus-tcp.toml", "retries = 1", 'retries = "one"', r"`retries` must be an integer"),
    ("sim-modbus-rtu.toml", 'port_url = "socket://127.0.0.1:5021"', 'port_url = ""', r"`port_url` must be"),
    ("sim-serial.toml", 'command_set = "../devices/mark10-esm303.toml"', "", r"needs `command_set"),
    (DAD, 'type = "float32"\naccess = "r"\nunit = "calibration unit"\nsource = "S1 p.3 (Index 2002',
     'type = "float64"\naccess = "r"\nunit = "calibration unit"\nsource = "S1 p.3 (Index 2002',
     r"flintec-dad141.toml: \[registers.net\] `type` must be one of"),
    (DAD, 'source = "S1 p.3 (Index 2002 Net Weight, Float, R); S2 p.40 (GN)"', "",
     r"flintec-dad141.toml: \[registers.net\] needs a `source`"),
    (DAD, 'count = 5\nlayout = ["gross", "net"', 'count = 6\nlayout = ["gross", "net"',
     r"\[blocks.result\] count 6 does not match its layout \(5 registers\)"),
    (CS2RS, 'settle = "the unit (ms per 1000 rpm) is not on a manual page read: time a move of known length on the bench"',
     "", r"leadshine-cs2rs.toml: \[registers.pr0_accel\] is `confirmed = false`: say what would settle it"),
    (CS2RS, "quick_stop  = { value = 0x0040", "stop  = { value = 0x0040",
     r"leadshine-cs2rs.toml: \[values.trigger\] lacks 'quick_stop'"),
    ("sim-serial.toml", "travel_sign = 1", "travel_sign = 2", r"sim-serial.toml: \[crosshead\] `travel_sign` must be 1 or -1"),
    ("sim-serial.toml", 'force_unit = "N"', 'force_unit = "lb"', r"sim-serial.toml: \[load_cell\] `force_unit` must be one of N,"),
    (MARK10, "[stand.commands.read_sample]", "[stand.commands.read_samples]",
     r"mark10-esm303.toml: \[stand.commands\] lacks read_sample"),
    (DAD, 'layout = ["gross", "net", "qualifier"]', 'layout = ["gross", "peak", "qualifier"]',
     r"flintec-dad141.toml: block 'result' must hold net and qualifier"),
    (MARK10, '"*10" = "illegal command"', '"E10" = "illegal command"', r"\[gauge.errors\] 'E10' must look like"),
    (MARK10, 'settle = "capture: send `x`; the reply', 'note = "',
     r"mark10-esm303.toml: \[stand.commands.read_travel\] is `confirmed = false`: say what foamlab assumes "
     r"\(`assumption`\) and what would settle it"),
    (MARK10, 'send = "?C"', 'send = 3', r"\[gauge.commands.read_current\] send must be a string"),
    ("sim-serial.toml", "[limits]", "[limits\n", r"not valid TOML"),
])
def test_invalid_profiles_fail_with_one_line_naming_file_and_key(machines, file, old, new, message):
    edit(machines / file, old, new)
    profile = {DAD: "sim-modbus-tcp", CS2RS: "sim-modbus-tcp", MARK10: "sim-serial"}.get(file, file[:-5])
    with pytest.raises(ProfileError, match=message) as info:
        load_profile(profile, configs_dir=machines)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("section, key, value, message", [
    ("crosshead", "travel_sign", 2, r"sim-serial.toml: \[crosshead\] `travel_sign` must be 1 or -1, got 2"),
    ("crosshead", "travel_unit", "cm", r"`travel_unit` must be one of mm, in, got 'cm'"),
    ("load_cell", "force_unit", "lb", r"`force_unit` must be one of N, mN, kN, lbF, ozF, kgF, gF, got 'lb'"),
])
def test_serial_profile_settings_fail_with_one_line(section, key, value, message):
    profile = load_profile("sim-serial")
    profile[section][key] = value
    with pytest.raises(ProfileError, match=message) as info:
        open_machine(profile, connect=False)
    assert "\n" not in str(info.value)


def test_open_machine_builds_the_protocols_machine_without_connecting():
    assert isinstance(open_machine(load_profile("sim-modbus-tcp"), connect=False), ModbusMachine)
    assert isinstance(open_machine(load_profile("sim-serial"), connect=False), AsciiMachine)
    assert isinstance(open_machine("sim-modbus-rtu", connect=False), ModbusMachine)   # by name


def test_overrides_replace_connection_settings_and_are_validated():
    profile = load_profile("sim-modbus-rtu")
    machine = open_machine(profile, connect=False, port_url="socket://127.0.0.1:1234", timeout_s="0.25",
                           retries=3, host=None)
    assert machine.link.where == "Modbus RTU socket://127.0.0.1:1234"
    assert (machine.link.timeout_s, machine.link.retries) == (0.25, 3)
    assert profile["connection"]["port_url"] == "socket://127.0.0.1:5021"   # the loaded profile is left alone
    with pytest.raises(ProfileError, match="unknown machine override 'speed'"):
        open_machine(profile, connect=False, speed=3)
    with pytest.raises(ProfileError, match="unknown machine override 'word_order'"):
        open_machine(profile, connect=False, word_order="little")          # the device's, not a setting
    with pytest.raises(ProfileError, match=r"override port='x': expected int"):
        open_machine(load_profile("sim-modbus-tcp"), connect=False, port="x")


def test_a_device_file_is_read_once_into_descriptors_with_their_sources():
    drive = device_map(load_profile("sim-modbus-tcp"), "crosshead")
    position = drive.registers["motor_position"]
    assert (position.address, position.type, position.count, position.unit) == (0x602C, "int32", 2, "pulse")
    assert drive.value("trigger", "start_path0") == 0x0010 and drive.value("trigger", "set_zero") == 0x0021
    assert position.encode(-20123, drive.word_order) == [0xFFFF, 0xB165]          # high word first
    assert position.decode([0xFFFF, 0xB165], "big") == -20123
    assert drive.provenance["[registers.motor_position]"].confirmed is False
    assert "S1 §5.5.4" in drive.provenance["[registers.pr0_position]"].source
    with pytest.raises(ValueError, match="does not fit"):
        drive.registers["status"].encode(70000, "big")


def test_every_modbus_device_entry_cites_its_manual():
    for role in ("load_cell", "crosshead"):
        device = device_map(load_profile("sim-modbus-rtu"), role)
        assert len(device.provenance) > 20
        for entry, where in device.provenance.items():
            assert where.source.strip(), entry
            assert where.confirmed or where.settle, entry
