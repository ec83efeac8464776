"""Machine profiles: lookup, merge of the wire contract, validation messages, overrides."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from drivers.ascii import AsciiMachine
from drivers.modbus import ModbusMachine, RegisterMap
from drivers.profile import MACHINES_DIR, ProfileError, available_profiles, load_profile, open_machine

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def machines(tmp_path: Path) -> Path:
    """A copy of the repository's machine profiles to break."""
    folder = tmp_path / "machines"
    shutil.copytree(MACHINES_DIR, folder)
    return folder


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path.name}"
    path.write_text(text.replace(old, new, 1))


def test_repository_profiles_load_and_merge_their_wire_contract():
    assert {"sim-modbus-tcp", "sim-modbus-rtu", "sim-serial"} <= set(available_profiles())
    tcp = load_profile("sim-modbus-tcp")
    assert tcp["register_map"] == "_modbus_map.toml"
    assert tcp["wire"]["load_cell"]["block"]["address"] == 0x3500
    assert tcp["source"].endswith("sim-modbus-tcp.toml")
    serial = load_profile("sim-serial")
    assert serial["wire"]["commands"]["read_both"] == "n"


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
    ("sim-modbus-tcp.toml", 'word_order = "big"', 'word_order = "middle"', r"`word_order` must be one of big, little"),
    ("sim-modbus-tcp.toml", "port = 5020", "port = 70000", r"\[connection\] `port` must be 1..65535"),
    ("sim-modbus-tcp.toml", "timeout_s = 0.04", "timeout_s = 0", r"`timeout_s` must be > 0"),
    ("sim-modbus-tcp.toml", 'transport = "tcp"', 'transport = "udp"', r"`transport` must be one of tcp, rtu"),
    ("sim-modbus-tcp.toml", "unit_id = 2", "unit_id = 300", r"\[crosshead\] `unit_id` must be 1..247"),
    ("sim-modbus-tcp.toml", "force_N = 450.0", "force_N = 600.0", r"exceeds the load-cell capacity"),
    ("sim-modbus-tcp.toml", "travel_upper_mm = -20.0", "travel_upper_mm = 80.0", r"must be smaller than"),
    ("sim-modbus-tcp.toml", '_modbus_map.toml', '_missing.toml', r"register_map file not found"),
    ("sim-modbus-tcp.toml", "retries = 1", 'retries = "one"', r"`retries` must be an integer"),
    ("sim-modbus-rtu.toml", 'port_url = "socket://127.0.0.1:5021"', 'port_url = ""', r"`port_url` must be"),
    ("sim-serial.toml", 'command_set = "_mark10_commands.toml"', "", r"needs `command_set"),
    ("_modbus_map.toml", 'type = "float32", unit = "N" }\nnet', 'type = "float64", unit = "N" }\nnet',
     r"_modbus_map.toml: \[load_cell\] gross_force: type must be one of"),
    ("_modbus_map.toml", "count = 5", "count = 6", r"block: count 6 does not match its layout \(5 registers\)"),
    ("_modbus_map.toml", 'command     = { address = 0x2061, type = "uint16" }', "",
     r"_modbus_map.toml: \[load_cell\] lacks register 'command'"),
    ("_mark10_commands.toml", 'read_both      = "n"', "", r"\[commands\] lacks read_both"),
    ("_modbus_map.toml", '"net_force", "status"]', '"net_force", "gross_force"]',
     r"block: count 5 does not match"),
    ("_modbus_map.toml", 'count = 5, layout = ["gross_force", "net_force", "status"]',
     'count = 5, layout = ["gross_force", "peak_force", "status"]', r"block must contain net_force and status"),
    ("_mark10_commands.toml", 'unknown_command = "*10"', 'unknown_command = "E10"', r"must look like"),
    ("sim-serial.toml", "[limits]", "[limits\n", r"not valid TOML"),
])
def test_invalid_profiles_fail_with_one_line_naming_file_and_key(machines, file, old, new, message):
    edit(machines / file, old, new)
    profile = {"_modbus_map.toml": "sim-modbus-tcp", "_mark10_commands.toml": "sim-serial"}.get(file, file[:-5])
    with pytest.raises(ProfileError, match=message) as info:
        load_profile(profile, configs_dir=machines)
    assert "\n" not in str(info.value)


def test_open_machine_builds_the_protocols_machine_without_connecting():
    assert isinstance(open_machine(load_profile("sim-modbus-tcp"), connect=False), ModbusMachine)
    assert isinstance(open_machine(load_profile("sim-serial"), connect=False), AsciiMachine)
    assert isinstance(open_machine("sim-modbus-rtu", connect=False), ModbusMachine)   # by name


def test_overrides_replace_connection_settings_and_are_validated():
    profile = load_profile("sim-modbus-rtu")
    machine = open_machine(profile, connect=False, port_url="socket://127.0.0.1:1234", word_order="big",
                           timeout_s="0.25", retries=3, host=None)
    assert machine.link.where == "Modbus RTU socket://127.0.0.1:1234"
    assert (machine.link.word_order, machine.link.timeout_s, machine.link.retries) == ("big", 0.25, 3)
    assert profile["word_order"] == "little"        # the loaded profile is left alone
    with pytest.raises(ProfileError, match="unknown machine override 'speed'"):
        open_machine(profile, connect=False, speed=3)
    with pytest.raises(ProfileError, match="`word_order` must be one of"):
        open_machine(profile, connect=False, word_order="middle")
    with pytest.raises(ProfileError, match=r"override port='x': expected int"):
        open_machine(load_profile("sim-modbus-tcp"), connect=False, port="x")


def test_register_map_is_read_once_into_descriptors():
    crosshead = RegisterMap.from_toml(load_profile("sim-modbus-tcp")["wire"], "crosshead")
    position = crosshead.registers["actual_position"]
    assert (position.address, position.type, position.count, position.unit) == (0x602A, "int32", 2, "um")
    assert crosshead.constants["triggers"]["move_absolute"] == 0x0010
    assert position.decode(position.encode(-20123, "little"), "little") == -20123
    assert position.encode(-20123, "little") == [0xB165, 0xFFFF]
    with pytest.raises(ValueError, match="does not fit"):
        crosshead.registers["status"].encode(70000, "big")
