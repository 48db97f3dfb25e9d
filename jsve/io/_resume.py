"""What a resumed job checks before it keeps an output: the key of the inputs and configuration it was
made from.

Every resumable output of jsve (a simulated log, a disturbed dataset, a fitting study's stages) records a
key when it is written: fingerprints of the configuration and of the inputs' content. A re-run computes
the key it would write and keeps an existing output only when the two are equal; otherwise it stops
with `StaleOutputError` (naming the folder and what differs) unless told to discard the stale outputs
(`force`, `jsve ... --force`). Outputs made under different keys are never mixed in one folder.

    fingerprint(obj)          16 hex digits of sha256 over obj's canonical JSON
    file_digest(paths)        sha256 over files' names and bytes
    differences(old, new)     'seed 0 != 1, config 3fa1... != 9bc2...' for two flat or nested dicts
    StaleOutputError          the one error of a mismatch
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from jsve.io._text import json_default


class StaleOutputError(Exception):
    """A folder holds outputs made from other inputs or another configuration than the job's.

    Attributes:
        folder: the output folder.
        what: what differs, in words (one line).
    """

    def __init__(self, folder: str | os.PathLike, what: str):
        super().__init__(folder, what)
        self.folder = os.fspath(folder)
        self.what = what

    def __str__(self) -> str:
        return f"{self.folder} holds outputs of another job ({self.what})"


def stop_if_stale(folder: str | os.PathLike, stale: list[tuple[os.PathLike | str, str]], what: str) -> None:
    """Raise StaleOutputError when `stale`, (output path, difference) pairs, is not empty: how many `what`
    (e.g. "logs simulated under another generator key") and the first, relative to `folder`."""
    if stale:
        path, difference = stale[0]
        rel = Path(path).relative_to(folder).as_posix()
        raise StaleOutputError(folder, f"{len(stale)} {what}, e.g. {rel}: {difference}")


def fingerprint(obj) -> str:
    """16 hex digits of sha256 over `obj` as canonical JSON (sorted keys; numpy values as numbers)."""
    text = json.dumps(obj, sort_keys=True, default=json_default, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def file_digest(paths: Iterable[str | os.PathLike]) -> str:
    """16 hex digits of sha256 over each file's name (not its folder) and bytes, in the order given: the
    content of a job's input files, whatever their modification times."""
    total = hashlib.sha256()
    for path in paths:
        path = Path(path)
        total.update(path.name.encode() + b"\0")
        with open(path, "rb") as stream:
            for chunk in iter(lambda: stream.read(1 << 20), b""):
                total.update(chunk)
        total.update(b"\0")
    return total.hexdigest()[:16]


def _flat(obj, prefix: str = "") -> dict:
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            out.update(_flat(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: obj}


def differences(old: Mapping, new: Mapping, limit: int = 4) -> str:
    """The keys whose values differ between two (nested) dicts, as `key OLD != NEW`, comma-separated
    (the first `limit`, then how many more); nested keys dotted (`fit.seed`), missing values `absent`."""
    a, b = _flat(old), _flat(new)
    keys = [k for k in sorted(set(a) | set(b)) if a.get(k, _ABSENT) != b.get(k, _ABSENT)]
    shown = [
        f"{k} {json.dumps(a.get(k, _ABSENT), default=json_default)} != "
        f"{json.dumps(b.get(k, _ABSENT), default=json_default)}"
        for k in keys[:limit]
    ]
    more = f" and {len(keys) - limit} more" if len(keys) > limit else ""
    return (", ".join(shown) + more).replace('"<absent>"', "absent")


_ABSENT = "<absent>"

__all__ = ["StaleOutputError", "fingerprint", "file_digest", "differences"]
