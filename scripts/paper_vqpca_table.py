"""Tables, BD-rates and a figure of gsplat VQ vs VQ + SHAC-PCA (sweeps/paper_vqpca.yaml).

    python scripts/paper_vqpca_table.py ../outputs/paper-vqpca/rd_vqpca [--figure docs/figures/gsplat_pca_bonsai.png]

Reads the sweep's ``results.csv``; methods are named ``<family>-k<K>`` (families vq, vq-pca,
vq6, vq-pca6). Rows with K >= N (one codebook entry per Gaussian) are left out. Prints a
markdown table per scene (bytes, bits/Gaussian, codebook bytes, PSNR against the photos and
against the uncompressed model, size change against vq of the same K and codebook bits),
BD-rates between the families over K (PCHIP, :mod:`gscodec_shac.rd.bd`), and writes
``OUT/vqpca_table.json`` and the figure (PSNR against bits/Gaussian, one curve per family).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from pathlib import Path

from gscodec_shac.rd.bd import bd_rate

PAIRS = (("vq-pca", "vq"), ("vq-pca6", "vq6"), ("vq6", "vq"))
METRICS = (("psnr_gt", "PSNR vs photos"), ("psnr_ref", "PSNR vs uncompressed"))


def load(folder: Path) -> dict[str, list[dict]]:
    by_scene: dict[str, list[dict]] = {}
    for row in csv.DictReader(open(folder / "results.csv")):
        match = re.fullmatch(r"(.+)-k(\d+)", row["method"])
        if row["status"] != "ok" or not match:
            continue
        k, n = int(match.group(2)), int(row["n_gaussians"])
        if k >= n:
            continue
        row.update(family=match.group(1), K=k)
        by_scene.setdefault(row["scene"], []).append(row)
    return by_scene


def _f(row: dict, key: str) -> float | None:
    return float(row[key]) if row.get(key) not in (None, "") else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args(argv)
    data = load(args.folder)
    out: dict = {}
    for scene, rows in data.items():
        rows.sort(key=lambda r: (r["K"], r["family"]))
        index = {(r["family"], r["K"]): r for r in rows}
        print(f"\n### {scene}\n")
        print("| K | method | codebook bits | bytes | bits/G | codebook bytes (zlib) | PSNR vs photos | PSNR vs uncompr. | size vs vq (same bits) |")
        print("|---|---|---|---|---|---|---|---|---|")
        table = []
        for r in rows:
            bits = 6 if r["family"].endswith("6") else 8
            ref = index.get(("vq6" if bits == 6 else "vq", r["K"]))
            change = (int(r["bytes"]) / int(ref["bytes"]) - 1) * 100 if ref and ref is not r else None
            gt = _f(r, "psnr_gt")
            print(f"| {r['K']:,} | {r['family']} | {bits} | {int(r['bytes']):,} | {float(r['bits_per_gaussian']):.1f} | "
                  f"{int(r['bytes_sh_state']):,} | {'-' if gt is None else f'{gt:.3f}'} | {float(r['psnr_ref']):.2f} | "
                  f"{'-' if change is None else f'{change:+.1f}%'} |")
            table.append({"K": r["K"], "family": r["family"], "bits": bits, "bytes": int(r["bytes"]),
                          "bits_per_gaussian": float(r["bits_per_gaussian"]), "sh_state_bytes": int(r["bytes_sh_state"]),
                          "psnr_gt": gt, "psnr_ref": float(r["psnr_ref"]), "size_change_vs_vq_pct": change})
        bd = []
        for test, anchor in PAIRS:
            for metric, label in METRICS:
                a = [r for r in rows if r["family"] == anchor and _f(r, metric) is not None]
                t = [r for r in rows if r["family"] == test and _f(r, metric) is not None]
                if len(a) < 2 or len(t) < 2:
                    continue
                res = bd_rate([float(r["bytes"]) for r in a], [_f(r, metric) for r in a],
                              [float(r["bytes"]) for r in t], [_f(r, metric) for r in t])
                bd.append({"test": test, "anchor": anchor, "metric": metric, "bd_rate_pct": res.value,
                           "note": getattr(res, "reason", "") or ""})
                print(f"BD-rate {test} vs {anchor} ({label}): {res.value:+.1f}% {getattr(res, 'reason', '') or ''}")
        out[scene] = {"rows": table, "bd_rate": bd}
    (args.folder / "vqpca_table.json").write_text(json.dumps(out, indent=1))
    if args.figure:
        _figure(data, args.figure)
    return 0


def _figure(data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = [s for s in data if any(_f(r, "psnr_gt") is not None for r in data[s])]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    rows = data[scenes[0]] if scenes else []
    for ax, (metric, label) in zip(axes, METRICS):
        for family, style in (("vq", "o-"), ("vq-pca", "s-"), ("vq6", "o--"), ("vq-pca6", "s--")):
            pts = sorted((float(r["bits_per_gaussian"]), _f(r, metric)) for r in rows if r["family"] == family)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=family, markersize=4)
        ax.set_xlabel("bits per Gaussian")
        ax.set_ylabel(f"{label} (dB)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{scenes[0] if scenes else ''}: gsplat PNG codec, K = 4,096 / 16,384 / 65,536", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
