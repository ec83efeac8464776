"""The recorder (foamlab.storage.recorder) on its own and under the run engine: a full disk
mid-run stops the machine, says why in one line and keeps every sample written; a folder it
cannot write refuses the run before any motion."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from foamlab import FoamlabError, cli
from foamlab.rundata import Specimen
from foamlab.storage.recorder import COLUMNS, Recorder, RecordingFailed
from foamlab.storage.runfile import read_run_file
from tests.hil_support import finish, inprocess_engine, machine_at_start, short_method

SPEEDUP = 10.0


class FullDisk:
    """A file whose writes fail with ENOSPC after `lines` successful ones (the header is one)."""

    def __init__(self, real, lines: int):
        self._real, self._left = real, lines

    def write(self, text: str) -> int:
        if self._left <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._left -= 1
        return self._real.write(text)

    def __getattr__(self, name):          # flush, fileno, close: the real file's
        return getattr(self._real, name)


def full_after(samples: int):
    """An opener for Recorder: the disk fills after the header and `samples` samples."""
    return lambda *args, **kwargs: FullDisk(open(*args, **kwargs), samples + 1)


HEADER = {"method": "short", "specimen": Specimen("full-disk", 72.5), "machine": "test"}


def test_a_full_disk_keeps_every_sample_written_and_says_why_in_one_line(tmp_path):
    recorder = Recorder(tmp_path, opener=full_after(5))
    path = recorder.open(dict(HEADER))
    for i in range(5):
        recorder.record(i * 0.0625, 0.1 * i, 2.0 * i, 1.5, 0, 1)
    with pytest.raises(RecordingFailed) as failed:
        recorder.record(5 * 0.0625, 0.5, 10.0, 1.5, 1, 1)
    message = str(failed.value)
    assert "\n" not in message and "No space left on device" in message and "5 samples" in message
    with pytest.raises(RecordingFailed):         # stays failed: nothing half-written later
        recorder.record(6 * 0.0625, 0.6, 12.0, 1.5, 1, 1)
    recorder.finish("aborted", message)          # never raises
    on_disk = read_run_file(path)
    assert on_disk.status == "aborted"
    np.testing.assert_array_equal(on_disk.force_N, [0.0, 2.0, 4.0, 6.0, 8.0])
    assert len(recorder) == 7                    # in memory nothing acquired is lost


def test_a_partial_line_left_by_a_failed_flush_is_cut(tmp_path):
    class HalfLine(FullDisk):
        def write(self, text):
            if self._left <= 0:          # half the line reaches the file, then the disk is full
                self._real.write(text[: len(text) // 2])
                self._real.flush()
            return super().write(text)

    recorder = Recorder(tmp_path, opener=lambda *a, **k: HalfLine(open(*a, **k), 4))
    path = recorder.open(dict(HEADER))
    for i in range(3):
        recorder.record(float(i), 0.1 * i, 1.0 + i, 1.0, 0, 1)
    with pytest.raises(RecordingFailed):
        recorder.record(3.0, 0.3, 4.0, 1.0, 0, 1)
    recorder.finish("aborted", "disk full")
    text = path.read_text()
    assert text.endswith("\n") and "# status: aborted" in text
    assert len(read_run_file(path)) == 3


def test_step_and_cycle_labels_are_columns(tmp_path):
    recorder = Recorder(tmp_path, run_name="labels")
    path = recorder.open(dict(HEADER))
    recorder.record(0.0, 0.0, 0.5, 1.0, 0, 1)
    recorder.record(0.0625, 0.1, 0.7, 1.0, 1, 1)
    recorder.finish("finished", "")
    assert path.name == "labels.csv"
    lines = path.read_text().splitlines()
    assert lines[lines.index(",".join(COLUMNS)) + 2] == "0.0625,0.1,0.7,1.0,1,1"
    assert read_run_file(path).metadata["extra_columns"] == ["rtt_ms", "step", "cycle"]
    steps, cycles = recorder.labels
    assert steps.tolist() == [0, 1] and cycles.tolist() == [1, 1]


def test_an_unwritable_folder_is_refused_in_one_line(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.raises(RecordingFailed, match="cannot write run files in") as refused:
        Recorder(blocker / "runs").check_folder()
    assert "\n" not in str(refused.value)
    if os.geteuid() != 0:                        # root writes into read-only folders anyway
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(RecordingFailed):
            Recorder(locked).check_folder()


# The engine's storage exits run on the in-process machine, in virtual time (tests/hil_support.py).

@pytest.mark.timeout(30)
def test_disk_full_mid_run_stops_the_crosshead_and_keeps_the_samples(tmp_path):
    machine = machine_at_start()
    written = 40                                 # ~2.5 s of machine time into the first loading
    recorder = Recorder(tmp_path / "runs", opener=full_after(written))
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path / "runs",
                              recorder=recorder)
    result = finish(engine)
    assert result.status == "aborted" and result.end == "storage"
    assert "\n" not in result.reason and "No space left on device" in result.reason
    assert not machine.sim.crosshead_status().moving          # stopped (and parked: a sound machine)
    assert result.park.startswith("parked at")
    on_disk = read_run_file(result.path)
    assert on_disk.status == "aborted" and len(on_disk) == written
    # every sample acquired before the failure, as acquired; the failed one is still in memory
    assert result.n_samples == written + 1
    np.testing.assert_array_equal(on_disk.force_N, result.run.force_N[:written])
    np.testing.assert_array_equal(on_disk.displacement_mm, result.run.displacement_mm[:written])
    assert on_disk.displacement_mm[-1] > 0.5     # the run was well under way


@pytest.mark.timeout(30)
def test_a_folder_that_turns_unwritable_before_the_file_opens_stops_the_run(tmp_path):
    def refused(*args, **kwargs):     # the check passed; by contact the folder is read-only
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))

    machine = machine_at_start()
    recorder = Recorder(tmp_path / "runs", opener=refused)
    result = finish(inprocess_engine(machine, short_method(tmp_path), tmp_path / "runs", recorder=recorder))
    assert result.status == "aborted" and result.end == "storage"
    assert "\n" not in result.reason and "Permission denied" in result.reason
    assert result.path is None and result.n_samples == 0
    assert not machine.sim.crosshead_status().moving and result.park.startswith("parked at")


def test_an_unwritable_folder_refuses_the_run_before_any_motion(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    machine = machine_at_start()
    with pytest.raises(FoamlabError, match="cannot write run files in"):
        inprocess_engine(machine, short_method(tmp_path), blocker / "runs")
    assert not machine.requests                  # not a request reached the machine


def test_foamlab_run_refuses_an_unwritable_folder_in_one_line(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    code = cli.main(["run", "--speedup", "10", "--out", str(blocker / "runs"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "cannot write run files in" in err


@pytest.mark.gui
@pytest.mark.hil
@pytest.mark.timeout(180)
def test_the_window_refuses_a_run_it_could_not_record(qtbot, tmp_path):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from foamlab.gui.window import MainWindow
    from tests.gui_support import connect_window

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    w = MainWindow(speedup=SPEEDUP, out_dir=blocker / "runs")
    qtbot.addWidget(w)
    try:
        connect_window(qtbot, w)
        form = w.specimen_form
        for edit, value in ((form.label_edit, "nowhere"), (form.edits["height_mm"], "72.5")):
            edit.clear()
            qtbot.keyClicks(edit, value)
        assert not w.start_run() and w.engine is None
        assert "cannot write run files in" in w.specimen_form.message.text()
        status = w.link.connection.simulator.crosshead_status()
        assert not status["moving"]
    finally:
        w.link.shutdown()
        w.analysis.shutdown(wait=True)
        w.estop_queue.shutdown(wait=True)
