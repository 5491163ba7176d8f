"""Tables and BD-rates from sweep results (rows as written by the driver).

* :func:`curves` - one RD curve per (scene, method): sizes and qualities sorted by size.
* :func:`bd_table` - BD-rate and BD-quality of every method against the anchor method,
  per scene and quality metric (PSNR/SSIM against ground truth and against the
  uncompressed model), with :mod:`gscodec_shac.rd.bd`; plus each pair of the sweep's
  ``settings.compare`` (a method against its own anchor, e.g. SHAC-auto against the same
  controller without an SH stage).
* :func:`markdown_report` / :func:`write_report` - the Markdown tables, ``bd.json`` /
  ``bd.csv``, one RD figure per scene (:mod:`gscodec_shac.rd.plots`) and ``report.html``,
  one self-contained page with the figures, BD tables and decoded renders (:mod:`gscodec_shac.rd.html`).
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from gscodec_shac.rd.bd import bd_quality, bd_rate, opposite_sign_reason
from gscodec_shac.atomic import write_atomic, write_json
from gscodec_shac.rd.cache import DURABLE
from gscodec_shac.rd.curves import Curve, bd_label, curves, num, ordered, short_rate_point
from gscodec_shac.rd.plots import plot_scene
from gscodec_shac.rd.results import load_results

#: Quality metrics a report looks at: (column, label, unit of the BD-quality).
METRICS = (
    ("psnr_gt", "PSNR vs GT", "dB"),
    ("ssim_gt", "SSIM vs GT", ""),
    ("psnr_ref", "PSNR vs uncompressed", "dB"),
    ("ssim_ref", "SSIM vs uncompressed", ""),
)
BD_FIELDS = ("scene", "method", "anchor", "metric", "bd_rate_pct", "bd_quality", "size_change_pct", "quality_change",
             "common_points", "points", "anchor_points", "overlap_lo", "overlap_hi", "monotonic", "note")


def bd_table(rows: list[dict[str, Any]], anchor: str = "baseline",
             compare: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """BD-rate (percent) and BD-quality of every method against ``anchor``, per scene and metric, then of
    each method of ``compare`` against its own anchor (``{method: anchor}``)."""
    table = []
    all_curves = curves(rows)
    compare = compare or {}
    pairs = [(key, anchor, False) for key in all_curves]
    pairs += [(key, compare[key[1]], True) for key in all_curves if compare.get(key[1], anchor) != anchor]
    for (scene, method), against, compared in pairs:
        curve = all_curves[(scene, method)]
        base = all_curves.get((scene, against))
        if method == against or base is None or len(curve.rows) < 2:
            continue  # single operating points (SPZ, SOG) have no curve: see the RD table
        for column, _, _ in METRICS:
            if not (curve.has(column) and base.has(column)):
                continue
            args = (base.values("bytes"), base.values(column), curve.values("bytes"), curve.values(column))
            rate, quality = bd_rate(*args), bd_quality(*args)
            size_change, quality_change, common = _same_point_changes(base, curve, column)
            table.append({
                "scene": scene, "method": method, "anchor": against, "metric": column, "compared": compared,
                "bd_rate_pct": rate.value if rate.ok else None,
                "bd_quality": quality.value if quality.ok else None,
                "size_change_pct": size_change, "quality_change": quality_change, "common_points": common,
                "points": len(curve.rows), "anchor_points": len(base.rows),
                "overlap_lo": rate.overlap[0] if rate.overlap else None,
                "overlap_hi": rate.overlap[1] if rate.overlap else None,
                "monotonic": rate.monotonic and quality.monotonic,
                "note": "; ".join(
                    [f"BD-rate: {rate.reason} in quality" for _ in [0] if rate.reason]
                    + [f"BD-quality: {quality.reason} in rate" for _ in [0] if quality.reason]
                    + _hull_notes(rate)
                    + [r for r in [opposite_sign_reason(rate, quality)] if r]
                    + _narrow_overlap_notes(base, column, rate, quality)),
            })
    return table


def _hull_notes(result: Any) -> list[str]:
    """Say that BD used the monotone hulls when some point's quality did not rise with rate."""
    if result.monotonic:
        return []
    return [f"quality not increasing with rate: BD on the monotone hulls ({result.dropped} dominated "
            f"point{'s' if result.dropped != 1 else ''} left out)"]


NARROW_OVERLAP = 0.25  # an overlap below this share of the anchor's span is flagged


def _narrow_overlap_notes(base: Curve, column: str, rate: Any, quality: Any) -> list[str]:
    """Flag BD values integrated over a small part of the anchor's range (indicative only)."""
    notes = []
    checks = (("BD-rate", rate, base.values(column), "quality"),
              ("BD-quality", quality, [math.log10(b) for b in base.values("bytes") if b > 0], "rate"))
    for label, result, raw, axis in checks:
        values = [v for v in raw if math.isfinite(v)]
        span = max(values) - min(values) if len(values) > 1 else 0.0
        if result.ok and result.overlap and span > 0:
            share = (result.overlap[1] - result.overlap[0]) / span
            if share < NARROW_OVERLAP:
                notes.append(f"{label} over {share:.0%} of the anchor's {axis} range: indicative only")
    return notes


