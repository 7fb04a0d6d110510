"""`usdrelight serve` against a hostile client: foreign Host/Origin (a web page the user visits, DNS rebinding),
the token beyond loopback, out-of-range and non-finite widget values, oversized uploads and decompression
bombs, a stage light beyond the widgets' default ranges, and saves from several tabs at once.

Clients here speak viser's own protocol over a real WebSocket (the `websockets` library viser uses): msgpack
messages {"type": <viser message class>, ...}, the same bytes the browser sends. Peak memory is the process's
VmHWM (reset through /proc/self/clear_refs before each measurement).
"""
from __future__ import annotations

import contextlib
import os
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")
import msgspec  # noqa: E402
import viser  # noqa: E402
import websockets.sync.client as ws_client  # noqa: E402
from websockets.datastructures import Headers  # noqa: E402
from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402
from websockets.http11 import Request  # noqa: E402

from test_serve import CHROMIUM, SIDE, _hdri, base_stage, stage  # noqa: E402,F401 (fixtures)
from usdrelight.errors import UsdRelightError  # noqa: E402
from usdrelight.serve.app import ServeApp  # noqa: E402
from usdrelight.serve.files import read_user_states, store_upload  # noqa: E402
from usdrelight.serve.saving import write_user_layer  # noqa: E402
from usdrelight.serve.guard import UPLOAD_PART, UPLOAD_START, Guard, guarded  # noqa: E402
from usdrelight.serve.state import LightState  # noqa: E402
from usdrelight.serve import uploads  # noqa: E402
from usdrelight.stage.layout import USER_LIGHTS  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402

MiB = 1 << 20


def _rss(key: str = "VmHWM") -> int:
    """This process's peak (VmHWM) or current (VmRSS) resident memory, bytes."""
    return int(re.search(rf"{key}:\s+(\d+)", Path("/proc/self/status").read_text()).group(1)) * 1024


def _reset_peak() -> int:
    Path("/proc/self/clear_refs").write_text("5")
    return _rss("VmRSS")


def _wait(cond, timeout=20.0, what="condition"):
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def _raw(port: int, request: str) -> bytes:
    """Send one raw HTTP request; what the server answers before closing (a 101's headers only)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(request.encode())
        out = b""
        while (chunk := s.recv(65536)) and not (out.startswith(b"HTTP/1.1 101") and b"\r\n\r\n" in out):
            out += chunk
    return out


def _together(fn, n: int) -> None:
    """Run ``fn`` in ``n`` threads at once."""
    go = threading.Barrier(n)
    threads = [threading.Thread(target=lambda: (go.wait(), fn())) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)


def _upgrade(path: str, host: str, origin: str | None = None) -> str:
    return (f"GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
            f"Sec-WebSocket-Protocol: viser-v{viser.__version__}\r\n" + (f"Origin: {origin}\r\n" if origin else "")
            + "\r\n")


def _refused(answer: bytes) -> bool:
    """A 403 (or a 400 from the HTTP parser) with a short text body: nothing of the page or the scene."""
    return answer.startswith((b"HTTP/1.1 403", b"HTTP/1.1 400")) and b"<html" not in answer.lower() \
        and len(answer) < 1000


class Client:
    """A viser client over a real WebSocket: announces a camera (viser then counts it as connected) and
    drains what the server sends in a thread."""

    def __init__(self, app, origin: str | None = None, token: bool = True, **kw):
        query = f"?token={app.guard.token}" if token else ""  # what the page's cookie carries for it
        self.ws = ws_client.connect(f"ws://127.0.0.1:{app.port}/{query}",
                                    origin=origin or f"http://127.0.0.1:{app.port}",
                                    subprotocols=[f"viser-v{viser.__version__}"], max_size=None, open_timeout=10,
                                    **kw)
        self.received = 0
        self.thread = threading.Thread(target=self._drain, daemon=True)
        self.thread.start()
        before = len(app.server.get_clients())
        self.send("ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0), fov=1.0, near=0.01,
                  far=100.0, image_height=480, image_width=640, look_at=(0.0, 0.0, -1.0), up_direction=(0.0, 1.0, 0.0))
        _wait(lambda: len(app.server.get_clients()) > before, what="the client to register")

    def _drain(self):
        with contextlib.suppress(ConnectionClosed):
            for message in self.ws:
                self.received += len(message)

    def send(self, kind: str, **fields) -> None:
        self.ws.send(msgspec.msgpack.encode({"type": kind, **fields}))

    def update(self, handle, **props) -> None:
        self.send("GuiUpdateMessage", uuid=handle._impl.uuid, updates=props)

    def upload(self, app, transfer: str, name: str, parts, size: int | None = None) -> None:
        """viser's upload protocol: a start message declaring name and size, then the parts in order."""
        button = app.gui.widgets["upload"]._impl.uuid
        self.send(UPLOAD_START, source_component_uuid=button, transfer_uuid=transfer, filename=name, mime_type="",
                  part_count=len(parts), size_bytes=size if size is not None else sum(map(len, parts)))
        for i, part in enumerate(parts):
            self.send(UPLOAD_PART, source_component_uuid=button, transfer_uuid=transfer, part_index=i, content=part)

    def close(self):
        self.ws.close()
        self.thread.join(timeout=10)


