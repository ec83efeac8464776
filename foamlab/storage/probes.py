"""Which machine profiles passed `foamlab probe` on this computer.

One JSON file in the user's configuration folder ($FOAMLAB_CONFIG, else ~/.config/foamlab):
per profile file, the digest of what the probe checked (the profile and the device files it
names) and when it passed. Editing the profile or a device file makes the record stale: the
next `foamlab run` asks again. Written only by `foamlab probe` (the user asked for it).
"""

from __future__ import annotations

import hashlib
import json
import os
from datetime import datetime, timezone
from pathlib import Path

from foamlab import FoamlabError

RECORD_NAME = "probed-machines.json"


def config_dir() -> Path:
    env = os.environ.get("FOAMLAB_CONFIG", "").strip()
    return Path(env).expanduser() if env else Path.home() / ".config" / "foamlab"


def profile_digest(profile: dict) -> str:
    """The digest of the profile as loaded (its devices' wire descriptions included)."""
    keep = {k: v for k, v in profile.items() if k != "source"}
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()


def _key(profile: dict) -> str:
    return str(Path(profile.get("source", profile.get("name", "?"))).resolve())


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise FoamlabError(f"{path}: cannot read the probe record: {exc}") from None


def record_passed(profile: dict) -> Path:
    """Remember that `profile` passed a probe now; returns the record file."""
    path = config_dir() / RECORD_NAME
    records = _read(path)
    records[_key(profile)] = {"digest": profile_digest(profile), "name": profile.get("name", ""),
                              "passed_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(records, indent=1, sort_keys=True), encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        raise FoamlabError(f"{path}: cannot write the probe record: {exc.strerror or exc}") from None
    return path


def passed_probe(profile: dict) -> str | None:
    """When `profile`, as it is now, passed a probe on this computer (None: never, or since edited)."""
    entry = _read(config_dir() / RECORD_NAME).get(_key(profile))
    if not entry or entry.get("digest") != profile_digest(profile):
        return None
    return entry.get("passed_at") or "?"
