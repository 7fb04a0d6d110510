"""``usdrelight batch`` as a photo collection meets it (found by probing the command): a user's hidden folders in
OUT survive, a dying worker fails no photo but its own, an ONNX model is checked before any photo and its bytes
are part of every input hash, a photo folder missing its stage is redone, names USD cannot carry and sidecars of
a type batch does not read are refused, a scheduler address Dask cannot parse and a full stdout are errors."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from argparse import Namespace

import pytest

from test_batch import FAST, _good, killing_cluster
from test_estimators import _half_albedo_model
from usdrelight.atomic import lock_token, stage_lock
from usdrelight.batch.args import options_from_args
from usdrelight.batch.manifest import COMPLETE, PAIR_FILES, RECORD, finished_record, make_job, read_manifest, \
    remove_leftovers
from usdrelight.batch.records import BatchOptions
from usdrelight.batch.run import run_batch
from usdrelight.batch.task import TEST_HOLD_ENV, process_photo
from usdrelight.neural.pairs import list_photos

from conftest import make_photo

distributed = pytest.importorskip("distributed")


def test_only_the_batchs_own_leftovers_are_removed(tmp_path):
    """Before: every hidden folder with '.tmp-' or '.old-' in its name went, with the user's files in it."""
    mine = [".photos.old-2023", ".notes.tmp-draft", ".a.tmp-abcd1234", ".a.usdrelight-batch-tmp-ABCD1234"]
    for name in mine:
        (tmp_path / name).mkdir()
        (tmp_path / name / "keep.txt").write_text("precious")
    ours = [".a.usdrelight-batch-tmp-k2_x9q0z", ".b.c.usdrelight-batch-old-4242-123456789"]
    for name in ours:
        (tmp_path / name).mkdir()
    (tmp_path / ".d.usdrelight-batch-tmp-abcdefgh").symlink_to(tmp_path / ".photos.old-2023")
    assert remove_leftovers(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(mine + [".d.usdrelight-batch-tmp-abcdefgh"])
    assert all((tmp_path / n / "keep.txt").read_text() == "precious" for n in mine)
    # the names of versions before the tags, only for this batch's photos ('a'): the others stay
    assert remove_leftovers(tmp_path, {"a", "photos"}) == 1 and not (tmp_path / ".a.tmp-abcd1234").exists()
    assert (tmp_path / ".photos.old-2023" / "keep.txt").is_file() and (tmp_path / ".notes.tmp-draft").is_dir()


def test_backslashed_names_and_unread_sidecar_types_are_refused(tmp_path):
    """A backslash in a name broke the stage after the whole build (USD reads it as a separator); a.depth.png was
    ignored in silence (depth sidecars are floats: .exr, .npy, .pfm), the photo built on the box-room prior."""
    for name in ("a", "back\\slash", "fine"):
        make_photo(tmp_path / f"{name}.png")
    make_photo(tmp_path / "a.depth.png")
    refused = []
    got = list_photos(tmp_path, refused)
    assert [p.name for p in got] == ["a.png", "fine.png"]
    why = {p.name: r for p, r in refused}
    assert set(why) == {"back\\slash.png", "a.depth.png"}
    assert "backslash" in why["back\\slash.png"]
    assert "depth sidecar is read from .exr, .npy, .pfm only (not .png)" in why["a.depth.png"]


def test_every_photo_type_build_reads_is_a_photo_and_other_files_are_reported(tmp_path):
    """WebP, BMP and Radiance HDR photos were passed over in silence (build reads them; the summary counted the
    others only); a file of another type is reported; sidecars, the manifest and hidden files are not."""
    from usdrelight.imageio import read_photo

    for name in ("a.webp", "b.bmp", "c.png"):
        make_photo(tmp_path / name)
    import shutil

    shutil.copy(tmp_path / "c.png", tmp_path / "d.hdr")  # a wrong suffix: found, and build says what it is
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "c.intrinsics.json").write_text("{}")
    (tmp_path / "c.scene.json").write_text("{}")  # a photo's companion (the training generator's scene)
    (tmp_path / "manifest.jsonl").write_text("")
    (tmp_path / ".DS_Store").write_bytes(b"")
    refused = []
    got = list_photos(tmp_path, refused)
    assert [p.name for p in got] == ["a.webp", "b.bmp", "c.png", "d.hdr"]
    assert [(p.name, "not a photo file" in r) for p, r in refused] == [("notes.txt", True)]
    assert read_photo(tmp_path / "a.webp").shape[:2] == read_photo(tmp_path / "b.bmp").shape[:2]


