"""Numbers as vendor exports write them: decimal point or comma, digit grouping.

Exports grow thousands separators once time passes 1000 s or force 1000 N:
``"1,000.06200"`` (quoted, in a comma-separated file), ``1.000,5`` (German),
``1 000,00`` with a space, no-break space (U+00A0) or narrow no-break space
(U+202F), ``1'000.5`` (Swiss). The grouping is removed before the table is
parsed, so pandas sees plain numbers; a field is changed only when it is a
whole, consistently grouped number (1-3 digits, then groups of exactly 3).
"""

from __future__ import annotations

import csv
import re

_GROUP_CHARS = ",.\u00a0\u202f\u2009 '"
_BOTH_MARKS = re.compile(r'^[-+]?\d{1,3}(?:[,.\u00a0\u202f\u2009 \']\d{3})+([.,])\d*$')
_DECIMAL_COMMA = re.compile(r"^[-+]?\d*,\d+(?:[eE][-+]?\d+)?$")


def _grouped(decimal: str, sep: str) -> re.Pattern:
    marks = _GROUP_CHARS.replace(decimal, "")  # the separator too: inside quotes
    cls = re.escape(marks)
    exponent = r"(?:[eE][-+]?\d+)?" if decimal == "." else ""
    return re.compile(rf"^[-+]?\d{{1,3}}([{cls}])\d{{3}}(?:\1\d{{3}})*(?:{re.escape(decimal)}\d*)?{exponent}$")


def fields_of(text: str, sep: str) -> list[str]:
    if '"' not in text:
        return text.split(sep)
    try:
        return next(csv.reader([text], delimiter=sep, quotechar='"'), [])
    except csv.Error:
        return text.split(sep)


def detect_decimal(texts: list[str], sep: str) -> str:
    """',' or '.': a number with both marks tells (the last one is the decimal),
    else a decimal comma anywhere (never in a comma-separated file)."""
    comma_seen = False
    for text in texts[:500]:
        for field in fields_of(text, sep):
            field = field.strip()
            m = _BOTH_MARKS.match(field)
            if m:
                return m.group(1)
            if sep != "," and not comma_seen and _DECIMAL_COMMA.match(field):
                comma_seen = True
    return "," if comma_seen else "."


def remove_grouping(texts: list[str], sep: str, decimal: str) -> tuple[list[str], list[int]]:
    """The rows with digit grouping removed, and the indices of the rows changed."""
    grouped = _grouped(decimal, sep)
    marks = _GROUP_CHARS.replace(decimal, "")  # the separator too: inside quotes
    suspect = re.compile(rf"\d[{re.escape(marks)}]\d\d\d")
    changed: list[int] = []
    out = texts
    for i, text in enumerate(texts):
        if not suspect.search(text):
            continue
        fields = fields_of(text, sep)
        new = [_ungroup(f, grouped) for f in fields]
        if any(a is not b for a, b in zip(new, fields)):
            if out is texts:
                out = list(texts)
            out[i] = sep.join(_quote(f, sep) for f in new)
            changed.append(i)
    return out, changed


def _ungroup(field: str, grouped: re.Pattern) -> str:
    stripped = field.strip()
    m = grouped.match(stripped)
    if not m:
        return field
    return stripped.replace(m.group(1), "")


def _quote(field: str, sep: str) -> str:
    if sep in field or '"' in field:
        return '"' + field.replace('"', '""') + '"'
    return field