def _same_point_changes(base: Curve, curve: Curve, column: str) -> tuple[float | None, float | None, int]:
    """Mean size change (percent) and quality change at the rate points both curves have."""
    anchor = {r["rate_point"]: r for r in base.rows}
    pairs = [(anchor[r["rate_point"]], r) for r in curve.rows if r["rate_point"] in anchor]
    pairs = [(a, t) for a, t in pairs if math.isfinite(num(a.get(column))) and math.isfinite(num(t.get(column)))]
    if not pairs:
        return None, None, 0
    size = sum(num(t["bytes"]) / num(a["bytes"]) - 1.0 for a, t in pairs) / len(pairs) * 100.0
    quality = sum(num(t[column]) - num(a[column]) for a, t in pairs) / len(pairs)
    return size, quality, len(pairs)


def _fmt(value: Any, digits: int = 2) -> str:
    number = num(value)
    return f"{number:.{digits}f}" if math.isfinite(number) else "-"


def _scene_header(scene: str, rows: list[dict[str, Any]]) -> list[str]:
    ok = [r for r in rows if r.get("status") == "ok"]
    first = ok[0] if ok else (rows[0] if rows else {})
    lines = [f"## {scene}", ""]
    facts = []
    if first.get("n_gaussians"):
        facts.append(f"{int(first['n_gaussians']):,} Gaussians")
    if first.get("uncompressed_bytes"):
        facts.append(f"uncompressed PLY {int(first['uncompressed_bytes']) / 1e6:.2f} MB")
    if first.get("n_views"):
        facts.append(f"{first['n_views']} test views")
    if first.get("has_gt"):
        facts.append(f"uncompressed model vs GT: PSNR {_fmt(first.get('uncompressed_psnr_gt'))} dB, "
                     f"SSIM {_fmt(first.get('uncompressed_ssim_gt'), 4)}")
    else:
        facts.append("no ground truth: scores are against the uncompressed model's renders")
    if facts:
        lines += ["; ".join(facts) + ".", ""]
    return lines


