"""Tables of docs/rate_control.md from an RD sweep's results (``sweeps/rate_control.yaml``).

Per scene and quality measure (PSNR against the photos, ``psnr_gt``; against the
uncompressed model, ``psnr_ref``):

* **BD-rates against the baseline** over the quality range both curves cover (PCHIP,
  :mod:`gscodec_shac.rd.bd`), for every other curve method;
* **our size at an anchor's quality**: for SPZ and SOG (one point each), the size of
  each of our curves at the anchor's quality (log-size interpolated linearly in PSNR
  between the two curve points around it), as a ratio to the anchor's size; ``-`` when
  the anchor's quality is outside the curve.

    python scripts/rate_control_tables.py ../outputs/rd/rate_control > /tmp/tables.md
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gscodec_shac.rd.bd import bd_rate  # noqa: E402
from gscodec_shac.rd.results import load_results  # noqa: E402

METRICS = {"psnr_gt": "PSNR vs photos", "psnr_ref": "PSNR vs uncompressed"}
ANCHORS = ("spz", "sog")
BASELINE = "baseline"


def curves(rows: list[dict]) -> dict[str, dict[str, list[tuple[float, dict]]]]:
    """scene -> method -> [(bytes, row)] of the ok rows, sorted by size."""
    out: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        if row.get("status") == "ok" and _num(row.get("bytes")) > 0:
            out[row["scene"]][row["method"]].append((_num(row["bytes"]), row))
    for methods in out.values():
        for points in methods.values():
            points.sort(key=lambda p: p[0])
    return out


def size_at(points: list[tuple[float, dict]], metric: str, quality: float) -> float | None:
    """The curve's size at ``quality``: log-size linear in PSNR between the bracketing points."""
    pts = [(q, b) for b, r in points if math.isfinite(q := _num(r.get(metric)))]
    for (q0, b0), (q1, b1) in zip(pts, pts[1:]):
        lo, hi = sorted((q0, q1))
        if lo <= quality <= hi and q1 != q0:
            t = (quality - q0) / (q1 - q0)
            return float(np.exp(np.log(b0) + t * (np.log(b1) - np.log(b0))))
    return None


def tables(rows: list[dict]) -> str:
    lines = []
    for scene, methods in curves(rows).items():
        n = _num(next(iter(methods.values()))[0][1].get("n_gaussians"))
        lines += [f"### {scene} ({n:,.0f} Gaussians)", ""]
        curve_methods = [m for m in methods if m not in ANCHORS]
        lines += ["| method | points | bits/G range | " + " | ".join(f"BD-rate vs baseline, {v}" for v in METRICS.values())
                  + " |", "|---|---|---|" + "---|" * len(METRICS)]
        for method in curve_methods:
            pts = methods[method]
            bpg = [8 * b / n for b, _ in pts]
            cells = []
            for metric in METRICS:
                if method == BASELINE or BASELINE not in methods:
                    cells.append("-")
                    continue
                base = methods[BASELINE]
                result = bd_rate([b for b, _ in base], [_num(r.get(metric)) for _, r in base],
                                 [b for b, _ in pts], [_num(r.get(metric)) for _, r in pts])
                cells.append(f"{result.value:+.1f}%" if result.ok else f"n/a ({result.reason})")
            lines.append(f"| {method} | {len(pts)} | {min(bpg):.0f}-{max(bpg):.0f} | " + " | ".join(cells) + " |")
        lines.append("")
        times = {m: np.median([_num(r.get("encode_s")) for _, r in pts]) for m, pts in methods.items()}
        lines += ["Encode seconds (median over the curve's points; on a shared 2-core machine): "
                  + ", ".join(f"{m} {t:.1f}" for m, t in times.items()), ""]
        for anchor in ANCHORS:
            if anchor not in methods:
                continue
            size, row = methods[anchor][0]
            head = (f"At {anchor.upper()}'s quality ({8 * size / n:.1f} bits/G; "
                    + ", ".join(f"{_num(row.get(m)):.2f} dB {v}" for m, v in METRICS.items()) + ")")
            lines += [head + ": our size / its size", "",
                      "| method | " + " | ".join(METRICS.values()) + " |", "|---|" + "---|" * len(METRICS)]
            for method in curve_methods:
                cells = []
                for metric in METRICS:
                    ours = size_at(methods[method], metric, _num(row.get(metric)))
                    cells.append(f"{ours / size:.2f}x ({8 * ours / n:.1f} bits/G)" if ours else "-")
                lines.append(f"| {method} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def _num(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="the sweep's output folder (holds results.json)")
    args = parser.parse_args()
    print(tables(load_results(args.results)))


if __name__ == "__main__":
    main()
