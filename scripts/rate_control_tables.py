"""Tables of docs/rate_control.md from an RD sweep's results (``sweeps/rate_control.yaml``).

Per scene and quality measure (PSNR against the photos, ``psnr_gt``; against the
uncompressed model, ``psnr_ref``):

* **BD-rates against the baseline** over the quality range both curves cover (PCHIP,
  :mod:`gscodec_shac.rd.bd`), for every other curve method, and of SHAC-auto against the
  same controller without an SH stage (``shac-auto-nosh``): the SH stage's own gain;
* **our size at an anchor's quality**: for SPZ and SOG (one point each), the size of
  each of our curves at the anchor's quality (log-size interpolated linearly in PSNR
  between the two curve points around it), as a ratio to the anchor's size, with the
  Gaussians those two points kept (``n_decoded``: what the pruning left); ``-`` when
  the anchor's quality is outside the curve;
* per curve, the median encode seconds and the real encodes its rate-controlled targets took (with
  how many of those targets left the importance tiers for one grid: controller version 23).

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
#: extra BD-rates: method -> the curve it is measured against
PAIRS = {"shac-auto": "shac-auto-nosh"}


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


def size_at(points: list[tuple[float, dict]], metric: str, quality: float) -> tuple[float, list[dict]] | None:
    """The curve's size at ``quality`` (log-size linear in PSNR between the bracketing points) and
    those two points' rows."""
    pts = [(q, b, r) for b, r in points if math.isfinite(q := _num(r.get(metric)))]
    for (q0, b0, r0), (q1, b1, r1) in zip(pts, pts[1:]):
        lo, hi = sorted((q0, q1))
        if lo <= quality <= hi and q1 != q0:
            t = (quality - q0) / (q1 - q0)
            return float(np.exp(np.log(b0) + t * (np.log(b1) - np.log(b0)))), [r0, r1]
    return None


def kept(rows: list[dict]) -> str:
    """The Gaussians the rows' decoded models have: ``45,000`` or ``45,000-60,000``."""
    counts = sorted({int(_num(r.get("n_decoded"))) for r in rows if math.isfinite(_num(r.get("n_decoded")))})
    if not counts:
        return "?"
    return f"{counts[0]:,}" if len(counts) == 1 else f"{counts[0]:,}-{counts[-1]:,}"


def bd_cell(anchor: list[tuple[float, dict]], points: list[tuple[float, dict]], metric: str) -> str:
    """BD-rate of ``points`` against ``anchor`` on ``metric`` as a table cell."""
    result = bd_rate([b for b, _ in anchor], [_num(r.get(metric)) for _, r in anchor],
                     [b for b, _ in points], [_num(r.get(metric)) for _, r in points])
    return f"{result.value:+.1f}%" if result.ok else f"n/a ({result.reason})"


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
                missing = method == BASELINE or BASELINE not in methods
                cells.append("-" if missing else bd_cell(methods[BASELINE], pts, metric))
            lines.append(f"| {method} | {len(pts)} | {min(bpg):.0f}-{max(bpg):.0f} | " + " | ".join(cells) + " |")
        lines.append("")
        for method, anchor in PAIRS.items():
            if method in methods and anchor in methods:
                lines += [f"{method} against {anchor} (the SH stage's own gain): BD-rate "
                          + ", ".join(f"{bd_cell(methods[anchor], methods[method], m)} ({v})" for m, v in METRICS.items()),
                          ""]
        times = {m: np.median([_num(r.get("encode_s")) for _, r in pts]) for m, pts in methods.items()}
        lines += ["Encode seconds (median over the curve's points; on a shared 2-core machine): "
                  + ", ".join(f"{m} {t:.1f}" for m, t in times.items()), ""]
        counted = {m: encodes([r for _, r in pts]) for m, pts in methods.items()}
        counted = {m: c for m, c in counted.items() if c is not None}
        if counted:
            lines += ["Rate-control encodes over the curve's targets (in brackets: targets whose tiered file fell "
                      "short and were searched again in one grid, controller version 23): "
                      + ", ".join(f"{m} {total} ({fallbacks})" for m, (total, fallbacks) in counted.items()), ""]
        for anchor in ANCHORS:
            if anchor not in methods:
                continue
            size, row = methods[anchor][0]
            head = (f"At {anchor.upper()}'s quality ({8 * size / n:.1f} bits/G; "
                    + ", ".join(f"{_num(row.get(m)):.2f} dB {v}" for m, v in METRICS.items()) + ")")
            lines += [head + ": our size / its size (Gaussians kept by the two points around it)", "",
                      "| method | " + " | ".join(METRICS.values()) + " |", "|---|" + "---|" * len(METRICS)]
            for method in curve_methods:
                cells = []
                for metric in METRICS:
                    found = size_at(methods[method], metric, _num(row.get(metric)))
                    cells.append(f"{found[0] / size:.2f}x ({8 * found[0] / n:.1f} bits/G; {kept(found[1])})"
                                 if found else "-")
                lines.append(f"| {method} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def encodes(rows: list[dict]) -> tuple[int, int] | None:
    """The real encodes a curve's rate-controlled rows took, summed, and how many of its targets went on in
    one grid after a tiered encode (a tiered trial followed by a one-grid one); None for a curve without
    rate control."""
    outcomes = [(row.get("extra") or {}).get("rate_control") for row in rows]
    outcomes = [outcome for outcome in outcomes if isinstance(outcome, dict) and "encodes" in outcome]
    if not outcomes:
        return None
    fallbacks = 0
    for outcome in outcomes:
        kinds = [bool(trial.get("tiered")) for trial in outcome.get("trials", [])]
        fallbacks += any(first and not second for first, second in zip(kinds, kinds[1:]))
    return sum(int(outcome["encodes"]) for outcome in outcomes), fallbacks


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
