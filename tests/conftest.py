"""Shared pytest setup. Qt tests draw offscreen: no display needed (CI, SSH)."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import sys  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _garbage_collected_between_tests():
    """A window test turns Python's automatic collection off for its process (the window collects
    on its GUI thread: foamlab.gui.background); the tests after it in the same worker collect here,
    on the main thread, by the same thresholds (a cheap count check when there is nothing to do)."""
    yield
    background = sys.modules.get("foamlab.gui.background")   # only where a test imported the window
    if background is not None:
        background.collect_pending_garbage()


#: Window tests assert what the window shows, not the link's timing: there a machine gets this long
#: to answer (a device's own 40 ms is the schedule tests' and the fault tests'). In the first phase's
#: idle class the window's client can wait tens of ms for a core with the reply already sent (run 85,
#: docs/benchmarks.md: a move unanswered 3 x 2 x 40 ms, the replies arriving 4 transactions late), as
#: tests/test_drivers_hil.py's functional tests allow for (PATIENT).
PATIENT_WINDOW_TIMEOUT_S = 0.25


@pytest.fixture(autouse=True)
def _patient_window_link(request, monkeypatch):
    """A window test (marked gui, not schedule) opens its machine with PATIENT_WINDOW_TIMEOUT_S."""
    node = request.node
    if node.get_closest_marker("gui") is not None and node.get_closest_marker("schedule") is None:
        import drivers.profile as profiles    # where foamlab.session opens a machine from

        opened = profiles.open_machine

        def patient(profile, *, connect: bool = True, **overrides):
            # never shorter than the profile's own (or a caller's) timeout
            loaded = profile if isinstance(profile, dict) else profiles.load_profile(profile)
            own = overrides.get("timeout_s") or loaded["connection"]["timeout_s"]
            overrides["timeout_s"] = max(PATIENT_WINDOW_TIMEOUT_S, float(own))
            return opened(loaded, connect=connect, **overrides)

        monkeypatch.setattr(profiles, "open_machine", patient)
    yield
