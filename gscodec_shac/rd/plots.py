"""RD figures in the style of the paper's Fig. 4/5: quality against size, one panel per metric.

One PNG per scene (matplotlib, Agg backend): PSNR and SSIM against megabytes (or bits per
Gaussian), a row of panels against ground truth where the scene has it and a row against
the uncompressed model. Each method is one line; formats with a single operating point
(SPZ, SOG) are single markers. A dashed line marks the uncompressed model's score against
ground truth.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from gscodec_shac.rd.curves import Curve, curves, short_rate_point

X_AXES = {"mb": ("size (MB)", lambda r: float(r["bytes"]) / 1e6),
          "bpg": ("bits per input Gaussian", lambda r: float(r["bits_per_gaussian"]))}
_MARKERS = "os^Dv<>pPX*h"


def plot_scene(rows: list[dict[str, Any]], scene: str, path: str | Path, *, x_axis: str = "mb",
               anchor: str = "baseline", dpi: int = 90) -> bool:
    """Write the RD figure of ``scene``; False (nothing written) when it has no ok rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if x_axis not in X_AXES:
        raise ValueError(f"x_axis must be one of {', '.join(X_AXES)}")
    scene_curves = [c for (s, _), c in curves(rows).items() if s == scene]
    if not scene_curves:
        return False
    panel_rows = []
    if any(c.has("psnr_gt") for c in scene_curves):
        panel_rows.append(("gt", "vs ground truth"))
    if any(c.has("psnr_ref") for c in scene_curves):
        panel_rows.append(("ref", "vs uncompressed"))
    if not panel_rows:
        return False
    label, x_of = X_AXES[x_axis]
    fig, axes = plt.subplots(len(panel_rows), 2, figsize=(8.4, 3.1 * len(panel_rows)), squeeze=False)
    uncompressed = next((c.rows[0] for c in scene_curves if c.rows and c.rows[0].get("uncompressed_psnr_gt") is not None), None)
    for i, (suffix, what) in enumerate(panel_rows):
        for j, (metric, name) in enumerate((("psnr", "PSNR (dB)"), ("ssim", "SSIM"))):
            ax = axes[i][j]
            column = f"{metric}_{suffix}"
            for k, curve in enumerate(sorted(scene_curves, key=lambda c: (c.method != anchor, c.method))):
                _draw(ax, curve, column, x_of, _MARKERS[k % len(_MARKERS)], curve.method == anchor)
            if suffix == "gt" and uncompressed is not None:
                value = uncompressed.get(f"uncompressed_{metric}_gt")
                if value is not None:
                    ax.axhline(float(value), color="0.4", linestyle="--", linewidth=0.8, label="uncompressed")
            ax.set_xlabel(label)
            ax.set_ylabel(name)
            ax.set_title(f"{scene}: {name.split()[0]} {what}", fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.tick_params(labelsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(5, max(1, len(labels))), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06 + 0.02 * ((len(labels) - 1) // 5), 1, 1))
    from gscodec_shac.atomic import atomic_output

    with atomic_output(path, make_dirs=True) as handle:
        fig.savefig(handle, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")
    plt.close(fig)
    return True


def _draw(ax: Any, curve: Curve, column: str, x_of: Any, marker: str, is_anchor: bool) -> None:
    points = [(x_of(r), float(r[column]), short_rate_point(r["rate_point"])) for r in curve.rows
              if r.get(column) is not None and math.isfinite(float(r[column]))]
    if not points:
        return
    xs, ys, _ = zip(*points)
    style = {"marker": marker, "markersize": 5, "linewidth": 1.8 if is_anchor else 1.2, "label": curve.method}
    if len(points) == 1:
        ax.plot(xs, ys, linestyle="none", **style)
    else:
        ax.plot(xs, ys, **style)
