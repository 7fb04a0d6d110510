"""The client side of ``usdrelight batch``: list the photos, decide what a re-run may skip, start a Dask
LocalCluster (worker processes, 1 thread each) or connect to an existing scheduler, hand the photos to Dask
one per free slot (each worker's ``photo`` resource: a worker holds no queue of photos that its death would
fail), record each result in the manifest as it arrives, and summarise.

Before anything starts (guard.py): ``--workers`` within the machine's cores and memory, the output folder's
lock (one batch per folder), the photo folder confined (``list_photos``: links out of it, control characters
in names ... are refused, each reported once per run and listed in the manifest as ``refused``). The
LocalCluster listens on 127.0.0.1 only; the dashboard's address is read from its bound socket.

Exit status (cli): 0 when every photo ended done, skipped or recorded failed (refused files included); 2 when
the batch itself cannot run (no such folder, no photos, too many workers, the output folder in use,
unreachable scheduler): :class:`usdrelight.errors.UsdRelightError`.
"""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from concurrent.futures import CancelledError
from pathlib import Path

from ..atomic import lock_token, revoke_lock_token
from ..errors import UsdRelightError, one_line
from ..neural.pairs import MANIFEST, list_photos
from .guard import LOOPBACK, check_path_text, loopback_dashboard, output_lock, resolve_workers
from .manifest import RECORD, make_job, read_manifest, remove_leftovers, reusable, write_manifest
from .records import REFUSED, BatchOptions, BatchSummary, PhotoJob, PhotoRecord
from .task import process_photo

log = logging.getLogger(__name__)
PHOTO_RESOURCE = "photo"
"""Dask worker resource: a worker with ``photo=1`` runs one photo at a time and holds no queue of them."""
RESERVED = frozenset({MANIFEST})
"""Names of the output folder that no photo may take."""


def _dask():
    """dask and distributed (the ``batch`` extra), imported when a batch has work to do."""
    try:
        import dask
        import distributed
    except ImportError:
        raise UsdRelightError("usdrelight batch needs Dask: pip install 'usdrelight[batch]'") from None
    return dask, distributed


def _client(options: BatchOptions, workers: int):
    """(client, the LocalCluster or None when connected to ``options.scheduler``)."""
    dask, distributed = _dask()
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if options.scheduler:
        try:
            return Client(options.scheduler, timeout="10s"), None
        except (OSError, TimeoutError, ValueError) as exc:  # ValueError: an address Dask cannot parse
            raise UsdRelightError(f"cannot reach the Dask scheduler {options.scheduler}: {one_line(exc)}") from None
    # a worker that dies mid-photo makes the tasks it holds 'suspicious'; after `retries` more deaths a task
    # fails. The PHOTO resource (1 per worker) sets how many photos the client hands Dask at once (_slots), so
    # a dying worker holds only the photo it runs and never marks a waiting one. Everything listens on
    # loopback: the dashboard too (a bare ":0" would bind it to every interface).
    with dask.config.set({"distributed.scheduler.allowed-failures": options.retries}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host=LOOPBACK,
                               resources={PHOTO_RESOURCE: 1},
                               dashboard_address=f"{LOOPBACK}:0" if options.dashboard else None,
                               silence_logs=logging.ERROR)
    return Client(cluster), cluster


def _slots(client, limit) -> int:
    """Photos the cluster runs at once: its workers' ``photo`` resources (their threads when they declare none),
    at least 1 (a scheduler waiting for its first worker)."""
    workers = client.scheduler_info(n_workers=-1)["workers"].values()
    if limit is None:
        return max(1, sum(int(w.get("nthreads", 1)) for w in workers))
    return max(1, sum(int(w.get("resources", {}).get(PHOTO_RESOURCE, 0)) for w in workers))


SLOT_POLL_S = 2.0
"""Seconds between asks for free slots while photos wait and none finishes: workers that join a running batch
(``dask worker`` started later, an adaptive cluster) get photos without waiting for one to finish."""


def _finished(completed, submit_more, waiting, poll_s: float = SLOT_POLL_S):
    """The futures of ``completed`` (distributed.as_completed) one at a time as they finish; while
    ``waiting()`` and none finishes, ``submit_more()`` every ``poll_s`` seconds."""
    asked = time.monotonic()
    while not completed.is_empty():
        batch = completed.next_batch(block=not waiting())
        if batch:
            yield from batch
        elif time.monotonic() - asked >= poll_s:
            submit_more()
            asked = time.monotonic()
        else:
            time.sleep(0.05)


def _crash_record(job: PhotoJob, exc: BaseException) -> PhotoRecord:
    text = one_line(exc)
    return PhotoRecord(job.name, "failed", job.input_hash, str(job.photo),
                       error=f"worker died while processing the photo ({type(exc).__name__}: {text})"[:500],
                       error_kind="crash", pairs=job.options.pairs)


