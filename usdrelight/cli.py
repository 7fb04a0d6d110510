"""``usdrelight`` command line: thin wrappers over the library functions.

Every subcommand takes ``--json`` (a machine-readable summary on stdout). Logs and progress go
to stderr. Bad input ends with one line ``usdrelight: error: ...`` on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from . import __version__
from .argtypes import add_frames_argument, add_time_argument, non_negative_int as _non_negative_int, port as _port, \
    positive_int as _positive_int, OneLineParser
from .batch.args import add_batch_parser
from .relight.args import add_relight_parser
from .errors import UsdRelightError, one_line
from .estimate.names import add_estimator_arguments
from .native_io import command_context

log = logging.getLogger("usdrelight")
EXIT_USER_ERROR = 2
EXIT_INTERNAL = 1


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING - 10 * verbosity
    try:
        from rich.logging import RichHandler

        handler = RichHandler(console=_stderr_console(), show_time=False, show_path=False, markup=False)
        fmt = "%(message)s"
    except ImportError:  # pragma: no cover - rich is a dependency
        handler, fmt = logging.StreamHandler(sys.stderr), "%(levelname)s %(message)s"
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger("usdrelight")
    root.handlers[:] = [handler]
    root.setLevel(max(level, logging.DEBUG))
    root.propagate = False


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)


class _Steps:
    """A rich progress bar over named steps, on stderr; silent when stderr is not a terminal."""

    def __init__(self, names, title):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
        self.names = list(names)
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                                 console=_stderr_console(), transient=True,
                                 disable=not sys.stderr.isatty())
        self.task = None
        self.title = title

    def __enter__(self):
        self.progress.__enter__()
        self.task = self.progress.add_task(f"{self.title}: {self.names[0]}", total=len(self.names))
        return self

    def __call__(self, done_name):
        i = self.names.index(done_name) + 1 if done_name in self.names else 0
        nxt = self.names[i] if i < len(self.names) else "done"
        self.progress.update(self.task, advance=1, description=f"{self.title}: {nxt}")
        log.info("%s: %s done", self.title, done_name)

    def __exit__(self, *exc):
        return self.progress.__exit__(*exc)


def _emit(args, summary: dict, human: str) -> None:
    if args.json:
        sys.stdout.write(json.dumps(summary, indent=2, default=str) + "\n")
    else:
        sys.stdout.write(human + "\n")


# ---- subcommands ------------------------------------------------------------------------------
def cmd_build(args) -> int:
    from .stage.build import BuildOptions, build

    opts = BuildOptions(depth=args.depth, points=args.points, intrinsics=args.intrinsics, fov_x=args.fov_x,
                        albedo=args.albedo, shading=args.shading, mask=args.mask,
                        geometry_model=args.geometry_model, albedo_model=args.albedo_model,
                        geometry=args.geometry, albedo_from=args.albedo_from, model_paths=tuple(args.model_path),
                        device=args.device, stride=args.decimate, max_grazing_deg=args.max_grazing_deg)
    with _Steps(["read", "geometry", "albedo", "mesh", "write"], "build") as steps:
        res = build(args.photo, args.output, opts, progress=steps)
    summary = {
        "stage": str(res.stage), "width": res.width, "height": res.height, "vertices": res.n_vertices,
        "faces": res.n_faces, "vertex_fraction": round(res.vertex_fraction, 6), "triangles_cut": res.triangles_cut,
        "geometry": res.geometry_source, "albedo": res.albedo_source, "intrinsics_opencv": res.intrinsics,
        "seconds": {k: round(v, 4) for k, v in res.seconds.items()}, "bytes": res.files,
        "estimators": res.estimators,
    }
    _emit(args, summary, f"wrote {res.stage} ({res.width}x{res.height}, {res.n_vertices} vertices, "
                         f"{res.n_faces} triangles, {res.seconds['total']:.2f} s)")
    return 0


def cmd_validate(args) -> int:
    from .stage.validate import errors_only, open_stage, validate_stage
    stage = open_stage(args.stage)
    findings = validate_stage(stage)
    errors = errors_only(findings)
    summary = {"stage": str(args.stage), "errors": len(errors), "findings": [f.__dict__ for f in findings]}
    lines = [f"{f.severity}: [{f.validator}] {f.message} {' '.join(f.sites)}".rstrip() for f in findings]
    lines.append(f"{args.stage}: {len(errors)} error(s), {len(findings) - len(errors)} other finding(s)")
    _emit(args, summary, "\n".join(lines))
    return 0 if not errors else 1


def cmd_render(args) -> int:
    from .mitsuba.render import render_stage

    res = render_stage(args.stage, args.output, args.aov, spp=args.spp, max_depth=args.max_depth, seed=args.seed,
                       time=args.time)
    summary = {"stage": str(args.stage), "files": res.files, "seconds": {k: round(v, 4) for k, v in res.seconds.items()},
               "warnings": res.warnings}
    _emit(args, summary, "\n".join(f"wrote {p}" for p in res.files.values()) + f" ({res.seconds['total']:.2f} s)")
    return 0


def cmd_fit(args) -> int:
    from .fit.run import FitSettings, fit
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("fit {task.description}"), BarColumn(), TimeElapsedColumn(), console=_stderr_console(),
                  transient=True, disable=not sys.stderr.isatty()) as bar:
        task = bar.add_task(args.method, total=None)

        def progress(it, total, mse):
            bar.update(task, completed=it, total=total, description=f"{args.method} mse={mse:.3e}")

        settings = FitSettings(method=args.method, lights=args.lights, env_res=args.env_res,
                               iterations=args.iterations, max_side=args.max_side, verify_spp=args.verify_spp,
                               seed=args.seed)
        rep = fit(args.stage, settings, report_dir=args.report, progress=progress)
    summary = {k: v for k, v in rep.to_dict().items() if k != "curve"}
    verified = "not rendered" if rep.render_psnr_db is None else f"{rep.render_psnr_db:.2f} dB"
    _emit(args, summary, f"fit ({rep.method}): PSNR {rep.psnr_db:.2f} dB (model), {verified} "
                         f"(Mitsuba render), {rep.lights_kept} point light(s), environment "
                         f"{'kept' if rep.environment_kept else 'dropped'}, {rep.seconds:.2f} s")
    return 0


def cmd_neural(args) -> int:
    from .neural.model import neural_stage

    res = neural_stage(args.stage, args.model, args.output, render_missing=args.render_missing, spp=args.spp)
    summary = {"exr": str(res.exr), "png": str(res.png), "seconds": {k: round(v, 4) for k, v in res.seconds.items()}}
    _emit(args, summary, f"wrote {res.exr} and {res.png} ({res.seconds['total']:.2f} s)")
    return 0


def cmd_relight(args) -> int:
    from .relight.run import relight

    res = relight(args.stage, args.light or [], args.output, args.model, args.with_fitted, args.spp,
                  max_side=args.max_side, renderer=args.renderer, sequence=args.sequence, mode=args.mode,
                  fitted_scale=args.fitted_scale, contact_sheet=args.contact_sheet, time=args.time,
                  frames=args.frames, video=args.video, save_lights=args.save_lights, area_samples=args.area_samples)

    def secs(d):
        return {k: round(v, 4) for k, v in d.items()}
    frames = [{"exr": str(f.exr), "png": str(f.png), "diffuse": str(f.diffuse), "lights": f.lights,
               "time": f.time, "seconds": secs(f.seconds)} for f in res.frames]
    first = res.frames[0]
    cache = None if res.cache_hit is None else ("hit" if res.cache_hit else "built")
    summary = {"renderer": res.renderer, "mode": res.mode, "cache": cache, "area_samples": res.area_samples,
               "resolution": list(res.resolution), "exr": frames[0]["exr"], "png": frames[0]["png"],
               "contact_sheet": str(res.contact_sheet) if res.contact_sheet else None,
               "diffuse": frames[0]["diffuse"], "lights": first.lights, "frames": frames,
               "video": str(res.video) if res.video else None,
               "lights_layer": str(res.lights_layer) if res.lights_layer else None,
               "seconds": secs({**res.seconds, **(first.seconds if len(res.frames) == 1 else {}),
                                "total": res.seconds["total"]})}
    per_frame = np.median([f.seconds["total"] for f in res.frames])
    _emit(args, summary, f"wrote {len(res.frames)} relit frame(s) to {first.exr.parent} ({res.resolution[0]}x"
                         f"{res.resolution[1]}, {res.renderer} renderer, {first.lights} light(s)); prepare "
                         f"{res.seconds['prepare']:.2f} s, {per_frame:.2f} s per frame")
    return 0


def cmd_train(args) -> int:
    from .neural.train import train_folder

    res = train_folder(args.data, args.output, args.work, steps=args.steps)
    summary = {"model": str(res.model), "log": str(res.log), "pairs": res.pairs, "pair_names": res.pair_names,
               "pairs_seconds": res.pairs_seconds, "steps": res.steps, "seconds": res.seconds,
               "parameters": res.parameters, "device": res.device}
    _emit(args, summary, f"wrote {res.model} ({res.pairs} pairs, {res.steps} steps, {res.seconds:.0f} s)")
    return 0


def cmd_batch(args) -> int:
    from .batch.console import run_command
    return run_command(args, _stderr_console(), _emit)


def cmd_convert(args) -> int:
    from .converters.convert import convert

    options = {k: v for k, v in (("spp", args.spp), ("max_depth", args.max_depth), ("time", args.time))
               if v is not None}
    res = convert(args.src, args.dst, frames=args.frames, **options)  # only the options given: writer defaults
    for kind, n in res.read_warnings.items():  # what USD cannot hold of SRC: a line per kind, in the order met
        log.warning("%s: %d", kind, n)
    for kind, n in sorted(res.write_warnings.items()):  # what DST cannot represent: a line per kind
        log.warning("%s: %d", kind, n)
    summary = {"src": str(args.src), "dst": str(args.dst), **res.to_dict()}
    shown = args.dst if args.frames is None else f"{res.files[0]} and {len(res.files) - 1} more file(s)"
    _emit(args, summary, f"wrote {shown}")  # with --frames no file is named DST itself
    return 0


def cmd_serve(args) -> int:
    from .serve.app import ServeApp
    from .serve.signals import stop_on_signals

    with stop_on_signals():
        app = ServeApp(args.stage, host=args.host, port=args.port, hdris=args.hdri or (), max_side=args.max_side,
                       mode=args.mode)
        try:
            summary = {"url": app.url, "host": app.host, "port": app.port, "mode": app.mode,
                       "resolution": list(app.live.resolution), "lights": len(app.states),
                       "seconds": {k: round(v, 4) for k, v in app.seconds.items()}}
            _emit(args, summary, f"usdrelight serve: open {app.url} ({app.seconds['start']:.1f} s to start; "
                                 f"Ctrl-C stops)")
            sys.stdout.flush()
            app.wait_forever()
        except KeyboardInterrupt:
            log.info("serve: stopping")
        finally:
            app.stop()
    return 0


# ---- parser ---------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    reads = argparse.ArgumentParser(add_help=False)  # commands that read scene files
    reads.add_argument("--allow-path", action="append", type=Path, default=[], metavar="DIR",
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
    b.add_argument("photo", type=Path, help="photograph (JPEG/PNG/TIFF: sRGB; EXR: linear)")
    b.add_argument("-o", "--output", type=Path, required=True, help="output directory (gets scene.usda)")
    g = b.add_mutually_exclusive_group()
    g.add_argument("--depth", type=Path, help="z-depth map in metres (.npy/.exr/.pfm); <=0, NaN, Inf = invalid")
    g.add_argument("--points", type=Path, help="point map HxWx3, OpenCV camera frame, Inf/NaN = invalid")
    g.add_argument("--geometry-model", type=Path, help="ONNX geometry model (see README, model contracts)")
    k = b.add_mutually_exclusive_group()
    k.add_argument("--intrinsics", type=Path, help='JSON: {"fx","fy","cx","cy"} (OpenCV pixels) or normalized 3x3')
    k.add_argument("--fov-x", type=float, help="horizontal field of view in degrees")
    b.add_argument("--albedo", type=Path, help="albedo map (linear), e.g. CID hr_alb")
    b.add_argument("--shading", type=Path, help="diffuse shading map (linear), e.g. CID dif_shd; needs --albedo")
    b.add_argument("--albedo-model", type=Path, help="ONNX albedo model (see README, model contracts)")
    add_estimator_arguments(b, g)
    b.add_argument("--mask", type=Path, help="valid-pixel mask (non-zero = keep)")
    b.add_argument("--decimate", type=_positive_int, default=1, metavar="N",
                   help="keep every N-th pixel row and column as vertices (projective UVs are kept)")
    b.add_argument("--max-grazing-deg", type=float, default=88.0,
                   help="cut triangles whose normal is more than this many degrees from the view ray")
    b.set_defaults(func=cmd_build)

    r = sub.add_parser("render", parents=[common, reads, device], help="render the AOVs the stage's RenderSettings declare",
                       description="Render the stage's RenderProducts with Mitsuba (llvm_ad_rgb) to linear EXR.")
    r.add_argument("stage", type=Path)
    r.add_argument("-o", "--output", type=Path, help="output folder (default: the stage's folder)")
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
    f.add_argument("stage", type=Path)
    f.add_argument("--method", choices=["adam", "fast"], default="fast")
    f.add_argument("--lights", type=int, default=16, help="number of point lights to start from (K)")
    f.add_argument("--env-res", help="environment resolution HxW (fast: basis cells, default 8x16; adam: "
                                     "texels, default 128x256; 0x0 = no environment)")
    f.add_argument("--iterations", type=_positive_int)
    f.add_argument("--max-side", type=_positive_int, default=512, help="longer image side of the fit")
    f.add_argument("--report", type=Path, help="write fit_report.json and an error-vs-time plot here")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--verify-spp", type=_non_negative_int, default=128, metavar="N",
                   help="samples per pixel of the Mitsuba verification render (0: skip it)")
    f.set_defaults(func=cmd_fit)

    n = sub.add_parser("neural", parents=[common, reads, device], help="run the neural renderer on the stage's AOVs",
                       description="Read D~, albedo and valid mask through the stage's RenderProducts, fill "
                                   "holes, run the ONNX network; write linear EXR and sRGB PNG.")
    n.add_argument("stage", type=Path)
    n.add_argument("--model", type=Path, help="ONNX model (default: the shipped one)")
    n.add_argument("-o", "--output", type=Path, help="output folder (default: STAGE_DIR/neural)")
    n.add_argument("--render-missing", action="store_true", help="render AOVs whose files are missing")
    n.add_argument("--spp", type=_positive_int, default=64)
    n.set_defaults(func=cmd_neural)

    add_relight_parser(sub, [common, reads, device], cmd_relight)

    tr = sub.add_parser("train", parents=[common], help="train the neural renderer (needs torch)",
                        description="Self-supervised pairs from a folder of photos (+ optional estimator "
                                    "outputs NAME.depth.exr, NAME.intrinsics.json, NAME.albedo.exr), then training "
                                    "and ONNX export.")
    tr.add_argument("data", type=Path)
    tr.add_argument("-o", "--output", type=Path, required=True, help="ONNX file to write")
    tr.add_argument("--work", type=Path, help="folder for the per-photo stages (cached)")
    tr.add_argument("--steps", type=_positive_int, default=1500)
    tr.set_defaults(func=cmd_train)

    add_batch_parser(sub, common, cmd_batch)
    c = sub.add_parser("convert", parents=[common, reads], help="convert between USD and Mitsuba XML, Blender, glTF/PLY/OBJ",
                       description="Convert SRC to DST, each format chosen by its suffix.")
    c.add_argument("src", type=Path)
    c.add_argument("dst", type=Path)
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
    sv.add_argument("stage", type=Path)
    sv.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (default 127.0.0.1: this machine only)")
    sv.add_argument("--port", type=_port, default=8080, help="port (the next free one when taken; 0 = any)")
    sv.add_argument("--hdri", type=Path, action="append", metavar="FILE",
                    help="latlong HDRI (.exr/.hdr) offered to dome lights (repeatable)")
    sv.add_argument("--mode", choices=["auto", "neural", "ratio", "add", "render", "transfer", "residual"],
                    help="initial output mode (default: auto, resolved per frame as relight resolves it)")
    sv.add_argument("--max-side", type=_positive_int, default=512, help="longer side of the live frames, pixels")
    sv.set_defaults(func=cmd_serve)

    v = sub.add_parser("validate", parents=[common], help="run every pxr.UsdValidation validator",
                       description="Exit 0 only when no validator reports an error.")
    v.add_argument("stage", type=Path)
    v.set_defaults(func=cmd_validate)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    try:
        if getattr(args, "uses_render_device", False):
            from .device import select_device
            select_device(args.device)
        with command_context(getattr(args, "allow_path", [])):  # native logs off stdout, --allow-path
            return int(args.func(args) or 0)
    except UsdRelightError as exc:
        sys.stderr.write(f"usdrelight: error: {one_line(exc)}\n")
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        sys.stderr.write("usdrelight: interrupted\n")
        return 130
    except Exception as exc:  # never a traceback for the user unless asked
        if args.debug:
            raise
        sys.stderr.write(f"usdrelight: error: unexpected {type(exc).__name__}: {one_line(exc)} "
                         f"(rerun with --debug for a traceback)\n")
        return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
