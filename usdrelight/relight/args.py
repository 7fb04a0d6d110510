"""The ``usdrelight relight`` command-line arguments (argparse only, so building the command line stays light)."""
from __future__ import annotations

import argparse

from ..argtypes import add_frames_argument, add_time_argument, path as _path, positive_int as _positive_int
from ..stage.light_syntax import MAX_AREA_SAMPLES, SYNTAX as LIGHT_SYNTAX

DESCRIPTION = ("Relight the photo: the stage's lights (its user layer, time samples read at --time or at each "
               "time code of --frames) and --light, rendered, then composited (ratio, add) or through the network "
               "(neural). Writes relit.exr/.png (linear EXR, sRGB PNG) and render_diffuse.exr, or for several "
               "frames relit_NNNN.* (NNNN: the frame's index in the run), optionally an H.264 MP4.")


def add_relight_parser(sub, parents, func) -> argparse.ArgumentParser:
    """Add the ``relight`` subcommand to the subparsers ``sub``; ``func(args)`` runs it."""
    rl = sub.add_parser("relight", parents=parents, help="apply lights, render, composite or run the network",
                        description=DESCRIPTION)
    rl.add_argument("stage", type=_path)
    rl.add_argument("--light", action="append", metavar="SPEC",
                    help=f"{LIGHT_SYNTAX} (repeatable; applies to every frame)")
    frames = rl.add_mutually_exclusive_group()
    frames.add_argument("--sequence", type=_path, metavar="LIGHTS.json",
                        help="JSON list of frames, each a list of --light strings: writes relit_NNNN.exr/.png and "
                             "render_diffuse_NNNN.exr")
    add_frames_argument(frames, "relit frames (lights whose time samples do not change between frames are not "
                                "rendered again)")
    add_time_argument(rl)
    rl.add_argument("--video", type=_path, metavar="OUT.mp4",
                    help="also encode the frames as an H.264 MP4 (PyAV) in the stage's time: --frames at "
                         "timeCodesPerSecond / STEP, a --sequence at framesPerSecond")
    rl.add_argument("--save-lights", type=_path, metavar="LAYER.usda",
                    help="with --sequence: also write the sequence as a new time-sampled UsdLux layer (frame i at "
                         "time code 1 + i), to sublayer into lights_user.usda")
    rl.add_argument("--renderer", choices=["fast", "mitsuba"], default="fast",
                    help="fast: cached deterministic renderer (default); mitsuba: path tracing (reference)")
    rl.add_argument("--with-fitted", action="store_true", help="keep the fitted (original) lighting too")
    rl.add_argument("--fitted-scale", type=float, default=None, metavar="S",
                    help="scale the fitted (original) lighting, e.g. 0.1 for night; implies --with-fitted")
    rl.add_argument("--mode", choices=["auto", "neural", "ratio", "add", "render", "transfer", "residual"], default="auto",
                    help="auto (default): add when the fitted lighting is kept (--with-fitted), transfer when it is "
                         "scaled by --fitted-scale, residual when it is off (render without a fit); ratio: photo x new render / "
                         "fitted render (needs `usdrelight fit`); add: photo + render of the added lights; transfer: "
                         "the physics render with the photo's own detail (needs the fit); render: the physics "
                         "render D~, holes filled; residual: transfer corrected by a network's bounded gain; neural: the "
                         "network on the render")
    rl.add_argument("--contact-sheet", action="store_true",
                    help="also write contact_sheet.png: photo, diffuse render and every mode's result")
    rl.add_argument("--model", type=_path,
                    help="ONNX network: a relight one (output 'output') for --mode neural, a residual one (output "
                         "'log_gain') for residual; the other mode keeps the shipped one")
    rl.add_argument("-o", "--output", type=_path, help="output folder (default: STAGE_DIR/relit)")
    rl.add_argument("--spp", type=_positive_int, default=32, help="samples per pixel (mitsuba renderer)")
    rl.add_argument("--area-samples", type=int, metavar="N",
                    help=f"shadow rays per pixel for sphere, disk, rect and wide sun lights (fast renderer; default "
                         f"16, at most {MAX_AREA_SAMPLES}): more for smoother penumbrae, fewer for speed")
    rl.add_argument("--max-side", type=_positive_int, help="render at most this many pixels on the longer side")
    rl.set_defaults(func=func)
    return rl
