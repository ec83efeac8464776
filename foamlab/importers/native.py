"""Native binary files of testing software, refused with how to export text.

testXpert (ZwickRoell) keeps a test series in a gzip-compressed binary file
(.zs2; .zse, .zp2 for its templates and single results). Its layout is
undocumented and version dependent: zs2decode 0.3.3 misreads channels on
current files (its issues #9 and #10), so foamlab reads testXpert's own text
export instead.
"""

from __future__ import annotations

from pathlib import Path

from foamlab import FoamlabError

TESTXPERT_SUFFIXES = {".zs2", ".zse", ".zp2", ".zs3"}
TESTXPERT_HOW = ("export the raw data as text in testXpert (testXpert II: File > Export > "
                 "ASCII / 'Export to text file', tick the series and the channels time, "
                 "standard force and standard travel; testXpert III: Export > Text file) "
                 "and read that .txt/.csv file")
_GZIP = b"\x1f\x8b"


def refuse(path: str | Path) -> None:
    """Raise a one-line FoamlabError for a native binary file foamlab does not read."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in TESTXPERT_SUFFIXES:
        raise FoamlabError(f"{p}: a testXpert native file ({p.suffix}), not a text export; "
                           f"{TESTXPERT_HOW}")
    try:
        with p.open("rb") as f:
            head = f.read(2)
    except OSError:
        return  # read_text reports missing or unreadable files
    if head == _GZIP:
        raise FoamlabError(f"{p}: a compressed binary file (gzip, as testXpert .zs2 files are), "
                           f"not a text export; for testXpert, {TESTXPERT_HOW}")
