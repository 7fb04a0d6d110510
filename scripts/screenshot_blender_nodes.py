"""A screenshot of Blender's Node Editor showing the compositor node group "usdrelight relight" of a converted .blend.

Usage (from the repository root)::

    .venv/bin/usdrelight convert out/motorcycle/scene.usda /tmp/shot/scene.blend   # a photo stage
    .venv/bin/python scripts/screenshot_blender_nodes.py /tmp/shot/scene.blend docs/manual/images/X.png \\
        [--blender BLENDER] [--size 2400x1300] [--width 0] [--colors 256] [--keep DIR]

The ``bpy`` module of ``.venv-blender`` (Blender 5.0 as a Python module) has no window, so this needs a GUI
Blender binary: ``--blender``, else ``$BLENDER``, else ``blender`` on PATH (Debian 12: ``apt-get install blender
xvfb xauth``, Blender 3.4.1). Without ``$DISPLAY`` it runs under ``xvfb-run`` (software OpenGL is enough).

* A Blender >= 5.0 opens the .blend itself, shows ``scene.compositing_node_group`` in the Compositor, frames all
  nodes and takes the screenshot (not tried yet: no GUI Blender 5 was at hand; Debian 12 has 3.4).
* An older Blender cannot read a 5.0 .blend (zstd + the new ``BLENDER17-01v0500`` header: "not a blend file"),
  and its compositor has neither Vector Math nor Menu Switch nodes. The tree is then dumped from the .blend with
  usdrelight's own bpy (every node's type, name, label, location, width, operation and unlinked input values,
  every link by socket identifier; the packed images I and F written out) and rebuilt, node for node at the same
  locations with the same labels and links, as the scene's compositing tree of the old Blender, with these
  type mappings (each printed, and listed in ``DIR/mapping.json`` with ``--keep DIR``):

  - Vector Math Add / Subtract / Multiply / Divide / Maximum -> Mix (Color) Add / Subtract / Multiply / Divide /
    Lighten, factor 1 (per channel the same);
  - Vector Math Sign, Vector Math Multiply Add, Menu Switch -> a group node of a node group built for it ("Vector
    Math: Sign": Separate RGBA, three Math Sign, Combine RGBA; "Vector Math: Multiply Add": Mix Multiply then Add;
    "Menu Switch": the item picked in 5.0 wired through a chain of Switch nodes), vector-typed inputs as in 5.0;
  - Math (shader) -> Math (compositor); Group Output -> Composite (before 5.0 the compositor is the scene's own
    tree, the only place a Render Layers node may be); Set Alpha, Inpaint, Alpha Over: the 5.0 menu/int inputs
    (Type, Size) become the old node's properties (mode, distance); Render Layers shows the "fitted" light group
    pass as in 5.0 (Cycles, the view layer's light group).

The PNG is the Node Editor area only (header included), scaled to ``--width`` pixels and reduced to ``--colors``
colours.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

# Run with usdrelight's bpy (Blender 5.0 as a module): the compositor node group as JSON, the packed images as files.
DUMP = (HERE / "screenshot_blender_nodes_dump.py.txt").read_text()

# Run by the GUI Blender: (rebuild the tree,) show it in the Node Editor, frame it, screenshot the area, quit.
GUI = (HERE / "screenshot_blender_nodes_gui.py.txt").read_text()


def blender_version(blender: str) -> tuple[int, ...]:
    out = subprocess.run([blender, "--version"], capture_output=True, text=True, timeout=120).stdout
    m = re.search(r"Blender (\d+)\.(\d+)\.(\d+)", out)
    if not m:
        raise SystemExit(f"cannot tell the version of {blender}: {out[:200]!r}")
    return tuple(int(x) for x in m.groups())


def dump_tree(blend: Path, work: Path) -> dict:
    """The compositor node group of ``blend`` as read by usdrelight's bpy (Blender 5.0)."""
    sys.path.insert(0, str(ROOT))
    from usdrelight.converters.blender_run import run_blender

    (work / "dump.py").write_text(DUMP)
    run_blender(work / "dump.py", str(blend.resolve()), str(work.resolve()))
    return json.loads((work / "tree.json").read_text())


def finish_png(raw: Path, png: Path, width: int, colors: int) -> None:
    from PIL import Image

    im = Image.open(raw).convert("RGB")
    if width and im.width > width:
        im = im.resize((width, round(im.height * width / im.width)), Image.LANCZOS)
    if colors:
        im = im.quantize(colors=colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    png.parent.mkdir(parents=True, exist_ok=True)
    im.save(png, optimize=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("blend", type=Path, help="a .blend converted from a photo stage (usdrelight convert)")
    ap.add_argument("png", type=Path, help="where to write the screenshot")
    ap.add_argument("--blender", default=os.environ.get("BLENDER", "blender"),
                    help="a GUI Blender binary (default: $BLENDER, else blender)")
    ap.add_argument("--size", default="2400x1300", help="the X screen (window) size under xvfb-run, WxH")
    ap.add_argument("--width", type=int, default=0, help="scale the PNG down to this width (default 0: keep)")
    ap.add_argument("--colors", type=int, default=256, help="reduce the PNG to this many colours (0: keep)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the dump, the GUI script and the log here")
    a = ap.parse_args(argv)
    blender = shutil.which(a.blender) or a.blender
    if not Path(blender).is_file():
        raise SystemExit(f"no GUI Blender at {a.blender!r}: give --blender or set $BLENDER")
    version = blender_version(blender)
    with tempfile.TemporaryDirectory() as td:
        work = a.keep or Path(td)
        work.mkdir(parents=True, exist_ok=True)
        raw = (work / "raw.png").resolve()
        spec = {"png": str(raw), "mapping": str((work / "mapping.json").resolve())}
        cmd = [blender, "--factory-startup"]
        if version >= (5, 0, 0):
            cmd.append(str(a.blend.resolve()))
        else:
            spec["tree"] = dump_tree(a.blend, work)
        (work / "gui.py").write_text(GUI)
        (work / "spec.json").write_text(json.dumps(spec))
        cmd += ["--python", str((work / "gui.py").resolve()), "--", str((work / "spec.json").resolve())]
        if not os.environ.get("DISPLAY"):
            if not shutil.which("xvfb-run"):
                raise SystemExit("no $DISPLAY and no xvfb-run (apt-get install xvfb xauth)")
            cmd = ["xvfb-run", "-a", "-s", f"-screen 0 {a.size.replace('X', 'x')}x24"] + cmd
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        (work / "blender.log").write_text(r.stdout + r.stderr)
        if not raw.is_file():
            tail = [l for l in (r.stdout + r.stderr).splitlines() if l.strip()][-5:]
            raise SystemExit("Blender took no screenshot:\n" + "\n".join(tail))
        finish_png(raw, a.png, a.width, a.colors)
        if "tree" in spec:
            for m in json.loads((work / "mapping.json").read_text()):
                if m["blender_5"].split()[0] != m["here"].split()[0]:
                    print(f"mapped {m['label'] or m['name']!r}: {m['blender_5']} -> {m['here']}")
    print(f"Blender {'.'.join(map(str, version))}: wrote {a.png} ({a.png.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
