"""`foamlab run` and the window assemble a run the same way (foamlab.session).

The simulator process and the driver are replaced by recorders: what each front end asks
for (the simulator's options, the profile and connection the driver is built from, the
engine's clock rate and connection handling) is compared, not run.
"""

import copy
import dataclasses
from types import SimpleNamespace

import pytest

pytest.importorskip("PySide6")

from drivers.profile import load_profile  # noqa: E402
from foamlab import FoamlabError, cli  # noqa: E402
from foamlab.acquisition import engine as engine_module  # noqa: E402
from foamlab.acquisition.settings import DEFAULT, AcquisitionSettings  # noqa: E402
from foamlab.session import MachineChoice, MachineSession  # noqa: E402

pytestmark = pytest.mark.timeout(60)

SPEEDUP = 20.0


class _Stop(FoamlabError):
    """Raised by the recording engine: the assembly is what is compared."""


class _FakeSim:
    def __init__(self, transport: str, **kwargs):
        profile = copy.deepcopy(load_profile("sim-modbus-tcp"))
        profile["crosshead"]["watchdog_ms"] = 2000     # a drive with a host watchdog, as once built in
        self.transport, self.kwargs, self.profile = transport, kwargs, profile
        self.profile_overrides = {"host": "127.0.0.1", "port": 15020}
        self.address = "127.0.0.1:15020"
        self.stopped = False

    def stop(self):
        self.stopped = True


class _FakeMachine:
    """A built machine: closing a session asks its crosshead's status (at rest here) before closing."""

    def __init__(self, profile, connect, overrides):
        self.profile, self.connect_now, self.overrides = profile, connect, overrides
        self.crosshead = SimpleNamespace(status=lambda: SimpleNamespace(moving=False))

    def close(self):
        pass


@pytest.fixture
def recorded(monkeypatch):
    """Every simulator start, driver build and engine the session makes, in order."""
    seen = {"sims": [], "machines": [], "engines": []}

    def start(transport, **kwargs):
        seen["sims"].append(_FakeSim(transport, **kwargs))
        return seen["sims"][-1]

    def open_machine(profile, *, connect=True, **overrides):
        seen["machines"].append(_FakeMachine(copy.deepcopy(profile), connect, overrides))
        return seen["machines"][-1]

    class RecordingEngine:
        def __init__(self, machine, method, specimen, out_dir, **kwargs):
            seen["engines"].append(dict(kwargs, machine=machine))
            raise _Stop("assembled")

    monkeypatch.setattr("simulator.process.start_simulator_process", start)
    monkeypatch.setattr("drivers.profile.open_machine", open_machine)
    monkeypatch.setattr(engine_module, "RunEngine", RecordingEngine)
    return seen


def _window_session(qtbot, speedup: float) -> MachineSession:
    from foamlab.gui.machine_link import BUILTIN_SIMULATOR, MachineLink

    link = MachineLink(simulator={"seed": 0, "effects": None})
    try:
        with qtbot.waitSignal(link.connected, timeout=10_000) as blocker:
            link.connect_machine(BUILTIN_SIMULATOR, speedup)
        return blocker.args[0]
    finally:
        link.queue.shutdown(wait=True)


def _engine_options(session: MachineSession, seen) -> dict:
    from foamlab.methods import load_method
    from foamlab.rundata import Specimen

    with pytest.raises(_Stop):
        session.engine(load_method("paper-3cycle"), Specimen("", 50.0), "unused")
    return seen["engines"][-1]


