"""What a worker does for one photo: build its stage, fit its lights and (``--pairs``) render the training
pair into a hidden temp folder beside ``OUT_DIR/NAME``, write ``batch.json`` last, then publish the folder by
one rename. A worker killed at any point leaves only a temp folder (removed by the next run); the photo's
previous folder, if any, is replaced only by a complete one.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import time
from pathlib import Path

from ..atomic import fsync_tree, lock_token, publish, temp_dir_beside, write_bytes_atomic, write_text_atomic
from ..errors import UsdRelightError, one_line
from ..neural.pairs import make_pair_files
from ..stage.layout import USER_LIGHTS
from .manifest import OLD_TAG, RECORD, TEMP_TAG
from .records import PhotoJob, PhotoRecord

log = logging.getLogger(__name__)
TEST_KILL_ENV = "USDRELIGHT_BATCH_TEST_KILL"
"""Test-only hook, ``NAME:TIMES[,NAME:TIMES...]``: the worker processing photo NAME kills its own process
(SIGKILL) halfway through, after the build, the first TIMES times (counted by marker files
``OUT_DIR/.test-kill-NAME.I`` holding the killed process's id)."""
TEST_HOLD_ENV = "USDRELIGHT_BATCH_TEST_HOLD"
"""Test-only hook, ``NAME``: the worker processing photo NAME, after the build, writes
``OUT_DIR/.test-hold-NAME`` and waits (at most 120 s) until ``OUT_DIR/.test-go-NAME`` exists: a batch held
mid-photo, with its temp folder, for tests of what a second batch may touch."""


class BatchEnded(UsdRelightError):
    """The batch that sent a photo no longer holds the output folder when the photo is done."""


def _one_line(exc: BaseException) -> str:
    text = one_line(exc)
    return text if isinstance(exc, UsdRelightError) else f"{type(exc).__name__}: {text}"


def _worker_address() -> str | None:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return None


def _test_kill_hook(job: PhotoJob) -> None:
    specs = dict(item.partition(":")[::2] for item in os.environ.get(TEST_KILL_ENV, "").split(",") if item)
    if job.name not in specs:
        return
    for i in range(int(specs[job.name] or 1)):
        marker = job.out_dir / f".test-kill-{job.name}.{i}"
        if not marker.exists():
            marker.write_text(f"{os.getpid()}\n")
            os.kill(os.getpid(), signal.SIGKILL)


def _test_hold_hook(job: PhotoJob) -> None:
    if os.environ.get(TEST_HOLD_ENV) != job.name:
        return
    (job.out_dir / f".test-hold-{job.name}").write_text(f"{os.getpid()}\n")
    deadline = time.monotonic() + 120
    while not (job.out_dir / f".test-go-{job.name}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)


def _after_build(job: PhotoJob) -> None:
    _test_kill_hook(job)
    _test_hold_hook(job)


def process_photo(job: PhotoJob) -> PhotoRecord:
    """Build, fit and (with ``pairs``) render one photo into ``out_dir/NAME``. Never raises for a bad photo:
    a usdrelight error (bad file, no valid depth, fit error) or an unexpected exception becomes a failed
    record; only the death of the worker process itself is left to the scheduler."""
    t0 = time.perf_counter()
    o = job.options
    final = job.out_dir / job.name
    rec = PhotoRecord(job.name, "failed", job.input_hash, str(job.photo), pairs=o.pairs, worker=_worker_address())
    tmp = temp_dir_beside(final, TEMP_TAG)
    try:
        work = make_pair_files(job.photo, tmp, max_side=o.max_side, fit_iterations=o.iterations, spp=o.spp,
                               lights=o.lights, verify_spp=o.verify_spp, render=o.pairs,
                               after_build=lambda: _after_build(job), estimators=o.estimators())
        fit = work.fit
        rec.status = "done"
        rec.fit_mse, rec.fit_psnr_db, rec.fit_mse_rel = fit.mse, fit.psnr_db, work.fit_mse_rel
        rec.render_psnr_db = fit.render_psnr_db
        rec.fit_seconds, rec.build_seconds, rec.render_seconds = fit.seconds, work.build_seconds, work.render_seconds
        rec.lights_kept, rec.environment_kept = fit.lights_kept, fit.environment_kept
        rec.seconds = time.perf_counter() - t0
        write_text_atomic(tmp / RECORD, json.dumps(rec.to_dict(), indent=2, sort_keys=True) + "\n")
        fsync_tree(tmp)
        if job.lock_token and lock_token(job.out_dir) != job.lock_token:
            raise BatchEnded(f"the batch that sent this photo no longer holds {job.out_dir} (it ended or was "
                             f"interrupted): not published")
        _replace(tmp, final)
    except Exception as exc:  # a bad photo must not stop the batch: it is recorded with its error
        shutil.rmtree(tmp, ignore_errors=True)
        rec.status = "failed"
        rec.error = _one_line(exc)
        rec.error_kind = "input" if isinstance(exc, UsdRelightError) and not isinstance(exc, BatchEnded) else "crash"
        rec.seconds = time.perf_counter() - t0
        log.warning("%s: failed: %s", job.name, rec.error)
    return rec


def _replace(tmp: Path, final: Path) -> None:
    """Publish ``tmp`` as ``final``; an existing ``final`` is moved aside first and removed after (its
    ``lights_user.usda``, the user's own lights, is carried into the new stage first). Only a
    batch's own photo folder (a folder holding ``batch.json``) is replaced: anything else under that name
    (your folder, a file, a symbolic link) is a UsdRelightError and stays as it is."""
    old = None
    if final.is_symlink() or (final.exists() and not (final / RECORD).is_file()):
        raise UsdRelightError(f"{final} exists and is not a batch photo folder (no {RECORD}): not replaced; "
                              f"move it away and rerun with --retry-failed")
    if final.exists():
        mine = final / USER_LIGHTS
        if mine.is_file() and not mine.is_symlink():  # the user's own lights survive a re-run of the photo
            write_bytes_atomic(tmp / USER_LIGHTS, mine.read_bytes())
        old = final.with_name(f".{final.name}{OLD_TAG}{os.getpid()}-{time.monotonic_ns()}")
        publish(final, old)
    publish(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
