"""``usdrelight batch`` used by an attacker or a careless user: the dashboard listens on loopback at the address
it prints, ``--workers`` is bounded by the machine, the photo folder is confined (links out refused, links in
named by the link), one batch per output folder, and every file name is processed or reported.

One real batch (a subprocess, 1 worker, 64 px photos) is held mid-photo by the test-only hook
``USDRELIGHT_BATCH_TEST_HOLD``: while it holds its lock, its temp folder and its dashboard, the tests look at its
sockets and start a second batch on the same output folder; then it is released and finishes.
"""
from __future__ import annotations

import contextlib
import io
import ipaddress
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from usdrelight.batch import guard
from usdrelight.batch.manifest import input_hash, make_job, read_manifest
from usdrelight.batch.records import BatchOptions
from usdrelight.batch.task import TEST_HOLD_ENV, _replace
from usdrelight.cli import main
from usdrelight.errors import UsdRelightError
from usdrelight.mitsuba.procedural import random_spec, write_training_photo

psutil = pytest.importorskip("psutil")
pytest.importorskip("distributed")

FLAGS = ["--max-side", "64", "--lights", "2", "--iterations", "6", "--workers", "1"]
OPTIONS = BatchOptions(max_side=64, lights=2, iterations=6)  # what FLAGS hash as
CONTROL = {"new\nline.exr": "U+000A", "tab\tname.exr": "U+0009", "evil\u202egnp.exr": "U+202E"}


def _copy_photo(src: Path, name: str, sidecars: bool = True) -> None:
    shutil.copy(src.with_suffix(".exr"), src.with_name(f"{name}.exr"))
    for kind in ("depth.exr", "albedo.exr", "intrinsics.json") if sidecars else ():
        shutil.copy(src.with_name(f"{src.stem}.{kind}"), src.with_name(f"{name}.{kind}"))


def _wait(cond, seconds, what, proc, err_lines):
    deadline = time.monotonic() + seconds
    while not cond():
        if proc.poll() is not None:
            time.sleep(0.5)  # its last lines
            pytest.fail(f"the batch ended (status {proc.returncode}) before {what}: {err_lines}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} within {seconds} s")
        time.sleep(0.05)


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def _listening(pid: int) -> list[tuple[int, str, int]]:
    out = []
    for proc in [psutil.Process(pid)] + psutil.Process(pid).children(recursive=True):
        with contextlib.suppress(psutil.Error):
            out += [(proc.pid, c.laddr.ip, c.laddr.port) for c in proc.net_connections(kind="inet")
                    if c.status == psutil.CONN_LISTEN]
    return out


def _other_addresses() -> list[str]:
    """This machine's IPv4 addresses other than loopback."""
    return [a.address for addrs in psutil.net_if_addrs().values() for a in addrs
            if a.family == socket.AF_INET and not ipaddress.ip_address(a.address).is_loopback]


def _connect(ip: str, port: int) -> int:
    """0 when a TCP connection to ip:port opens, the error number otherwise."""
    with socket.socket() as s:
        s.settimeout(2)
        return s.connect_ex((ip, port))


