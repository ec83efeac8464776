"""Write the small vendor-format fixtures in tests/data/ (run: python tests/data/make_fixtures.py).

Every fixture holds the same known run (tests/synthetic.py: 2 triangular cycles
of 10 mm at 60 mm/min, 5 Hz, foam-like force, peak about 27 N) written the way
each vendor export writes it: layout, channel names, units, sign, separator,
decimal mark and encoding. FIXTURES says what each one is, so the tests can
check the import against the truth. tests/test_importers.py also checks that
running this script again reproduces the committed files byte for byte.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))

from tests.synthetic import triangle_run  # noqa: E402

STROKE_MM = 10.0
CYCLES = 2
RATE_HZ = 5.0
SPEED_MM_MIN = 60.0
PRELOAD_OFFSET_MM = 3.5   # where the vendor's displacement channel starts


def truth_run():
    run, truth = triangle_run(cycles=CYCLES, stroke_mm=STROKE_MM, speed_mm_min=SPEED_MM_MIN,
                              rate_hz=RATE_HZ, noise_mm=0.0005, noise_N=0.02,
                              zero_offset_N=-0.1, seed=3)
    return run, truth


@dataclass
class Fixture:
    name: str
    encoding: str
    sep: str
    decimal: str
    header: list[str]                    # lines before the names row
    names: list[str]
    units: list[str]
    scale: tuple[float, float, float]    # file value = foamlab value * scale (t, x, f)
    sign: int = -1                       # -1: compression stored negative
    extra_columns: list[tuple[str, str]] = field(default_factory=list)
    label: str = ""
    started_at: str = ""
    fmt: str = "Instron Bluehill"
    order: str = "txf"                   # order of the time/displacement/force columns
    bom: bool = False
    crlf: bool = True


FIXTURES = [
    Fixture("bluehill_en_utf8.csv", "utf-8", ",", ".",
            ['Text Inputs : Specimen label,"PU-45 A"', "General : Start Date,13/11/2018 5:14 PM", ""],
            ["Time", "Extension", "Load", "Segment ID", "Total Cycle Count"],
            ["(sec)", "(mm)", "(N)", "", ""], (1, 1, 1),
            extra_columns=[("Segment ID", "22476"), ("Total Cycle Count", "0")],
            label="PU-45 A", started_at="2018-11-13T17:14:00"),
    Fixture("bluehill_zh_gbk.csv", "gbk", ",", ".",
            ['文本输入 : 试样标记,"泡沫-1"', "常规 : 开始日期,2019/5/6 10:20", ""],
            ["时间", "拉伸", "负荷"], ["(秒)", "(毫米)", "(牛)"], (1, 1, 1),
            label="泡沫-1", started_at="2019-05-06T10:20:00"),
    Fixture("bluehill_zh_utf8bom_ms_kN.csv", "utf-8", ",", ".",
            ['文本输入 : 试样标记,"样品二"', ""],
            ["时间", "位移", "力"], ["(ms)", "(mm)", "(kN)"], (1000, 1, 0.001),
            label="样品二", bom=True),
    Fixture("bluehill_de_cp1252.csv", "cp1252", ";", ",",
            ["Texteingaben : Probenbezeichnung;Würfel Ä", "Allgemein : Startdatum;13.11.2018 17:14", ""],
            ["Zeit", "Weg", "Kraft"], ["(s)", "(mm)", "(N)"], (1, 1, 1),
            label="Würfel Ä", started_at="2018-11-13T17:14:00"),
    Fixture("bluehill_us_in_lbf.csv", "cp1252", ",", ".",
            ['Text Inputs : Specimen label,"US-1"', "General : Start Date,11/23/2020 3:05 PM",
             "Specimen : Thickness,2.854 in", ""],
            ["Time", "Compressive extension", "Compressive load"], ["(s)", "(in)", "(lbf)"],
            (1, 1 / 25.4, 1 / 4.4482216152605), sign=+1,
            label="US-1", started_at="2020-11-23T15:05:00", crlf=False),
    Fixture("testxpert_de_semicolon.txt", "cp1252", ";", ",",
            ["Probenbezeichnung;Schaum 7", "Prüfdatum;05.02.2021", "Prüfer;Müller", ""],
            ["Prüfzeit", "Standardkraft", "Standardweg", "Traversenweg"], ["s", "N", "mm", "mm"],
            (1, 1, 1), sign=+1, extra_columns=[("Traversenweg", "x")],
            label="Schaum 7", started_at="2021-02-05T00:00:00", fmt="ZwickRoell testXpert",
            order="tfx"),
    Fixture("testxpert_en_tab.txt", "utf-8", "\t", ".",
            ["Specimen\tFoam B"],
            ["Test time", "Standard force", "Standard travel"], ["[s]", "[kN]", "[mm]"],
            (1, 1, 0.001), sign=-1, label="Foam B", fmt="ZwickRoell testXpert", crlf=False,
            order="tfx"),
    Fixture("testxpert_en_comma.csv", "utf-8", ",", ".",
            [],
            ['"Test time"', '"Standard force"', '"Standard travel"'], ['"s"', '"N"', '"mm"'],
            (1, 1, 1), sign=+1, fmt="ZwickRoell testXpert", order="tfx"),
]


def _number(value: float, decimal: str) -> str:
    text = f"{value:.6f}"
    return text.replace(".", ",") if decimal == "," else text


def render(fx: Fixture) -> bytes:
    run, _ = truth_run()
    st, sx, sf = fx.scale
    lines = list(fx.header)
    lines.append(fx.sep.join(fx.names))
    lines.append(fx.sep.join(fx.units))
    extra = dict(fx.extra_columns)
    for t, x, f in zip(run.time_s, run.displacement_mm, run.force_N):
        values = {"t": t * st, "x": fx.sign * (x + PRELOAD_OFFSET_MM) * sx, "f": fx.sign * f * sf}
        fields = [_number(values[role], fx.decimal) for role in fx.order]
        for name in fx.names[3:]:
            fields.append(_number(fx.sign * (x + PRELOAD_OFFSET_MM + 20.0), fx.decimal)
                          if extra.get(name) == "x" else extra.get(name, ""))
        lines.append(fx.sep.join(fields))
    newline = "\r\n" if fx.crlf else "\n"
    data = (newline.join(lines) + newline).encode(fx.encoding)
    return (b"\xef\xbb\xbf" + data) if fx.bom else data


def plain_csv() -> bytes:
    run, _ = truth_run()
    lines = ["# plain CSV written by hand (tests/data/make_fixtures.py)",
             "# specimen_label: plain-1", "time_s,displacement_mm,force_N"]
    for t, x, f in zip(run.time_s, run.displacement_mm, run.force_N):
        lines.append(f"{t:.3f},{x:.5f},{f:.5f}")
    return ("\n".join(lines) + "\n").encode()


def write_all(folder: Path = HERE) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for fx in FIXTURES:
        path = folder / fx.name
        path.write_bytes(render(fx))
        written.append(path)
    path = folder / "plain.csv"
    path.write_bytes(plain_csv())
    written.append(path)
    return written


if __name__ == "__main__":
    for p in write_all():
        print(p.relative_to(HERE.parent.parent), p.stat().st_size, "bytes")
