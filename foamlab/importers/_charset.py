"""cp1250 (Central European) or cp1252 (Western): which one the letters say.

Both code pages decode almost any byte, and German text decodes the same in
both (ä ö ü ß é share their bytes), so a file's few non-ASCII characters are
scored as they read in each: a letter of the language family inside a word
scores, a symbol where a letter should be costs. Polish "Siła" read as cp1252
is "Si³a" (a superscript inside a word), "wartość" is "wartoœæ" (rare
ligatures); German "mm³" read as cp1250 is "mmł" (the superscript after a
unit is the plausible reading). Ties go to cp1252, the more common install.
"""

from __future__ import annotations

import unicodedata

CANDIDATES = ("cp1252", "cp1250")

# Letters common in the languages each code page is used for (both share äöüßé...).
_COMMON = set("äöüßÄÖÜéáíóúýÉÁÍÓÚÝôÔ"
              "èàçêâîûëïñãõøåùÀÇÊÂÎÛËÏÑÃÕØÅ"           # French, Spanish, Portuguese, Nordic
              "ąęłńśźżćĄĘŁŃŚŹŻĆ"                         # Polish
              "čřšžěůďťňČŘŠŽĚŮĎŤŇőűŐŰ")                  # Czech, Slovak, Hungarian
# Symbols that real headers use (units, quotes, dashes): neutral wherever they are.
_NEUTRAL = set("°µ±§€·«»–—‘’‚“”„…×÷\u00a0\u202f\u2009®©")
_SUPERSCRIPTS = set("²³")


def _char_score(text: str, i: int) -> float:
    c = text[i]
    before = text[i - 1] if i else " "
    after = text[i + 1] if i + 1 < len(text) else " "
    if c in _SUPERSCRIPTS:  # m², mm³: right after a letter, not followed by one
        return 1.0 if before.isalpha() and not after.isalpha() else -1.0
    if c in _NEUTRAL:
        return 0.0
    if c.isalpha():
        in_word = before.isalpha() or after.isalpha()
        if not in_word:
            return 0.0
        if c.isupper() and before.isalpha() and before.islower():
            return -1.0  # "wyraŸny": a capital inside a lower-case word
        return 1.0 if c in _COMMON else 0.5
    category = unicodedata.category(c)
    return 0.0 if category.startswith("Z") or c in "\r\n\t" else -1.0


def score(text: str) -> float:
    """Plausibility of the non-ASCII characters of a decoded text (higher is better)."""
    return sum(_char_score(text, i) for i, c in enumerate(text) if ord(c) > 127)


def best_single_byte(raw: bytes) -> tuple[str, str] | None:
    """The better reading of ``raw`` as cp1252 or cp1250, or None if neither decodes."""
    readings = []
    for encoding in CANDIDATES:
        try:
            readings.append((raw.decode(encoding), encoding))
        except UnicodeDecodeError:
            continue
    if not readings:
        return None
    if len(readings) == 1:
        return readings[0]
    # only the non-ASCII lines matter, and scoring them all is cheap
    scored = [(score(_non_ascii_lines(text)), -k, text, enc) for k, (text, enc) in enumerate(readings)]
    best = max(scored)
    return best[2], best[3]


def _non_ascii_lines(text: str) -> str:
    return "\n".join(line for line in text.splitlines() if not line.isascii())
