"""What ``usdrelight batch`` refuses before it starts anything: more workers than the machine can run, a
second batch on one output folder, folder paths that print as something else; and where its LocalCluster
listens (loopback only, checked on the sockets the dashboard really bound).
"""
from __future__ import annotations

import ipaddress
import os
import unicodedata
from contextlib import ExitStack, contextmanager
from pathlib import Path

from ..atomic import LOCK_NAME, stage_lock
from ..errors import UsdRelightError

WORKER_MEMORY = 2 << 30
"""Memory one LocalCluster worker is counted to need, bytes: 2 GiB. Measured peak resident memory of one process
building and fitting the motorcycle example (true depth) at the default options (``benchmarks/bench_worker_memory.py``):
1.01 GiB at 741 x 500 px, 2.31 GiB up-sampled to 2223 x 1500 (3.3 MP), before the Dask worker's own runtime; the
build runs at full resolution, so larger photos need more."""
DEFAULT_WORKERS = 2
"""Workers when ``--workers`` is not given (fewer when the machine has fewer cores or too little memory)."""
LOOPBACK = "127.0.0.1"
"""The LocalCluster's scheduler, workers and dashboard listen here only."""


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))  # the cores this process may run on
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _available_memory() -> int:
    """Bytes of memory available to new processes without swapping."""
    try:
        import psutil  # a dependency of distributed (the batch extra)

        return int(psutil.virtual_memory().available)
    except ImportError:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def worker_limit() -> tuple[int, str]:
    """(most LocalCluster workers this machine runs, why): one per core this process may use and one per
    :data:`WORKER_MEMORY` of available memory, at least 1."""
    cores, memory = _cores(), _available_memory()
    limit = max(1, min(cores, memory // WORKER_MEMORY))
    return limit, (f"{cores} CPU core(s), {memory / 2 ** 30:.1f} GiB memory available at "
                   f"{WORKER_MEMORY / 2 ** 30:.0f} GiB per worker")


def resolve_workers(requested: int | None) -> int:
    """The LocalCluster's worker count: ``requested`` when the machine can run it (UsdRelightError
    otherwise), or :data:`DEFAULT_WORKERS` bounded by the machine when None."""
    limit, why = worker_limit()
    if requested is None:
        return min(DEFAULT_WORKERS, limit)
    if requested < 1:
        raise UsdRelightError(f"--workers must be >= 1, got {requested}")
    if requested > limit:
        raise UsdRelightError(f"--workers {requested} is more than this machine can run: at most {limit} "
                              f"({why})")
    return requested


def check_path_text(path: Path, what: str) -> None:
    """UsdRelightError when the absolute path of ``path`` has a control character (its messages and
    manifest rows would print as something else, and the tools downstream choke on it)."""
    text = str(Path(path).absolute())
    for ch in text:
        if unicodedata.category(ch) in ("Cc", "Zl", "Zp"):
            raise UsdRelightError(f"the {what}'s path {text!r} has a control character (U+{ord(ch):04X})")


@contextmanager
def output_lock(out: Path):
    """Hold the lock of the batch output folder ``out`` (created if missing) for the block: a second batch
    (or any usdrelight writer of that folder) is a UsdRelightError naming the holder's PID. Stale locks
    (their process gone) are taken over (:func:`usdrelight.atomic.stage_lock`)."""
    with ExitStack() as stack:
        try:
            stack.enter_context(stage_lock(out))
        except UsdRelightError as exc:
            try:
                holder = f"PID {int((Path(out) / LOCK_NAME).read_text().split()[0])}"
            except (OSError, ValueError, IndexError):
                holder = "another process"
            raise UsdRelightError(f"output folder {out} is in use by another batch ({holder}, lock "
                                  f"{Path(out) / LOCK_NAME}); wait for it to end or choose another -o (if no batch runs "
                                  f"there, that process is another program: remove the lock file)"
                                  if "being written" in str(exc) else str(exc)) from None
        yield out


def bound_addresses(server) -> list[tuple[str, int]]:
    """(host, port) of every socket a started Tornado HTTP server listens on."""
    return [tuple(s.getsockname()[:2]) for s in getattr(server, "_sockets", {}).values()]


def loopback_dashboard(cluster, dashboard: bool) -> str | None:
    """The address of the LocalCluster's dashboard, from the sockets its HTTP server really bound (None
    when ``dashboard`` is off: the scheduler still serves its health routes there, on loopback);
    UsdRelightError when one of them is not a loopback address."""
    server = getattr(cluster.scheduler, "http_server", None)
    bound = bound_addresses(server) if server is not None else []
    wrong = [f"{h}:{p}" for h, p in bound if not ipaddress.ip_address(h.split("%")[0]).is_loopback]
    if wrong:
        raise UsdRelightError(f"the Dask dashboard listens on {', '.join(wrong)}, not only on this machine")
    if not dashboard or not bound:
        return None
    host, port = bound[0]
    return f"http://{host if ':' not in host else f'[{host}]'}:{port}/status"
