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

ROOT = Path(__file__).resolve().parents[1]

# Run with usdrelight's bpy (Blender 5.0 as a module): the compositor node group as JSON, the packed images as files.
DUMP = r'''
import bpy, json, os, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
blend, out_dir = args[0], args[1]
bpy.ops.wm.open_mainfile(filepath=blend)
scene = bpy.context.scene
ng = scene.compositing_node_group
if ng is None:
    raise SystemExit("the scene has no compositing node group: not a converted photo stage")

def plain(v):
    if isinstance(v, (bool, int, float, str)) or v is None:
        return v
    try:
        return [plain(x) for x in v]
    except TypeError:
        return str(v)

nodes = []
for n in ng.nodes:
    d = {"name": n.name, "label": n.label, "type": n.bl_idname, "location": list(n.location), "width": n.width,
         "inputs": [],
         "outputs": [{"identifier": s.identifier, "name": s.name, "enabled": s.enabled} for s in n.outputs]}
    for key in ("operation", "blend_type", "data_type", "use_clamp"):
        if hasattr(n, key):
            d[key] = getattr(n, key)
    if n.bl_idname == "GeometryNodeMenuSwitch":
        d["items"] = [i.name for i in n.enum_items]
    if n.bl_idname == "CompositorNodeImage" and n.image is not None:
        path = os.path.join(out_dir, "image_%d.exr" % len(nodes))
        img = n.image
        data = img.packed_file.data if img.packed_file else open(bpy.path.abspath(img.filepath), "rb").read()
        with open(path, "wb") as f:
            f.write(data)
        d["image"] = {"name": n.image.name, "file": path, "colorspace": n.image.colorspace_settings.name}
    for s in n.inputs:
        d["inputs"].append({"identifier": s.identifier, "name": s.name, "enabled": s.enabled, "linked": s.is_linked,
                            "type": s.bl_idname, "value": plain(getattr(s, "default_value", None))})
    nodes.append(d)
links = [{"from_node": l.from_node.name, "from_socket": l.from_socket.identifier, "to_node": l.to_node.name,
          "to_socket": l.to_socket.identifier} for l in ng.links]
vl = scene.view_layers[0]
json.dump({"name": ng.name, "blender": bpy.app.version_string, "nodes": nodes, "links": links,
           "resolution": [scene.render.resolution_x, scene.render.resolution_y],
           "lightgroups": [g.name for g in vl.lightgroups], "use_pass_z": vl.use_pass_z,
           "use_denoising": scene.cycles.use_denoising},
          open(os.path.join(out_dir, "tree.json"), "w"), indent=1)
'''

