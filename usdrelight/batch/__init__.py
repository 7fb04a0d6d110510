"""``usdrelight batch``: a folder of photos -> one stage per photo (built, lights fitted, optionally the training
pair rendered), on Dask distributed, resumable, with a manifest (``OUT_DIR/manifest.jsonl``).

records.py  the typed records: options, one photo's job, one manifest row, the run's summary
task.py     what a worker does for one photo (build, fit, render into a temp folder, then publish)
manifest.py input hashing, the manifest file, what a re-run may skip
run.py      the Dask client side: LocalCluster or an existing scheduler, submission, progress, summary
guard.py    what is refused before anything starts (too many workers, a second batch on one output folder)
            and the loopback check of the LocalCluster's dashboard
args.py     the command-line arguments (argparse only); console.py: progress bar and summary in a terminal
"""
