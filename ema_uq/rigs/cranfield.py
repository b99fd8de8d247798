"""The Cranfield linear actuator as a rig (its study code: :mod:`ema_uq.cranfield`)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from . import Rig


def _data_files(study: Mapping[str, Any]) -> list[tuple[str, Path]]:
    from .. import io

    files = [io.cranfield_file(name, study, must_exist=False) for name in io.CRANFIELD_FILES]
    return [(f"{f.name} (measured)", f) for f in files]


RIG = Rig(concept="cranfield", title="Cranfield linear actuator", data_files=_data_files, fault_diagnosis=True)
