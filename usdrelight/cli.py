"""``usdrelight`` command line: thin wrappers over the library functions.

Every subcommand takes ``--json`` (a machine-readable summary on stdout). Logs and progress go
to stderr. Bad input ends with one line ``usdrelight: error: ...`` on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import logging
import re
import signal
import sys
import threading

from . import __version__
from .argtypes import add_frames_argument, add_time_argument, non_negative_int as _non_negative_int, path as _path, \
    port as _port, positive_float as _positive_float, positive_int as _positive_int, OneLineParser
from .batch.args import add_batch_parser
from .commands import stderr_console, cmd_batch, cmd_build, cmd_convert, cmd_fit, cmd_neural, cmd_relight, \
    cmd_render, cmd_serve, cmd_train, cmd_validate
from .relight.args import add_relight_parser
from .errors import UsdRelightError, one_line
from .estimate.names import add_estimator_arguments
from .native_io import command_context

log = logging.getLogger("usdrelight")
EXIT_USER_ERROR = 2
EXIT_INTERNAL = 1


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING - 10 * verbosity
    handler, fmt = logging.StreamHandler(sys.stderr), "%(levelname)s %(message)s"
    if sys.stderr.isatty():  # rich in a terminal; a file or pipe gets one line per record, never wrapped
        try:
            from rich.logging import RichHandler

            handler = RichHandler(console=stderr_console(), show_time=False, show_path=False, markup=False)
            fmt = "%(message)s"
        except ImportError:  # pragma: no cover - rich is a dependency
            pass
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger("usdrelight")
    root.handlers[:] = [handler]
    root.setLevel(max(level, logging.DEBUG))
    root.propagate = False


# ---- parser ---------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    reads = argparse.ArgumentParser(add_help=False)  # commands that read scene files
    reads.add_argument("--allow-path", action="append", type=_path, default=[], metavar="DIR",
                       help="also let the scene read files under DIR (repeatable; by default a scene reads only "
                            "inside its own folder tree)")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print a machine-readable JSON summary on stdout")
    common.add_argument("-v", "--verbose", action="count", default=0, help="more logging on stderr (-vv for debug)")
    common.add_argument("--debug", action="store_true", help="show tracebacks of unexpected errors")
    device = argparse.ArgumentParser(add_help=False)  # commands that render or run the network
    device.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu",
                        help="where Mitsuba/drjit and the network run (default cpu; auto: CUDA when drjit finds a "
                             "GPU; cuda: a GPU or one clear error)")
    device.set_defaults(uses_render_device=True)

    p = OneLineParser(prog="usdrelight", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"usdrelight {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    b = sub.add_parser("build", parents=[common], help="photo -> OUTDIR/scene.usda",
                       description="Build a relightable USD scene from one photograph.")
    b.add_argument("photo", type=_path, help="photograph (JPEG/PNG/TIFF: sRGB; EXR: linear)")
    b.add_argument("-o", "--output", type=_path, required=True, help="output directory (gets scene.usda)")
    g = b.add_mutually_exclusive_group()
    g.add_argument("--depth", type=_path, help="z-depth map in metres (.npy/.exr/.pfm; 16-bit PNG with --depth-scale); "
                   "<=0, NaN, Inf = invalid")
    g.add_argument("--points", type=_path, help="point map HxWx3, OpenCV camera frame, Inf/NaN = invalid")
    g.add_argument("--geometry-model", type=_path, help="ONNX geometry model (manual: Photo to stage, Model contracts)")
    b.add_argument("--depth-scale", type=_positive_float, metavar="M",
                   help="metres per stored unit of --depth/--points (0.001: millimetres); needed for integer files")
    k = b.add_mutually_exclusive_group()
    k.add_argument("--intrinsics", type=_path, help='JSON: {"fx","fy","cx","cy"} (OpenCV pixels) or normalized 3x3')
    k.add_argument("--fov-x", type=float, help="horizontal field of view in degrees")
    b.add_argument("--albedo", type=_path, help="albedo map (linear), e.g. CID hr_alb")
    b.add_argument("--shading", type=_path, help="diffuse shading map (linear), e.g. CID dif_shd; needs --albedo")
    b.add_argument("--albedo-model", type=_path, help="ONNX albedo model (manual: Photo to stage, Model contracts)")
    add_estimator_arguments(b, g)
    b.add_argument("--mask", type=_path, help="valid-pixel mask (non-zero = keep)")
    b.add_argument("--decimate", type=_positive_int, default=1, metavar="N",
                   help="keep every N-th pixel row and column as vertices (projective UVs are kept)")
    b.add_argument("--max-grazing-deg", type=_positive_float, default=88.0,
                   help="cut triangles whose normal is more than this many degrees from the view ray")
    b.set_defaults(func=cmd_build)

    r = sub.add_parser("render", parents=[common, reads, device], help="render the AOVs the stage's RenderSettings declare",
                       description="Render the stage's RenderProducts with Mitsuba (llvm_ad_rgb) to linear EXR.")
    r.add_argument("stage", type=_path)
    r.add_argument("-o", "--output", type=_path, help="output folder (default: the stage's folder)")
    r.add_argument("--spp", type=_positive_int, default=64, help="samples per pixel of the path-traced AOV")
    r.add_argument("--max-depth", type=_positive_int, default=3,
                   help="path length as in Mitsuba (2 = direct only, 3 = one indirect bounce)")
    r.add_argument("--aov", nargs="+", metavar="NAME", help="render only these declared products")
    r.add_argument("--seed", type=int, default=0)
    add_time_argument(r)
    r.set_defaults(func=cmd_render)

    f = sub.add_parser("fit", parents=[common, reads, device], help="fit lights to the photo's diffuse image",
                       description="Fit an environment map and point lights so the render reproduces D; write "
                                   "them into the fitted-lights layer.")
    f.add_argument("stage", type=_path)
    f.add_argument("--method", choices=["adam", "fast"], default="fast")
    f.add_argument("--lights", type=int, default=16, help="point lights: the most the fit keeps (fast, the default), "
                                                           "or the number to start from (adam)")
    f.add_argument("--env-res", help="environment resolution HxW (fast: basis cells, default 8x16; adam: "
                                     "texels, default 128x256; 0x0 = no environment)")
    f.add_argument("--iterations", type=_positive_int)
    f.add_argument("--max-side", type=_positive_int, default=512, help="longer image side of the fit")
    f.add_argument("--report", type=_path, help="write fit_report.json and an error-vs-time plot here")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--verify-spp", type=_non_negative_int, default=128, metavar="N",
                   help="samples per pixel of the Mitsuba verification render (0: skip it)")
    f.set_defaults(func=cmd_fit)

    n = sub.add_parser("neural", parents=[common, reads, device], help="run the neural renderer on the stage's AOVs",
                       description="Read D~, albedo and valid mask through the stage's RenderProducts, fill "
                                   "holes, run the ONNX network; write linear EXR and sRGB PNG.")
    n.add_argument("stage", type=_path)
    n.add_argument("--model", type=_path, help="ONNX model (default: the shipped one)")
    n.add_argument("-o", "--output", type=_path, help="output folder (default: STAGE_DIR/neural)")
    n.add_argument("--render-missing", action="store_true", help="render AOVs whose files are missing")
    n.add_argument("--spp", type=_positive_int, default=64)
    n.set_defaults(func=cmd_neural)

    add_relight_parser(sub, [common, reads, device], cmd_relight)

    tr = sub.add_parser("train", parents=[common], help="train the neural renderer (needs torch)",
                        description="Self-supervised pairs from a folder of photos (+ optional estimator "
                                    "outputs NAME.depth.exr, NAME.intrinsics.json, NAME.albedo.exr), then training "
                                    "and ONNX export.")
    tr.add_argument("data", type=_path)
    tr.add_argument("-o", "--output", type=_path, required=True, help="ONNX file to write")
    tr.add_argument("--work", type=_path, help="folder for the per-photo stages (cached)")
    tr.add_argument("--steps", type=_positive_int, default=1500)
    tr.set_defaults(func=cmd_train)

    add_batch_parser(sub, common, cmd_batch)
    c = sub.add_parser("convert", parents=[common, reads], help="convert between USD and Mitsuba XML, Blender, glTF/PLY/OBJ",
                       description="Convert SRC to DST, each format chosen by its suffix.")
    c.add_argument("src", type=_path)
    c.add_argument("dst", type=_path)
    c.add_argument("--spp", type=_positive_int, metavar="N",
                   help="samples per pixel the written scene renders with (Mitsuba XML, Blender; default 64)")
    c.add_argument("--max-depth", type=_positive_int, metavar="N",
                   help="path length as in Mitsuba (2 = direct only, 3 = one indirect bounce; Mitsuba XML, "
                        "Blender; default 3)")
    when = c.add_mutually_exclusive_group()
    add_time_argument(when)
    add_frames_argument(when, "Mitsuba XML, mesh files: one file DST_NNNN.SUFFIX")
    c.set_defaults(func=cmd_convert)

    sv = sub.add_parser("serve", parents=[common, reads, device], help="interactive relighting web app (the serve extra)",
                        description="A local web app: the photo mesh, camera and lights in 3D, light editing, "
                                    "the relit photo live; saves lights_user.usda. Ctrl-C stops it.")
    sv.add_argument("stage", type=_path)
    sv.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (default 127.0.0.1: this machine only)")
    sv.add_argument("--port", type=_port, default=8080, help="port (the next free one when taken; 0 = any)")
    sv.add_argument("--hdri", type=_path, action="append", metavar="FILE",
                    help="latlong HDRI (.exr/.hdr) offered to dome lights (repeatable)")
    sv.add_argument("--mode", choices=["auto", "neural", "ratio", "add", "render", "transfer", "residual"],
                    help="initial output mode (default: auto, resolved per frame as relight resolves it)")
    sv.add_argument("--max-side", type=_positive_int, default=512, help="longer side of the live frames, pixels")
    sv.set_defaults(func=cmd_serve)

    v = sub.add_parser("validate", parents=[common, reads], help="run every pxr.UsdValidation validator",
                       description="Exit 0 only when no validator reports an error: every pxr.UsdValidation validator, "
                                   "and usdrelight's own reader (usdrelight:ReadScene: what render and fit would "
                                   "refuse, as errors; what they leave out, as warnings).")
    v.add_argument("stage", type=_path)
    v.set_defaults(func=cmd_validate)
    return p


class Terminated(KeyboardInterrupt):
    """SIGTERM (how batch schedulers and ``kill`` stop a job), raised where the main thread is, so it unwinds
    through the same clean-up as Ctrl-C (temp folders, locks, the Dask cluster)."""


def _on_sigterm(signum, frame):
    raise Terminated()


def _quiet_after_interrupt() -> None:
    """A second Ctrl-C while the first one's clean-up runs (closing the Dask cluster at exit) is ignored: it
    printed a traceback from an atexit callback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _joined_negative_values(argv: list[str]) -> list[str]:
    """``--frames -3:-1`` as ``--frames=-3:-1``: argparse takes a value that starts with '-' and is not a plain
    negative number for an option (a pre-roll range was 'unrecognized arguments')."""
    out = []
    for arg in argv:
        if out and out[-1] in ("--frames", "--time") and re.fullmatch(r"-[\d.][\w.:+-]*", arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(_joined_negative_values(sys.argv[1:] if argv is None else [str(a) for a in argv]))
    _setup_logging(args.verbose)
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        if getattr(args, "uses_render_device", False):
            from .device import select_device
            select_device(args.device)
        with command_context(getattr(args, "allow_path", [])):  # native logs off stdout, --allow-path
            return int(args.func(args) or 0)
    except UsdRelightError as exc:
        sys.stderr.write(f"usdrelight: error: {one_line(exc)}\n")
        return EXIT_USER_ERROR
    except Terminated:
        if argv is None:  # the CLI process itself, about to exit (not main() called by a library or a test)
            _quiet_after_interrupt()
        sys.stderr.write("usdrelight: terminated\n")
        return 143
    except KeyboardInterrupt:
        if argv is None:
            _quiet_after_interrupt()
        sys.stderr.write("usdrelight: interrupted\n")
        return 130
    except Exception as exc:  # never a traceback for the user unless asked
        if args.debug:
            raise
        sys.stderr.write(f"usdrelight: error: unexpected {type(exc).__name__}: {one_line(exc)} "
                         f"(rerun with --debug for a traceback)\n")
        return EXIT_INTERNAL
    finally:
        if previous is not None and signal.getsignal(signal.SIGTERM) is _on_sigterm:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
