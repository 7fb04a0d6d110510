"""Atomic stage updates (issue 10): build and fit publish a complete new version or nothing, under a lock.

The kill tests make a real ``usdrelight`` process die (``os._exit``) right before its k-th rename, for every k
until the run gets through, and check that the folder then holds exactly the old or exactly the new version,
that ``validate`` passes and that a new ``fit`` works."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import make_photo, write_plane_depth
from usdrelight.atomic import LOCK_NAME, stage_lock
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import read_photo
from usdrelight.stage.versions import VERSIONS, referenced_version, version_folder

USDRELIGHT = Path(sys.executable).with_name("usdrelight")


def _run(*args, kill_at=None):
    env = {**os.environ, "USDRELIGHT_TEST_EXIT_BEFORE_RENAME": str(kill_at)} if kill_at else None
    return subprocess.run([str(USDRELIGHT), *map(str, args)], capture_output=True, text=True, env=env, timeout=300)


def _state(folder: Path):
    """What the stage is: scene.usda (version id normalised), the referenced version's files (EXR as pixels:
    OpenEXR headers carry a time stamp) and the user's layer."""
    vid = referenced_version(folder)
    assert vid is not None
    scene = (folder / "scene.usda").read_text().replace(vid, "V")
    vdir = folder / VERSIONS / vid
    files = {}
    for p in sorted(vdir.rglob("*")):
        if p.is_file():
            files[p.relative_to(vdir).as_posix()] = \
                read_photo(p).tobytes() if p.suffix == ".exr" else p.read_bytes()
    return scene, files, (folder / "lights_user.usda").read_bytes()


def _leftovers(folder: Path):
    """(versions kept, temporary files left in the folder or beside it)."""
    vids = [p.name for p in (folder / VERSIONS).iterdir() if p.name != "current"]
    temps = [*folder.parent.glob(f".{folder.name}.tmp-*"), *folder.glob(".*usdrelight-tmp-*")]
    return vids, sorted(p.name for p in temps)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("in")
    make_photo(d / "a.png", 24, 32, seed=1)
    make_photo(d / "b.png", 24, 32, seed=2)
    write_plane_depth(d / "d.npy", 24, 32)
    return d


def _build(inputs, photo, out, kill_at=None):
    return _run("build", inputs / photo, "--depth", inputs / "d.npy", "--fov-x", "60", "-o", out, kill_at=kill_at)


def test_a_build_killed_at_every_rename_leaves_old_or_new(cli, inputs, tmp_path):
    ref = tmp_path / "ref"
    assert _build(inputs, "b.png", ref).returncode == 0
    # the reference was built from b.png at another path: compare it as if it were built into `out`
    new = _state(ref)
    base, out = tmp_path / "base", tmp_path / "out"
    assert _build(inputs, "a.png", base).returncode == 0
    (base / "lights_user.usda").write_text('#usda 1.0\nover "Scene" {}\n')  # the user's own edit
    (base / "notes.txt").write_text("mine")
    old = _state(base)
    seen = set()
    for k in range(1, 30):
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(base, out, symlinks=True)
        p = _build(inputs, "b.png", out, kill_at=k)
        state = _state(out)
        assert state[2] == b'#usda 1.0\nover "Scene" {}\n' and (out / "notes.txt").read_text() == "mine"
        if state[:2] == old[:2]:
            seen.add("old")
        else:
            assert state[:2] == new[:2], f"killed before rename {k}: a mixed stage"
            seen.add("new")
        rc, _, err = cli("validate", out / "scene.usda")
        assert rc == 0, err
        if p.returncode == 0:
            break
        assert p.returncode == 70, p.stderr  # the test hook, not an error
    assert seen == {"old", "new"} and k > 2
    # the next writer takes the dead writer's lock over and cleans up after it
    assert _build(inputs, "a.png", out).returncode == 0
    assert len(_leftovers(out)[0]) == 1 and _leftovers(out)[1] == [] and not (out / LOCK_NAME).exists()


def _fitted(folder: Path) -> bool:
    text = (version_folder(folder) / "lights_fitted.usda").read_text()
    return 'usdrelight:fit:method = "fast"' in text


