"""``usdrelight batch`` on a real Dask LocalCluster (worker processes, 1 thread each): a mixed folder gives the
right manifest, a re-run is a no-op, a worker killed mid-photo loses nothing, a changed photo is redone."""
from __future__ import annotations

import json
import os
import shutil
import time
from contextlib import contextmanager

import numpy as np
import pytest

from usdrelight.batch.manifest import read_manifest
from usdrelight.batch.records import BatchOptions
from usdrelight.batch.run import run_batch
from usdrelight.batch.task import TEST_KILL_ENV
from usdrelight.mitsuba.procedural import random_spec, write_training_photo
from usdrelight.neural.pairs import prepare_pairs

distributed = pytest.importorskip("distributed")

# tiny photos and a short fit keep a photo at about a second
FAST = dict(max_side=64, lights=2, iterations=6, spp=4, dashboard=False)


def _good(folder, name, seed):
    write_training_photo(folder, name, random_spec(seed, 64, 48), spp=8)


@pytest.fixture(scope="module")
def photo_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("photos")
    _good(d, "good0", 0)
    _good(d, "good1", 1)
    (d / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a png")
    shutil.copy(d / "good0.exr", d / "nodepth.exr")  # no sidecar: build's box-room prior, still done
    shutil.copy(d / "good1.exr", d / "baddepth.exr")
    np.save(d / "baddepth.depth.npy", np.full((48, 64), np.nan, np.float32))  # no valid depth: failed
    return d


def _hidden_dirs(out):
    return [p.name for p in out.iterdir() if p.name.startswith(".") and p.is_dir()]


def test_mixed_folder_gives_the_right_manifest_and_a_rerun_is_a_noop(photo_dir, tmp_path, cli):
    out = tmp_path / "out"
    done_calls = []
    first = run_batch(photo_dir, out, BatchOptions(workers=2, pairs=True, **FAST),
                      progress=lambda n, total, rec: done_calls.append((n, total, rec.name)))
    assert (first.done, first.failed, first.skipped) == (3, 2, 0)
    assert first.workers == 2 and first.scheduler.startswith("tcp://")
    assert sorted(c[0] for c in done_calls) == [1, 2, 3, 4, 5] and all(c[1] == 5 for c in done_calls)
    rows = read_manifest(out)
    assert sorted(rows) == ["baddepth", "corrupt", "good0", "good1", "nodepth"]
    assert {n: r.status for n, r in rows.items()} == {"baddepth": "failed", "corrupt": "failed", "good0": "done",
                                                      "good1": "done", "nodepth": "done"}
    assert "cannot read image" in rows["corrupt"].error and "\n" not in rows["corrupt"].error
    assert "no valid pixel" in rows["baddepth"].error
    assert rows["corrupt"].error_kind == rows["baddepth"].error_kind == "input"
    for name in ("good0", "good1", "nodepth"):
        r = rows[name]
        assert r.error is None and len(r.input_hash) == 64
        assert r.fit_seconds > 0 and r.build_seconds > 0 and r.seconds >= r.fit_seconds + r.build_seconds
        assert r.lights_kept is not None and r.lights_kept <= 2
        assert (out / name / "scene.usda").is_file() and (out / name / "renders" / "diffuse.exr").is_file()
        assert json.loads((out / name / "batch.json").read_text())["input_hash"] == r.input_hash
        assert r.fit_mse_rel > 0
    # with their true depth and albedo, the lights fitted to the (8 spp, noisy) procedural photos explain them
    assert rows["good0"].fit_psnr_db > 20 and rows["good1"].fit_psnr_db > 20
    assert not (out / "corrupt").exists() and not (out / "baddepth").exists()
    assert _hidden_dirs(out) == []  # no temp folder left behind
    # the manifest lines are JSON objects with at least the fields
    line = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    for key in ("name", "status", "error", "fit_mse", "fit_psnr_db", "fit_seconds", "build_seconds", "lights_kept",
                "input_hash"):
        assert key in line
    # `usdrelight train` reads a batch folder as it is; the worst-fit filter ranks by the manifest
    pairs = prepare_pairs(out, None, drop_fraction=0.34)
    worst = max(("good0", "good1", "nodepth"), key=lambda n: rows[n].fit_mse_rel)
    assert sorted(p.name for p in pairs) == sorted({"good0", "good1", "nodepth"} - {worst})
    assert pairs[0].dtilde.shape == (48, 64, 3)

    # re-run: nothing changed -> every photo skipped, no cluster started, a fraction of the first run's time
    manifest_before = (out / "manifest.jsonl").read_bytes()
    second = run_batch(photo_dir, out, BatchOptions(workers=2, pairs=True, **FAST))
    assert (second.done, second.failed, second.skipped) == (0, 0, 5)
    assert second.scheduler is None and second.cluster_seconds == 0
    assert second.seconds < 0.1 * first.seconds, (second.seconds, first.seconds)
    assert (out / "manifest.jsonl").read_bytes() == manifest_before
    assert {e["outcome"] for e in second.per_photo} == {"skipped"}

    # the CLI on the same folder: --json only on stdout, the same no-op
    rc, stdout, _ = cli("batch", photo_dir, "-o", out, "--pairs", "--max-side", 64, "--lights", 2, "--iterations", 6,
                        "--spp", 4, "--no-dashboard", "--json")
    assert rc == 0
    s = json.loads(stdout)
    assert (s["skipped"], s["manifest_done"], s["manifest_failed"]) == (5, 3, 2)



def test_bad_batch_folder_is_one_line_exit_2(tmp_path, cli):
    rc, _, err = cli("batch", tmp_path / "missing", "-o", tmp_path / "out")
    assert rc == 2 and err.strip().startswith("usdrelight: error:") and len(err.strip().splitlines()) == 1
    (tmp_path / "empty").mkdir()
    rc, _, err = cli("batch", tmp_path / "empty", "-o", tmp_path / "out")
    assert rc == 2 and "no photos" in err


@contextmanager
def killing_cluster(hook: str, allowed_failures: int):
    """A real LocalCluster of two worker processes, one photo slot each (the ``photo`` resource, as `usdrelight
    batch` configures its own), whose workers kill themselves on the photos the test-only hook names (``hook``:
    NAME:TIMES,...), and ``allowed_failures`` retries after a worker death; reached through ``--scheduler`` as an
    existing cluster would be."""
    import dask
    from distributed import LocalCluster

    old = os.environ.get(TEST_KILL_ENV)
    os.environ[TEST_KILL_ENV] = hook  # inherited by the worker processes
    try:
        with dask.config.set({"distributed.scheduler.allowed-failures": allowed_failures}):
            cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=40, resources={"photo": 1})
        yield cluster
        cluster.close()
    finally:
        if old is None:
            os.environ.pop(TEST_KILL_ENV, None)
        else:
            os.environ[TEST_KILL_ENV] = old