def test_a_photo_folder_missing_its_stage_or_pair_is_redone(tmp_path):
    """A folder with batch.json (and pair.json) but without scene.usda or the renders was skipped as complete."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    photos.mkdir()
    make_photo(photos / "p.png")
    job = make_job(photos / "p.png", out, BatchOptions(pairs=True))
    folder = out / "p"
    for name in (RECORD,) + COMPLETE + PAIR_FILES:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text("{}")
    (folder / RECORD).write_text(json.dumps({"name": "p", "status": "done", "input_hash": job.input_hash,
                                             "photo": str(job.photo)}))
    assert finished_record(job) is not None
    for gone in ("renders/valid.exr", "scene.usda"):
        (folder / gone).rename(folder / (gone.replace("/", "_") + ".bak"))
        assert finished_record(job) is None, gone
        (folder / (gone.replace("/", "_") + ".bak")).rename(folder / gone)
    (folder / "geometry.usdc").unlink()
    (folder / "geometry.usdc").symlink_to("versions/current/geometry.usdc")  # dangling: incomplete
    assert finished_record(job) is None


def _args(**kw):
    base = dict(max_side=64, lights=2, iterations=6, verify_spp=0, pairs=False, spp=4, workers=1, scheduler=None,
                retries=0, retry_failed=False, no_dashboard=True, geometry=None, albedo_from=None, model_path=(),
                device=None)
    return Namespace(**{**base, **kw})


def test_an_onnx_model_is_checked_first_and_its_bytes_are_hashed(tmp_path, cli, monkeypatch):
    """Before: a missing model failed every photo one by one (exit 0, recorded as input errors, never retried
    after the model was fixed), and a changed model's photos were skipped as unchanged."""
    photos = tmp_path / "photos"
    photos.mkdir()
    make_photo(photos / "p.png")
    rc, out, err = cli("batch", photos, "-o", tmp_path / "out", "--albedo-from", f"onnx:{tmp_path / 'nope.onnx'}")
    assert rc == 2 and out == "" and "model not found" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    (tmp_path / "junk.onnx").write_text("SECRET TEXT not a model")
    rc, _, err = cli("batch", photos, "-o", tmp_path / "out", "--albedo-from", f"onnx:{tmp_path / 'junk.onnx'}")
    assert rc == 2 and "cannot load ONNX model" in err and "SECRET" not in err and not (tmp_path / "out").exists()

    model = tmp_path / "m.onnx"
    _half_albedo_model(model)
    monkeypatch.chdir(tmp_path)  # a relative model path is made absolute for the workers
    first = options_from_args(_args(albedo_from="onnx:m.onnx"))
    assert first.albedo_from == f"onnx:{model}" and len(first.model_digests) == 1
    _half_albedo_model(model, input_name="image")  # the same bytes: the same hash
    assert options_from_args(_args(albedo_from="onnx:m.onnx")).model_digests == first.model_digests
    _half_albedo_model(model, input_name="x")  # another model (it loads): other input hashes
    second = options_from_args(_args(albedo_from="onnx:m.onnx"))
    assert second.model_digests != first.model_digests
    assert make_job(photos / "p.png", tmp_path / "o", first).input_hash != \
        make_job(photos / "p.png", tmp_path / "o", second).input_hash
    # without ONNX models the hash is what it was (no new key)
    assert "model_digests" not in BatchOptions().hashed()


@pytest.fixture
def dying_cluster():
    """Two workers of one photo slot each, no retries, and the worker of photo 'dies' SIGKILLed once."""
    with killing_cluster("dies:1", 0) as cluster:
        yield cluster


def test_a_dying_worker_fails_only_its_own_photo(dying_cluster, tmp_path):
    """Before: Dask placed the waiting photos on the workers up front, so the photos queued behind 'dies' on its
    worker failed with it ('1 workers died while trying to run it')."""
    photos = tmp_path / "photos"
    for i, name in enumerate(["dies", "p1", "p2", "p3", "p4"]):
        _good(photos, name, 10 + i)
    s = run_batch(photos, tmp_path / "out", BatchOptions(scheduler=dying_cluster.scheduler_address, **FAST))
    status = {n: r.status for n, r in read_manifest(tmp_path / "out").items()}
    assert status == {"dies": "failed", "p1": "done", "p2": "done", "p3": "done", "p4": "done"}, status
    assert (s.done, s.failed) == (4, 1)


def test_an_address_dask_cannot_parse_is_one_line(tmp_path, cli):
    photos = tmp_path / "photos"
    photos.mkdir()
    make_photo(photos / "p.png")
    rc, _, err = cli("batch", photos, "-o", tmp_path / "out", "--scheduler", "foo")
    assert rc == 2 and "cannot reach the Dask scheduler foo" in err and len(err.strip().splitlines()) == 1, err