def test_a_fit_killed_at_every_rename_leaves_old_or_new(cli, inputs, tmp_path):
    base, out = tmp_path / "base", tmp_path / "out"
    assert _build(inputs, "a.png", base).returncode == 0
    old = _state(base)
    fit = ("fit", out / "scene.usda", "--max-side", "16", "--iterations", "3")
    seen = set()
    for k in range(1, 30):
        shutil.rmtree(out, ignore_errors=True)  # each kill starts from the unfitted stage
        shutil.copytree(base, out, symlinks=True)
        p = _run(*fit, kill_at=k)
        state = _state(out)
        if state == old:
            seen.add("old")
        else:  # new: the same scene and carried-over files, a fitted layer whose map exists
            seen.add("new")
            assert state[0] == old[0] and state[2] == old[2]
            for name in ("geometry.usdc", "textures/albedo.exr", "estimates/diffuse.exr"):
                assert state[1][name] == old[1][name]
            assert _fitted(out)
            if "fitted_env" in (version_folder(out) / "lights_fitted.usda").read_text():
                assert np.isfinite(read_photo(version_folder(out) / "lights" / "fitted_env.exr")).all()
        rc, _, err = cli("validate", out / "scene.usda")
        assert rc == 0, err
        if p.returncode == 0:
            break
        assert p.returncode == 70, p.stderr
    assert seen == {"old", "new"} and k > 1
    rc, _, err = cli(*fit)  # a fit after a killed fit works and cleans up
    assert rc == 0, err
    assert len(_leftovers(out)[0]) == 1 and not (out / LOCK_NAME).exists()


def test_a_second_writer_is_refused_and_a_dead_writers_lock_is_taken_over(cli, inputs, tmp_path):
    out = tmp_path / "out"
    assert _build(inputs, "a.png", out).returncode == 0
    before = _state(out)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / LOCK_NAME).write_text(f"{sleeper.pid}\n")
        for argv in (("build", inputs / "b.png", "--depth", inputs / "d.npy", "--fov-x", "60", "-o", out),
                     ("fit", out / "scene.usda", "--max-side", "16", "--iterations", "2")):
            rc, _, err = cli(*argv)
            assert rc == 2 and err.count("\n") == 1 and f"is being written by PID {sleeper.pid}" in err, err
        assert _state(out) == before
        with pytest.raises(UsdRelightError, match=f"PID {sleeper.pid}"):
            with stage_lock(out):
                pass
    finally:
        sleeper.kill()
        sleeper.wait()
    # the lock's PID is dead now: stale, taken over
    rc, _, err = cli("build", inputs / "b.png", "--depth", inputs / "d.npy", "--fov-x", "60", "-o", out)
    assert rc == 0, err
    assert not (out / LOCK_NAME).exists() and _state(out)[:2] != before[:2]


def test_stage_lock_is_reentrant_and_released(tmp_path):
    import threading

    errors = []

    def other_thread():
        try:
            with stage_lock(tmp_path / "s"):
                errors.append(None)
        except UsdRelightError as exc:
            errors.append(str(exc))

    with stage_lock(tmp_path / "s") as folder:
        assert (folder / LOCK_NAME).read_text().strip() == str(os.getpid())
        with stage_lock(tmp_path / "s"):
            pass
        assert (folder / LOCK_NAME).exists()
        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
    assert errors and errors[0] and f"PID {os.getpid()}" in errors[0]  # another thread is another writer
    assert not (tmp_path / "s" / LOCK_NAME).exists()