@pytest.fixture
def kill_cluster():
    """Workers killed once on 'killonce', on every try on 'killalways'; one retry."""
    with killing_cluster("killonce:1,killalways:9", 1) as cluster:
        yield cluster


def test_a_killed_worker_loses_nothing_and_a_changed_photo_is_redone(kill_cluster, tmp_path):
    photos = tmp_path / "photos"
    _good(photos, "killonce", 2)
    _good(photos, "calm", 4)
    out = tmp_path / "out"
    opts = BatchOptions(scheduler=kill_cluster.scheduler_address, **FAST)
    t = time.perf_counter()
    s = run_batch(photos, out, opts)
    assert time.perf_counter() - t < 60
    # killonce: its worker was SIGKILLed after the build, the task went to a fresh worker and finished
    pid = int((out / ".test-kill-killonce.0").read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    rows = read_manifest(out)
    assert {n: r.status for n, r in rows.items()} == {"killonce": "done", "calm": "done"}, rows
    assert (s.done, s.failed) == (2, 0)
    assert _hidden_dirs(out) == []  # the killed attempt's temp folder is gone
    for name in ("killonce", "calm"):
        assert json.loads((out / name / "batch.json").read_text())["status"] == "done"
        assert (out / name / "lights_fitted.usda").is_file()

    # killalways: killed on every try -> recorded failed (a crash), nothing published, the others unharmed
    photos2 = tmp_path / "photos2"
    _good(photos2, "killalways", 3)
    out2 = tmp_path / "out2"
    s2 = run_batch(photos2, out2, opts)
    r = read_manifest(out2)["killalways"]
    assert (s2.done, s2.failed) == (0, 1) and r.status == "failed" and r.error_kind == "crash"
    assert "worker died" in r.error
    assert not (out2 / "killalways").exists() and _hidden_dirs(out2) == []
    # the next run retries a crash (hook disarmed: its markers say it was killed enough)
    for i in range(9):
        (out2 / f".test-kill-killalways.{i}").write_text("0\n")
    again = run_batch(photos2, out2, opts)
    assert (again.done, again.failed, again.skipped) == (1, 0, 0)
    assert read_manifest(out2)["killalways"].status == "done"

    # a changed input is redone, alone
    before = rows["calm"].input_hash
    k = json.loads((photos / "calm.intrinsics.json").read_text())
    k["fx"] *= 1.01
    (photos / "calm.intrinsics.json").write_text(json.dumps(k))
    third = run_batch(photos, out, opts)
    assert (third.done, third.failed, third.skipped) == (1, 0, 1)
    assert [e["name"] for e in third.per_photo if e["outcome"] == "done"] == ["calm"]
    assert read_manifest(out)["calm"].input_hash != before