def test_json_into_a_full_stdout_is_an_error(tmp_path):
    """``--json > /dev/full``: the summary was lost and the exit status 0 (the flush's OSError was swallowed)."""
    stage = tmp_path / "s.usda"
    stage.write_text('#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Y"\n)\n'
                     'def Xform "World"\n{\n}\n')
    ok = subprocess.run([sys.executable, "-m", "usdrelight", "validate", str(stage), "--json"], capture_output=True,
                        text=True)
    assert ok.returncode == 0 and json.loads(ok.stdout)
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "usdrelight", "validate", str(stage), "--json"], stdout=full,
                           stderr=subprocess.PIPE, text=True)
    assert p.returncode == 2 and p.stderr.strip() == "usdrelight: error: cannot write to stdout: No space left on " \
        "device", p.stderr


def test_sigterm_stops_a_batch_as_cleanly_as_ctrl_c(tmp_path):
    """A batch scheduler stops a job with SIGTERM: before, exit 143 with no message, a leaked-semaphore warning and
    the lock left behind; now the clean-up of Ctrl-C (cluster closed, lock released), one line, exit 143."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "hold", 20)
    env = dict(os.environ, **{TEST_HOLD_ENV: "hold", "PYTHONUNBUFFERED": "1"})
    proc = subprocess.Popen([sys.executable, "-m", "usdrelight", "batch", str(photos), "-o", str(out), "--workers",
                             "1", "--no-dashboard", "--max-side", "64", "--lights", "2", "--iterations", "6"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while not (out / ".test-hold-hold").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    lines = [x for x in err.splitlines() if x.strip()]
    assert lines[-1] == "usdrelight: terminated" and "Traceback" not in err, err
    assert not (out / ".usdrelight.lock").exists()
    assert not (out / "hold").exists()  # the held photo never published


def test_a_photo_finished_after_its_batch_ended_is_not_published(tmp_path):
    """With --scheduler, an interrupted batch exited and released its lock, and the external worker still
    published its photo into OUT a second later (another batch could have started there)."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "late", 30)
    opts = BatchOptions(**FAST)
    with stage_lock(out):
        token = lock_token(out)
        assert token and token == lock_token(out)
        ours = process_photo(make_job(photos / "late.exr", out, opts, token))
    assert ours.status == "done" and (out / "late" / "batch.json").is_file()
    shutil.rmtree(out / "late")
    assert lock_token(out) is None  # the batch ended
    rec = process_photo(make_job(photos / "late.exr", out, opts, token))
    assert rec.status == "failed" and rec.error_kind == "crash" and "not published" in rec.error
    assert sorted(p.name for p in out.iterdir()) == []  # no folder, no temp folder
    with stage_lock(out):  # another batch holds it now: its token differs
        assert lock_token(out) != token
        rec = process_photo(make_job(photos / "late.exr", out, opts, token))
    assert rec.status == "failed" and not (out / "late").exists()


def _scheduler(tmp_path, procs: list) -> str:
    """Start a Dask scheduler on loopback (its process appended to ``procs``); its address once it listens."""
    procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                   "--port", "0", "--no-dashboard", "--scheduler-file", str(tmp_path / "s.json")],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    deadline = time.monotonic() + 60
    while not (tmp_path / "s.json").exists():
        assert time.monotonic() < deadline
        time.sleep(0.2)
    time.sleep(0.5)
    return json.loads((tmp_path / "s.json").read_text())["address"]


def _worker(address: str, env: dict, procs: list) -> None:
    """Start a Dask worker with one 'photo' resource (appended to ``procs``)."""
    procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                   "--resources", "photo=1", "--no-dashboard"], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))


