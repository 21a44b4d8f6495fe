"""The artifact store: a directory (``FOLDWISE_DATA_DIR``) of images and checkpoints.

Paths in the database are relative to it, and every artifact's name is derived from the id
of the row it belongs to, so a task delivered twice rewrites the same file.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path


def data_dir() -> Path:
    # Read here, not at import: a role that only digests or writes files needs no settings.
    from foldwise.settings import get_settings

    return get_settings().data_dir


def resolve(relative: str | Path) -> Path:
    return data_dir() / relative


def image_path(experiment_id: int, parameter_set_id: int) -> str:
    return f"experiments/{experiment_id}/images/{parameter_set_id}.png"


def checkpoint_path(experiment_id: int, model_id: int) -> str:
    return f"experiments/{experiment_id}/models/{model_id}.pt"


def ensemble_path(study: str) -> str:
    """Where a study's ensemble file goes (``foldwise run --members``), which the API serves."""
    return f"studies/{study}/ensemble.pt"


def uploaded_assets_root() -> Path:
    """Where ``POST /assets/{kind}`` keeps uploaded asset folders, one per content hash. The API
    takes configs naming a folder under it whatever FOLDWISE_ASSET_ROOTS says: every file in it
    passed the asset check on arrival."""
    return (data_dir() / "assets" / "uploads").resolve()


def report_dir(experiment_id: int) -> str:
    return f"experiments/{experiment_id}/report"


# atomic_write_bytes writes "<name>" through ".<name>.<random>.tmp" beside it.
_TEMPORARY_SUFFIX = ".tmp"


def atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write via a temporary file and rename, so readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=_TEMPORARY_SUFFIX)
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(payload)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def unfinished_write_target(file_name: str) -> str | None:
    """The file name an ``atomic_write_bytes`` temporary file was to become, or None when
    ``file_name`` is not one. Such a file is left only by a writer killed before its rename
    (any other failure removes it): half a write, never read."""
    if not (file_name.startswith(".") and file_name.endswith(_TEMPORARY_SUFFIX)):
        return None
    parts = file_name[1:].rsplit(".", 2)  # name, mkstemp's random part (no dots), "tmp"
    if len(parts) != 3 or not parts[0]:
        return None
    return parts[0]


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, hex (read in blocks, not whole)."""
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()
