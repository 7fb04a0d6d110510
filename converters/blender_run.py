"""Running Blender: the interpreter with bpy (:func:`blender_command`), a script in it (:func:`run_blender`) and
a render of a .blend to a linear EXR (:func:`render_blend`: the raw render, or the compositor's output)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from usdrelight.errors import UsdRelightError


def blender_command() -> list[str]:
    """The command that runs a Python file with bpy available: [python] or [blender, -b, --python-exit-code...]."""
    env = os.environ.get("USDRELIGHT_BLENDER_PYTHON")
    if env:
        return [env]
    here = Path(sys.prefix)
    for cand in (here.parent / ".venv-blender" / "bin" / "python", Path.cwd() / ".venv-blender" / "bin" / "python"):
        if cand.is_file():
            return [str(cand)]
    exe = shutil.which("blender")
    if exe:
        return [exe, "--background", "--factory-startup", "--python-exit-code", "1", "--python"]
    raise UsdRelightError("Blender is not available: run scripts/setup.sh (creates .venv-blender with bpy==5.0.1), "
                          "set USDRELIGHT_BLENDER_PYTHON, or put `blender` on PATH")


def run_blender(script: Path, *args: str, timeout: float = 1800) -> subprocess.CompletedProcess:
    cmd = blender_command()
    full = cmd + [str(script)] + (["--"] if len(cmd) > 1 else []) + list(args)
    r = subprocess.run(full, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        tail = [l for l in (r.stderr or r.stdout).strip().splitlines() if l.strip()]
        raise UsdRelightError(f"Blender failed: {tail[-1] if tail else 'exit ' + str(r.returncode)}")
    return r


RENDER_SCRIPT = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
scene = bpy.context.scene
if args[2] != "-":
    scene.cycles.samples = int(args[2])
scene.render.use_compositing = args[3] == "composite"
if len(args) > 4 and args[4] != "-":
    f = float(args[4])
    scene.frame_set(int(f // 1), subframe=f - f // 1)
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = args[1]
bpy.ops.render.render(write_still=True)
'''


def render_blend(path, out_exr, spp: int | None = None, composite: bool = False, frame: float | None = None) -> Path:
    """Render a .blend with Cycles (its own settings; ``spp``: samples per pixel instead of the .blend's) to a
    linear EXR; returns the EXR path. ``composite``: the compositor's output (what F12 shows: for a photo stage
    the relit photo), else the render itself (RGBA; alpha 0 where a photo stage's camera sees no geometry).
    ``frame``: the frame rendered (default: the .blend's current one)."""
    with tempfile.TemporaryDirectory() as td:
        script = Path(td) / "render.py"
        script.write_text(RENDER_SCRIPT)
        run_blender(script, str(Path(path).absolute()), str(Path(out_exr).absolute()), str(spp) if spp else "-",
                    "composite" if composite else "render", "-" if frame is None else repr(float(frame)))
    return Path(out_exr)
