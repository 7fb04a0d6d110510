"""Result files switch together (issue 10): the EXR, the PNG and the diffuse render of one `relight` (or `neural`)
run appear at once, so a reader never pairs one run's EXR with another run's PNG.

A real ``usdrelight relight`` process is made to die right before its k-th rename (``os._exit``), for every k
until the run gets through, over an output folder holding a previous run's files written the old way (plain
files); after each kill every public name must still show the previous run, or every one the new run."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from conftest import build_procedural
from usdrelight.atomic import RESULTS_DIR, result_group
from usdrelight.imageio import read_map

USDRELIGHT = Path(sys.executable).with_name("usdrelight")
NAMES = ("relit.exr", "relit.png", "render_diffuse.exr")
LIGHT_A, LIGHT_B = "point:0.5,1.0,-2.5:3,2.5,2", "point:-0.8,0.6,-2.0:9,1,1"


def _relight(stage, out, light, kill_at=None):
    env = {**os.environ, "USDRELIGHT_TEST_EXIT_BEFORE_RENAME": str(kill_at)} if kill_at else None
    return subprocess.run([str(USDRELIGHT), "relight", str(stage), "--mode", "neural", "--light", light,
                           "--max-side", "48", "-o", str(out)], capture_output=True, text=True, env=env, timeout=300)


def _pixels(folder: Path) -> dict:
    return {n: read_map(folder / n, 3) for n in NAMES if (folder / n).exists()}


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.allclose(a[k], b[k], atol=1e-6) for k in a)


def test_a_relight_killed_at_every_rename_leaves_old_or_new_files_together(tmp_path):
    stage = build_procedural(tmp_path / "st")
    for light, name in ((LIGHT_A, "ref_a"), (LIGHT_B, "ref_b")):
        assert _relight(stage, tmp_path / name, light).returncode == 0
    ref_a, ref_b = _pixels(tmp_path / "ref_a"), _pixels(tmp_path / "ref_b")
    assert not _same(ref_a, ref_b)
    legacy = tmp_path / "legacy"  # run A's files as plain files, as an older usdrelight wrote them
    legacy.mkdir()
    for n in NAMES:
        shutil.copyfile(tmp_path / "ref_a" / n, legacy / n)
    (legacy / "notes.txt").write_text("mine")
    finished = False
    for k in range(1, 30):
        out = tmp_path / f"k{k}"
        shutil.copytree(legacy, out)
        proc = _relight(stage, out, LIGHT_B, kill_at=k)
        assert proc.returncode in (0, 70), proc.stderr
        now = _pixels(out)
        assert _same(now, ref_a) or _same(now, ref_b), f"killed before rename {k}: a mix of two runs"
        assert (out / "notes.txt").read_text() == "mine"
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # nothing beside the folders
        if proc.returncode == 0:
            assert _same(now, ref_b) and all((out / n).is_symlink() for n in NAMES)
            # the next run cleans what killed runs left (old versions, unrenamed links)
            assert _relight(stage, out, LIGHT_A).returncode == 0 and _same(_pixels(out), ref_a)
            assert len([p for p in (out / RESULTS_DIR).iterdir() if p.is_dir() and not p.is_symlink()]) == 1
            finished = True
            break
    assert finished and k > 4  # the run really renamed several times before getting through


def test_a_failed_write_publishes_nothing(tmp_path):
    out = tmp_path / "o"
    with result_group(out) as folder:
        (folder / "a.txt").write_text("first")
        (folder / "b.txt").write_text("first")
    try:
        with result_group(out) as folder:
            (folder / "a.txt").write_text("second")
            raise RuntimeError("the writer failed half way")
    except RuntimeError:
        pass
    assert (out / "a.txt").read_text() == "first" and (out / "b.txt").read_text() == "first"
    with result_group(out) as folder:  # a result without b.txt: b.txt goes with the previous result
        (folder / "a.txt").write_text("third")
    assert (out / "a.txt").read_text() == "third" and not (out / "b.txt").exists()
    try:
        with result_group(tmp_path / "new") as folder:
            raise RuntimeError("failed before writing anything")
    except RuntimeError:
        pass
    assert not (tmp_path / "new").exists()  # a folder the failed run created is gone again
