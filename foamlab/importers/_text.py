"""Reading a data file as text: existence checks, encoding detection, lines."""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from foamlab import FoamlabError
from foamlab.importers._charset import best_single_byte

#: Files larger than this are not data exports; refuse before reading them whole.
MAX_BYTES = 2 * 1024 ** 3

# Encoding detection is a short ordered trial, not a statistical guess
# (chardet-style detectors are unreliable on files that are 99 % ASCII digits):
# 1. UTF-8 (with or without BOM): strict, so legacy bytes fail it almost surely;
# 2. GB18030 (superset of GBK/GB2312): Chinese Bluehill installs write it; it
#    decodes many Latin-1 byte pairs too, so it is kept only if the result has no
#    CJK character glued to a Latin letter ("Prüfzeit" in cp1252 would become
#    "Pr" + a CJK character + "zeit");
# 3. cp1250 (Central European Windows: Polish, Czech) against cp1252 (Western):
#    both decode almost any bytes, so the letters decide (foamlab.importers._charset);
# 4. Latin-1, which decodes anything, as the last resort.
# UTF-16 is recognised by its BOM only (Windows "Unicode text" exports have one).
_CJK = "\u3400-\u4dbf\u4e00-\u9fff\uf900-\ufaff"
_HAS_CJK = re.compile(f"[{_CJK}]")
_MOJIBAKE = re.compile(rf"[A-Za-z\u00c0-\u00ff][{_CJK}]|[{_CJK}][A-Za-z\u00c0-\u00ff]")


@dataclass
class TextFile:
    path: Path
    text: str
    encoding: str

    @cached_property
    def lines(self) -> list[str]:
        return split_lines(self.text)

    @property
    def ends_with_newline(self) -> bool:
        return self.text.endswith(("\n", "\r"))


_OTHER_LINE_BREAKS = "\v\f\x1c\x1d\x1e\x85\u2028\u2029"  # str.splitlines() breaks on these too


def split_lines(text: str) -> list[str]:
    """Lines as an editor numbers them (CRLF, LF or CR), without a trailing empty line."""
    if any(c in text for c in _OTHER_LINE_BREAKS):
        lines = re.split(r"\r\n|\r|\n", text)  # slower, but only CR/LF break lines
        if lines and lines[-1] == "":
            lines.pop()
        return lines
    return text.splitlines()


def read_text(path: str | Path) -> TextFile:
    p = Path(path)
    if not p.exists():
        raise FoamlabError(f"{p}: file not found")
    if p.is_dir():
        raise FoamlabError(f"{p}: is a folder, not a data file")
    try:
        size = p.stat().st_size
        if size > MAX_BYTES:
            raise FoamlabError(f"{p}: {size / 1e9:.1f} GB is too large for a data export")
        raw = p.read_bytes()
    except OSError as exc:
        raise FoamlabError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if not raw.strip():
        raise FoamlabError(f"{p}: file is empty")
    text, encoding = decode(raw)
    if "\x00" in text:
        raise FoamlabError(f"{p}: binary file, not a text data export")
    return TextFile(p, text, encoding)


def decode(raw: bytes) -> tuple[str, str]:
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        try:
            return raw.decode("utf-16"), "utf-16"
        except UnicodeDecodeError:
            pass
    for encoding in ("utf-8-sig", "gb18030"):
        try:
            text = raw.decode(encoding)
        except UnicodeDecodeError:
            continue
        if encoding == "gb18030" and (_MOJIBAKE.search(text) or not _HAS_CJK.search(text)):
            continue  # Latin bytes read as Chinese, or no Chinese at all
        if encoding == "utf-8-sig":
            encoding = "utf-8-bom" if raw.startswith(b"\xef\xbb\xbf") else "utf-8"
        return text, encoding
    best = best_single_byte(raw)
    if best is not None:
        return best
    return raw.decode("latin-1"), "latin-1"