# ---- Host, Origin, token -------------------------------------------------------------------------------------
def test_foreign_origin_and_host_get_403_and_no_state(stage):
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        port, own = app.port, f"http://127.0.0.1:{app.port}"
        assert app.guard.installed and app.guard.token_required and app.url.endswith(f"/?token={app.guard.token}")
        for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{port + 1}",
                       f"https://127.0.0.1:{port}", "null"):
            with pytest.raises(InvalidStatus) as info:
                Client(app, origin=origin)
            assert info.value.response.status_code == 403, origin
            assert b"Forbidden" in info.value.response.body and len(info.value.response.body) < 200
        # DNS rebinding: evil.example resolves to 127.0.0.1, the browser sends its own name as Host
        page = _raw(port, f"GET / HTTP/1.1\r\nHost: evil.example:{port}\r\n\r\n")
        assert page.startswith(b"HTTP/1.1 403") and _refused(page)
        sock = _raw(port, _upgrade("/", f"evil.example:{port}", f"http://evil.example:{port}"))
        assert sock.startswith(b"HTTP/1.1 403") and _refused(sock)
        for bad_host in (f"127.0.0.1:{port + 1}", "127.0.0.1", "", f"localhost.evil.example:{port}"):
            assert _refused(_raw(port, f"GET / HTTP/1.1\r\nHost: {bad_host}\r\n\r\n")), bad_host
        assert _refused(_raw(port, f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nHost: evil.example\r\n\r\n"))
        # a WebSocket without an Origin (not a browser) needs the token
        assert _raw(port, _upgrade("/", f"127.0.0.1:{port}")).startswith(b"HTTP/1.1 403")
        assert _raw(port, _upgrade(f"/?token={app.guard.token}", f"127.0.0.1:{port}")).startswith(b"HTTP/1.1 101")
        assert _raw(port, _upgrade("/?token=wrong", f"127.0.0.1:{port}")).startswith(b"HTTP/1.1 403")
        refused = app.guard.refusals
        # a local program sends the page's own Origin: without the token it gets nothing (any local user could
        # drive the app, and write lights_user.usda as its owner, before the token was asked on loopback too)
        with pytest.raises(InvalidStatus) as info:
            Client(app, origin=own, token=False)
        assert info.value.response.status_code == 403 and b"token" in info.value.response.body
        assert _refused(_raw(port, f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"))
        # the app's own page (the printed URL) and socket still work, under each loopback name
        for host in (f"127.0.0.1:{port}", f"localhost:{port}"):
            page = _raw(port, f"GET /?token={app.guard.token} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n")
            assert page.startswith(b"HTTP/1.1 200") and b"<html" in page.lower()
        refused = app.guard.refusals
        client = Client(app, origin=own)
        _wait(lambda: client.received > 10_000, what="the scene")
        client.close()
        assert app.guard.refusals == refused


def test_guard_rules_and_the_token_beyond_loopback(stage):
    """Unit rules of Guard, then a server on 0.0.0.0: nothing without the token; the printed URL's token sets
    a cookie that the page's own WebSocket then carries."""
    def req(path="/", **headers):
        h = Headers()
        for k, v in headers.items():
            h[k.replace("_", "-")] = v
        return Request(path, h)

    g = Guard("127.0.0.1")
    t = f"/?token={g.token}"
    assert not g.refusal(req(t, Host="127.0.0.1:8080"), 8080)
    assert g.refusal(req(Host="127.0.0.1:8080"), 8080).startswith("the token")  # loopback asks it too
    assert not g.refusal(req(t, Host="[::1]:8080", Origin="http://[::1]:8080", Upgrade="websocket"), 8080)
    assert g.refusal(req(Host="[::1]:8080", Origin="http://[::1]:8080", Upgrade="websocket"), 8080)
    assert g.refusal(req(Host="192.168.1.5:8080"), 8080)  # loopback server: loopback names only
    assert g.refusal(req(Host="127.0.0.1:8080", Origin="http://127.0.0.1:8080/x"), 8080)
    assert g.refusal(req(Host="127.0.0.1:8080", Upgrade="WebSocket"), 8080)  # no Origin, no token
    wide = Guard("0.0.0.0")
    assert wide.token_required and wide.refusal(req(Host="192.168.1.5:8080"), 8080).startswith("the token")
    assert not wide.refusal(req(f"/?token={wide.token}", Host="192.168.1.5:8080"), 8080)  # an IP literal
    assert wide.refusal(req(f"/?token={wide.token}", Host="evil.example:8080"), 8080).startswith("Host")
    assert not wide.refusal(req(Host="192.168.1.5:8080", Cookie=f"a=b; usdrelight-serve-8080={wide.token}"), 8080)
    assert wide.refusal(req(Host="192.168.1.5:8080", Cookie=f"usdrelight-serve-8081={wide.token}"), 8080)

    with ServeApp(stage, host="0.0.0.0", port=0, max_side=SIDE) as app:
        port, token = app.port, app.guard.token
        assert app.url == f"http://0.0.0.0:{port}/?token={token}"
        assert _raw(port, f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").startswith(b"HTTP/1.1 403")
        page = _raw(port, f"GET /?token={token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n")
        assert page.startswith(b"HTTP/1.1 200")
        cookie = re.search(rb"Set-Cookie: (usdrelight-serve-\d+=[^;]+);([^\r]*)", page)
        assert cookie and b"HttpOnly" in cookie.group(2) and b"SameSite=Strict" in cookie.group(2)
        with pytest.raises(InvalidStatus):
            Client(app, token=False)  # the right Origin, no cookie
        Client(app, additional_headers={"Cookie": cookie.group(1).decode()}).close()


def test_guard_fails_closed_when_viser_builds_its_server_otherwise():
    """The guard hooks websockets.asyncio.server.serve as viser 1.1 calls it, and the upload screening knows
    viser's message names and fields: if viser changes either, this fails (and serve refuses to start)."""
    from viser import _messages

    with pytest.raises(UsdRelightError, match="cannot guard"):
        with guarded(Guard("127.0.0.1")):
            pass  # no server built inside the block
    fields = {c.__name__: {f for f in c.__dataclass_fields__} for c in (_messages.FileTransferStartUpload,
                                                                       _messages.FileTransferPart)}
    assert {"transfer_uuid", "filename", "part_count", "size_bytes"} <= fields[UPLOAD_START]
    assert {"transfer_uuid", "part_index", "content"} <= fields[UPLOAD_PART]


# ---- client values -------------------------------------------------------------------------------------------
def test_out_of_range_and_non_finite_client_values_change_nothing_on_disk(stage):
    lights = stage.parent / USER_LIGHTS
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        name = app.add_light("point")
        app.save()
        saved = lights.read_bytes()
        before = app.states[name]
        client = Client(app)
        gui = app.gui

        def refused(handle, value, what, **props):
            gui.status.content = "-"
            client.update(handle, value=value, **props)
            _wait(lambda: gui.status.content.startswith("**not applied:**"), what=f"{what} refused")

        f = gui._fields
        refused(f["exposure"], float("nan"), "NaN exposure")
        refused(f["intensity"], float("inf"), "Inf intensity")
        refused(f["position"], (float("nan"), 0.0, 0.0), "NaN position")
        refused(f["position"], (1e300, 0.0, 0.0), "a far position")
        refused(f["position"], (1.0, 2.0), "two coordinates")
        assert app.states[name] == before and lights.read_bytes() == saved
        client.update(gui.widgets["kind"], value="laser")
        refused(gui.widgets["add"], True, "an unknown kind")
        assert set(app.states) == {name}
        # a change of anything but the value (viser would set it on the widget's server state) is dropped
        client.update(f["exposure"], value=5.0, update_cb=[], max=1e9)
        client.update(f["exposure"], value=1.5)
        _wait(lambda: app.states[name].exposure == 1.5)
        assert f["exposure"]._impl.update_cb and f["exposure"].max == 10.0
        # beyond the slider: clamped to the slider's range
        client.update(f["exposure"], value=1000.0)
        client.update(f["intensity"], value=3e38)
        top = float(np.float32(gui._ranges["intensity"][1][1]))  # a light keeps float32 values (as USD)
        _wait(lambda: app.states[name].exposure == 10.0 and app.states[name].intensity == top)
        _wait(lambda: f["exposure"].value == 10.0 and f["exposure"].max == 10.0)
        assert top < 1e3
        for key, value in (("dimmer", -3.0), ("exposure", 1000.0), ("split", 5.0)):
            client.update(gui.widgets[key], value=value)
        _wait(lambda: (app.dimmer, app.exposure, app.split) == (0.0, 6.0, 1.0))
        refused(gui.widgets["exposure"], float("nan"), "a NaN display exposure")
        assert app.exposure == 6.0
        gizmo = app.view.handles[name]["gizmo"]
        app.move_light(name, (float("nan"), 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))  # the gizmo's callback
        assert np.allclose(gizmo.position, app.states[name].position)
        assert app.states[name].position == before.position
        gui.status.content = "-"
        client.update(gui.widgets["save"], value=True)
        _wait(lambda: gui.status.content.startswith("Saved"), what="the save")
        client.close()
    back, _ = read_user_states(open_stage(stage), {})
    (light,) = back
    assert (light.exposure, light.position) == (10.0, before.position) and light.intensity < 1e3
    assert read_scene(open_stage(stage)).lights  # every command still reads the stage
    for intensity, exposure in ((3e38, 1000.0), (1e25, 40.0)):  # whatever the path: never such a light
        with pytest.raises(UsdRelightError, match="over 1e"):
            LightState("L", "point", intensity=intensity, exposure=exposure)


def test_a_stage_light_beyond_the_default_ranges_loads_and_shows(stage):
    """exposure 12 (legal UsdLux; the sliders' default range is [-10, 10]), a 120-degree spot cone."""
    from pxr import Sdf, Usd, UsdLux

    layer = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    s = Usd.Stage.Open(layer)
    s.OverridePrim("/Scene")
    hot = UsdLux.SphereLight.Define(s, "/Scene/Lights/User/Hot")
    hot.CreateTreatAsPointAttr(True)
    hot.CreateExposureAttr(12.0)
    hot.CreateIntensityAttr(0.001)
    wide = UsdLux.SphereLight.Define(s, "/Scene/Lights/User/Wide")
    wide.CreateTreatAsPointAttr(True)
    UsdLux.ShapingAPI.Apply(wide.GetPrim()).CreateShapingConeAngleAttr(120.0)
    layer.Save()
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        assert app.states["Hot"].exposure == 12.0 and app.gui.selected.value == "Hot"
        expo = app.gui._fields["exposure"]
        assert expo.value == 12.0 and expo.min == -10.0 and expo.max >= 12.0
        shown = app.wait_shown(app.update())
        assert not shown.error and shown.seconds["total"] > 0
        app.gui.select("Wide")
        cone = app.gui._fields["cone"]
        assert app.states["Wide"].kind == "spot" and cone.value == 120.0 and cone.max >= 120.0
        client = Client(app)
        client.update(cone, value=100.0)
        _wait(lambda: app.states["Wide"].cone_angle == 100.0)
        client.update(cone, value=150.0)  # beyond its range: clamped to 120
        _wait(lambda: app.states["Wide"].cone_angle == 120.0 and cone.value == 120.0)
        client.close()


# ---- uploads -------------------------------------------------------------------------------------------------
def _rle_hdr(width: int, height: int) -> bytes:
    """A valid run-length Radiance HDR of one colour: ~640 bytes a scanline (runs of 127), whatever its width."""
    def runs(v):
        return b"".join(bytes([128 + min(127, width - i), v]) for i in range(0, width, 127))
    scan = bytes([2, 2, width >> 8, width & 255]) + runs(128) * 3 + runs(129)
    return f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n".encode() + scan * height


def test_declared_oversize_upload_is_refused_before_its_parts_are_buffered(stage, tmp_path):
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        client, n = Client(app), 96
        base = _reset_peak()
        client.upload(app, "big", "sky.exr", [bytes(MiB)] * n, size=336 * MiB)  # 96 of its 336 parts
        _wait(lambda: app.uploads.dropped == n, 60, "the parts")
        peak = _rss() - base
        assert "upload refused" in app.gui.status.content and "MiB" in app.gui.status.content
        assert not app.server.gui._current_file_upload_states  # viser holds nothing of it
        assert peak < 40 * MiB, f"peak +{peak / MiB:.0f} MiB for {n} MiB sent"
        print(f"\noversize upload: {n} MiB sent, peak RSS +{peak / MiB:.1f} MiB")
        sky = _hdri(tmp_path / "sky.exr").read_bytes()  # a real upload then goes through, parts and all
        client.upload(app, "ok", "my sky.exr", [sky[:len(sky) // 2], sky[len(sky) // 2:]])
        _wait(lambda: "my_sky" in app.hdris, what="the upload")
        assert app.hdris["my_sky"].read_bytes() == sky and not app.uploads.busy
        client.close()


def test_hdr_declaring_120_megapixels_is_refused_without_decoding(stage, tmp_path):
    bomb = _rle_hdr(10000, 11999)
    assert len(bomb) < 8 * MiB
    (tmp_path / "bomb.hdr").write_bytes(bomb)
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        base = _reset_peak()
        t0 = time.perf_counter()
        with pytest.raises(UsdRelightError, match=r"10000x11999 \(120 megapixels\), over the limit of 34"):
            app.upload_hdri("bomb.hdr", bomb)
        direct = _rss() - base, time.perf_counter() - t0
        client, parts = Client(app), [bomb[i:i + MiB] for i in range(0, len(bomb), MiB)]
        base = _reset_peak()
        client.upload(app, "bomb", "bomb.hdr", parts)
        _wait(lambda: app.uploads.dropped == len(parts), 30, "the parts")
        wire = _rss() - base
        assert "120 megapixels" in app.gui.status.content
        assert not list(stage.parent.glob("serve/uploads/*"))
        client.close()
    assert direct[0] < 30 * MiB and wire < 30 * MiB, (direct, wire)
    print(f"\n120 MP .hdr ({len(bomb) / MiB:.1f} MiB): refused in {direct[1] * 1e3:.0f} ms, peak RSS "
          f"+{direct[0] / MiB:.1f} MiB (direct), +{wire / MiB:.1f} MiB (over the socket)")
    with pytest.raises(UsdRelightError, match="over the limit"):
        ServeApp(stage, port=0, max_side=SIDE, hdris=[tmp_path / "bomb.hdr"])
    with pytest.raises(UsdRelightError, match="over the limit"):
        store_upload(stage.parent, "x.hdr", bomb)


def test_upload_gate_one_at_a_time_in_order_and_bounded(monkeypatch, tmp_path):
    sky = _hdri(tmp_path / "sky.exr").read_bytes()
    gate = uploads.UploadGate()
    a, b = object(), object()
    assert gate.start(a, "1", "sky.exr", len(sky), 2) == uploads.PASS
    assert gate.start(b, "2", "sky.exr", len(sky), 1) == uploads.DROP  # one at a time
    assert gate.part(b, "1", 0, sky[:10]) == uploads.DROP  # not its transfer
    assert gate.part(a, "1", 1, sky[10:]) == uploads.CLOSE  # out of order
    gate = uploads.UploadGate()
    assert gate.start(a, "1", "sky.exr", len(sky), 2) == uploads.PASS
    assert gate.part(a, "1", 0, sky[:100]) == uploads.PASS
    assert gate.part(a, "1", 1, sky[100:] + b"x") == uploads.CLOSE  # more than it declared
    assert not gate.busy
    assert gate.start(a, "3", "sky.exr", len(sky), 1) == uploads.PASS
    assert gate.part(a, "3", 0, sky) == uploads.PASS and gate.busy  # complete, not yet stored
    gate.release()
    assert not gate.busy
    assert gate.start(a, "4", "x.exr", 10, 1) == uploads.PASS
    assert gate.part(a, "4", 0, b"not an exr") == uploads.DROP and "4" in gate._refused
    assert gate.start(a, "5", "sky.png", 10, 1) == uploads.DROP
    assert gate.start(a, "6", "sky.exr", uploads.MAX_UPLOAD_BYTES + 1, 200) == uploads.DROP
    assert gate.start(a, "7", "sky.exr", 100, 101) == uploads.DROP  # more parts than bytes
    evicted = []
    gate = uploads.UploadGate(on_evict=evicted.append)
    assert gate.start(a, "8", "sky.exr", len(sky), 2) == uploads.PASS
    monkeypatch.setattr(uploads, "STALL_SECONDS", 0.0)
    assert gate.start(b, "9", "sky.exr", len(sky), 1) == uploads.PASS and evicted == [a]  # a stalled one
    # the header reader: EXR data window, HDR resolution line, incomplete headers
    assert uploads.header_size(sky, ".exr") == (16, 8)
    assert uploads.header_size(sky[:12], ".exr") is None
    assert uploads.header_size(_rle_hdr(300, 20), ".hdr") == (300, 20)
    assert uploads.header_size(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2", ".hdr") is None
    for bad, suffix in ((b"GIF89a" + bytes(100), ".exr"), (b"P6\n", ".hdr"), (b"#?X\n\nnonsense\n", ".hdr")):
        with pytest.raises(UsdRelightError):
            uploads.header_size(bad, suffix)


# ---- saves ---------------------------------------------------------------------------------------------------
def test_saves_from_several_tabs_are_serialised(stage):
    from usdrelight.atomic import LOCK_NAME

    with ServeApp(stage, port=0, max_side=SIDE) as app:
        for kind in ("point", "spot", "sun"):
            app.add_light(kind)
        errors = []

        def tab():
            for _ in range(10):
                try:
                    app.save()
                except Exception as exc:  # noqa: BLE001 - what the test counts
                    errors.append(exc)

        t0 = time.perf_counter()
        _together(tab, 2)
        print(f"\n20 saves from 2 threads: {time.perf_counter() - t0:.2f} s")
        assert not errors, errors
        back, _ = read_user_states(open_stage(stage), {})
        assert sorted(s.name for s in back) == ["Point1", "Spot1", "Sun1"]
        # two writers calling the file writer itself (no app lock) also both succeed: they wait for the lock
        done = []
        _together(lambda: done.append(write_user_layer(stage.parent, list(app.states.values()), wait=10.0)), 4)
        assert len(done) == 4
        # another process holding the stage lock briefly: the save waits for it
        lock = stage.parent / LOCK_NAME
        lock.write_text(f"{os.getppid()}\n")
        threading.Timer(0.5, lock.unlink).start()
        app.set_light("Point1", intensity=3.0)  # a change to write (a Save with nothing changed writes nothing)
        t0 = time.perf_counter()
        app.save()
        assert time.perf_counter() - t0 >= 0.4
    back, _ = read_user_states(open_stage(stage), {})
    assert len(back) == 3 and read_scene(open_stage(stage)).lights


# ---- a real browser --------------------------------------------------------------------------------------------
def test_browser_page_of_another_site_cannot_connect_and_the_token_url_works(stage, tmp_path):
    """Headless Chromium: pages of other origins open a WebSocket to the app and are refused, even with the
    token; the app's own URL with its token loads the app (cookie, WebSocket). Chromium itself blocks a public
    site's request to a loopback address (http://evil.example, served by Playwright's router); the page that
    reaches the app's own check is served by another server on this machine."""
    import functools
    import http.server

    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (the test extra)")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} not found: scripts/setup.sh installs Debian's chromium")
    js = """url => new Promise(done => { const ws = new WebSocket(url, ["viser-v%s"]);
            ws.onopen = () => done("open"); ws.onerror = () => done("refused"); })""" % viser.__version__
    (tmp_path / "index.html").write_text("another site")
    other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(
        http.server.SimpleHTTPRequestHandler, directory=str(tmp_path)))
    threading.Thread(target=other.serve_forever, daemon=True).start()
    with ServeApp(stage, host="0.0.0.0", port=0, max_side=SIDE) as app, sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            for site in ("http://evil.example/", f"http://127.0.0.1:{other.server_port}/"):
                page = browser.new_page()
                page.route("http://evil.example/", lambda route: route.fulfill(content_type="text/html", body="hi"))
                page.goto(site)
                for url in (f"ws://127.0.0.1:{app.port}/", f"ws://127.0.0.1:{app.port}/?token={app.guard.token}"):
                    assert page.evaluate(js, url) == "refused", (site, url)
            assert app.guard.refusals == 2 and not app.server.get_clients()
            page = browser.new_page(viewport={"width": 1400, "height": 850})
            page.goto(app.url.replace("0.0.0.0", "127.0.0.1"))
            page.get_by_role("button", name="Add light").wait_for(timeout=30000)
            page.locator("img[src^='blob:']").first.wait_for(timeout=30000)  # a relit frame came over the socket
            assert len(app.server.get_clients()) == 1
        finally:
            browser.close()
            other.shutdown()


def test_oversized_deeply_nested_and_overbright_client_data_is_refused(tmp_path):
    """One frame bigger than MAX_FRAME_BYTES or nested past Python's recursion limit closes its connection before
    viser decodes it (a 45 MB frame of empty arrays would be ~3 GB of Python objects there); an uploaded HDRI whose
    pixels go beyond any light's radiance limit is not kept (x a dome's intensity it would overflow)."""
    import numpy as np

    from usdrelight.errors import UsdRelightError
    from usdrelight.imageio import write_image
    from usdrelight.serve.files import store_upload
    from usdrelight.serve.guard import GUI_UPDATE, MAX_FRAME_BYTES, screen

    gate, owner = uploads.UploadGate(), object()
    deep = b"\x91" * 200_000 + b"\xc0"
    assert screen(gate, owner, b"\x81\xa4type" + deep) == uploads.CLOSE  # a "type" nested 200,000 deep
    assert screen(gate, owner, deep) == uploads.CLOSE
    assert screen(gate, owner, b"\x90" * (MAX_FRAME_BYTES + 1)) == uploads.CLOSE
    assert screen(gate, owner, msgspec.msgpack.encode({"type": GUI_UPDATE, "uuid": "x", "updates": {"value": 1}})) \
        == uploads.PASS  # an ordinary widget change still goes through
    img = np.full((4, 8, 3), 1e35, np.float32)
    with pytest.raises(UsdRelightError, match="beyond 1e"):
        store_upload(tmp_path, "sun.exr", write_image(tmp_path / "src.exr", img, "float").read_bytes())
    assert not list((tmp_path / "serve" / "uploads").glob("hdri-*"))  # not kept


def test_probed_messages_a_quaternion_and_a_broken_layer(stage, tmp_path):
    """Found by probing the running app over its WebSocket: an upload whose part named another widget ('Selected')
    made viser set that widget's value to the file (every later selection failed) and held the upload slot for
    60 s; text frames, non-msgpack bytes and unknown message types each printed a traceback; a (1e300, 1e300, 0, 0)
    gizmo quaternion was saved as (0, 0, 0, 0); Save over a lights_user.usda broken meanwhile raised
    Tf.ErrorException (the status stuck at 'save ...')."""
    import shutil

    from usdrelight.serve.guard import screen

    sky = _hdri(tmp_path / "sky.exr").read_bytes()
    gate = uploads.UploadGate()
    gate.buttons = {"button"}
    a = object()
    assert gate.start(a, "1", "sky.exr", len(sky), 1, "selected") == uploads.DROP  # not an upload button
    assert gate.start(a, "2", "sky.exr", len(sky), 1, "button") == uploads.PASS
    assert gate.part(a, "2", 0, sky, "selected") == uploads.DROP and not gate.busy  # refused, the slot free
    assert gate.start(a, "3", "sky.exr", len(sky), 1, "button") == uploads.PASS
    assert gate.part(a, "3", 0, sky, "button") == uploads.PASS
    for data in ("hello", b"\xc1", msgspec.msgpack.encode(5), msgspec.msgpack.encode({"type": "NoSuchMessage"})):
        assert screen(gate, a, data) in (uploads.CLOSE, uploads.DROP), data
    assert screen(gate, a, msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": "x", "updates":
                                                   {"value": 1}})) == uploads.PASS
    with pytest.raises(UsdRelightError, match="quaternion must be finite and not zero"):
        LightState("L", "spot", rotation=(0.0, 0.0, 0.0, 0.0))
    big = LightState("L", "spot", rotation=(1e300, 1e300, 0.0, 0.0))
    np.testing.assert_allclose(big.rotation, (0.5 ** 0.5, 0.5 ** 0.5, 0.0, 0.0))
    assert LightState("L", "spot", rotation=(1e-170, 0.0, 0.0, 0.0)).rotation == (1.0, 0.0, 0.0, 0.0)  # was NaN
    copy = tmp_path / "st"
    shutil.copytree(stage.parent, copy)
    broken = '#usda 1.0\nover "Scene" {\n def Scope "Lights" {\n'
    (copy / USER_LIGHTS).write_text(broken)
    with pytest.raises(UsdRelightError, match="cannot read lights_user.usda"):
        write_user_layer(copy, [big])
    assert (copy / USER_LIGHTS).read_text() == broken  # left as it was
    with pytest.raises(UsdRelightError, match="cannot read image hdri-[0-9a-f]+.exr") as err:  # no server folders
        store_upload(copy, "sky.exr", sky[:300])
    assert str(tmp_path) not in str(err.value)


def test_a_light_the_user_added_to_the_file_meanwhile_is_not_replaced(stage, tmp_path):
    """Save replaced the user's DistantLight 'Point3', added to lights_user.usda while the app ran, with the app's
    new SphereLight of that name. A new light now skips the file's names, and a clash at Save writes nothing."""
    import shutil

    copy = tmp_path / "st"
    shutil.copytree(stage.parent, copy)
    user = copy / USER_LIGHTS

    def add_to_file(name: str) -> str:
        from pxr import Sdf

        layer = Sdf.Layer.FindOrOpen(str(user))
        scope = Sdf.CreatePrimInLayer(layer, "/Scene/Lights/User")
        scope.specifier, scope.typeName = Sdf.SpecifierDef, "Scope"
        Sdf.CreatePrimInLayer(layer, f"/Scene/Lights/User/{name}").specifier = Sdf.SpecifierDef
        layer.GetPrimAtPath(f"/Scene/Lights/User/{name}").typeName = "DistantLight"
        layer.Save()
        return user.read_text()

    with ServeApp(copy / stage.name, port=0, max_side=SIDE) as app:
        first = app.add_light("point")
        add_to_file(f"Point{int(first[5:]) + 1}")
        second = app.add_light("point")
        assert second == f"Point{int(first[5:]) + 2}"  # the file's new name skipped
        text = add_to_file(second)  # and now one of the app's new names taken in the file
        with pytest.raises(UsdRelightError, match=f"lights_user.usda gained {second} while the app ran"):
            app.save()
        assert user.read_text() == text  # nothing written
