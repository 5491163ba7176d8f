"""One self-contained HTML page of an RD sweep: plots, BD table and decoded renders to compare.

Per scene: the RD figure, the BD table (the numbers of :func:`gscodec_shac.rd.report.bd_table`)
and, for each method at up to three rate points (lowest, middle, highest size), its decoded
render of the first test view next to the uncompressed model's render and the ground truth,
with a slider that wipes between decoded and uncompressed. Every image is embedded as a
``data:`` URI and the script and style are inline, so the file can be mailed or opened
offline. The renders come from :mod:`gscodec_shac.rd.renders`.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path
from typing import Any

from gscodec_shac.rd.curves import num, ordered, short_rate_point
from gscodec_shac.rd.renders import reference_paths, run_render_path
from gscodec_shac.rd.report import bd_label

#: Rate points shown per method: the lowest, middle and highest size.
SHOWN_POINTS = 3

STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;max-width:1400px}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #bbb;padding:.2em .5em;text-align:right}
th{background:#eee}td.l{text-align:left}.worse{color:#a40000}.better{color:#006400}
.rd{max-width:100%}.row{display:flex;gap:1em;flex-wrap:wrap;align-items:flex-start;margin:.5em 0 1.2em}
figure{margin:0;width:360px}figcaption{font-size:.85em;color:#555}
img.shot{width:360px;height:auto;image-rendering:pixelated;display:block}
.wipe{position:relative;display:inline-block;line-height:0}
.wipe .top{position:absolute;top:0;left:0;clip-path:inset(0 50% 0 0)}
.wipe input{width:100%}
"""

SCRIPT = """
function wipe(slider){const top=slider.parentNode.querySelector('.top');
top.style.clipPath='inset(0 '+(100-slider.value)+'% 0 0)';}
window.addEventListener('load',()=>{const images=[...document.images];
const decoded=images.filter(i=>i.complete&&i.naturalWidth>0).length;
document.body.dataset.images=decoded+'/'+images.length;});
"""


def data_uri(path: Path) -> str | None:
    """The PNG at ``path`` as a ``data:image/png;base64,...`` URI, or None when absent."""
    if not path.is_file():
        return None
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _img(uri: str, alt: str, extra: str = "") -> str:
    return f'<img src="{uri}" alt="{html.escape(alt)}"{extra}>'


def _figure(uri: str | None, caption: str) -> str:
    if uri is None:
        return ""
    return "<figure>" + _img(uri, caption, ' class="shot"') + f"<figcaption>{html.escape(caption)}</figcaption></figure>"


def _signed(value: Any, unit: str, digits: int) -> tuple[str, str]:
    """Text and CSS class (better/worse) of a BD value; ``unit`` '%' is a rate (negative is better)."""
    number = num(value)
    if not math.isfinite(number):
        return "n/a", ""
    good = number < 0 if unit == "%" else number > 0
    return f"{number:+.{digits}f}{unit}", ("better" if good else "worse") if number else ""


def bd_html(table: list[dict[str, Any]], scene: str, labels: dict[str, str]) -> str:
    """The BD table of one scene (one row per method and quality metric; ``labels``: metric names)."""
    entries = [e for e in table if e["scene"] == scene]
    if not entries:
        return "<p>No BD values: fewer than two methods with curves.</p>"
    anchor = next((e["anchor"] for e in entries if not e.get("compared")), entries[0]["anchor"])
    lines = [f"<p>BD against <b>{html.escape(anchor)}</b> (rows 'A vs B': A against B): negative BD-rate = fewer bytes at equal "
             "quality, positive BD-quality = better quality at equal size.</p>",
             '<table class="bd"><tr><th>method</th><th>quality</th><th>BD-rate</th><th>BD-quality</th>'
             "<th>note</th></tr>"]
    for e in entries:
        name = bd_label(e)
        psnr = e["metric"].startswith("psnr")
        rate, rate_class = _signed(e.get("bd_rate_pct"), "%", 1)
        quality, quality_class = _signed(e.get("bd_quality"), " dB" if psnr else "", 3 if psnr else 4)
        lines.append(f'<tr><td class="l">{html.escape(name)}</td><td class="l">{labels.get(e["metric"], e["metric"])}'
                     f'</td><td class="{rate_class}">{rate}</td><td class="{quality_class}">{quality}</td>'
                     f'<td class="l">{html.escape(e.get("note") or "")}</td></tr>')
    return "\n".join(lines + ["</table>"])


