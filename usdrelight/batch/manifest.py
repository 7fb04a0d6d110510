"""The batch's bookkeeping: input hashes, ``manifest.jsonl``, and what a re-run may skip.

A finished photo's folder ``OUT_DIR/NAME`` holds ``batch.json`` (its manifest row), written inside the temp
folder before the folder is published by one rename, so a folder with a ``batch.json`` is complete. The
manifest is the client's copy of every row, rewritten atomically after each photo; failed photos live only
there (they have no folder).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
from pathlib import Path

from .. import __version__
from ..atomic import write_text_atomic
from ..errors import UsdRelightError
from ..neural.pairs import MANIFEST, photo_inputs
from ..stage.layout import FITTED_LIGHTS, GEOMETRY, SCENE
from .records import MANIFEST_FIELDS_VERSION, REFUSED, BatchOptions, PhotoJob, PhotoRecord

log = logging.getLogger(__name__)
RECORD = "batch.json"
"""A finished photo's own manifest row, inside its folder."""
COMPLETE = (SCENE, GEOMETRY, FITTED_LIGHTS)
"""What a finished photo's folder holds besides ``batch.json`` (the stage and the files it references)."""
PAIR_FILES = ("pair.json", "renders/diffuse.exr", "renders/albedo.exr", "renders/valid.exr")
"""And with ``--pairs``: the training pair."""
TEMP_TAG, OLD_TAG = ".usdrelight-batch-tmp-", ".usdrelight-batch-old-"
"""In the names of the hidden folders of unfinished and of replaced photos, ``.NAME.usdrelight-batch-tmp-XXXXXXXX``
(8 random characters) and ``.NAME.usdrelight-batch-old-PID-NS``: what :func:`remove_leftovers` removes between
runs, and nothing else (a user's ``.photos.old-2023`` or ``.notes.tmp-draft`` stays)."""
_LEGACY = re.compile(r"\.(.+)\.(?:tmp-[a-z0-9_]{8}|old-[0-9]+-[0-9]+)")
_LEFTOVER = re.compile(r"\..+(" + re.escape(TEMP_TAG) + r"[a-z0-9_]{8}|" + re.escape(OLD_TAG) + r"[0-9]+-[0-9]+)")


def input_hash(files, options: BatchOptions) -> str:
    """sha256 over each input file's name and bytes, the hashed options, the package version and the
    manifest version: equal hashes mean the outputs would be the same."""
    h = hashlib.sha256()
    h.update(json.dumps({"options": options.hashed(), "version": __version__,
                         "manifest": MANIFEST_FIELDS_VERSION}, sort_keys=True).encode())
    for f in files:
        f = Path(f)
        h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()


def make_job(photo: Path, out_dir: Path, options: BatchOptions, lock_token: str = "") -> PhotoJob:
    """The job of ``photo``, an entry of the photo folder: named, and its sidecars found, by the entry's own
    name (a symbolic link's, never its target's). UsdRelightError when a sidecar leads out of the folder or
    an input cannot be read."""
    photo = Path(photo).parent.resolve() / Path(photo).name
    files = tuple(photo_inputs(photo))
    try:
        digest = input_hash(files, options)
    except OSError as exc:
        name = Path(exc.filename).name if exc.filename else photo.name
        raise UsdRelightError(f"cannot read {name!r}: {exc.strerror or exc}") from None
    return PhotoJob(photo.stem, photo, files, digest, Path(out_dir).resolve(), options, lock_token)


def read_manifest(out_dir: Path) -> dict[str, PhotoRecord]:
    """name -> row of ``out_dir/manifest.jsonl`` (empty when there is none; unreadable lines are ignored)."""
    path = Path(out_dir) / MANIFEST
    if os.path.lexists(path) and not path.is_file():  # before any photo is processed, not after them all
        raise UsdRelightError(f"{path} is not a file: batch keeps its manifest there (nothing was processed)")
    rows = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = PhotoRecord.from_dict(json.loads(line))
            except (ValueError, TypeError):
                log.warning("manifest: ignoring an unreadable line")
                continue
            if rec.status != REFUSED:  # refused files are listed again by every run
                rows[rec.name] = rec
    return rows


def write_manifest(out_dir: Path, rows: dict[str, PhotoRecord]) -> Path:
    """Replace ``manifest.jsonl`` atomically: one JSON object per photo, sorted by name."""
    text = "".join(json.dumps(rows[k].to_dict(), sort_keys=True) + "\n" for k in sorted(rows))
    return write_text_atomic(Path(out_dir) / MANIFEST, text)


def finished_record(job: PhotoJob) -> PhotoRecord | None:
    """The photo's ``NAME/batch.json`` row when its folder is complete (:data:`COMPLETE`, and with ``--pairs``
    :data:`PAIR_FILES`, each a file, links followed) and was made from the same inputs and options; None
    otherwise (a folder whose stage or renders were removed is redone)."""
    path = job.out_dir / job.name / RECORD
    try:
        rec = PhotoRecord.from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None
    if rec.status != "done" or rec.input_hash != job.input_hash:
        return None
    folder = job.out_dir / job.name
    need = COMPLETE + (PAIR_FILES if job.options.pairs else ())
    if not all((folder / name).is_file() for name in need):  # through the stage's links into versions/
        return None
    return rec


def reusable(job: PhotoJob, previous: PhotoRecord | None) -> PhotoRecord | None:
    """The record a re-run keeps instead of processing ``job``: a complete, unchanged done photo, or an
    unchanged photo that failed on an input error (unless ``retry_failed``)."""
    rec = finished_record(job)
    if rec is not None:
        return rec
    if (previous is not None and previous.status == "failed" and previous.error_kind == "input"
            and previous.input_hash == job.input_hash and not job.options.retry_failed):
        return previous
    return None


def remove_leftovers(out_dir: Path, names=()) -> int:
    """Remove temp and replaced folders left by killed workers or an interrupted run (named as :data:`TEMP_TAG`
    and :data:`OLD_TAG` say, real folders, not links), and those of versions before these tags
    (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-PID-NS``) for the photo names ``names`` of this batch only; returns how
    many."""
    n = 0
    for p in Path(out_dir).iterdir():
        legacy = _LEGACY.fullmatch(p.name)
        if (_LEFTOVER.fullmatch(p.name) or legacy and legacy.group(1) in names) and p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
            n += 1
    return n
