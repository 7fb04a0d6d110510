"""Hostile and broken inputs (issue 10, first cases): confined product paths, decompression bombs, bogus
mesh counts, include bombs. Each: exit 2 with one line, nothing written outside the output folder, fast."""
from __future__ import annotations

import struct
import time
import zlib


from usd_scenes import looking_down_at_floor

from conftest import make_photo, write_plane_depth


def _png_bomb(path, w=20000, h=20000):
    """A valid 8-bit grey PNG of w x h zero pixels: a few hundred kB on disk, w*h bytes decoded."""
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
    comp = zlib.compressobj(9)
    row = b"\x00" * (w + 1)
    body = b"".join(comp.compress(row) for _ in range(h)) + comp.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))
    return path


def test_render_product_names_cannot_leave_the_output_folder(cli, tmp_path):
    victim = tmp_path / "outside" / "photo.png"
    victim.parent.mkdir()
    victim.write_bytes(b"precious")
    for i, name in enumerate((str(victim), "../outside/photo.png", "renders/../../outside/photo.png")):
        stage = looking_down_at_floor(tmp_path / f"s{i}.usda", width=8, height=6)
        stage.GetPrimAtPath("/Render/Products/color").GetAttribute("productName").Set(name)
        stage.GetRootLayer().Save()
        rc, out, err = cli("render", tmp_path / f"s{i}.usda", "-o", tmp_path / "o", "--spp", "1")
        assert rc == 2 and err.count("\n") == 1 and "productName" in err and "Traceback" not in err
        assert victim.read_bytes() == b"precious" and not (tmp_path / "o").exists()


def test_a_decompression_bomb_is_refused_from_its_header(cli, tmp_path):
    bomb = _png_bomb(tmp_path / "bomb.png")
    assert bomb.stat().st_size < 2_000_000
    t = time.perf_counter()
    rc, _, err = cli("build", bomb, "-o", tmp_path / "out")
    assert time.perf_counter() - t < 10
    assert rc == 2 and "400 megapixels" in err and "USDRELIGHT_MAX_MEGAPIXELS" in err
    assert not (tmp_path / "out").exists()


def test_the_megapixel_limit_is_configurable(cli, tmp_path, monkeypatch):
    photo = make_photo(tmp_path / "p.png", 24, 32)
    write_plane_depth(tmp_path / "d.npy", 24, 32)
    monkeypatch.setenv("USDRELIGHT_MAX_MEGAPIXELS", "0.0005")
    rc, _, err = cli("build", photo, "--depth", tmp_path / "d.npy", "-o", tmp_path / "a")
    assert rc == 2 and "over the limit of 0.0005" in err
    monkeypatch.setenv("USDRELIGHT_MAX_MEGAPIXELS", "1")
    assert cli("build", photo, "--depth", tmp_path / "d.npy", "-o", tmp_path / "b")[0] == 0


def test_bogus_face_counts_fail_before_allocating(cli, tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda", width=8, height=6)
    from pxr import UsdGeom

    bad = UsdGeom.Mesh.Define(stage, "/World/Bad")
    bad.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    bad.CreateFaceVertexCountsAttr([2000000000, -1999999997])
    bad.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.GetRootLayer().Save()
    t = time.perf_counter()
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.xml")
    assert rc == 2 and "inconsistent faceVertexCounts" in err and time.perf_counter() - t < 10
    assert not (tmp_path / "s.xml").exists()


def test_an_include_bomb_is_bounded(cli, tmp_path):
    for i in range(17):  # each file includes the next one twice: 2^16 includes unbounded
        nxt = f'<include filename="f{i + 1}.xml"/>' * 2 if i < 16 else ""
        (tmp_path / f"f{i}.xml").write_text(f'<scene version="3.0.0">{nxt}</scene>')
    t = time.perf_counter()
    rc, _, err = cli("convert", tmp_path / "f0.xml", tmp_path / "out.usda")
    assert time.perf_counter() - t < 10
    assert rc == 2 and "more than 256 <include>s" in err and not (tmp_path / "out.usda").exists()
