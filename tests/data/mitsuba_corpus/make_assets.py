"""Regenerate the corpus's small binary assets (run from the repository root with the project's Python):

    .venv/bin/python tests/data/mitsuba_corpus/make_assets.py

meshes/rectangle.obj  copy of Mitsuba's common/meshes/rectangle.obj (the [-1, 1]^2 quad in z = 0, normal +Z)
meshes/sphere.obj     unit UV sphere, 32 x 16 segments, outward normals, (u, v) texture coordinates
meshes/sphere.ply     the same sphere as binary PLY (written by Mitsuba itself)
textures/env.exr      64 x 32 latlong HDR, linear RGB: ../shared/testdata/hdri/forest.exr box-downscaled
textures/pattern.png  32 x 32 sRGB checker of four colours (spot texture, diffuse texture)
textures/leaf_mask.png copy of Mitsuba's common/textures/leaf_mask.png (mask opacity)
"""
import shutil
from pathlib import Path

import numpy as np

import usdrelight  # noqa: F401  (configures drjit's libLLVM)
from usdrelight.imageio import read_raw, write_image
from usdrelight.mitsuba.runtime import load_mitsuba

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[2].parent / "shared" / "testdata"


def sphere_obj(path: Path, nu: int = 32, nv: int = 16) -> None:
    lines = []
    for j in range(nv + 1):
        th = np.pi * j / nv
        for i in range(nu + 1):
            ph = 2 * np.pi * i / nu
            lines.append(f"v {np.sin(th) * np.cos(ph):.6f} {np.sin(th) * np.sin(ph):.6f} {np.cos(th):.6f}")
    for j in range(nv + 1):
        for i in range(nu + 1):
            lines.append(f"vt {i / nu:.6f} {1 - j / nv:.6f}")
    for j in range(nv):
        for i in range(nu):
            a, b = j * (nu + 1) + i + 1, j * (nu + 1) + i + 2
            c, d = a + nu + 1, b + nu + 1
            if j > 0:
                lines.append(f"f {a}/{a} {c}/{c} {b}/{b}")
            if j < nv - 1:
                lines.append(f"f {b}/{b} {c}/{c} {d}/{d}")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    common = SHARED / "mitsuba-data" / "common"
    shutil.copyfile(common / "meshes" / "rectangle.obj", HERE / "meshes" / "rectangle.obj")
    shutil.copyfile(common / "textures" / "leaf_mask.png", HERE / "textures" / "leaf_mask.png")
    sphere_obj(HERE / "meshes" / "sphere.obj")
    mi = load_mitsuba()
    mesh = mi.load_dict({"type": "obj", "filename": str(HERE / "meshes" / "sphere.obj")})
    mesh.write_ply(str(HERE / "meshes" / "sphere.ply"))
    env = read_raw(SHARED / "hdri" / "forest.exr")[0][..., :3].astype(np.float64)
    h, w = env.shape[:2]
    env = env[: h - h % 32, : w - w % 64].reshape(32, h // 32, 64, w // 64, 3).mean(axis=(1, 3))
    write_image(HERE / "textures" / "env.exr", env.astype(np.float32), "half")
    tile = np.array([[[0.9, 0.2, 0.1], [0.1, 0.7, 0.2]], [[0.2, 0.3, 0.9], [0.9, 0.9, 0.8]]])
    pattern = np.kron(tile, np.ones((16, 16, 1)))
    write_image(HERE / "textures" / "pattern.png", pattern.astype(np.float32), "uint8", srgb=True)


if __name__ == "__main__":
    main()
