"""Print the markdown tables of docs/manual/relighting.md#generalisation-held-out-scene-families from
benchmarks/results/generalisation.json (written by bench_generalisation.py), so the docs quote the JSON exactly.

    python benchmarks/generalisation_tables.py [--json benchmarks/results/generalisation.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUTPUTS = ("dtilde", "ratio", "add", "neural", "render", "transfer", "residual")
KINDS = ("add", "dim", "replace", "recolour")


def psnr_table(means_per_family: dict, means_over: dict, auto_is: dict) -> list[str]:
    """PSNR per family and kind, best bold, ``auto`` with the mode it resolved to, ``auto - render``."""
    lines = ["| family | kind | D~ | `ratio` | `add` | `neural` | `render` | `transfer` | `residual` | `auto` | "
             "photo | `auto` - `render` |", "|---" * 12 + "|"]
    rows = [(f, means_per_family[f]) for f in sorted(means_per_family)] + [("**mean of families**", means_over)]
    for fam, per in rows:
        for kind in KINDS:
            r = per[kind]
            vals = {o: r[o]["psnr_db"] for o in OUTPUTS if o in r}
            best = max(vals.values())
            cells = [("**%.2f**" if v == best else "%.2f") % v if (v := vals.get(o)) is not None else "-"
                     for o in OUTPUTS]
            auto = r["auto"]["psnr_db"]
            lines.append(f"| {fam} | {kind} | " + " | ".join(cells) + f" | {auto:.2f} ({auto_is[kind]}) | "
                         f"{r['photo']['psnr_db']:.2f} | {auto - r['render']['psnr_db']:+.2f} dB |")
    return lines


def ssim_detail_table(means_over: dict) -> list[str]:
    """SSIM / detail correlation with the photo, mean of families."""
    lines = ["| kind | D~ | `ratio` | `add` | `neural` | `render` | `transfer` | `residual` | `auto` | photo |",
             "|---" * 10 + "|"]
    for kind in KINDS:
        r = means_over[kind]
        cells = [f"{r[o]['ssim']:.3f} / {r[o]['detail_photo']:.2f}" if o in r else "-"
                 for o in OUTPUTS + ("auto", "photo")]
        lines.append(f"| {kind} | " + " | ".join(cells) + " |")
    return lines


def real_photo_table(real: dict) -> list[str]:
    """Detail correlation (blacked-out %) per view, kind and output on the real photos."""
    lines = ["| view | kind | D~ | `ratio` | `add` | `neural` | `render` | `transfer` | `residual` | `auto` |",
             "|---" * 10 + "|"]
    for view in ("left", "right"):
        for kind, r in real.get(view, {}).items():
            if not isinstance(r, dict) or "auto" not in r:
                continue
            cells = [f"{r[o]['detail_photo']:.3f} ({r[o]['blacked_pct']:.2f}%)" if o in r else "-"
                     for o in OUTPUTS + ("auto",)]
            cells[-1] += f" = `{r['auto_is']}`"
            lines.append(f"| {view} | {kind} | " + " | ".join(cells) + " |")
    return lines


def tables(d: dict) -> list[str]:
    """The three tables (markdown text each) of a bench_generalisation.py JSON, as the docs quote them."""
    auto_is = {}
    for sc in d["scenes"]:
        for kind, r in sc["kinds"].items():
            auto_is.setdefault(kind, r.get("auto_is", "?"))
    real = d.get("real_photo", {})
    real = {"left": real.get("kinds", {}), "right": real.get("right", {})}  # the left view's kinds are top-level
    return ["\n".join(t) for t in (psnr_table(d["means_per_family"], d["means_over_families"], auto_is),
                                   ssim_detail_table(d["means_over_families"]), real_photo_table(real))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=HERE / "results" / "generalisation.json")
    for table in tables(json.loads(ap.parse_args().json.read_text())):
        print(table + "\n")


if __name__ == "__main__":
    main()