def test_cli_and_window_build_the_same_machine_and_engine(recorded, qtbot, tmp_path):
    code = cli.main(["run", "--speedup", f"{SPEEDUP:g}", "--out", str(tmp_path), "--quiet", "--no-predict"])
    assert code == 2                                   # the recording engine stops it, as a one-line error
    cli_sim, cli_machine, cli_engine = recorded["sims"][-1], recorded["machines"][-1], recorded["engines"][-1]
    assert cli_sim.stopped                             # the CLI's session let its simulator go

    window = _window_session(qtbot, SPEEDUP)
    window_sim, window_machine = recorded["sims"][-1], recorded["machines"][-1]
    assert window_sim is not cli_sim and window.simulator is window_sim
    window_engine = _engine_options(window, recorded)

    def started(sim):
        return sim.transport, {k: v for k, v in sim.kwargs.items() if v is not None}

    assert started(cli_sim) == started(window_sim)
    assert started(cli_sim)[1]["speedup"] == SPEEDUP
    # the same drive settings (its watchdog included) and connection for the same speedup
    assert cli_machine.profile == window_machine.profile
    assert cli_machine.profile["crosshead"]["watchdog_ms"] == 2000
    assert cli_machine.overrides == window_machine.overrides
    same = ("speedup", "machine_name", "limits")
    assert {k: cli_engine[k] for k in same} == {k: window_engine[k] for k in same}
    assert cli_engine["speedup"] == SPEEDUP
    # one link owner each: the CLI's engine connects, the window's session already has
    assert (cli_machine.connect_now, cli_engine["connect"]) == (False, True)
    assert (window_machine.connect_now, window_engine["connect"]) == (True, False)
    window.close()
    assert window_sim.stopped


def test_a_profile_keeps_the_speedup_given(recorded):
    # `foamlab sim --speedup 20` prints `foamlab run --machine sim-modbus-tcp --speedup 20`
    session = MachineSession.open(MachineChoice(profile="sim-modbus-tcp", speedup=SPEEDUP,
                                                overrides={"port": 5999}), connect=False)
    assert recorded["sims"] == [] and session.speedup == SPEEDUP
    assert recorded["machines"][-1].overrides == {"port": 5999}
    assert _engine_options(session, recorded)["speedup"] == SPEEDUP


@pytest.mark.parametrize("choice, message", [
    (dict(speedup=0.0), "--speedup must be a positive number"),
    (dict(speedup=float("nan")), "--speedup must be a positive number"),
    (dict(overrides={"port": 1}), "apply with --machine only"),
])
def test_a_bad_choice_is_one_line(choice, message):
    with pytest.raises(FoamlabError, match=message) as caught:
        MachineChoice(**choice)
    assert "\n" not in str(caught.value)


def test_an_unknown_profile_is_one_line(recorded, capsys):
    assert cli.main(["run", "--machine", "no-such-machine", "--specimen-height", "50", "--unprobed-ok"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no-such-machine" in err, err


def test_the_cli_and_the_window_predict_through_the_session(recorded, monkeypatch, tmp_path, capsys):
    # the window's LivePrediction.begin calls foamlab.session.start_prediction too (gui/prediction.py)
    import inspect

    from foamlab.gui import prediction as gui_prediction

    assert "start_prediction(engine, method" in inspect.getsource(gui_prediction.LivePrediction.begin)
    asked = []

    class QuietEngine:
        def __init__(self, machine, method, specimen, out_dir, **kwargs):
            self.settings = kwargs.get("settings", DEFAULT)

        def add_listener(self, listener):
            pass

    def start_prediction(engine, method, listener):
        asked.append((engine, method))
        raise _Stop("predicted")

    monkeypatch.setattr(engine_module, "RunEngine", QuietEngine)
    monkeypatch.setattr("foamlab.session.start_prediction", start_prediction)
    assert cli.main(["run", "--speedup", "5", "--out", str(tmp_path), "--quiet", "--full"]) == 2
    assert len(asked) == 1 and isinstance(asked[0][0], QuietEngine) and asked[0][1].name == "paper-3cycle"
    assert recorded["sims"][-1].stopped
    # --full: the acquisition's thresholds the run obeys, each with its value
    out = capsys.readouterr().out
    for f in dataclasses.fields(AcquisitionSettings):
        assert f"{f.name} = {getattr(DEFAULT, f.name):g}" in " ".join(out.split()), f.name