def test_the_layout_before_versions_is_migrated_and_user_files_kept(cli, inputs, tmp_path):
    """A folder written by an older usdrelight (files at the top) and a killed run's temp folder beside it."""
    out = tmp_path / "out"
    assert _build(inputs, "a.png", out).returncode == 0
    vdir = version_folder(out)
    for name in ("geometry.usdc", "lights_fitted.usda", "textures", "estimates", "lights"):
        (out / name).unlink()
        shutil.move(str(vdir / name), str(out / name))
    shutil.rmtree(out / VERSIONS)
    text = (out / "scene.usda").read_text().replace(f"./{VERSIONS}/{vdir.name}/", "./")
    # the layout before versions also named the source photo by its absolute path, outside the folder
    text = text.replace("@./source/photo.png@", f"@{(inputs / 'a.png').resolve()}@")
    (out / "scene.usda").write_text(text)
    (out / "textures" / "mine.png").write_bytes(b"user")
    (tmp_path / ".out.tmp-abc123").mkdir()  # beside the folder: never touched (it may be the user's)
    rc, _, err = cli("validate", out / "scene.usda")
    assert rc == 0, err
    rc, _, err = cli("fit", out / "scene.usda", "--max-side", "16", "--iterations", "2")
    assert rc == 0, err
    assert referenced_version(out) is not None and _fitted(out)
    assert (out / "textures" / "mine.png").read_bytes() == b"user"  # the user's file, in a real folder
    assert not (out / "textures" / "albedo.exr").exists() and (out / "geometry.usdc").is_symlink()
    assert (tmp_path / ".out.tmp-abc123").is_dir()
    assert cli("validate", out / "scene.usda")[0] == 0


def test_the_lock_of_a_killed_but_unreaped_writer_is_stale(tmp_path):
    """A writer SIGKILLed under a parent that has not reaped it yet (a zombie) no longer holds the lock."""
    import time

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    while open(f"/proc/{child.pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z":
        time.sleep(0.05)  # exited, not waited for: a zombie, which os.kill(pid, 0) still finds
    (tmp_path / LOCK_NAME).write_text(f"{child.pid}\n")
    with stage_lock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text().strip() == str(os.getpid())
    child.wait()


def test_a_failed_rebuild_leaves_the_previous_stage_untouched(cli, inputs, tmp_path, monkeypatch):
    """One output that cannot be written (here the diffuse target): nothing of the new build is visible, the
    fitted lights are not reset, no temporary folder is left."""
    import usdrelight.stage.write as write

    out = tmp_path / "out"
    assert _build(inputs, "a.png", out).returncode == 0
    assert cli("fit", out / "scene.usda", "--max-side", "16", "--iterations", "2")[0] == 0
    before = _state(out)
    real = write.write_image

    def failing(path, *a, **k):
        if "diffuse" in str(path):
            raise OSError(28, "No space left on device")
        return real(path, *a, **k)
    monkeypatch.setattr(write, "write_image", failing)
    rc, _, err = cli("build", inputs / "b.png", "--depth", inputs / "d.npy", "--fov-x", "60", "-o", out)
    assert rc == 2 and err.count("\n") == 1 and "No space left on device" in err, err
    assert _state(out) == before and _fitted(out)
    assert _leftovers(out) == ([referenced_version(out)], []) and not (out / LOCK_NAME).exists()


def test_a_build_removes_only_its_own_temporaries_and_nothing_beside_the_folder(cli, inputs, tmp_path):
    """What a killed writer leaves in the folder (``.scene.usdrelight-tmp-XXXXXXXX.usda``) goes; the user's
    ``.scene-backup.usda`` in the folder and a ``.out.tmp-backup`` folder beside it stay (before: both were
    removed, the one outside the output folder with its contents)."""
    out = tmp_path / "out"
    assert _build(inputs, "a.png", out).returncode == 0
    ours = out / ".scene.usdrelight-tmp-ab12cd_9.usda"
    ours.write_text("#usda 1.0\n")
    (out / ".scene-backup.usda").write_text("mine")
    (out / ".lights_user-20240101.usda").write_text("mine too")
    beside = tmp_path / ".out.tmp-backup"
    beside.mkdir()
    (beside / "thesis.txt").write_text("precious")
    assert _build(inputs, "b.png", out).returncode == 0
    assert not ours.exists()
    assert (out / ".scene-backup.usda").read_text() == "mine"
    assert (out / ".lights_user-20240101.usda").read_text() == "mine too"
    assert (beside / "thesis.txt").read_text() == "precious"
