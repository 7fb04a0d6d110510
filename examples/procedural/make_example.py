"""Regenerate the procedural ground-truth example (rendered by usdrelight itself with Mitsuba).

Writes photo.exr (linear, path traced, 256 spp), depth.exr (exact z-depth), albedo.exr,
shading.exr (= photo / albedo), intrinsics.json and scene.json (the known lights and shapes).
Run with: python examples/procedural/make_example.py
"""
from pathlib import Path

from usdrelight.mitsuba.procedural import random_spec, write_example

if __name__ == "__main__":
    write_example(Path(__file__).resolve().parent, random_spec(seed=7, width=256, height=192, n_lights=1), spp=256)
