"""One load-unload cycle - the most common shape of a real export (issue 19, item 4) - from a
file foamlab did not write: a Bluehill export with Chinese headers in GBK, a tensile test (load
and extension stored positive), made by the independent generator (tests/independent_model.py).
Fitted in the structure the data determine (the largest, 23 parameters on one loading and one
unloading, found damping amplitudes of +-1.1e5 N cancelling at 2.8 x the noise), with a turn that
the samples cannot place fitted both ways, and diagnosed with the causes that apply to one cycle."""

from __future__ import annotations

import json

import numpy as np
import pytest

from foamlab import cli
from tests.independent_model import REGIMES, generate


def _bluehill_gbk_tensile(path, run) -> None:
    """Bluehill 2's raw-data layout, localized: header lines, a blank line, names, units, data."""
    lines = ['文本输入 : 试样标记,"拉伸-1"', "常规 : 开始日期,2021/3/8 9:41", "",
             "时间,拉伸,负荷", "(秒),(毫米),(牛)"]
    lines += [f"{t:.6f},{x:.6f},{f:.6f}" for t, x, f in zip(run.time_s, run.displacement_mm, run.force_N)]
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("gbk"))


@pytest.mark.parametrize("regime,seed", [("A", 3), ("B", 5), ("B", 9)])   # B 9: its turn 1.7 ms before a sample
def test_one_cycle_export_is_fitted_at_the_noise_and_diagnosed_none(tmp_path, capsys, regime, seed):
    run = generate(REGIMES[regime].with_(sampling_hz=10.0), seed, cycles=1)
    path = tmp_path / "Specimen_RawData_1.csv"
    _bluehill_gbk_tensile(path, run)

    assert cli.main(["fit", str(path), "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert fit["rmse"] <= 1.05 * run.sigma, fit["rmse"]      # 40 runs of one cycle: median 1.00, max 1.03 (docs)
    assert not [w for w in fit["warnings"] if "cancel" in w], fit["warnings"]
    assert all(abs(p["value"]) < 1e4 for name, p in fit["parameters"].items() if name[0] in "ar"), fit["parameters"]
    assert any("a single cycle" in w for w in fit["warnings"])
    # nothing written beside someone's export
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]

    assert cli.main(["diagnose", str(path), "--json", "--no-store"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["verdict"] == "none", d
    assert {"cycle_softening", "damping_cycle_change"} <= set(d["skipped"]), d["skipped"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
