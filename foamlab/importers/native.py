"""Native binary files of testing software, refused with how to export text.

testXpert (ZwickRoell) keeps a test series in a gzip-compressed binary file
(.zs2; .zse from older versions; .zp2 is a test program and holds no
measurements). The layout is undocumented and changes with versions:
zs2decode 0.3.3 stops on testXpert III .zs2 files (its issue #10) and does not
recover data from old .zse files (issue #9), so foamlab reads testXpert's own
text export instead.
"""

from __future__ import annotations

from pathlib import Path

from foamlab import FoamlabError

TESTXPERT_SUFFIXES = {".zs2", ".zse", ".zs3"}
TESTXPERT_HOW = ("export the raw data as text in testXpert (testXpert II: File > Export > "
                 "ASCII / 'Export to text file', tick the series and the channels time, "
                 "standard force and standard travel; testXpert III: Export > Text file) "
                 "and read that .txt/.csv file")
_GZIP = b"\x1f\x8b"


def refuse(path: str | Path) -> None:
    """Raise a one-line FoamlabError for a native binary file foamlab does not read."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".zp2":
        raise FoamlabError(f"{p}: a testXpert test program (.zp2), which holds no measurements; "
                           f"{TESTXPERT_HOW}")
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