def _shown_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Up to :data:`SHOWN_POINTS` ok rows spread over the size range (lowest, middle, highest)."""
    ok = sorted((r for r in rows if r.get("status") == "ok"), key=lambda r: num(r.get("bytes")))
    if len(ok) <= SHOWN_POINTS:
        return ok
    picks = sorted({round(i * (len(ok) - 1) / (SHOWN_POINTS - 1)) for i in range(SHOWN_POINTS)})
    return [ok[i] for i in picks]


def comparison_html(folder: Path, scene: str, rows: list[dict[str, Any]]) -> str:
    """Per method and shown rate point: decoded (wipe slider over uncompressed), uncompressed, ground truth."""
    uncompressed_path, truth_path = reference_paths(folder, scene)
    uncompressed, truth = data_uri(uncompressed_path), data_uri(truth_path)
    parts = []
    for method in ordered(r["method"] for r in rows):
        blocks = []
        for row in _shown_rows([r for r in rows if r["method"] == method]):
            decoded = data_uri(run_render_path(folder, scene, method, row["rate_point"]))
            if decoded is None:
                continue
            point = short_rate_point(row["rate_point"])
            psnr = num(row.get("psnr_ref"))
            caption = (f"{method} @ {point}: {num(row.get('bytes')) / 1e6:.3f} MB, "
                       f"{num(row.get('bits_per_gaussian')):.1f} bits/G"
                       + (f", PSNR vs uncompressed {psnr:.2f} dB" if math.isfinite(psnr) else ""))
            if uncompressed is not None:
                wipe = ('<div class="wipe">' + _img(uncompressed, "uncompressed", ' class="shot"')
                        + _img(decoded, caption, ' class="shot top"') +
                        '<input type="range" min="0" max="100" value="50" oninput="wipe(this)" '
                        'aria-label="wipe between decoded (left) and uncompressed (right)"></div>')
                blocks.append(f"<figure>{wipe}<figcaption>{html.escape(caption)}; slider: decoded left of it, "
                              "uncompressed right</figcaption></figure>")
            else:
                blocks.append(_figure(decoded, caption))
        if blocks:
            parts.append(f"<h3>{html.escape(method)}</h3><div class=\"row\">" + "".join(blocks)
                         + _figure(uncompressed, "uncompressed model") + _figure(truth, "ground truth") + "</div>")
    if not parts:
        return "<p>No decoded renders kept for this scene (a sweep run before renders were kept).</p>"
    return "\n".join(parts)


def html_report(rows: list[dict[str, Any]], table: list[dict[str, Any]], folder: str | Path, title: str,
                figures: dict[str, Path] | None = None, labels: dict[str, str] | None = None) -> str:
    """The whole page: per scene its RD figure, BD table and image comparison (``folder``: the
    sweep's output folder, holding ``renders/``; ``labels``: display names of the BD metrics)."""
    folder = Path(folder)
    body = [f"<h1>{html.escape(title)}</h1>"]
    for scene in ordered(r["scene"] for r in rows):
        scene_rows = [r for r in rows if r["scene"] == scene]
        body.append(f"<h2>{html.escape(scene)}</h2>")
        figure = data_uri(figures[scene]) if figures and scene in figures else None
        if figure is not None:
            body.append(_img(figure, f"RD curves, {scene}", ' class="rd"'))
        body.append(bd_html(table, scene, labels or {}))
        body.append("<h3>Decoded renders (first test view)</h3>")
        body.append(comparison_html(folder, scene, scene_rows))
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{STYLE}</style><script>{SCRIPT}</script></head>\n<body>\n"
            + "\n".join(body) + "\n</body></html>\n")