def run_batch(photo_dir, out_dir, options: BatchOptions = BatchOptions(), progress=None,
              on_cluster=None, on_refused=None) -> BatchSummary:
    """Process every photo of ``photo_dir`` into ``out_dir`` (see the module docstring).
    ``progress(done, total, record)`` after each photo; ``on_cluster(scheduler, dashboard)`` once the cluster
    is up (the dashboard is None when there is none); ``on_refused(file_name, reason)`` once per refused
    file (default: a logged warning)."""
    t0 = time.perf_counter()
    workers = 0 if options.scheduler else resolve_workers(options.workers)
    photo_dir, out = Path(photo_dir), Path(out_dir)
    check_path_text(photo_dir, "photo folder")
    check_path_text(out, "output folder")
    if not photo_dir.is_dir():
        raise UsdRelightError(f"photo folder not found: {photo_dir}")
    if out.exists() and not out.is_dir():
        raise UsdRelightError(f"output {out} exists and is not a folder")
    real_out = out.resolve()
    if photo_dir.resolve() == real_out or real_out in photo_dir.resolve().parents:
        raise UsdRelightError("the photo folder must not be the output folder or inside it")
    refused: list = []
    photos = list_photos(photo_dir, refused)
    refused += [(p, f"{p.stem!r} is a name the output folder keeps for itself") for p in photos
                if p.stem in RESERVED]
    photos = [p for p in photos if p.stem not in RESERVED]
    names = [p.stem for p in photos]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise UsdRelightError(f"{photo_dir}: two photos share a name ({', '.join(twice)})")
    with output_lock(out):
        return _locked(photos, refused, out, options, workers, progress, on_cluster, on_refused, t0)


def _refused_record(path: Path, reason: str) -> PhotoRecord:
    return PhotoRecord(path.name, REFUSED, "", str(path.parent.resolve() / path.name), error=reason)


def _locked(photos, refused, out, options, workers, progress, on_cluster, on_refused, t0) -> BatchSummary:
    """run_batch's work while it holds the output folder's lock."""
    remove_leftovers(out, {p.stem for p in photos})
    token = lock_token(out) or ""  # the workers publish only while this batch holds the folder
    previous = read_manifest(out)
    rows: dict[str, PhotoRecord] = {}
    per_photo, todo, jobs = [], [], []
    for p in photos:
        try:
            jobs.append(make_job(p, out, options, token))
        except UsdRelightError as exc:  # a sidecar out of the folder, an unreadable input
            refused.append((p, one_line(exc)))
    for p, reason in sorted(refused):
        rec = _refused_record(p, reason)
        rows["\0" + rec.name] = rec  # apart from the photos' rows: a refused file's name is no photo's name
        per_photo.append(_entry(rec, REFUSED))
        if on_refused is not None:
            on_refused(p.name, reason)
        else:
            log.warning("batch: %r not processed: %s", p.name, reason)
    for job in jobs:
        kept = reusable(job, previous.get(job.name))
        if kept is not None:
            rows[job.name] = kept
            per_photo.append(_entry(kept, "skipped"))
        else:
            todo.append(job)
            if job.name in previous:
                rows[job.name] = previous[job.name]
    summary = BatchSummary(out_dir=str(out.resolve()), manifest=str(out.resolve() / MANIFEST), photos=len(jobs),
                           done=0, failed=0, skipped=len(jobs) - len(todo), manifest_done=0, manifest_failed=0,
                           seconds=0.0, cluster_seconds=0.0, scheduler=None, dashboard=None, workers=0,
                           refused=len(refused), per_photo=per_photo)
    here = {p.stem for p in photos} | {p.stem for p, _ in refused}
    made = {d.name for d in out.iterdir() if not d.name.startswith(".") and (d / RECORD).is_file()}
    summary.orphaned = sorted(n for n in set(previous) | made if n not in here and (out / n).is_dir())
    if summary.orphaned:
        log.warning("batch: %d folder(s) in %s were made for photos no longer in %s (kept, left out of the manifest): "
                    "%s", len(summary.orphaned), out, photos[0].parent if photos else "the photo folder",
                    ", ".join(summary.orphaned[:10]) + (" ..." if len(summary.orphaned) > 10 else ""))
    if todo:
        _run(todo, options, workers, rows, summary, out, progress, on_cluster, len(jobs) - len(todo), len(jobs))
    write_manifest(out, rows)
    remove_leftovers(out, {p.stem for p in photos})
    summary.manifest_done = sum(r.status == "done" for r in rows.values())
    summary.manifest_failed = sum(r.status == "failed" for r in rows.values())
    summary.per_photo.sort(key=lambda e: e["name"])
    summary.seconds = time.perf_counter() - t0
    return summary


