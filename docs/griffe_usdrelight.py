"""Griffe extension used by the API reference (docs/mkdocs.yml): static analysis only, nothing is imported.

1. ``[tool.setuptools.package-dir]`` in pyproject.toml installs sub-packages from other folders
   (``usdrelight.converters`` from ``converters/``, ``usdrelight.schemas`` from ``schemas/``). Griffe's static
   finder looks for them inside ``usdrelight/`` and cannot see them, so the public API's names that come from
   there would be left out. Once the top package is loaded, this visits those folders as its sub-packages, so
   every alias in ``usdrelight.api`` resolves.
2. The docstrings use Sphinx roles (``:mod:`x```, ``:func:`~x```); Markdown would show the role's name. They are
   turned into plain code spans.
"""
from __future__ import annotations

import re
from pathlib import Path

import griffe

ROOT = Path(__file__).resolve().parents[1]
_ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|obj|exc|const|ref):`~?([^`]+)`")


def _package_dirs() -> dict[str, Path]:
    """``{"usdrelight.converters": ROOT / "converters", ...}``: the mapped sub-packages, not the top ones."""
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    try:
        import tomllib  # Python >= 3.11
        mapping = tomllib.loads(text).get("tool", {}).get("setuptools", {}).get("package-dir", {})
    except ImportError:  # Python 3.10: the section is plain `"name" = "folder"` lines
        section = re.search(r"^\[tool\.setuptools\.package-dir\]\n(.*?)(?=^\[|\Z)", text, re.M | re.S)
        mapping = dict(re.findall(r'^"([^"]+)"\s*=\s*"([^"]*)"', section.group(1), re.M)) if section else {}
    return {name: ROOT / folder for name, folder in mapping.items() if "." in name and name}


def _visit_package(loader: griffe.GriffeLoader, name: str, folder: Path, parent: griffe.Module) -> griffe.Module:
    init = folder / "__init__.py"
    module = griffe.visit(name, filepath=init, code=init.read_text(encoding="utf-8-sig"), parent=parent,
                          extensions=loader.extensions, docstring_parser=loader.docstring_parser,
                          docstring_options=loader.docstring_options, lines_collection=loader.lines_collection,
                          modules_collection=loader.modules_collection)
    parent.set_member(name, module)
    for path in sorted(folder.iterdir()):
        if path.is_dir() and (path / "__init__.py").is_file():
            _visit_package(loader, path.name, path, module)
        elif path.suffix == ".py" and path.name != "__init__.py" and "." not in path.stem:
            sub = griffe.visit(path.stem, filepath=path, code=path.read_text(encoding="utf-8-sig"), parent=module,
                               extensions=loader.extensions, docstring_parser=loader.docstring_parser,
                               docstring_options=loader.docstring_options,
                               lines_collection=loader.lines_collection,
                               modules_collection=loader.modules_collection)
            module.set_member(path.stem, sub)
    return module


class UsdRelightPackageDirs(griffe.Extension):
    """Adds the sub-packages installed from other folders; plain code spans for Sphinx roles."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        for dotted, folder in _package_dirs().items():
            top, _, rest = dotted.partition(".")
            if top != pkg.name or not (folder / "__init__.py").is_file():
                continue
            parent = pkg
            *parents, leaf = rest.split(".")
            for part in parents:
                parent = parent.members[part]
            if leaf not in parent.members:
                _visit_package(loader, leaf, folder, parent)

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(r"`\1`", obj.docstring.value)
