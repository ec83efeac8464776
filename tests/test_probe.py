"""Commissioning (`foamlab probe`, issue 24 item 5): against each simulated device the probe reads
every channel, checks the profile against the device and moves 1 mm up and back only when told;
a device that differs from its profile is named, not run; `foamlab run --machine` asks about a
profile that never passed a probe on this computer."""

from __future__ import annotations

import copy

import pytest

from drivers.profile import open_machine
from foamlab import FoamlabError, cli
from foamlab.acquisition.commissioning import probe
from foamlab.acquisition.safety import Limits
from foamlab.commands.run import _check_probed
from foamlab.storage.probes import passed_probe, record_passed
from tests.hil_support import simulated

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]


def _probe(sim, profile=None, move=True):
    profile = profile or sim.profile
    # the probe's checks, not reply latency, are under test: a loaded CI core may not schedule the
    # simulator process within the profile's 40 ms (seen: "no reply to 'RS' (2 x 40 ms)" at load 8)
    machine = open_machine(profile, connect=False, timeout_s=0.5, **sim.profile_overrides)
    try:
        return probe(machine, machine.profile, Limits.from_profile(profile), confirm_move=lambda question: move)
    finally:
        machine.close()


@pytest.mark.parametrize("transport", ["modbus-tcp", "serial"])
def test_the_probe_reads_every_channel_and_moves_only_when_told(transport):
    with simulated(transport, speedup=5.0) as sim:
        still = _probe(sim, move=False)
        report = _probe(sim, move=True)
    names = [c.name for c in report.checks]
    for channel in ("connection", "force", "position", "crosshead status", "travel limits", "move up", "move back"):
        assert channel in names, report.text()
    assert report.passed and report.moved, report.text()
    assert "arrived at" in next(c.detail for c in report.checks if c.name == "move back")
    assert still.passed and not still.moved and "not confirmed" in still.text(), still.text()


def test_the_probe_reads_the_laumas_tlu_beside_the_drive():
    """The fourth device (sim-modbus-rtu-tlu): identified, every channel read, its open status bits
    tested, its decimals said to be the profile's."""
    with simulated("modbus-rtu", profile="sim-modbus-rtu-tlu", speedup=5.0) as sim:
        report = _probe(sim, move=True)
    details = {c.name: c.detail for c in report.checks}
    assert report.passed and report.moved, report.text()
    assert details["identity"].startswith("Laumas TLU: instrument type")
    assert "Laumas TLU status bits" in details and "uses 2 decimals (the profile's)" in details["Laumas TLU decimals"]


def test_a_drive_set_otherwise_than_its_profile_is_named_not_run():
    """The profile says 5 000 pulses per revolution, the drive holds 10 000 (0x0001): every
    position would be off by two."""
    with simulated("modbus-tcp", speedup=5.0) as sim:
        profile = copy.deepcopy(sim.profile)
        profile["crosshead"]["pulses_per_rev"] = 5000
        report = _probe(sim, profile)
    assert not report.passed
    failed = report.failures()[0]
    assert failed.name == "connection" and "10000" in failed.detail and "5000" in failed.detail, report.text()
    assert "do not run a test" in report.text()


def test_run_asks_about_a_profile_that_never_passed_a_probe(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FOAMLAB_CONFIG", str(tmp_path / "config"))
    profile = {"name": "lab-stand", "source": str(tmp_path / "lab-stand.toml"), "protocol": "modbus",
               "connection": {"host": "192.0.2.7"}}
    with pytest.raises(FoamlabError, match="has not passed `foamlab probe --machine lab-stand`.*--unprobed-ok"):
        _check_probed(profile, "lab-stand", unprobed_ok=False)        # not a terminal: refused
    _check_probed(profile, "lab-stand", unprobed_ok=True)
    assert "warning" in capsys.readouterr().err
    record_passed(profile)
    assert passed_probe(profile) is not None
    _check_probed(profile, "lab-stand", unprobed_ok=False)
    profile["connection"]["host"] = "192.0.2.8"                       # edited since: asked again
    assert passed_probe(profile) is None


def test_probe_cli_bad_profile_is_one_line(capsys):
    assert cli.main(["probe", "--machine", "no-such-machine"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown machine profile" in err[0]