def _entry(rec: PhotoRecord, outcome: str) -> dict:
    return {"name": rec.name, "outcome": outcome, "status": rec.status, "seconds": rec.seconds,
            "build_seconds": rec.build_seconds, "fit_seconds": rec.fit_seconds, "fit_psnr_db": rec.fit_psnr_db,
            "error": rec.error}


@contextmanager
def _quiet_dask():
    """Dask's own log records (a lost scheduler's reconnect tracebacks, 'marked as failed because 1 workers
    died') off stderr while the batch reports those events itself in one line; kept with -vv."""
    _dask()  # imported first: its logging configuration sets the levels this overrides
    if logging.getLogger("usdrelight").getEffectiveLevel() <= logging.DEBUG:
        yield
        return
    names = ["distributed"] + [n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]
    before = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for n, level in before.items():
            logging.getLogger(n).setLevel(level)


def _run(todo, options, workers, rows, summary, out, progress, on_cluster, done0, total) -> None:
    with _quiet_dask():
        _run_quietly(todo, options, workers, rows, summary, out, progress, on_cluster, done0, total)


def _run_quietly(todo, options, workers, rows, summary, out, progress, on_cluster, done0, total) -> None:
    t = time.perf_counter()
    client, cluster = _client(options, workers)
    try:
        summary.cluster_seconds = time.perf_counter() - t
        summary.scheduler = client.scheduler.address
        # the LocalCluster's dashboard as its socket is bound (not the link Dask formats from the scheduler)
        summary.dashboard = client.dashboard_link if cluster is None else loopback_dashboard(cluster, options.dashboard)
        summary.workers = len(client.scheduler_info(n_workers=-1)["workers"])
        if on_cluster is not None:
            on_cluster(summary.scheduler, summary.dashboard)
        if not summary.workers:  # an external scheduler with no worker yet: what they declare decides below
            log.info("batch: waiting for a worker to join %s (Ctrl-C stops)", summary.scheduler)
            client.wait_for_workers(1)
            summary.workers = len(client.scheduler_info(n_workers=-1)["workers"])
        log.info("batch: %d photo(s) to process on %d worker(s) (%s)", len(todo), summary.workers,
                 summary.scheduler)
        workers = client.scheduler_info(n_workers=-1)["workers"].values()
        limit = {PHOTO_RESOURCE: 1} if any(PHOTO_RESOURCE in w.get("resources", {}) for w in workers) else None
        if limit is None:
            log.warning("batch: the workers declare no '%s' resource (dask worker --resources %s=1): photos run "
                        "one per worker thread", PHOTO_RESOURCE, PHOTO_RESOURCE)
        # at most one photo per free slot is handed to Dask: a task restricted to a resource goes to a worker at
        # once and waits in its queue, so a worker that died took its queued photos' retries with it
        pending, in_flight = list(todo), {}
        completed = _dask()[1].as_completed()

        def submit_more() -> None:
            slots = _slots(client, limit)  # asked once per finished photo, not once per photo handed out
            while pending and len(in_flight) < slots:
                job = pending.pop(0)
                fut = client.submit(process_photo, job, key=f"photo-{job.name}-{job.input_hash[:12]}", pure=False,
                                    resources=limit)
                in_flight[fut] = job
                completed.add(fut)

        submit_more()
        n = done0
        for fut in _finished(completed, submit_more, lambda: bool(pending)):
            job = in_flight.pop(fut)
            try:
                rec = fut.result()
            except CancelledError as exc:  # the scheduler went away (not this photo's fault: no crash recorded)
                left = 1 + len(in_flight) + len(pending)
                raise UsdRelightError(f"lost the Dask scheduler {summary.scheduler} ({one_line(exc)[:120]}): "
                                      f"{left} photo(s) not processed, the others recorded; run the batch again "
                                      f"to finish") from None
            except Exception as exc:  # the task's worker died (KilledWorker) or the cluster failed
                rec = _crash_record(job, exc)
                log.warning("%s: %s", job.name, rec.error)
            rows[job.name] = rec
            write_manifest(out, rows)
            if rec.status == "done":
                summary.done += 1
            else:
                summary.failed += 1
            summary.per_photo.append(_entry(rec, rec.status))
            n += 1
            if progress is not None:
                progress(n, total, rec)
            submit_more()
    except BaseException:  # Ctrl-C, SIGTERM, a lost scheduler: photos still running publish nothing into OUT
        revoke_lock_token(out)  # while the cluster shuts down (before: published, and left out of the manifest)
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
