"""The transport cache shared by sessions and processes: content keys, leases that survive another process's
eviction, eviction by age and by size, damaged entries rebuilt."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from conftest import build_procedural

from usdrelight.engine.fast import EngineSettings, FastRenderer
from usdrelight.stage.light_specs import parse_light
from usdrelight.stage.read import read_scene
from usdrelight.transport.cache import TransportCache, prepare_transport, scene_key

@pytest.fixture(scope="module")
def procedural(tmp_path_factory):
    return build_procedural(tmp_path_factory.mktemp("proc") / "st")


SMALL = EngineSettings(max_side=48, env_samples=16, indirect_samples=4)


def _entry(cache: TransportCache, key: str, nbytes: int, age_s: float = 0.0):
    path = cache.path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\0" * nbytes)
    t = time.time() - age_s
    os.utime(path, (t, t))
    return path


def test_a_lease_held_by_another_process_is_never_evicted(tmp_path):
    cache = TransportCache(tmp_path / "c", max_bytes=0)  # everything over the limit
    held = _entry(cache, "held", 1000, age_s=10)
    free = _entry(cache, "free", 1000, age_s=20)
    code = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from usdrelight.transport.cache import TransportCache
        lease = TransportCache({str(cache.folder)!r})._lock(Path({str(held)!r}))
        print("locked", flush=True)
        sys.stdin.readline()
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        deleted = cache.evict()
        assert deleted == [free] and held.is_file() and not free.exists()
    finally:
        proc.communicate("\n", timeout=30)
    assert cache.evict() == [held]  # released with its process: now it goes


def test_eviction_by_age_then_least_recently_used_within_the_size(tmp_path):
    cache = TransportCache(tmp_path / "c", max_bytes=2500, max_age_s=3600)
    old = _entry(cache, "old", 100, age_s=7200)  # past the age limit, though small
    a = _entry(cache, "a", 1000, age_s=300)
    b = _entry(cache, "b", 1000, age_s=200)
    c = _entry(cache, "c", 1000, age_s=100)
    assert cache.evict() == [old, a]  # old by age; then a, the least recently used, brings 3100 B to 2000 B
    assert b.is_file() and c.is_file()
    fd = cache._lock(b)  # b in use by this process's session
    try:
        cache.max_bytes = 0
        assert cache.evict(keep={c}) == []
    finally:
        os.close(fd)


def test_sessions_share_entries_and_a_stale_one_stays_until_evicted(procedural, tmp_path):
    rec = read_scene(procedural)
    cache = TransportCache(tmp_path / "cache")
    one = FastRenderer(rec, SMALL, cache)
    two = FastRenderer(rec, SMALL, cache)
    assert not one.cache_hit and two.cache_hit and one.key == two.key
    light = [parse_light("point:0.5,1,-2.5:3,3,3")]
    np.testing.assert_array_equal(one.render(light).beauty, two.render(light).beauty)
    np.testing.assert_array_equal(one.render(light).coverage, two.render(light).coverage)
    # another resolution: a second entry, the first one kept (a live session holds it)
    other = FastRenderer(rec, EngineSettings(max_side=40, env_samples=16, indirect_samples=4), cache)
    assert other.key != one.key and len(cache.entries()) == 2
    cache.max_bytes = 0
    assert cache.evict() == []  # all three renderers hold leases
    one.close(), two.close()
    assert [p.name for p in cache.evict()] == [f"transport-{one.key}.npz"]
    other.close()


def test_a_damaged_entry_is_rebuilt(procedural, tmp_path, caplog):
    rec = read_scene(procedural)
    cache = TransportCache(tmp_path / "cache")
    key = scene_key(rec, SMALL.transport)
    cache.folder.mkdir()
    cache.path(key).write_bytes(b"not an npz")
    prep, lease = prepare_transport(rec, SMALL.transport, cache)
    assert not prep.cache_hit and "unreadable" in caplog.text
    again, lease2 = prepare_transport(rec, SMALL.transport, cache)
    assert again.cache_hit
    np.testing.assert_array_equal(again.transport.H, prep.transport.H)
    np.testing.assert_array_equal(again.coverage, prep.coverage)
    lease.release(), lease2.release()


def test_coverage_is_the_covered_fraction_of_each_pixel(procedural):
    """Fully covered pixels have coverage 1; pixels on a silhouette of the pixel mesh lie strictly between."""
    rec = read_scene(procedural)
    prep, _ = prepare_transport(rec, SMALL.transport, None)
    cov = prep.coverage
    assert cov.min() >= 0 and cov.max() == 1.0
    assert np.mean(cov == 1.0) > 0.8  # most of the photo is one surface
    assert np.all((cov > 0) & (cov <= 1))  # every valid pixel's centre sees geometry
