"""``usdrelight batch`` in a terminal: the cluster's addresses and a progress bar over photos on stderr (one line
per photo where stderr is not a terminal), the summary on stdout (only JSON with ``--json``)."""
from __future__ import annotations

import sys

from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from .args import options_from_args
from .run import run_batch


def run_command(args, console, emit) -> int:
    """Run the batch of the parsed ``args``; ``console`` is a rich Console on stderr, ``emit(args, summary,
    human)`` prints the summary."""
    with Progress(TextColumn("batch {task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, disable=not sys.stderr.isatty()) as bar:
        task = bar.add_task("photos", total=None)

        def on_cluster(scheduler, dashboard):
            console.print(f"dask scheduler {scheduler}, dashboard {dashboard or '(none)'}", highlight=False,
                          markup=False, emoji=False, soft_wrap=True)

        def on_refused(name, reason):  # one line each, however long (a logged warning would wrap)
            console.print(f"batch: {name!r} not processed: {reason}", highlight=False, markup=False,
                          emoji=False, soft_wrap=True)

        def progress(n, total, rec):
            bar.update(task, completed=n, total=total, description=f"{escape(rec.name)}: {rec.status}")
            if not sys.stderr.isatty():  # a log file, nohup, CI: one line per photo instead of the bar
                took = f" in {rec.seconds:.1f} s" if rec.seconds is not None else ""
                console.print(f"batch {n}/{total}: {rec.name!r} {rec.status}{took}", highlight=False, markup=False,
                              emoji=False, soft_wrap=True)

        res = run_batch(args.photos, args.output, options_from_args(args), progress=progress, on_cluster=on_cluster,
                        on_refused=on_refused)
    refused = f", {res.refused} file(s) not processed" if res.refused else ""
    emit(args, res.to_dict(), f"batch: {res.done} done, {res.failed} failed, {res.skipped} skipped of {res.photos} "
                              f"photo(s){refused} in {res.seconds:.1f} s; manifest {res.manifest}")
    return 0
