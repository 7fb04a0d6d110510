"""The figures of docs/manual/blender.md for issue 26, from a run of bench_photo_stage.py (``--work DIR``).

* ``blender_relight_nodes.png``: the compositor node group "usdrelight relight" of DIR/scene.blend, drawn from the
  .blend itself (every node at its location with its label and linked sockets, every link); bpy as a Python
  module has no window to take a screenshot of the Node Editor, so this is a drawing of the real tree's data.
* ``blender_f12_relit.png``: F12 with the lights unchanged (the photo); Cycles' raw render of the converted
  stage with the World seen by the camera (before) and hidden (after: the cuts black, alpha 0); F12 with one
  fitted light moved in Blender (the compositor's ``ratio``); ``usdrelight relight --mode ratio`` with the same
  lights; their difference x 10.

    .venv/bin/python benchmarks/figure_blender_relight.py DIR
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from usdrelight.converters.blender import run_blender  # noqa: E402
from usdrelight.imageio import read_map  # noqa: E402

IMAGES = ROOT / "docs" / "manual" / "images"
DUMP = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
ng = bpy.context.scene.compositing_node_group
nodes = []
for n in ng.nodes:
    linked_in = [s.name for s in n.inputs if s.is_linked]
    values = {s.name: (list(s.default_value) if hasattr(s.default_value, "__len__")
                       and not isinstance(s.default_value, str) else s.default_value) for s in n.inputs
              if not s.is_linked and s.enabled and hasattr(s, "default_value") and s.name and not s.hide}
    op = getattr(n, "operation", None)
    nodes.append({"name": n.name, "label": n.label or n.bl_label, "type": n.bl_idname, "op": op,
                  "x": n.location.x, "y": n.location.y, "inputs": linked_in,
                  "outputs": [s.name for s in n.outputs if s.is_linked],
                  "values": {k: v for k, v in values.items() if isinstance(v, (int, float, str, list))}})
links = [[l.from_node.name, l.from_socket.name, l.to_node.name, l.to_socket.name] for l in ng.links]
json.dump({"name": ng.name, "nodes": nodes, "links": links}, open(args[1], "w"))
'''


def dump_tree(blend: Path) -> dict:
    with tempfile.TemporaryDirectory() as td:
        (Path(td) / "dump.py").write_text(DUMP)
        run_blender(Path(td) / "dump.py", str(blend), str(Path(td) / "tree.json"))
        return json.loads((Path(td) / "tree.json").read_text())


def _short(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.3g}" for x in v[:3]) + ")"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def node_tree_figure(tree: dict, png: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch

    nodes = {n["name"]: n for n in tree["nodes"]}
    xs, ys = [n["x"] for n in nodes.values()], [n["y"] for n in nodes.values()]
    fig, ax = plt.subplots(figsize=(24, 11.5), dpi=110)
    ax.set_facecolor("#2b2b2b")
    fig.patch.set_facecolor("#2b2b2b")
    box_w, pos = 235.0, {}
    for n in nodes.values():
        title = n["label"] + (f" [{n['op']}]" if n["op"] and n["label"] != n["op"] else "")
        lines = [f"{k} = {_short(v)}" for k, v in n["values"].items()
                 if k not in ("Vector", "Value") or n["type"] != "ShaderNodeVectorMath" or isinstance(v, list)]
        if n["type"] == "ShaderNodeVectorMath":
            lines = [f"const {_short(v)}" for k, v in n["values"].items() if isinstance(v, list)][:2]
        h = 46 + 15 * len(lines[:3])
        colour = {"CompositorNodeRLayers": "#7a3b3b", "CompositorNodeImage": "#6b5530", "NodeGroupOutput": "#3b4f7a",
                  "GeometryNodeMenuSwitch": "#3b6b4f", "CompositorNodeViewer": "#3b4f7a"}.get(n["type"], "#4a4a55")
        ax.add_patch(FancyBboxPatch((n["x"], n["y"] - h), box_w, h, boxstyle="round,pad=4", fc=colour,
                                    ec="#bbbbbb", lw=0.8))
        ax.text(n["x"] + 6, n["y"] - 14, title, color="white", fontsize=7.2, weight="bold", va="center")
        ax.text(n["x"] + 6, n["y"] - 30, n["type"].replace("CompositorNode", "").replace("ShaderNode", ""),
                color="#cccccc", fontsize=6, va="center", style="italic")
        for i, line in enumerate(lines[:3]):
            ax.text(n["x"] + 6, n["y"] - 44 - 15 * i, line, color="#dddddd", fontsize=6, va="center")
        pos[n["name"]] = (n["x"], n["y"], h)
    for a, sa, b, sb in tree["links"]:
        xa, ya, ha = pos[a]
        xb, yb, hb = pos[b]
        ax.annotate("", xy=(xb, yb - hb / 2), xytext=(xa + box_w, ya - ha / 2),
                    arrowprops=dict(arrowstyle="->", color="#e0c060", lw=0.9, shrinkA=0, shrinkB=0,
                                    connectionstyle="arc3,rad=0.08"))
    ax.set_xlim(min(xs) - 40, max(xs) + box_w + 40)
    ax.set_ylim(min(ys) - 160, max(ys) + 40)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(f'Compositor node group "{tree["name"]}" (drawn from the .blend: {len(nodes)} nodes, '
                 f'{len(tree["links"])} links)', color="white", fontsize=10)
    fig.savefig(png, bbox_inches="tight", facecolor=fig.get_facecolor())
    plt.close(fig)


def relit_figure(work: Path, png: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f12, ref = read_map(work / "f12_moved.exr", 3), read_map(work / "relight_moved.exr", 3)
    tiles = [("F12 in Blender, lights unchanged: the photo", read_map(work / "f12_same.exr", 3)),
             ("Cycles, World seen by the camera (before)", read_map(work / "cyc_vis.exr", 3)),
             ("Cycles, emitters hidden (after): cuts black, alpha 0", read_map(work / "cycles.exr", 3)),
             ("F12 in Blender: one fitted light moved", f12),
             ("usdrelight relight --mode ratio, same lights", ref),
             ("|F12 - relight| x 10", np.abs(f12 - ref) * 10)]
    scale = float(np.percentile(tiles[0][1], 99.5))
    fig, axes = plt.subplots(2, 3, figsize=(13.5, 6.6), dpi=110)
    for ax, (title, img) in zip(axes.ravel(), tiles):
        srgb = np.clip(img / scale, 0, 1)
        srgb = np.where(srgb <= 0.0031308, 12.92 * srgb, 1.055 * srgb ** (1 / 2.4) - 0.055)
        ax.imshow(srgb)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main(argv=None) -> int:
    work = Path((argv or sys.argv[1:])[0])
    IMAGES.mkdir(parents=True, exist_ok=True)
    node_tree_figure(dump_tree(work / "scene.blend"), IMAGES / "blender_relight_nodes.png")
    relit_figure(work, IMAGES / "blender_f12_relit.png")
    print(f"wrote {IMAGES / 'blender_relight_nodes.png'} and {IMAGES / 'blender_f12_relit.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
