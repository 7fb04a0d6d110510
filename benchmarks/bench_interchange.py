"""Benchmark issue 15: interchange fidelity on Mitsuba scene files, XML -> USD -> XML.

Scenes: every Mitsuba regression scene in ``../shared/testdata/mitsuba-data/tests/scenes/*/test_*.xml`` (others
wrote them; their reference EXRs are in ``refs/``) and, with ``--corpus`` (the default), our own small scenes in
``tests/data/mitsuba_corpus/`` (one per feature; no references: the original's render is the reference). Each is
converted with ``usdrelight convert`` (in-process, ``--allow-path`` the data folders) XML -> USD -> XML, and
Mitsuba (llvm_ad_rgb) renders the original and the round trip at ``--spp`` with seeds 0 .. ``--seeds``-1 (the
same seed for both: what the round trip reproduces exactly then renders the same paths).

Reported per scene: the image means (original and round trip: mean over seeds +- its standard error), the
reference EXR's mean, the round trip's mean error against the reference and against the original (+- the
standard error of the paired per-seed differences), the per-pixel relative RMSE of the seed-0 round trip against
the seed-0 original (sqrt(mean((b - a)^2)) / mean(a)), "USD alone": the error when the Mitsuba-only data the
XML reader kept in materials' and lights' customData is dropped before the XML export (what another USD tool
sees: UsdPreviewSurface and UsdLux approximations only), the seconds of each conversion and the converter's warnings.

A scene whose own files are missing from the data set (Mitsuba cannot render it either) is reported as such;
when the missing file is an envmap, a variant without that emitter is also measured (against Mitsuba's render
of the same variant: no reference exists for it). Issue 15's "dielectric spheres and a point light" scene is not
in the data set; a variant of bsdf_spheres with dielectric spheres is built and measured, and ``--noise`` adds
how its image mean spreads over seeds at 16 .. 1024 spp (``noise`` in the JSON).

    python benchmarks/bench_interchange.py [--spp 128] [--seeds 4] [--no-corpus] [--noise]
                                           [--out benchmarks/results/interchange.json]
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
CORPUS = ROOT / "tests" / "data" / "mitsuba_corpus"


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


def _renders(path: Path, spp: int, seeds: int) -> list[np.ndarray]:
    mi = load_mitsuba()
    scene = mi.load_file(str(path))
    return [np.array(mi.render(scene, spp=spp, seed=s), dtype=np.float64)[..., :3] for s in range(seeds)]


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


def _copy_without_missing_envmaps(scene_dir: Path, dst: Path) -> int:
    """Copy a regression scene's folder to ``dst`` with the data set's common folder made absolute and envmap
    emitters whose file is missing removed; returns how many were removed."""
    shutil.copytree(scene_dir, dst)
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
    return removed


def dielectric_variant(work: Path) -> Path | None:
    """Issue 15's unstable scene rebuilt from bsdf_spheres: its four roughplastic spheres become two smooth
    dielectrics (bk7 / air) and two roughdielectrics (alpha 0.1, 0.4), lit by its area light on an obj quad and
    its point light (its missing envmap removed)."""
    src = DATA / "tests" / "scenes" / "bsdf_spheres"
    if not src.exists():
        return None
    dst = work / "dielectric_variant" / "bsdf_spheres"
    _copy_without_missing_envmaps(src, dst)
    text = (dst / "test_roughplastic_linear_path.xml").read_text()
    bsdfs = ['<bsdf type="dielectric"><string name="int_ior" value="bk7"/><string name="ext_ior" value="air"/>'
             '</bsdf>'] * 2 + [f'<bsdf type="roughdielectric"><float name="alpha" value="{a}"/>'
                               f'<string name="int_ior" value="bk7"/></bsdf>' for a in (0.1, 0.4)]
    parts = re.split(r'<bsdf type="roughplastic">.*?</bsdf>', text, flags=re.S)
    if len(parts) != 5:
        return None
    out = dst / "test_dielectric_point_light.xml"
    out.write_text(parts[0] + "".join(b + p for b, p in zip(bsdfs, parts[1:])))
    return out


def strip_kept_mitsuba(usd: Path) -> tuple[Path, int]:
    """A copy of ``usd`` (same folder, so relative asset paths hold) without the Mitsuba BSDFs, emitter textures
    and microfacet distributions the XML reader kept in materials' and lights' ``customData["mitsuba"]``: what
    another USD tool sees. The RenderSettings' kept integrator and sampler stay, so that only the
    UsdPreviewSurface / UsdLux approximations differ. Returns (path, prims stripped)."""
    from pxr import Usd, UsdRender

    stage = Usd.Stage.Open(str(usd))
    n = 0
    for prim in stage.Traverse():
        if "mitsuba" in prim.GetCustomData() and not prim.IsA(UsdRender.SettingsBase):
            prim.ClearCustomDataByKey("mitsuba")
            n += 1
    out = usd.with_name(usd.stem + "_usd_only.usda")
    stage.GetRootLayer().Export(str(out))
    return out, n


def _mean_se(x) -> tuple[float, float]:
    x = np.asarray(x, np.float64)
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else 0.0


def measure(scene: Path, work: Path, spp: int, seeds: int, ref: Path | None, label: str, allow: list) -> dict:
    row = {"scene": label, "spp": spp, "seeds": seeds}
    ref_img = None
    if ref is not None:
        ref_img = np.array(load_mitsuba().Bitmap(str(ref)), dtype=np.float64)[..., :3]
        row.update(reference=str(ref.relative_to(DATA)), mean_reference=float(ref_img.mean()))
    allow_args = [a for d in allow for a in ("--allow-path", d)]
    t = time.perf_counter()
    try:
        original = _renders(scene, spp, seeds)
    except Exception as exc:  # Mitsuba itself cannot render it (a file missing from the data set)
        row.update(status="original does not render",
                   error=str(exc).splitlines()[-1].replace(str(DATA) + "/", "")[:400])
        return row
    row["seconds_render_original"] = round(time.perf_counter() - t, 2)
    usd, back = work / f"{label}.usda", work / "back" / label / "scene.xml"
    for what, src, dst, failed in (("usd", scene, usd, "XML -> USD failed"), ("xml", usd, back, "USD -> XML failed")):
        t = time.perf_counter()
        rc, err = _cli("convert", src, dst, *allow_args)
        row[f"seconds_to_{what}"] = round(time.perf_counter() - t, 3)
        row[f"warnings_to_{what}"] = [e for e in err if "error" not in e]
        if rc != 0:
            row.update(status=failed, error=err[-1] if err else "")
            return row
    t = time.perf_counter()
    ours = _renders(back, spp, seeds)
    row["seconds_render_round_trip"] = round(time.perf_counter() - t, 2)
    usd_only, stripped = strip_kept_mitsuba(usd)
    row["prims_with_kept_mitsuba_data"] = stripped
    alone = ours  # nothing kept: USD alone is the round trip
    if stripped:
        alone_xml = work / "usd_only" / label / "scene.xml"
        alone = _renders(alone_xml, spp, seeds) if _cli("convert", usd_only, alone_xml, *allow_args)[0] == 0 else None
    row["_images"] = (original[0], ours[0], ours[0] if alone is None else alone[0])
    mo = np.array([a.mean() for a in original])
    mr = np.array([b.mean() for b in ours])
    (m_orig, se_orig), (m_ours, se_ours) = _mean_se(mo), _mean_se(mr)
    row.update(status="ok", mean_original=m_orig, se_original=se_orig, mean_round_trip=m_ours, se_round_trip=se_ours)
    if m_orig > 0 and original[0].shape == ours[0].shape:
        diff = _mean_se(mr - mo)
        row.update(round_trip_vs_original=m_ours / m_orig - 1, se_round_trip_vs_original=diff[1] / m_orig,
                   pixel_rel_rmse_vs_original=float(np.sqrt(np.mean((ours[0] - original[0]) ** 2)) / mo[0]))
        if alone is ours:
            row.update(usd_alone_vs_original=row["round_trip_vs_original"])
        elif alone is not None:
            ma = np.array([b.mean() for b in alone])
            row.update(usd_alone_vs_original=float(ma.mean()) / m_orig - 1,
                       se_usd_alone_vs_original=_mean_se(ma - mo)[1] / m_orig)
    if ref_img is not None:
        m_ref = row["mean_reference"]
        row.update(original_vs_reference=m_orig / m_ref - 1, round_trip_vs_reference=m_ours / m_ref - 1,
                   se_round_trip_vs_reference=se_ours / m_ref,
                   pixel_rel_rmse_round_trip_vs_reference=float(np.sqrt(np.mean((ours[0] - ref_img) ** 2)) / m_ref)
                   if ours[0].shape == ref_img.shape else None)
    return row


def noise_study(scene: Path, seeds: int = 8, spps=(16, 64, 256, 1024)) -> list[dict]:
    """How the image mean of ``scene`` spreads over seeds: per spp, the relative standard deviation of one
    render's mean, and the range of relative differences between two renders with different seeds (what a
    comparison sees when the round trip's paths are not the original's)."""
    rows = []
    for spp in spps:
        m = np.array([im.mean() for im in _renders(scene, spp, seeds)])
        other = m / np.roll(m, 1) - 1
        rows.append({"spp": spp, "seeds": seeds, "mean": float(m.mean()),
                     "rel_std_of_one_render": float(m.std(ddof=1) / m.mean()),
                     "rel_se_of_the_mean": float(m.std(ddof=1) / np.sqrt(seeds) / m.mean()),
                     "other_seed_difference_min": float(other.min()), "other_seed_difference_max": float(other.max())})
    return rows


def _pct(v, se=None) -> str:
    if v is None:
        return "-"
    return f"{100 * v:+.1f}%" + (f" ± {100 * se:.1f}" if se is not None and se >= 0.0005 else "")


def _mean(r, key) -> str:
    if key not in r:
        return "-"
    se = r.get(key.replace("mean_", "se_"))
    return f"{r[key]:.4f}" + (f" ± {se:.4f}" if se is not None and se >= 0.00005 else "")


def table(rows: list[dict]) -> str:
    lines = ["| scene | reference mean | original mean | round-trip mean | error vs reference | error vs original "
             "| pixel rel. RMSE | USD alone vs original | convert s (to USD + to XML) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"| {r['scene']} | {_mean(r, 'mean_reference')} | {r['status']} | - | - | - | - | - | - |")
            continue
        rmse = r.get("pixel_rel_rmse_vs_original")
        lines.append(
            f"| {r['scene']} | {_mean(r, 'mean_reference')} | {_mean(r, 'mean_original')} | "
            f"{_mean(r, 'mean_round_trip')} | "
            f"{_pct(r.get('round_trip_vs_reference'), r.get('se_round_trip_vs_reference'))} | "
            f"{_pct(r.get('round_trip_vs_original'), r.get('se_round_trip_vs_original'))} | "
            f"{'-' if rmse is None else f'{rmse:.3f}'} | "
            f"{_pct(r.get('usd_alone_vs_original'), r.get('se_usd_alone_vs_original'))} | {r['seconds_to_usd']:.2f} + {r['seconds_to_xml']:.2f} |")
    return "\n".join(lines)


def contact_sheet(rows: list[dict], path: Path) -> None:
    """Seed-0 renders, scene by scene: original | round trip | USD alone (each scene tone-mapped with its
    original's 99.5th percentile), two scenes a row, for a person to look at."""
    from usdrelight.relight.contact_sheet import write_contact_sheet

    panels = []
    for r in (r for r in rows if "_images" in r):
        ref = r["_images"][0]
        name = r["scene"].replace("corpus/", "")[:28]
        panels += [(f"{name}\n{what}" if j == 0 else f"\n{what}", img, ref)
                   for j, (what, img) in enumerate(zip(("original", "round trip", "USD alone"), r["_images"]))]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_contact_sheet(path, panels, panels[0][2], columns=6, fontsize=6)


def main_bench(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--seeds", type=int, default=4, help="renders per image (seeds 0 .. N-1) for mean +- s.e.")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--corpus", action=argparse.BooleanOptionalAction, default=True,
                    help="also our own scenes in tests/data/mitsuba_corpus (default on)")
    ap.add_argument("--noise", action="store_true", help="seed spread of the dielectric + point light scene")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "interchange.json")
    ap.add_argument("--contact-sheet", type=Path, default=None,
                    help="PNG of every scene's seed-0 renders: original | round trip | USD alone")
    args = ap.parse_args(argv)
    mi = load_mitsuba()
    mi.set_log_level(mi.LogLevel.Error)  # e.g. the stratified sampler rounding 128 spp to 144, on stdout
    rows, noise = [], None
    with tempfile.TemporaryDirectory() as td:
        jobs = []
        for scene in sorted(args.data.glob("tests/scenes/*/test_*.xml")):
            jobs.append((scene, _reference(scene), scene.stem, [args.data]))
        variant = dielectric_variant(Path(td))
        if variant is not None:
            jobs.append((variant, None, "bsdf_spheres with dielectric spheres + point light (issue 15)",
                         [args.data, variant.parent]))
        if args.corpus:
            jobs += [(s, None, f"corpus/{s.stem}", [CORPUS]) for s in sorted(CORPUS.glob("*.xml"))]
        for i, (scene, ref, label, allow) in enumerate(jobs):
            work = Path(td) / f"job{i}"
            work.mkdir()
            row = measure(scene, work, args.spp, args.seeds, ref, label, allow)
            rows.append(row)
            if row["status"] != "ok" and label == scene.stem:
                dst = work / "variant" / scene.parent.name
                if _copy_without_missing_envmaps(scene.parent, dst):
                    rows.append(measure(dst / scene.name, work, args.spp, args.seeds, None,
                                        scene.stem + " (missing envmap removed)", [args.data]))
            print(f"{label}: {row['status']}", file=sys.stderr, flush=True)
        if args.noise and variant is not None:
            noise = noise_study(variant)
    if args.contact_sheet is not None:
        contact_sheet(rows, args.contact_sheet)
    for r in rows:
        r.pop("_images", None)
    doc = {"spp": args.spp, "seeds": args.seeds, "data": str(args.data), "scenes": rows,
           "note": "means over seeds 0..seeds-1 (+- standard error); errors are relative errors of image means "
                   "(+- the standard error of the paired per-seed differences); pixel_rel_rmse = "
                   "sqrt(mean((b - a)^2)) / mean(a) of the seed-0 renders"}
    if noise is not None:
        doc["noise"] = {"scene": "bsdf_spheres with dielectric spheres + point light (issue 15)", "rows": noise}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(table(rows))
    if noise is not None:
        print("\n| spp | mean | rel. std of one render | difference between two seeds (min .. max) |")
        print("|---|---|---|---|")
        for n in noise:
            print(f"| {n['spp']} | {n['mean']:.5f} | {100 * n['rel_std_of_one_render']:.1f}% | "
                  f"{_pct(n['other_seed_difference_min'])} .. {_pct(n['other_seed_difference_max'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
