"""The ``usdrelight`` subcommands: each ``cmd_*`` takes the parsed arguments of :mod:`usdrelight.cli`, runs the
library function, prints its summary (``--json``: JSON only on stdout) and returns the exit status.

A subcommand's code is imported when it runs, so ``usdrelight --help`` and ``validate`` start fast.
"""
from __future__ import annotations

import json
import logging
import sys

import numpy as np

from .errors import UsdRelightError, one_line


log = logging.getLogger("usdrelight")


def stderr_console():
    """A rich console on stderr (logs and progress never touch stdout, which ``--json`` keeps for JSON)."""
    from rich.console import Console

    return Console(stderr=True)


class _Steps:
    """A rich progress bar over named steps, on stderr; silent when stderr is not a terminal."""

    def __init__(self, names, title):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
        self.names = list(names)
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                                 console=stderr_console(), transient=True,
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

    opts = BuildOptions(depth=args.depth, depth_scale=args.depth_scale, points=args.points, intrinsics=args.intrinsics, fov_x=args.fov_x,
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
    from .stage.read import read_scene
    from .stage.validate import Finding, errors_only, open_stage, validate_stage
    stage = open_stage(args.stage)
    findings = validate_stage(stage)
    try:  # what usdrelight's own reader refuses (a camera naming nothing, bad indices, a negative light ...) or
        # leaves out, as render and fit would say it: the pxr validators pass such stages
        rec = read_scene(stage)
        findings += [Finding("usdrelight:ReadScene", "Warn", f"{kind}: {n}", []) for kind, n in rec.warnings.items()]
    except UsdRelightError as exc:
        findings.append(Finding("usdrelight:ReadScene", "Error", one_line(exc), []))
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

    with Progress(TextColumn("fit {task.description}"), BarColumn(), TimeElapsedColumn(), console=stderr_console(),
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
    return run_command(args, stderr_console(), _emit)


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
