"""Provenance recorded in every result: package version, input checksums, seed, settings hash."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
from typing import Any, Iterable


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def settings_hash(settings: Any) -> str:
    """Stable short hash of a JSON-serialisable settings object."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def provenance(inputs: Iterable[str | os.PathLike] = (), *, seed: int | None = None,
               settings: Any = None) -> dict[str, Any]:
    """Provenance block; ``created`` is the only field that differs between identical reruns."""
    from . import __version__

    return {
        "package": "ema_uq",
        "version": __version__,
        "python": platform.python_version(),
        "seed": seed,
        "settings_hash": settings_hash(settings) if settings is not None else None,
        "inputs": {os.path.basename(str(p)): file_sha256(p) for p in inputs},
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