def rd_table_markdown(rows: list[dict[str, Any]]) -> list[str]:
    """One Markdown table of the ok rows of one scene (method x rate point)."""
    has_gt = any(r.get("psnr_gt") is not None for r in rows)
    has_lpips = any(r.get("lpips_ref") is not None for r in rows)
    head = ["method", "rate point", "MB", "bits per input G", "G kept", "SH share"]
    if has_gt:
        head += ["PSNR gt", "SSIM gt"] + (["LPIPS gt"] if has_lpips else [])
    head += ["PSNR ref", "SSIM ref"] + (["LPIPS ref"] if has_lpips else []) + ["enc s", "dec s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        if row.get("status") != "ok":
            continue
        sizes = row.get("sizes") or {}
        sh = sum(v for k, v in sizes.items() if k in ("sh", "sh_state"))
        share = f"{100.0 * sh / row['bytes']:.0f}%" if sh and row.get("bytes") else "-"
        cells = [row["method"], short_rate_point(row["rate_point"]), _fmt(num(row["bytes"]) / 1e6, 3),
                 _fmt(row.get("bits_per_gaussian"), 1), kept_cell(row), share]
        if has_gt:
            cells += [_fmt(row.get("psnr_gt")), _fmt(row.get("ssim_gt"), 4)] + ([_fmt(row.get("lpips_gt"), 4)] if has_lpips else [])
        cells += [_fmt(row.get("psnr_ref")), _fmt(row.get("ssim_ref"), 4)] + ([_fmt(row.get("lpips_ref"), 4)] if has_lpips else [])
        cells += [_fmt(row.get("encode_s"), 1), _fmt(row.get("decode_s"), 1)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return lines


def kept_cell(row: dict[str, Any]) -> str:
    """Gaussians the decoded model has (what the pruning kept), their share of the input and the rate
    controller's pruning choice where it made one: ``45,000 (60%, keep 0.6)``."""
    kept, total = num(row.get("n_decoded")), num(row.get("n_gaussians"))
    if not math.isfinite(kept):
        return "-"
    notes = [f"{100.0 * kept / total:.0f}%"] if math.isfinite(total) and total > 0 else []
    settings = ((row.get("extra") or {}).get("rate_control") or {}).get("settings") or {}
    if num(settings.get("keep_share")) < 1.0:
        notes.append(f"keep {num(settings['keep_share']):g}")
    elif num(settings.get("min_opacity")) > 0.0:
        notes.append(f"opacity >= {num(settings['min_opacity']):g}")
    return f"{kept:,.0f}" + (f" ({', '.join(notes)})" if notes else "")


def bd_markdown(table: list[dict[str, Any]], scene: str) -> list[str]:
    """BD-rate / BD-quality of one scene as a Markdown table (one row per method and metric)."""
    entries = [e for e in table if e["scene"] == scene]
    if not entries:
        return []
    labels = {m: label for m, label, _ in METRICS}
    against = ordered(f"against `{e['anchor']}`" if not e.get("compared") else f"of `{e['method']}` against `{e['anchor']}`"
                      for e in sorted(entries, key=lambda x: bool(x.get("compared"))))
    lines = ["BD " + ", ".join(against) + ": negative BD-rate = fewer bytes at equal quality (PCHIP over "
             "the overlapping interval); 'at equal rate point' = mean change over the rate points both ran at.", "",
             "| method | quality | BD-rate | BD-quality | size at equal rate point | quality at equal rate point | note |",
             "|---|---|---|---|---|---|---|"]
    order = {m: i for i, (m, _, _) in enumerate(METRICS)}
    methods = ordered(y["method"] for y in entries)
    for e in sorted(entries, key=lambda x: (bool(x.get("compared")), methods.index(x["method"]), order[x["metric"]])):
        digits = 3 if e["metric"].startswith("psnr") else 4
        unit = " dB" if e["metric"].startswith("psnr") else ""
        flag = "" if e["monotonic"] else "*"
        rate = f"{e['bd_rate_pct']:+.1f}%{flag}" if e["bd_rate_pct"] is not None else "n/a"
        quality = f"{e['bd_quality']:+.{digits}f}{unit}{flag}" if e["bd_quality"] is not None else "n/a"
        size = f"{e['size_change_pct']:+.1f}%" if e.get("size_change_pct") is not None else "-"
        same = f"{e['quality_change']:+.{digits}f}{unit}" if e.get("quality_change") is not None else "-"
        lines.append(f"| {bd_label(e)} | {labels[e['metric']]} | {rate} | {quality} | {size} | {same} | {e['note']} |")
    if any(not e["monotonic"] for e in entries):
        lines += ["", "\\* a curve whose quality does not increase with rate everywhere: BD is computed on the "
                  "monotone hulls (each curve without its dominated points, see the note)."]
    return lines


def markdown_report(rows: list[dict[str, Any]], table: list[dict[str, Any]], title: str = "RD results",
                    figures: dict[str, str] | None = None) -> str:
    """The whole report: per scene its facts, RD table, BD table, figure and unfinished runs."""
    lines = [f"# {title}", ""]
    for scene in ordered(r["scene"] for r in rows):
        scene_rows = [r for r in rows if r["scene"] == scene]
        lines += _scene_header(scene, scene_rows)
        lines += rd_table_markdown(scene_rows) + [""]
        bd = bd_markdown(table, scene)
        if bd:
            lines += bd + [""]
        if figures and scene in figures:
            lines += [f"![RD curves, {scene}]({figures[scene]})", ""]
        unfinished = [r for r in scene_rows if r.get("status") != "ok"]
        if unfinished:
            lines += ["Runs without numbers:", ""]
            lines += [f"- {r['method']} @ {short_rate_point(r['rate_point'])}: {r['status']}: {r.get('error') or ''}"
                      for r in unfinished]
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def bd_csv(table: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=BD_FIELDS, lineterminator="\n")
    writer.writeheader()
    for entry in table:
        writer.writerow({k: ("" if entry.get(k) is None else entry.get(k)) for k in BD_FIELDS})
    return buffer.getvalue()


def write_report(
    results: str | Path, out: str | Path | None = None, *, anchor: str | None = None, x_axis: str = "mb",
    title: str | None = None, figure_prefix: str = "rd_",
) -> dict[str, Path]:
    """Tables, BD-rates and plots of a results folder; returns the written paths by kind."""
    import json


    results = Path(results)
    rows = load_results(results)
    folder = results if results.is_dir() else results.parent
    out_dir = Path(out) if out is not None else folder / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    sweep_info: dict[str, Any] = {}
    if (folder / "sweep.json").is_file():
        sweep_info = json.loads((folder / "sweep.json").read_text())
    anchor = anchor or (sweep_info.get("settings") or {}).get("anchor") or "baseline"
    table = bd_table(rows, anchor, (sweep_info.get("settings") or {}).get("compare"))
    written: dict[str, Path] = {}
    figures: dict[str, str] = {}
    for scene in ordered(r["scene"] for r in rows):
        path = out_dir / f"{figure_prefix}{scene}.png"
        if plot_scene(rows, scene, path, x_axis=x_axis, anchor=anchor):
            figures[scene] = path.name
            written[f"figure:{scene}"] = path
    name = title or f"RD results: {sweep_info.get('name', folder.name)}"
    written["markdown"] = write_atomic(out_dir / "report.md", markdown_report(rows, table, name, figures), **DURABLE)
    written["bd_json"] = write_json(out_dir / "bd.json", table, **DURABLE)
    written["bd_csv"] = write_atomic(out_dir / "bd.csv", bd_csv(table), **DURABLE)
    from gscodec_shac.rd.html import html_report

    page = html_report(rows, table, folder, name, {s: out_dir / f for s, f in figures.items()},
                       {m: label for m, label, _ in METRICS})
    written["html"] = write_atomic(out_dir / "report.html", page, **DURABLE)
    return written
