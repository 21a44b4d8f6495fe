"""/assets/{kind}: upload asset images (objects, backgrounds, occluders) into the artifact store.

A server refuses configs that name folders outside FOLDWISE_ASSET_ROOTS, so a token holder
cannot make the workers read any folder of the server; uploading is the other way to bring
one's own object in. The token is checked before a byte of the body is read (the route declares no body parameter,
which FastAPI would read and spool to disk before any dependency runs); the app's BodyLimit
stops a body past MAX_UPLOAD_BYTES as it streams in. The files of one upload land in one folder
named by their content hash
(``<kind>-<sha256 of the names and bytes>``), checked by the same asset check as any folder
before it is kept: an upload repeated gives the same folder, a refused one leaves nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, HTTPException, Request, status
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile

from foldwise import store
from services.api.deps import TokenRequired
from services.api.schemas import WRITE_ERRORS, ErrorDetail, InvalidInput

# Bounds on one upload: a print photographed at 24 Mpixel is ~10 MB as JPEG.
MAX_FILES = 200
MAX_FILE_BYTES = 32 << 20
MAX_UPLOAD_BYTES = 256 << 20
MAX_NAME_CHARS = 128
# A file keeps its own name (an object's class is its name without the extension): letters,
# digits and a few marks, never a path.
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 ._+-]*$")

router = APIRouter(prefix="/assets", tags=["assets"])

# The body is read by hand, after the token check, so its schema is documented by hand.
UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["files"],
                    "properties": {
                        "files": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "the images, each under its own name",
                        }
                    },
                }
            }
        },
    }
}


def _file_name(upload: UploadFile) -> str:
    from foldwise.asset_check import IMAGE_SUFFIXES

    name = upload.filename or ""
    if not name:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "a file part has no file name")
    if len(name) > MAX_NAME_CHARS or not SAFE_NAME.match(name):
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"file name {name!r}: use at most {MAX_NAME_CHARS} letters, digits, spaces and . _ + -, "
            "starting with a letter or digit (no folders)",
        )
    if Path(name).suffix.lower() not in IMAGE_SUFFIXES:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"file {name!r}: not an image name ({' '.join(IMAGE_SUFFIXES)})"
        )
    return name


def _as_sent(error: Exception, staging: Path) -> HTTPException:
    """A 422 naming each file as the client sent it, not by its path in the staging folder."""
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(error).replace(str(staging) + os.sep, ""))


@router.post(
    "/{kind}",
    status_code=status.HTTP_201_CREATED,
    dependencies=[TokenRequired],
    openapi_extra=UPLOAD_BODY,
    responses={
        **WRITE_ERRORS,
        400: {"model": ErrorDetail, "description": "a multipart body that does not parse"},
        413: {
            "model": ErrorDetail,
            "description": f"a file over {MAX_FILE_BYTES >> 20} MiB or an upload over {MAX_UPLOAD_BYTES >> 20} MiB",
        },
        422: {
            "model": InvalidInput,
            "description": "no files, or a file that is not a usable image; the message names it",
        },
    },
)
async def upload_assets(
    kind: Literal["objects", "backgrounds", "occluders", "lookalikes"], request: Request
) -> dict[str, Any]:
    """Keep the uploaded images as one asset folder of the artifact store and answer its path,
    to put in a config as ``assets.<kind>``."""
    async with request.form(max_files=MAX_FILES + 1, max_fields=MAX_FILES + 1) as form:
        files = form.getlist("files")
        if not files:
            raise HTTPException(
                status.HTTP_422_UNPROCESSABLE_CONTENT,
                "no files: send the images as multipart/form-data, each in a part named 'files'",
            )
        if not all(isinstance(upload, UploadFile) for upload in files):
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "a part named 'files' is text, not a file")
        return await run_in_threadpool(_keep, kind, files)


def _keep(kind: str, files: list[UploadFile]) -> dict[str, Any]:
    """Check the files and keep them as one folder of the store (file work: run on a thread)."""
    from foldwise.asset_check import AssetError, check_class_names, check_image_file  # Pillow only

    if len(files) > MAX_FILES:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"{len(files)} files: at most {MAX_FILES} per upload"
        )
    names = [_file_name(upload) for upload in files]
    seen: set[str] = set()
    for name in names:
        if name.lower() in seen:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"file {name!r} is given twice")
        seen.add(name.lower())

    root = store.uploaded_assets_root()
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=root, prefix=".upload-"))
    try:
        total, described = 0, []
        for name, upload in zip(names, files):
            payload = upload.file.read(MAX_FILE_BYTES + 1)
            total += len(payload)
            if len(payload) > MAX_FILE_BYTES:
                raise HTTPException(
                    status.HTTP_413_CONTENT_TOO_LARGE, f"file {name!r} is larger than {MAX_FILE_BYTES >> 20} MiB"
                )
            if total > MAX_UPLOAD_BYTES:
                raise HTTPException(
                    status.HTTP_413_CONTENT_TOO_LARGE, f"the upload is larger than {MAX_UPLOAD_BYTES >> 20} MiB"
                )
            path = staging / name
            path.write_bytes(payload)
            try:
                width, height = check_image_file(path, kind)
            except AssetError as error:
                raise _as_sent(error, staging) from None
            described.append(
                {"name": name, "sha256": hashlib.sha256(payload).hexdigest(), "width": width, "height": height}
            )
        if kind in ("objects", "lookalikes"):
            try:
                check_class_names(sorted(staging.iterdir()), kind)
            except AssetError as error:
                raise _as_sent(error, staging) from None
        described.sort(key=lambda entry: entry["name"])
        digest = hashlib.sha256(json.dumps([[e["name"], e["sha256"]] for e in described]).encode()).hexdigest()
        folder = root / f"{kind}-{digest[:16]}"
        try:
            staging.rename(folder)
        except OSError:  # the same files were uploaded before (or by a request racing this one)
            if not folder.is_dir():
                raise
        return {"kind": kind, "folder": str(folder), "sha256": digest, "files": described}
    finally:
        shutil.rmtree(staging, ignore_errors=True)
