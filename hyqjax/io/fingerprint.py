"""The settings a run directory's results depend on, recorded once: ``DIR/fingerprint.json``.

A resumable run (``hyqjax tune``) records, on its first start, every setting that changes its results and
their SHA-256 (:func:`settings_sha256` of the canonical JSON). A later run into the same directory with the
same settings resumes; one whose settings differ is refused with :class:`SettingsMismatch`, one line that
names each differing setting with both values, before anything is computed. Call it under the directory's
lock (:class:`hyqjax.io.lock.DirLock`), so two runs cannot both record.
"""
from __future__ import annotations

import hashlib
import json
import os

FINGERPRINT_FILE = "fingerprint.json"


class SettingsMismatch(ValueError):
    """The directory holds a run of other settings (the message names them)."""


def settings_sha256(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def _flat(d, prefix=""):
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def differences(old: dict, new: dict) -> list[str]:
    """``"key: OLD there, NEW here"`` for every (dotted) setting that differs."""
    a, b = _flat(json.loads(json.dumps(old, default=str))), _flat(json.loads(json.dumps(new, default=str)))
    missing = object()
    return [f"{k}: {a.get(k, 'unset')!r} there, {b.get(k, 'unset')!r} here" for k in sorted(set(a) | set(b))
            if a.get(k, missing) != b.get(k, missing)]


def check_or_record(directory: str, settings: dict, what: str = "run", legacy: dict | None = None) -> str:
    """Refuse (:class:`SettingsMismatch`) if ``directory`` records other settings, else record these; returns
    their SHA-256. ``legacy``: the settings of a run recorded before fingerprints existed (derived by the
    caller from its own files), compared the same way when ``fingerprint.json`` is absent."""
    from hyqjax.io.atomic import write_json

    path = os.path.join(directory, FINGERPRINT_FILE)
    sha = settings_sha256(settings)
    old = legacy
    if os.path.exists(path):
        try:
            with open(path, "rb") as f:
                old = json.loads(f.read().decode("utf-8"))["settings"]
        except (OSError, ValueError, UnicodeDecodeError, KeyError, TypeError):
            raise SettingsMismatch(f"{path} is damaged: the settings of the {what} in {directory} are unknown; "
                                   f"use another --out or remove {directory}") from None
    if old is not None and settings_sha256(old) != sha:
        diff = differences(old, settings)
        raise SettingsMismatch(f"{directory} holds a {what} with other settings ({'; '.join(diff[:6])}"
                               f"{'; ...' if len(diff) > 6 else ''}): resume with the same settings, or use another "
                               f"--out")
    if not os.path.exists(path):
        write_json(path, dict(sha256=sha, settings=settings))
    return sha


__all__ = ["FINGERPRINT_FILE", "SettingsMismatch", "check_or_record", "differences", "settings_sha256"]
