"""What every device file and machine profile shares, whatever the wire: one-line errors naming
the file and the entry, and each entry's provenance read one way.

A device file entry (a Modbus register, an ASCII command, a setting) names the `source` that
documents it (manual short name + section/page); where the manual does not settle it,
`confirmed = false` with `settle` (what would), and in a file that states them, `assumption`
(what foamlab takes meanwhile). drivers.registers (Modbus) and drivers.mark10_device (ASCII)
read their entries with `FileReader.entry`; drivers.profile checks profiles with the same reader.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Entry:
    """One device-file entry: where it comes from and whether the manuals settle it."""

    name: str
    source: str
    confirmed: bool = True
    settle: str = ""
    assumption: str = ""


class FileReader:
    """Reads a file's tables; every message names the file (`where`, may be "") and the entry."""

    def __init__(self, where: str, error: type[ValueError] = ValueError):
        self.where, self.error = where, error

    def fail(self, entry: str, msg: str):
        text = f"{entry} {msg}" if entry else msg
        raise self.error(f"{self.where}: {text}" if self.where else text)

    def table(self, parent: dict, key: str, entry: str) -> dict:
        value = parent.get(key)
        if not isinstance(value, dict):
            self.fail(entry, f"needs a [{key}] table")
        return value

    def entry(self, table: dict, name: str, *, assumption: bool = False) -> Entry:
        """Nothing undocumented: a source, and for an unsettled entry what would settle it (and,
        with `assumption`, what is assumed until then)."""
        if not isinstance(table, dict):
            self.fail(name, "must be a table")
        source = table.get("source")
        if not isinstance(source, str) or not source.strip():
            self.fail(name, "needs a `source` (manual, section/page)")
        confirmed = table.get("confirmed", True)
        if not isinstance(confirmed, bool):
            self.fail(name, "`confirmed` must be true or false")
        entry = Entry(name, source, confirmed, str(table.get("settle", "")).strip(),
                      str(table.get("assumption", "")).strip())
        if not confirmed and not (entry.settle and (entry.assumption or not assumption)):
            wanted = "what foamlab assumes (`assumption`) and " if assumption else ""
            self.fail(name, f"is `confirmed = false`: say {wanted}what would settle it (`settle`)")
        return entry
