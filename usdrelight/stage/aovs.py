"""The render AOVs that a usdrelight stage declares through UsdRender, and what each one means.

Each AOV is one RenderVar and one RenderProduct (a single-layer linear EXR at
``renders/<name>.exr`` relative to the stage) so later steps find every image through the stage.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Aov:
    """One declared render output."""

    name: str
    """RenderVar and RenderProduct prim name."""
    data_type: str
    """UsdRender.Var dataType of a pixel (color3f, float, normal3f)."""
    source_name: str
    """UsdRender.Var sourceName: what the renderer computes."""
    source_type: str
    """UsdRender.Var sourceType: raw | lpe | primvar | intrinsic."""
    channels: int
    """Channels in the EXR file."""
    doc: str
    """What the AOV holds, with its units (written as the RenderVar's documentation)."""

    @property
    def product_name(self) -> str:
        """The AOV's EXR, relative to the render output folder (``renders/NAME.exr``)."""
        return f"renders/{self.name}.exr"


AOVS: dict[str, Aov] = {a.name: a for a in (
    Aov("diffuse", "color3f", "C.*", "lpe", 3,
        "Linear RGB radiance of the diffuse-only scene under the stage's lights (the render D~)."),
    Aov("albedo", "color3f", "albedo", "raw", 3, "Diffuse reflectance at the primary hit, linear RGB."),
    Aov("valid", "float", "valid", "raw", 1, "1 where the primary ray hits scene geometry, else 0."),
    Aov("depth", "float", "depth", "raw", 1,
        "Camera-space z-depth of the primary hit in scene units (0 where nothing is hit)."),
    Aov("normal", "normal3f", "normal", "raw", 3, "World-space shading normal at the primary hit."),
    Aov("color", "color3f", "color", "raw", 3,
        "Linear RGB radiance of the full scene (the beauty of a scene imported from another renderer)."),
)}

#: What `usdrelight build` declares: what the fit, the converters and the neural stage read.
BUILD_AOVS = ("diffuse", "albedo", "valid", "depth", "normal")