def test_a_lost_scheduler_is_one_error_not_photos_blamed_on_workers(tmp_path):
    """Before: exit 0, the photos left recorded failed as 'worker died while processing the photo
    (FutureCancelledError ... scheduler-connection-lost)' and a raw distributed.client error line."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "hold", 21)
    env = dict(os.environ, **{TEST_HOLD_ENV: "hold", "PYTHONUNBUFFERED": "1"})
    procs = []
    try:
        deadline = time.monotonic() + 60
        address = _scheduler(tmp_path, procs)
        sched = procs[0]
        _worker(address, env, procs)
        batch = subprocess.Popen([sys.executable, "-m", "usdrelight", "batch", str(photos), "-o", str(out),
                                  "--scheduler", address, "--max-side", "64", "--lights", "2", "--iterations", "6"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        procs.append(batch)
        while not (out / ".test-hold-hold").exists():
            assert batch.poll() is None and time.monotonic() < deadline + 60, batch.stderr.read()
            time.sleep(0.2)
        sched.kill()
        _, err = batch.communicate(timeout=90)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert batch.returncode == 2, err
    assert f"usdrelight: error: lost the Dask scheduler {address}" in err and "1 photo(s) not processed" in err, err
    assert "worker died" not in err and "Traceback" not in err, err
    assert "hold" not in read_manifest(out)  # not recorded as a failure: the next run takes it up


def test_workers_that_join_a_running_batch_get_photos_at_once(tmp_path):
    """With --scheduler, the free slots were asked for only when a photo finished (and, with no worker at the
    start, the batch warned that the workers declare no 'photo' resource and ran unrestricted): a worker that
    joined while the first photo ran stood idle until it finished. Photo 'a' is held on the first worker; 'b' must
    be done on the second before 'a' is let go."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "a", 31)
    _good(photos, "b", 32)
    env = dict(os.environ, **{TEST_HOLD_ENV: "a", "PYTHONUNBUFFERED": "1"})
    procs = []
    try:
        deadline = time.monotonic() + 60
        address = _scheduler(tmp_path, procs)
        batch = subprocess.Popen([sys.executable, "-m", "usdrelight", "batch", str(photos), "-o", str(out), "--json",
                                  "--scheduler", address, "--max-side", "64", "--lights", "2", "--iterations", "6"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        procs.append(batch)
        time.sleep(2.0)  # the batch starts with no worker
        _worker(address, env, procs)
        while not (out / ".test-hold-a").exists():
            assert batch.poll() is None and time.monotonic() < deadline + 60, batch.stderr.read()
            time.sleep(0.2)
        _worker(address, env, procs)
        while not (out / "b" / "batch.json").exists():
            assert batch.poll() is None and time.monotonic() < deadline + 120, "b waited for a"
            time.sleep(0.2)
        (out / ".test-go-a").write_text("")
        stdout, err = batch.communicate(timeout=120)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert batch.returncode == 0, err
    summary = json.loads(stdout)
    assert summary["done"] == 2 and summary["failed"] == 0, summary
    assert "declare no 'photo' resource" not in err, err
    rows = read_manifest(out)
    assert rows["a"].worker != rows["b"].worker, (rows["a"].worker, rows["b"].worker)


def test_folders_of_photos_no_longer_there_are_named(tmp_path, caplog):
    """A photo removed from the photo folder: its output folder stayed and the manifest dropped its row, with no
    word. Now the summary and one warning name it (the folder is kept: it is the user's to delete)."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "a", 41)
    _good(photos, "b", 42)
    first = run_batch(photos, out, BatchOptions(workers=1, **FAST))
    assert first.done == 2 and first.orphaned == []
    for f in photos.glob("b*"):
        f.unlink()
    second = run_batch(photos, out, BatchOptions(workers=1, **FAST))
    assert second.skipped == 1 and second.orphaned == ["b"]
    assert (out / "b").is_dir() and sorted(read_manifest(out)) == ["a"]
    assert "1 folder(s) in" in caplog.text and "no longer in" in caplog.text
    third = run_batch(photos, out, BatchOptions(workers=1, **FAST))  # named while the folder is there (before:
    assert third.orphaned == ["b"]  # once, then forgotten with the manifest's row)


def test_a_photo_that_finishes_after_the_batch_was_stopped_is_not_published(tmp_path):
    """SIGTERM while a photo runs: the batch unwinds (exit 143), and the photo, let go to finish while the
    cluster shuts down, publishes nothing (before: its folder appeared in OUT after the batch said it was
    terminated, and no manifest row named it)."""
    photos, out = tmp_path / "photos", tmp_path / "out"
    _good(photos, "hold", 23)
    env = dict(os.environ, **{TEST_HOLD_ENV: "hold", "PYTHONUNBUFFERED": "1"})
    batch = subprocess.Popen([sys.executable, "-m", "usdrelight", "batch", str(photos), "-o", str(out), "--workers",
                              "1", "--max-side", "64", "--lights", "2", "--iterations", "6", "--no-dashboard"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while not (out / ".test-hold-hold").exists():
            assert batch.poll() is None and time.monotonic() < deadline, batch.stderr.read()
            time.sleep(0.2)
        batch.send_signal(signal.SIGTERM)
        (out / ".test-go-hold").write_text("")
        _, err = batch.communicate(timeout=120)
    finally:
        if batch.poll() is None:
            batch.kill()
    time.sleep(3)  # a worker outliving the batch would publish by now
    assert batch.returncode == 143, err
    assert not (out / "hold").exists(), sorted(p.name for p in out.iterdir())
