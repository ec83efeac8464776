"""Write the small export-layout fixtures in tests/data/layouts/ (run this file).

Written by hand from the documented layouts (no vendor file copied): Instron
WaveMatrix ``*.steps.tracking.csv``, MTS 793 MPT ``specimen.dat`` (MTS Series
793 manual, "How to parse the MPT specimen data file": the
``MTS793|prog|language|version|delimiter|decimal|...`` first line and a header
per data buffer), Instron Bluehill 3 single-header raw data, and the quirks
real exports have (digit grouping, repeated timestamps, cp1250, German
labels). Each holds a synthetic triangular run (tests/synthetic.py) whose
cycle count LAYOUTS records, so the tests check the import and segmentation.
tests/test_import_layouts.py checks that this script reproduces the files.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "layouts"
sys.path.insert(0, str(HERE.parent.parent))

from tests.synthetic import triangle_run  # noqa: E402

NBSP, NNBSP = "\u00a0", "\u202f"


@dataclass
class Expect:
    fmt: str
    cycles: int
    label: str = ""
    operator: str = ""
    encoding: str = ""
    notes: list[str] = field(default_factory=list)   # substrings of metadata["import_notes"]
    force_max_N: float | None = None                  # peak force after conversion


def samples(cycles: int, stroke_mm: float, rate_hz: float, force_scale: float = 1.0, seed: int = 2):
    run, _ = triangle_run(cycles=cycles, stroke_mm=stroke_mm, speed_mm_min=60.0 * stroke_mm,
                          rate_hz=rate_hz, noise_mm=0.0005, noise_N=0.02, seed=seed)
    return run.time_s, run.displacement_mm, run.force_N * force_scale


def grouped(value: float, decimals: int, group: str, decimal: str) -> str:
    """'1234.5' with digit grouping: grouped(1234.5, 2, ',', '.') == '1,234.50'."""
    text = f"{value:,.{decimals}f}"
    return text.replace(",", "\0").replace(".", decimal).replace("\0", group)


def wavematrix_bom() -> bytes:
    # a test continuing past 1000 s: Total Time crosses 1000 and is grouped, quoted
    t, x, f = samples(20, 2.0, 10.0)
    names = ["Total Time (s)", "Cycle Elapsed Time (s)", "Total Cycles", "Elapsed Cycles", "Step",
             "Total Cycle Count(Linear Waveform)", "Position(Linear:Position) (mm)",
             "Load(Linear:Load) (kN)"]
    lines = [",".join(f'"{n}"' for n in names) + ","]
    for i, (ti, xi, fi) in enumerate(zip(t + 985.0, x, f)):
        cycle = int(ti // 2)
        total = grouped(ti, 5, ",", ".")
        total = f'"{total}"' if "," in total else total
        lines.append(",".join([total, f"{ti % 2:.5f}", str(cycle), str(cycle), "1", str(cycle),
                               f"{-(xi + 1.5):.5f}", f"{-fi / 1000:.7f}"]) + ",")
    return b"\xef\xbb\xbf" + ("\r\n".join(lines) + "\r\n").encode("utf-8")


def wavematrix_de() -> bytes:
    t, x, f = samples(12, 2.0, 10.0, force_scale=300.0)   # peak about 1760 N: grouped
    names = ["Gesamtzeit (s)", "Verstrichene Zykluszeit (s)", "Gesamtzyklen", "Verstrichene Zyklen",
             "Schritt", "Position des Aktuators (mm)", "Kraft (N)"]
    lines = [";".join(f'"{n}"' for n in names) + ";"]
    for ti, xi, fi in zip(t, x, f):
        cycle = int(ti // 2)
        lines.append(";".join([f"{ti:.4f}".replace(".", ","), f"{ti % 2:.4f}".replace(".", ","),
                               str(cycle), str(cycle), "2", f"{-xi:.5f}".replace(".", ","),
                               grouped(-fi, 3, ".", ",")]) + ";")
    return ("\r\n".join(lines) + "\r\n").encode("utf-8")


def _mts_block(title: str, names: list[str], units: list[str], rows: list[list[str]]) -> list[str]:
    return ["", title, "\t".join(names), "\t".join(units)] + ["\t".join(r) for r in rows]


def mts_enu_blocks() -> bytes:
    # a new "Data Header" block every second (every 10 samples); from the fourth
    # block on, the buffer has one more channel (another column set)
    t, x, f = samples(3, 5.0, 10.0, force_scale=0.001)    # force written in kN
    lines = ["MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A", "",
             "Operator Information\t\t\t\t\t\tTime:\t12.5\tSec\t3/29/2016 1:54:32 PM",
             "Operator :\tJ. Smith", "Specimen Name :\tPU foam 40-A", "Operator Information End"]
    for start in range(0, len(t), 10):
        sl = slice(start, start + 10)
        names = ["Running Time", "Axial Displacement", "Axial Force"]
        units = ["Sec", "mm", "kN"]
        extra = start >= 30
        if extra:
            names, units = names[:1] + ["Axial Strain"] + names[1:], units[:1] + ["mm/mm"] + units[1:]
        rows = []
        for ti, xi, fi in zip(t[sl] + 12.5, x[sl], f[sl]):
            row = [f"{ti:.4f}", f"{-xi:.6f}", f"{-fi:.7f}"]
            if extra:
                row.insert(1, f"{-xi / 50:.7f}")
            rows.append(row)
        title = f"Data Header\t\t\t\t\t\tTime:\t{t[sl][-1] + 12.5:.3f}\tSec\t3/29/2016 1:55:{start // 10:02d} PM"
        lines += _mts_block(title, names, units, rows)
    return ("\r\n".join(lines) + "\r\n").encode("cp1252")


def mts_deu_exceltime() -> bytes:
    # the only time column is an Excel day number written to 6 decimals (86.4 ms),
    # which a 20 Hz run repeats; a peak detector's two-row block at the end
    t, x, f = samples(3, 5.0, 20.0, force_scale=0.001)
    day0 = 45107.3125          # 2023-06-30 07:30
    lines = ["MTS793|MPT|DEU|1|2|,|.|:|49|1|1|A", "",
             "Bediener Information\t\t\t\t\t\tZeit:\t22,38\ts\t30.06.2023 07:29:37",
             "Datum : \t30.6.2023", "Prüfer : \tMüller", "Probenbezeichnung :  \tPU-Schaum Würfel 3",
             "Bemerkungen\tweggeregelt 5 mm/s", "Masse :\t31,5", "Höhe :\t50,0",
             "Bediener Information Ende"]
    for start in range(0, len(t), 100):
        sl = slice(start, start + 100)
        rows = [[f"{day0 + ti / 86400:.6f}".replace(".", ","), f"{-xi:.6f}".replace(".", ","),
                 f"{-fi:.8f}".replace(".", ",")] for ti, xi, fi in zip(t[sl], x[sl], f[sl])]
        title = f"Datenerfassung\t\t\t\t\t\tZeit:\t{t[sl][-1]:.3f}\ts\t30.06.2023 07:30:00".replace(".", ",", 1)
        lines += _mts_block(title, ["Datum", "Ch 1 Weg", "Ch 1 Kraft"], ["d", "mm", "kN"], rows)
    peak = [[f"{day0 + 999 / 86400:.7f}".replace(".", ","), "-4,9", "-0,012"],
            [f"{day0 + 5 / 86400:.7f}".replace(".", ","), "-0,1", "-0,001"]]
    lines += _mts_block("Spitzenwerte\t\t\t\t\t\tZeit:\t999\ts\t30.06.2023 07:46:39",
                        ["Datum", "Ch 1 Weg", "Ch 1 Kraft"], ["d", "mm", "kN"], peak)
    return ("\r\n".join(lines) + "\r\n").encode("cp1252")


def bluehill3_single() -> bytes:
    t, x, f = samples(3, 5.0, 10.0)
    lines = ["Time measurement (s),Extension (mm),Primary load measurement (N)"]
    lines += [f"{ti:.3f},{-xi:.5f},{-fi:.5f}" for ti, xi, fi in zip(t, x, f)]
    return ("\r\n".join(lines) + "\r\n").encode("utf-8")


def bluehill_de_thousands() -> bytes:
    # German Bluehill 2: semicolons, decimal comma, force past 1000 N grouped with a
    # no-break space (and a narrow one in some rows), "Probenbeschriftung", "Prüfer"
    t, x, f = samples(3, 5.0, 10.0, force_scale=250.0)
    lines = ["Texteingaben : Probenbeschriftung;Schaum Würfel 7", "Texteingaben : Prüfer;Müller",
             "Allgemein : Startdatum;13.11.2018 17:14", "", "Zeit;Weg;Standardkraft",
             "(s);(mm);(N)"]
    for i, (ti, xi, fi) in enumerate(zip(t, x, f)):
        force = grouped(-fi, 4, NNBSP if i % 2 else NBSP, ",")
        lines.append(f"{ti:.3f};{-xi:.5f};{force}".replace(".", ","))
    return ("\r\n".join(lines) + "\r\n").encode("utf-8")  # U+202F has no cp1252 byte


def bluehill_repeated_time() -> bytes:
    # two rows at t = 0 (Bluehill 2 writes the first sample twice), then time rounded to 0.1 s at 20 Hz
    t, x, f = samples(3, 5.0, 20.0)
    lines = ['Text Inputs : Specimen label,"R-1"', "", "Time,Extension,Load", "(sec),(mm),(N)"]
    lines.append(f"{0:.1f},{-x[0]:.5f},{-f[0]:.5f}")
    lines += [f"{np.round(ti, 1):.1f},{-xi:.5f},{-fi:.5f}" for ti, xi, fi in zip(t, x, f)]
    return ("\r\n".join(lines) + "\r\n").encode("utf-8")


def bluehill_pl_cp1250() -> bytes:
    t, x, f = samples(3, 5.0, 10.0)
    lines = ["Dane tekstowe : Etykieta próbki;Pianka żółta łódź", "Dane tekstowe : Operator;Paweł Wąs",
             "Ogólne : Data rozpoczęcia;05.03.2021 09:12", "",
             "Czas;Wydłużenie;Obciążenie", "(s);(mm);(N)"]
    lines += [f"{ti:.3f};{-xi:.5f};{-fi:.5f}".replace(".", ",") for ti, xi, fi in zip(t, x, f)]
    return ("\r\n".join(lines) + "\r\n").encode("cp1250")


def testxpert_aktuelle_probe() -> bytes:
    t, x, f = samples(3, 5.0, 10.0, force_scale=200.0)   # peak about 2400 N, '.'-grouped
    lines = ["Prüfer;Schmidt", "aktuelle Probe;Schaum 12", "Prüfdatum;05.02.2021", "",
             "Prüfzeit;Standardkraft;Standardweg", "s;N;mm"]
    lines += [f"{ti:.3f}".replace(".", ",") + ";" + grouped(fi, 3, ".", ",") + ";"
              + f"{xi:.5f}".replace(".", ",") for ti, xi, fi in zip(t, x, f)]
    return ("\r\n".join(lines) + "\r\n").encode("cp1252")


LAYOUTS = {
    "wavematrix_bom.steps.tracking.csv": (wavematrix_bom, Expect(
        "Instron WaveMatrix", 20, encoding="utf-8-bom", notes=["digit grouping"])),
    "wavematrix_de.steps.tracking.csv": (wavematrix_de, Expect(
        "Instron WaveMatrix", 12, notes=["digit grouping"], force_max_N=1700.0)),
    "mts_enu_blocks.dat": (mts_enu_blocks, Expect(
        "MTS 793 MPT", 3, label="PU foam 40-A", operator="J. Smith",
        notes=["7 data blocks joined"])),
    "mts_deu_exceltime.dat": (mts_deu_exceltime, Expect(
        "MTS 793 MPT", 3, label="PU-Schaum Würfel 3", operator="Müller", encoding="cp1252",
        notes=["time repeats", "left out: its time does not continue"])),
    "bluehill3_single.csv": (bluehill3_single, Expect("Instron Bluehill 3", 3)),
    "bluehill_de_thousands.csv": (bluehill_de_thousands, Expect(
        "Instron Bluehill", 3, label="Schaum Würfel 7", operator="Müller", encoding="utf-8",
        notes=["digit grouping"], force_max_N=2900.0)),
    "bluehill_repeated_time.csv": (bluehill_repeated_time, Expect(
        "Instron Bluehill", 3, label="R-1", notes=["time repeats"])),
    "bluehill_pl_cp1250.csv": (bluehill_pl_cp1250, Expect(
        "Instron Bluehill", 3, label="Pianka żółta łódź", operator="Paweł Wąs", encoding="cp1250")),
    "testxpert_aktuelle_probe.txt": (testxpert_aktuelle_probe, Expect(
        "ZwickRoell testXpert", 3, label="Schaum 12", operator="Schmidt", encoding="cp1252",
        notes=["digit grouping"], force_max_N=2300.0)),
}


def write_all(folder: Path = OUT) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, (render, _) in LAYOUTS.items():
        path = folder / name
        path.write_bytes(render())
        written.append(path)
    return written


if __name__ == "__main__":
    for p in write_all():
        print(p.relative_to(HERE.parent.parent), p.stat().st_size, "bytes")