# Run by the GUI Blender: (rebuild the tree,) show it in the Node Editor, frame it, screenshot the area, quit.
GUI = r'''
import bpy, json, sys, traceback
args = sys.argv[sys.argv.index("--") + 1:]
spec = json.load(open(args[0]))
MIX = {"ADD": "ADD", "SUBTRACT": "SUBTRACT", "MULTIPLY": "MULTIPLY", "DIVIDE": "DIVIDE", "MAXIMUM": "LIGHTEN"}
mapping = []


def fail(msg):
    print("SCREENSHOT FAILED:", msg, flush=True)
    import os
    os._exit(3)


def group(name, inputs, build):
    """A compositor node group with vector (or other) inputs and one output; build(nodes, links, gin, gout)."""
    if name in bpy.data.node_groups:
        return bpy.data.node_groups[name]
    g = bpy.data.node_groups.new(name, "CompositorNodeTree")
    for sock_type, sock_name in inputs:
        g.inputs.new(sock_type, sock_name)
    g.outputs.new("NodeSocketVector" if name.startswith("Vector") else "NodeSocketColor",
                  "Vector" if name.startswith("Vector") else "Output")
    gin, gout = g.nodes.new("NodeGroupInput"), g.nodes.new("NodeGroupOutput")
    gin.location, gout.location = (-400, 0), (600, 0)
    build(g.nodes, g.links, gin, gout)
    return g


def build_sign(nodes, links, gin, gout):
    sep, comb = nodes.new("CompositorNodeSepRGBA"), nodes.new("CompositorNodeCombRGBA")
    sep.location, comb.location = (-200, 0), (400, 0)
    links.new(gin.outputs[0], sep.inputs[0])
    for i in range(3):
        m = nodes.new("CompositorNodeMath")
        m.operation, m.location = "SIGN", (100, 150 - 150 * i)
        links.new(sep.outputs[i], m.inputs[0])
        links.new(m.outputs[0], comb.inputs[i])
    links.new(comb.outputs[0], gout.inputs[0])


def build_multiply_add(nodes, links, gin, gout):
    mul, add = nodes.new("CompositorNodeMixRGB"), nodes.new("CompositorNodeMixRGB")
    mul.blend_type, add.blend_type = "MULTIPLY", "ADD"
    mul.inputs[0].default_value = add.inputs[0].default_value = 1.0
    mul.location, add.location = (0, 100), (250, 0)
    links.new(gin.outputs[0], mul.inputs[1])
    links.new(gin.outputs[1], mul.inputs[2])
    links.new(mul.outputs[0], add.inputs[1])
    links.new(gin.outputs[2], add.inputs[2])
    links.new(add.outputs[0], gout.inputs[0])


def menu_switch_builder(items, picked):
    def build(nodes, links, gin, gout):
        prev = gin.outputs[0]
        for i in range(1, len(items)):
            sw = nodes.new("CompositorNodeSwitch")
            sw.location = (-150 + 200 * i, 100 - 100 * i)
            sw.check = items.index(picked) == i
            links.new(prev, sw.inputs[0])
            links.new(gin.outputs[i], sw.inputs[1])
            prev = sw.outputs[0]
        links.new(prev, gout.inputs[0])
    return build


def set_value(sock, value):
    if value is None or not hasattr(sock, "default_value"):
        return
    cur = sock.default_value
    if hasattr(cur, "__len__") and not isinstance(cur, str):
        vals = list(value)[:len(cur)] + [1.0] * (len(cur) - len(value))
        sock.default_value = vals
    else:
        sock.default_value = value


def ins_of(name, ins):
    return [sock for (node, _), sock in ins.items() if node == name]


def rebuild(tree_spec):
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.resolution_x, scene.render.resolution_y = tree_spec["resolution"]
    scene.render.resolution_percentage = 100
    vl = scene.view_layers[0]
    for name in tree_spec["lightgroups"]:
        vl.lightgroups.add(name=name)
    vl.use_pass_z = tree_spec.get("use_pass_z", False)  # the passes Render Layers shows, as in the .blend
    scene.cycles.use_denoising = tree_spec.get("use_denoising", False)
    scene.use_nodes = True
    tree = scene.node_tree
    tree.nodes.clear()
    ins, outs = {}, {}  # (5.0 node name, 5.0 input identifier) -> socket here; the same for outputs
    for d in tree_spec["nodes"]:
        t, op = d["type"], d.get("operation")
        vin = {s["identifier"]: s for s in d["inputs"]}
        if t == "ShaderNodeVectorMath" and op in MIX:
            n = tree.nodes.new("CompositorNodeMixRGB")
            n.blend_type = MIX[op]
            n.inputs[0].default_value = 1.0
            for ident, k in (("Vector", 1), ("Vector_001", 2)):
                set_value(n.inputs[k], vin[ident]["value"])
                ins[d["name"], ident] = n.inputs[k]
            outs[d["name"], "Vector"] = n.outputs[0]
            new = "CompositorNodeMixRGB " + MIX[op]
        elif t == "ShaderNodeVectorMath" and op in ("SIGN", "MULTIPLY_ADD"):
            idents = ["Vector"] if op == "SIGN" else ["Vector", "Vector_001", "Vector_002"]
            gname = "Vector Math: Sign" if op == "SIGN" else "Vector Math: Multiply Add"
            g = group(gname, [("NodeSocketVector", "Vector")] * len(idents),
                      build_sign if op == "SIGN" else build_multiply_add)
            n = tree.nodes.new("CompositorNodeGroup")
            n.node_tree = g
            for k, ident in enumerate(idents):
                set_value(n.inputs[k], vin[ident]["value"])
                ins[d["name"], ident] = n.inputs[k]
            outs[d["name"], "Vector"] = n.outputs[0]
            new = 'CompositorNodeGroup "%s"' % gname
        elif t == "ShaderNodeVectorMath":
            fail("no equivalent for Vector Math %s" % op)
        elif t == "ShaderNodeMath":
            n = tree.nodes.new("CompositorNodeMath")
            n.operation, n.use_clamp = op, d.get("use_clamp", False)
            for k, ident in enumerate(("Value", "Value_001", "Value_002")):
                set_value(n.inputs[k], vin[ident]["value"])
                ins[d["name"], ident] = n.inputs[k]
            outs[d["name"], "Value"] = n.outputs[0]
            new = "CompositorNodeMath " + op
        elif t == "GeometryNodeMenuSwitch":
            items, picked = d["items"], vin["Menu"]["value"]
            g = group("Menu Switch: " + picked, [("NodeSocketColor", i) for i in items],
                      menu_switch_builder(items, picked))
            n = tree.nodes.new("CompositorNodeGroup")
            n.node_tree = g
            by_name = {s["name"]: s["identifier"] for s in d["inputs"]}
            for k, item in enumerate(items):
                set_value(n.inputs[k], vin[by_name[item]]["value"])
                ins[d["name"], by_name[item]] = n.inputs[k]
            outs[d["name"], "Output"] = n.outputs[0]
            new = 'CompositorNodeGroup "%s" (Switch chain)' % g.name
        elif t == "NodeGroupOutput":
            n = tree.nodes.new("CompositorNodeComposite")
            ins[d["name"], d["inputs"][0]["identifier"]] = n.inputs["Image"]
            new = "CompositorNodeComposite"
        else:
            n = tree.nodes.new(t)
            new = t
            if t == "CompositorNodeImage" and "image" in d:
                img = bpy.data.images.load(d["image"]["file"], check_existing=False)
                img.name = d["image"]["name"]
                try:
                    img.colorspace_settings.name = d["image"]["colorspace"]
                except TypeError:
                    pass
                n.image = img
            if t == "CompositorNodeSetAlpha":
                n.mode = "REPLACE_ALPHA" if vin.get("Type", {}).get("value") in ("Replace Alpha", "REPLACE_ALPHA") \
                    else "APPLY"
            if t == "CompositorNodeInpaint" and "Size" in vin:
                n.distance = int(vin["Size"]["value"])
            if t == "CompositorNodeAlphaOver":
                if vin.get("Straight Alpha", {}).get("value"):
                    n.use_premultiply = True
                aliases = {"Fac": 0, "Background": 1, "Foreground": 2}
            else:
                aliases = {}
            by_ident = {s.identifier: s for s in n.inputs}
            for s in d["inputs"]:
                sock = n.inputs[aliases[s["identifier"]]] if s["identifier"] in aliases \
                    else by_ident.get(s["identifier"])
                if sock is not None:
                    ins[d["name"], s["identifier"]] = sock
                    if not s["linked"] and s["type"] not in ("NodeSocketMenu",):
                        set_value(sock, s["value"])
            for s in d["outputs"]:
                sock = {o.identifier: o for o in n.outputs}.get(s["identifier"])
                if sock is not None:
                    outs[d["name"], s["identifier"]] = sock
        n.location = d["location"]
        n.width = max(d["width"], 230) if n.bl_idname == "CompositorNodeGroup" else d["width"]  # the group's name
        if hasattr(n, "show_preview"):
            n.show_preview = False  # 5.0's compositor draws no node previews
        if t == n.bl_idname or n.bl_idname == "CompositorNodeComposite":
            # show only the sockets the 5.0 node shows (the old Image node's Depth, Render Layers' Depth, ...)
            shown_in = {s.identifier for s in ins_of(d["name"], ins)}
            shown_out = {o["identifier"] for o in d["outputs"] if o.get("enabled", True)}
            for sock in n.inputs:
                sock.hide = sock.identifier not in shown_in and not sock.is_linked
            for sock in n.outputs:
                sock.hide = sock.identifier not in shown_out and sock.name not in shown_out
        if n.bl_idname == "CompositorNodeMixRGB":
            n.inputs[0].hide = True  # factor 1: not part of the 5.0 Vector Math node
        if d["label"]:
            n.label = d["label"]
        mapping.append({"name": d["name"], "label": d["label"], "blender_5": t + (" " + op if op else ""),
                        "here": new})
    for l in tree_spec["links"]:
        a, b = outs.get((l["from_node"], l["from_socket"])), ins.get((l["to_node"], l["to_socket"]))
        if a is None or b is None:
            fail("no socket for link %s" % l)
        tree.links.new(a, b)
    bad = [(l.from_node.name, l.to_node.name) for l in tree.links if not l.is_valid]
    if len(tree.links) != len(tree_spec["links"]) or bad:
        fail("links: %d of %d, invalid %s" % (len(tree.links), len(tree_spec["links"]), bad))
    json.dump(mapping, open(spec["mapping"], "w"), indent=1)
    print("REBUILT %d nodes, %d links" % (len(tree.nodes), len(tree.links)), flush=True)


def node_area():
    win = bpy.context.window_manager.windows[0]
    areas = [a for a in win.screen.areas if a.type == "NODE_EDITOR"]
    return win, (areas[0] if areas else None)


def region(area, kind="WINDOW"):
    return [r for r in area.regions if r.type == kind][0]


def step_show():
    try:
        win = bpy.context.window_manager.windows[0]
        area = max(win.screen.areas, key=lambda a: a.width * a.height)
        area.type = "NODE_EDITOR"
        area.ui_type = "CompositorNodeTree"
        space = area.spaces.active
        space.show_backdrop = False
        space.show_region_ui = False
        space.show_region_toolbar = False
        with bpy.context.temp_override(window=win, area=area, region=region(area)):
            bpy.ops.screen.screen_full_area()
    except Exception:
        traceback.print_exc()
        fail("could not show the Node Editor")
    bpy.app.timers.register(step_frame, first_interval=1.0)


def edited_tree(area):
    space = area.spaces.active
    return space.edit_tree or space.node_tree


def view_rect(r):
    (x0, y0), (x1, y1) = r.view2d.region_to_view(0, 0), r.view2d.region_to_view(r.width, r.height)
    return x0, y0, x1, y1


def fit_view(area, margin=0.03):
    """Zoom and pan so that the nodes fill the region (node.view_all leaves half the tree's size free around it)."""
    r, nodes = region(area), list(edited_tree(area).nodes)
    f = nodes[0].dimensions.x / nodes[0].width  # view units per node unit (the UI scale)
    xs0 = min(n.location.x for n in nodes) * f
    xs1 = max(n.location.x * f + n.dimensions.x for n in nodes)
    ys1 = max(n.location.y for n in nodes) * f
    ys0 = min(n.location.y * f - n.dimensions.y for n in nodes)
    w, h = (xs1 - xs0) * (1 + 2 * margin), (ys1 - ys0) * (1 + 2 * margin)
    aspect = r.width / r.height
    w, h = max(w, h * aspect), max(h, w / aspect)
    x0, y0, x1, y1 = view_rect(r)
    bpy.ops.view2d.zoom(deltax=(x1 - x0 - w) / 2, deltay=(y1 - y0 - h) / 2)
    x0, y0, x1, y1 = view_rect(r)
    per_px = (x1 - x0) / r.width
    bpy.ops.view2d.pan(deltax=round(((xs0 + xs1) - (x0 + x1)) / 2 / per_px),
                       deltay=round(((ys0 + ys1) - (y0 + y1)) / 2 / per_px))
    print("VIEW", view_rect(r), "nodes", (xs0, ys0, xs1, ys1), flush=True)


def step_frame(again=1):
    """Frame all nodes; twice, as a node's size is known only once it has been drawn."""
    win, area = node_area()
    if area is None:
        fail("no Node Editor area after maximising")
    with bpy.context.temp_override(window=win, area=area, region=region(area)):
        bpy.ops.node.select_all(action="DESELECT")
        bpy.ops.node.view_all()
        if not again:
            fit_view(area)
    if again:
        bpy.app.timers.register(lambda: step_frame(again - 1), first_interval=1.0)
    else:
        bpy.app.timers.register(step_shot, first_interval=1.5)


def step_shot():
    win, area = node_area()
    with bpy.context.temp_override(window=win, area=area, region=region(area)):
        bpy.ops.screen.screenshot_area(filepath=spec["png"])
    print("SCREENSHOT", spec["png"], area.width, area.height, flush=True)
    bpy.ops.wm.quit_blender()


try:
    bpy.context.preferences.view.show_splash = False
    bpy.context.preferences.view.smooth_view = 0  # view_all jumps, no animation
    print("BLENDER", bpy.app.version_string, flush=True)
    if spec.get("tree"):
        rebuild(spec["tree"])
    elif bpy.context.scene.compositing_node_group is None:
        fail("the scene has no compositing node group")
except SystemExit:
    raise
except Exception:
    traceback.print_exc()
    fail("rebuild failed")
bpy.app.timers.register(step_show, first_interval=1.0)
'''


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
