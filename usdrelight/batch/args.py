"""The ``usdrelight batch`` command-line arguments (argparse only, so building the command line stays light)."""
from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

from ..argtypes import non_negative_int as _non_negative_int, path as _path, positive_int as _positive_int
from ..errors import UsdRelightError
from ..estimate import names
from ..estimate.hub import prepare as prepare_models
from ..onnx_runtime import open_session
from .records import BatchOptions

DESCRIPTION = ("Per photo of PHOTO_DIR (NAME.png/.jpg/.exr + optional NAME.depth.exr, NAME.intrinsics.json, "
               "NAME.albedo.exr ...): build the stage into OUT_DIR/NAME, fit its lights, with --pairs render the "
               "training pair, on Dask (an embedded LocalCluster or --scheduler); OUT_DIR/manifest.jsonl lists every "
               "photo. A re-run skips unchanged photos. Files that cannot be processed (a control character in the "
               "name, a link out of PHOTO_DIR ...) are reported and listed as refused. One batch per OUT_DIR at a "
               "time. Exit 0 when every photo ended done or recorded failed, 2 when the batch cannot run.")


def add_batch_parser(sub, common: argparse.ArgumentParser, func) -> argparse.ArgumentParser:
    """Add the ``batch`` subcommand to the subparsers ``sub``; ``func(args)`` runs it."""
    d = BatchOptions()
    bt = sub.add_parser("batch", parents=[common], help="build + fit a folder of photos on Dask (resumable)",
                        description=DESCRIPTION)
    bt.add_argument("photos", type=_path, metavar="PHOTO_DIR")
    bt.add_argument("-o", "--output", type=_path, required=True, metavar="OUT_DIR")
    where = bt.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, default=d.workers,
                       help="worker processes of the embedded Dask LocalCluster, 1 thread each (default 2; at most "
                            "one per CPU core and per 2 GiB of available memory: more is refused)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786")
    bt.add_argument("--pairs", action="store_true", help="also render the training pair (D~, albedo, valid)")
    bt.add_argument("--max-side", type=_positive_int, default=d.max_side, help="longer image side of the fit")
    bt.add_argument("--lights", type=_non_negative_int, default=d.lights, help="most point lights the fit keeps")
    bt.add_argument("--iterations", type=_positive_int, default=d.iterations, help="position iterations of the fit")
    bt.add_argument("--verify-spp", type=_non_negative_int, default=d.verify_spp, metavar="N",
                    help="samples per pixel of the fit's Mitsuba verification render (default 0: none)")
    bt.add_argument("--spp", type=_positive_int, default=d.spp, help="samples per pixel of the pair's D~ render")
    bt.add_argument("--retries", type=_non_negative_int, default=d.retries,
                    help="LocalCluster: how often a photo whose worker died is tried again (default %(default)s)")
    bt.add_argument("--retry-failed", action="store_true",
                    help="redo photos recorded failed on an input error even when their inputs are unchanged")
    bt.add_argument("--no-dashboard", action="store_true",
                    help="no Dask dashboard for the LocalCluster (by default one on 127.0.0.1, a free port)")
    names.add_estimator_arguments(bt, batch=True)
    bt.set_defaults(func=func)
    return bt


def _onnx_absolute(choice: str | None) -> str | None:
    """``onnx:FILE`` with FILE absolute (the workers may run elsewhere); any other choice as it is."""
    f = names.onnx_file(choice)
    return choice if f is None else f"onnx:{f.absolute()}"


def _onnx_digests(*choices) -> tuple:
    """sha256 of each ``onnx:FILE`` model, hashed into every photo's input hash (a changed model redoes the
    photos); each is opened here first, so a missing or broken model is one line and exit 2 before any photo."""
    out = []
    for choice in choices:
        f = names.onnx_file(choice)
        if f is None:
            continue
        open_session(f, threads=1)
        h = hashlib.sha256()
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        out.append(h.hexdigest())
    return tuple(out)


def options_from_args(args) -> BatchOptions:
    """The batch's options; the learned estimators' weights are found here, in the client, before any work (a
    missing extra or model is one line and exit 2), and handed to the workers as folders."""
    geometry, albedo_from = getattr(args, "geometry", None), getattr(args, "albedo_from", None)
    model_paths = tuple(getattr(args, "model_path", ()) or ())
    if model_paths and not (names.is_learned(geometry) or names.is_learned(albedo_from)):
        raise UsdRelightError("--model-path goes with --geometry or --albedo-from naming a hub model")
    model_paths = tuple(str(Path(p).absolute()) for p in prepare_models((geometry, albedo_from), model_paths))
    geometry, albedo_from = _onnx_absolute(geometry), _onnx_absolute(albedo_from)
    return BatchOptions(max_side=args.max_side, lights=args.lights, iterations=args.iterations,
                        verify_spp=args.verify_spp, pairs=args.pairs, spp=args.spp, workers=args.workers,
                        scheduler=args.scheduler, retries=args.retries, retry_failed=args.retry_failed,
                        dashboard=not args.no_dashboard, geometry=geometry, albedo_from=albedo_from,
                        model_paths=model_paths, device=getattr(args, "device", None),
                        model_digests=_onnx_digests(geometry, albedo_from))