@pytest.fixture(scope="module")
def held(tmp_path_factory):
    """Run one batch held mid-photo; returns what was seen meanwhile and after."""
    root = tmp_path_factory.mktemp("held")
    photos, outside, out = root / "photos", root / "outside", root / "out"
    write_training_photo(photos, "hold", random_spec(0, 64, 48), spp=8)
    _copy_photo(photos / "hold.exr", "a.b")  # a dotted name, with its sidecars a.b.depth.exr ...
    for name in CONTROL:
        shutil.copy(photos / "hold.exr", photos / name)
    outside.mkdir()
    shutil.copy(photos / "hold.exr", outside / "private.exr")
    shutil.copy(photos / "hold.depth.exr", outside / "private.depth.exr")
    (photos / "link.exr").symlink_to(outside / "private.exr")  # a link out of the folder
    (photos / "inlink.exr").symlink_to("hold.exr")  # a link inside: processed, named inlink
    _copy_photo(photos / "hold.exr", "side", sidecars=False)
    (photos / "side.depth.exr").symlink_to(outside / "private.depth.exr")  # a sidecar out of the folder
    outside_before = _snapshot(outside)

    env = dict(os.environ, **{TEST_HOLD_ENV: "hold", "PYTHONUNBUFFERED": "1"})
    proc = subprocess.Popen([sys.executable, "-m", "usdrelight", "batch", str(photos), "-o", str(out), *FLAGS,
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    err_lines: list[str] = []
    reader = threading.Thread(target=lambda: [err_lines.append(x) for x in proc.stderr], daemon=True)
    reader.start()
    seen = {"pid": proc.pid}
    try:
        _wait(lambda: (out / ".test-hold-hold").exists() and any("dashboard" in x for x in err_lines), 120,
              "held photo", proc, err_lines)
        seen["cluster_line"] = next(x for x in err_lines if "dashboard" in x).strip()
        seen["listening"] = _listening(proc.pid)
        port = int(re.search(r"dashboard http://127\.0\.0\.1:(\d+)/status$", seen["cluster_line"]).group(1))
        seen["port"] = port
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5) as r:
            seen["health"] = r.read().decode()
        seen["others"] = {ip: _connect(ip, port) for ip in _other_addresses()}
        seen["temp_dirs"] = sorted(p.name for p in out.iterdir() if p.name.startswith(".hold.usdrelight-batch-tmp-"))
        seen["lock"] = (out / ".usdrelight.lock").read_text()
        before = _snapshot(out)
        stdout, stderr = io.StringIO(), io.StringIO()
        t = time.perf_counter()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            seen["second_rc"] = main(["batch", str(photos), "-o", str(out), *FLAGS])
        seen["second_seconds"] = time.perf_counter() - t
        seen["second_err"], seen["second_out"] = stderr.getvalue(), stdout.getvalue()
        seen["second_disturbed"] = {k: v for k, v in _snapshot(out).items() if before.get(k) != v}
        seen["second_removed"] = sorted(set(before) - set(_snapshot(out)))
        (out / ".test-go-hold").write_text("go\n")
        proc.wait(timeout=120)
        stdout_text = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(5)
    seen.update(rc=proc.returncode, summary=json.loads(stdout_text), err_lines=[x.rstrip("\n") for x in err_lines],
                photos=photos, out=out, outside=outside, outside_before=outside_before)
    return seen


def test_dashboard_listens_on_loopback_at_the_address_it_prints(held):
    assert held["rc"] == 0, held["err_lines"]
    port = held["port"]
    assert held["cluster_line"].startswith("dask scheduler tcp://127.0.0.1:")
    assert held["summary"]["dashboard"] == f"http://127.0.0.1:{port}/status"
    # the socket really bound for the printed port is the loopback one, and nothing of the cluster (scheduler,
    # nanny, worker, dashboard) listens anywhere else
    assert [(ip, p) for pid, ip, p in held["listening"] if p == port] == [("127.0.0.1", port)]
    assert len({pid for pid, _, _ in held["listening"]}) >= 2  # the batch process and its worker's
    assert {ip for _, ip, _ in held["listening"]} == {"127.0.0.1"}, held["listening"]
    assert held["health"] == "ok"
    # from another address of this machine, the port is closed
    assert all(rc != 0 for rc in held["others"].values()), held["others"]


def test_dashboard_socket_is_checked(monkeypatch):
    class Sock:
        def __init__(self, addr):
            self.addr = addr

        def getsockname(self):
            return self.addr

    class Cluster:
        class scheduler:
            class http_server:
                _sockets = {1: Sock(("0.0.0.0", 8787))}

    with pytest.raises(UsdRelightError, match=r"listens on 0\.0\.0\.0:8787"):
        guard.loopback_dashboard(Cluster, True)
    Cluster.scheduler.http_server._sockets = {1: Sock(("127.0.0.1", 4321))}
    assert guard.loopback_dashboard(Cluster, True) == "http://127.0.0.1:4321/status"
    assert guard.loopback_dashboard(Cluster, False) is None


def test_a_second_batch_on_the_output_folder_is_refused_and_disturbs_nothing(held):
    out = held["out"]
    assert held["second_rc"] == 2 and held["second_out"] == ""
    lock = out / ".usdrelight.lock"
    assert held["second_err"] == (f"usdrelight: error: output folder {out} is in use by another batch (PID "
                                  f"{held['pid']}, lock {lock}); wait for it to end or choose another -o (if no "
                                  f"batch runs there, that process is another program: remove the lock file)\n")
    assert held["lock"].split()[0] == str(held["pid"])
    assert len(held["temp_dirs"]) == 1  # the first batch's photo in progress ...
    assert held["second_disturbed"] == {} and held["second_removed"] == []  # ... and nothing touched
    assert held["second_seconds"] < 10
    # the first batch then finished: its manifest and its folders agree, no temp folder, no lock left
    rows = read_manifest(out)
    assert {n for n, r in rows.items() if r.status == "done"} == {"hold", "a.b", "inlink"}
    for name, r in rows.items():
        assert json.loads((out / name / "batch.json").read_text())["input_hash"] == r.input_hash
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["a.b", "hold", "inlink"]
    assert not lock.exists()


def test_symlinks_are_named_by_the_link_and_links_out_of_the_folder_refused(held):
    out, photos, s = held["out"], held["photos"], held["summary"]
    assert not (out / "private").exists() and not (out / "link").exists() and not (out / "side").exists()
    rec = json.loads((out / "inlink" / "batch.json").read_text())
    assert rec["name"] == "inlink" and rec["photo"] == str(photos.resolve() / "inlink.exr")
    refused = {e["name"]: e["error"] for e in s["per_photo"] if e["outcome"] == "refused"}
    assert refused["link.exr"] == "a symbolic link that leads outside the photo folder"
    assert refused["side.exr"] == "sidecar 'side.depth.exr' is a symbolic link that leads outside the photo folder"
    for name in ("link.exr", "side.exr"):
        assert held["err_lines"].count(f"batch: {name!r} not processed: {refused[name]}") == 1
    assert _snapshot(held["outside"]) == held["outside_before"]
    rows = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert {r["name"]: r["status"] for r in rows if r["status"] == "refused"} == {
        "link.exr": "refused", "side.exr": "refused", **{n: "refused" for n in CONTROL}}


def test_dotted_names_are_processed_and_control_characters_reported_once(held, cli):
    out, photos, s = held["out"], held["photos"], held["summary"]
    # a.b.exr is photo "a.b" with its own sidecars (the hash covers them), published as OUT/a.b
    job = make_job(photos / "a.b.exr", out, OPTIONS)
    assert job.name == "a.b" and [p.name for p in job.inputs] == [
        "a.b.exr", "a.b.depth.exr", "a.b.intrinsics.json", "a.b.albedo.exr"]
    assert read_manifest(out)["a.b"].input_hash == input_hash(job.inputs, OPTIONS)
    assert (out / "a.b" / "scene.usda").is_file()
    # names with control characters: one stderr line each, a manifest row, no folder, no crash
    refused = {e["name"]: e["error"] for e in s["per_photo"] if e["outcome"] == "refused"}
    for name, code in CONTROL.items():
        assert refused[name] == f"its name has a control character ({code})"
        assert held["err_lines"].count(f"batch: {name!r} not processed: {refused[name]}") == 1
    assert (s["photos"], s["done"], s["failed"], s["refused"]) == (3, 3, 0, len(CONTROL) + 2)
    assert all(n.isprintable() for n in os.listdir(out))
    rows = {json.loads(x)["name"]: json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()}
    assert all(rows[n]["error_kind"] is None and rows[n]["error"] == refused[n] for n in CONTROL)
    # a re-run: nothing to do (no cluster), the names reported again once each, never retried as a crash
    rc, stdout, err = cli("batch", photos, "-o", out, *FLAGS, "--json")
    again = json.loads(stdout)
    assert rc == 0 and (again["done"], again["failed"], again["skipped"]) == (0, 0, 3)
    assert again["scheduler"] is None and again["refused"] == len(CONTROL) + 2
    lines = err.splitlines()
    assert sorted(lines) == sorted(f"batch: {n!r} not processed: {refused[n]}" for n in refused)
    assert read_manifest(out)["a.b"].status == "done"


def test_workers_are_bounded_by_the_machine(tmp_path, cli, monkeypatch):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "p.png").write_bytes(b"not read")
    children = len(psutil.Process().children(recursive=True))
    limit, why = guard.worker_limit()
    assert 1 <= limit <= os.cpu_count()
    rc, out, err = cli("batch", photos, "-o", tmp_path / "out", "--workers", 1000)
    assert rc == 2 and out == ""
    cores = why.split()[0]  # the memory available may change between the two calls: any figure
    assert re.fullmatch(rf"usdrelight: error: --workers 1000 is more than this machine can run: at most {limit} "
                        rf"\({cores} CPU core\(s\), \d+\.\d GiB memory available at 2 GiB per worker\)\n", err), err
    assert not (tmp_path / "out").exists()
    assert len(psutil.Process().children(recursive=True)) == children  # no worker started
    # 16 cores but memory for 3 workers: 4 refused, the default 2 kept; 1 core: the default becomes 1
    monkeypatch.setattr(guard, "_cores", lambda: 16)
    monkeypatch.setattr(guard, "_available_memory", lambda: 3 * guard.WORKER_MEMORY + 5)
    rc, _, err = cli("batch", photos, "-o", tmp_path / "out", "--workers", 4)
    assert rc == 2 and err == ("usdrelight: error: --workers 4 is more than this machine can run: at most 3 "
                               "(16 CPU core(s), 6.0 GiB memory available at 2 GiB per worker)\n")
    assert guard.resolve_workers(3) == 3 and guard.resolve_workers(None) == 2
    monkeypatch.setattr(guard, "_cores", lambda: 1)
    assert guard.resolve_workers(None) == 1
    monkeypatch.setattr(guard, "_available_memory", lambda: guard.WORKER_MEMORY // 4)
    monkeypatch.setattr(guard, "_cores", lambda: 8)
    assert guard.worker_limit()[0] == 1  # too little memory still runs one worker
    assert not (tmp_path / "out").exists()


def test_careless_folders_are_one_line_exit_2(tmp_path, cli):
    out = tmp_path / "out"
    photos = out / "photos"  # the photo folder inside the output folder: a photo named "photos" would replace it
    photos.mkdir(parents=True)
    (photos / "photos.png").write_bytes(b"never read")
    rc, _, err = cli("batch", photos, "-o", out)
    assert rc == 2 and err == "usdrelight: error: the photo folder must not be the output folder or inside it\n"
    bad = tmp_path / "a\nb"
    rc, _, err = cli("batch", photos, "-o", bad)
    assert rc == 2 and err.count("\n") == 1 and "control character (U+000A)" in err and not bad.exists()
    # a folder under a photo's name that the batch did not make is never replaced
    final, tmp = tmp_path / "mine", tmp_path / ".mine.tmp-1"
    final.mkdir()
    (final / "notes.txt").write_text("keep")
    tmp.mkdir()
    with pytest.raises(UsdRelightError, match="is not a batch photo folder"):
        _replace(tmp, final)
    assert (final / "notes.txt").read_text() == "keep" and tmp.is_dir()
