"""Stage outputs kept between runs, so that a rerun can start at a later stage.

:func:`pmvir.pipeline.run` with ``cache=<folder>`` saves what the decode stage
(the decoded views) and the geometry stage (cameras, initial surface,
visibility: a :class:`~pmvir.geometry.stage.GeometryResult`) produced; with
``resume_from="geometry"`` or ``"refine"`` it loads the earlier stages' outputs
from that folder instead of computing them again.

Each saved output carries the key of the options it was made with (the option
groups of its stage and every stage before it); loading it with other options
raises, so a cached surface is never reused after its geometry options
changed. The files are pickles written by the pipeline itself: never point
``cache`` at a folder others can write to.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import uuid
from pathlib import Path
from typing import Any

from pmvir.config import PipelineConfig
from pmvir.errors import PmvirError
from pmvir.stages import Stage

#: The stages whose outputs are cached, and their file names in the cache folder.
CACHED_STAGES: dict[Stage, str] = {Stage.DECODE: "decode.pkl", Stage.GEOMETRY: "geometry.pkl"}


def options_key(config: PipelineConfig, stage: Stage) -> str:
    """Digest of the option groups that determine ``stage``'s output (its own and earlier stages')."""
    groups = {
        str(s): getattr(config, str(s)).model_dump(mode="json") for s in Stage if s.position <= stage.position
    }
    return hashlib.sha256(json.dumps(groups, sort_keys=True).encode()).hexdigest()


def _paths(cache: str | Path, stage: Stage) -> tuple[Path, Path]:
    path = Path(cache) / CACHED_STAGES[stage]
    return path, path.with_suffix(".key")


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def save_stage(cache: str | Path, stage: Stage, config: PipelineConfig, value: Any) -> Path:
    """Save ``stage``'s output and its options key (each atomically: temporary name, then rename)."""
    path, key = _paths(cache, stage)
    path.parent.mkdir(parents=True, exist_ok=True)
    key.unlink(missing_ok=True)  # no key while the output is replaced: never a stale pair
    _write_atomic(path, pickle.dumps(value, protocol=5))
    _write_atomic(key, options_key(config, stage).encode())
    return path


def has_stage(cache: str | Path, stage: Stage, config: PipelineConfig) -> bool:
    """Whether ``stage``'s output is cached, made with these options for it and every earlier stage."""
    path, key = _paths(cache, stage)
    try:
        return path.is_file() and key.read_text() == options_key(config, stage)
    except OSError:
        return False


def load_stage(cache: str | Path, stage: Stage, config: PipelineConfig) -> Any:
    """The saved output of ``stage``.

    Raises:
        PmvirError: nothing saved for the stage, or saved with other options for it or an earlier stage.
    """
    path, _ = _paths(cache, stage)
    if not has_stage(cache, stage, config):
        why = "made with other options for it or an earlier stage" if path.is_file() else "not saved"
        raise PmvirError(f"{path.name}: the cached output of the {stage} stage is {why}; run from {stage}")
    with open(path, "rb") as f:
        return pickle.load(f)  # written by save_stage into the run's own folder
