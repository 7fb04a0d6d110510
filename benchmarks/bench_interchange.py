"""Benchmark issue 15: interchange fidelity on Mitsuba scene files others wrote.

Every Mitsuba regression scene in ``../shared/testdata/mitsuba-data/tests/scenes/*/test_*.xml`` is converted
XML -> USD -> XML with ``usdrelight convert`` (in-process, ``--allow-path`` the data folder) and both the original
and the round trip are rendered by Mitsuba (llvm_ad_rgb, the same spp). Reported per scene: the image means of
the reference EXR (``refs/``), the original and the round trip, the round trip's mean error against the
reference and against the original, the per-pixel mean absolute difference to the original (relative to its
mean), and the converter's warnings.

A scene whose own files are missing from the data set (Mitsuba cannot render it either) is reported as such;
when the missing file is an envmap, a variant without that emitter is also measured (against Mitsuba's render
of the same variant: no reference exists for it).

    python benchmarks/bench_interchange.py [--spp 128] [--out benchmarks/results/interchange.json]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import usdrelight  # noqa: F401  (configures drjit's libLLVM before Mitsuba is imported)
from usdrelight.cli import main
from usdrelight.mitsuba.runtime import load_mitsuba

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "testdata" / "mitsuba-data"


def _cli(*args) -> tuple[int, list[str]]:
    """Run ``usdrelight`` in-process; returns the exit status and the stderr lines."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in args])
    lines: list[str] = []
    for line in err.getvalue().splitlines():  # the log handler wraps long lines: join the continuations
        if not line.strip():
            continue
        if line.startswith(" ") and lines:
            lines[-1] += " " + line.strip()
        else:
            lines.append(" ".join(line.split()))
    return rc, lines


def _render(path: Path, spp: int) -> np.ndarray:
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=spp), dtype=np.float64)[..., :3]


def _reference(scene: Path) -> Path | None:
    """The refs/*.exr whose name shares the longest prefix with the scene's."""
    refs = sorted((scene.parent / "refs").glob("*.exr"))
    if not refs:
        return None

    def common(a: str, b: str) -> int:
        n = 0
        while n < min(len(a), len(b)) and a[n] == b[n]:
            n += 1
        return n
    return max(refs, key=lambda r: common(r.stem, scene.stem))


def _without_missing_envmaps(scene: Path, work: Path) -> Path | None:
    """A copy of the scene's folder with envmap emitters whose file is missing removed (None: nothing to remove)."""
    dst = work / "variant" / scene.parent.name
    shutil.copytree(scene.parent, dst)
    removed = 0
    for xml in dst.rglob("*.xml"):
        text = xml.read_text()
        text = text.replace('value="../../../common"', f'value="{DATA / "common"}"')

        def drop(m):
            nonlocal removed
            name = re.search(r'name="filename"\s+value="([^"]+)"', m.group(0))
            if name and not any((d / name.group(1)).exists() for d in (xml.parent, DATA / "common")):
                removed += 1
                return ""
            return m.group(0)
        text = re.sub(r'<emitter type="envmap">.*?</emitter>', drop, text, flags=re.S)
        xml.write_text(text)
    return dst / scene.name if removed else None


def measure(scene: Path, work: Path, spp: int, ref: Path | None, label: str) -> dict:
    row = {"scene": label, "spp": spp}
    t = time.perf_counter()
    try:
        original = _render(scene, spp)
    except Exception as exc:  # Mitsuba itself cannot render it (a file missing from the data set)
        row.update(status="original does not render",
                   error=str(exc).splitlines()[-1].replace(str(DATA) + "/", "")[:400])
        return row
    row["seconds_original"] = round(time.perf_counter() - t, 2)
    usd, back = work / f"{label}.usda", work / "back" / label / "scene.xml"
    rc, err = _cli("convert", scene, usd, "--allow-path", DATA)
    row["warnings_to_usd"] = [e for e in err if "error" not in e]
    if rc != 0:
        row.update(status="XML -> USD failed", error=err[-1] if err else "")
        return row
    rc, err = _cli("convert", usd, back, "--allow-path", DATA)
    row["warnings_to_xml"] = [e for e in err if "error" not in e]
    if rc != 0:
        row.update(status="USD -> XML failed", error=err[-1] if err else "")
        return row
    t = time.perf_counter()
    ours = _render(back, spp)
    row["seconds_round_trip"] = round(time.perf_counter() - t, 2)
    m_orig, m_ours = float(original.mean()), float(ours.mean())
    row.update(status="ok", mean_original=m_orig, mean_round_trip=m_ours,
               round_trip_vs_original=m_ours / m_orig - 1 if m_orig > 0 else None,
               pixel_mad_vs_original=float(np.abs(ours - original).mean() / m_orig) if m_orig > 0 else None)
    if ref is not None:
        mi = load_mitsuba()
        r = np.array(mi.Bitmap(str(ref)), dtype=np.float64)[..., :3]
        m_ref = float(r.mean())
        row.update(reference=str(ref.relative_to(DATA)), mean_reference=m_ref,
                   original_vs_reference=m_orig / m_ref - 1, round_trip_vs_reference=m_ours / m_ref - 1,
                   pixel_mad_round_trip_vs_reference=float(np.abs(ours - r).mean() / m_ref)
                   if ours.shape == r.shape else None)
    return row


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:+.1f}%"


def main_bench(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "interchange.json")
    args = ap.parse_args(argv)
    scenes = sorted(args.data.glob("tests/scenes/*/test_*.xml"))
    rows = []
    with tempfile.TemporaryDirectory() as td:
        for scene in scenes:
            work = Path(td) / scene.stem
            work.mkdir()
            row = measure(scene, work, args.spp, _reference(scene), scene.stem)
            rows.append(row)
            if row["status"] != "ok":
                variant = _without_missing_envmaps(scene, work)
                if variant is not None:
                    rows.append(measure(variant, work, args.spp, None, scene.stem + " (missing envmap removed)"))
    doc = {"spp": args.spp, "data": str(args.data), "scenes": rows,
           "note": "relative errors of image means; pixel_mad = mean |difference| / mean of the other image"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print("| scene | status | reference mean | original vs ref. | round trip vs ref. | round trip vs original "
          "| pixel MAD vs original |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['status']} | {r.get('mean_reference', float('nan')):.4f} | "
              f"{_pct(r.get('original_vs_reference'))} | {_pct(r.get('round_trip_vs_reference'))} | "
              f"{_pct(r.get('round_trip_vs_original'))} | {_pct(r.get('pixel_mad_vs_original'))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
