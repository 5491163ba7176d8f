"""What is in a model: counts, SH degree, attribute ranges and the SH share of the size."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from gscodec_shac.gaussians import GaussianCloud


def describe_cloud(cloud: GaussianCloud, path: str | os.PathLike | None = None) -> dict[str, Any]:
    """A JSON-serialisable summary of ``cloud`` (and of its file, when ``path`` is given)."""
    n = cloud.num_gaussians
    params = cloud.num_parameters_per_gaussian
    sh_params = cloud.num_sh_parameters_per_gaussian
    summary: dict[str, Any] = {
        "num_gaussians": n,
        "sh_degree": cloud.sh_degree,
        "parameters_per_gaussian": params,
        "sh_parameters_per_gaussian": sh_params,
        "sh_share": sh_params / params,
        "float32_bytes_per_gaussian": 4 * params,
        "extra_properties": list(cloud.extra),
        "ranges": _ranges(cloud),
    }
    if path is not None:
        from gscodec_shac.io.models import model_bytes

        size = model_bytes(path)
        summary["file"] = str(path)
        summary["file_bytes"] = size
        summary["file_bytes_per_gaussian"] = size / n
    return summary


def format_cloud_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines for :func:`describe_cloud`'s output."""
    lines = []
    if "file" in summary:
        lines.append(f"file              {summary['file']} ({summary['file_bytes']:,} bytes)")
    degree = summary["sh_degree"]
    lines += [
        f"Gaussians         {summary['num_gaussians']:,}",
        f"SH degree         {degree} ({(degree + 1) ** 2} coefficients per channel, "
        f"{3 * ((degree + 1) ** 2 - 1)} AC values)",
        f"parameters        {summary['parameters_per_gaussian']} per Gaussian "
        f"({summary['float32_bytes_per_gaussian']} B as float32); SH {summary['sh_parameters_per_gaussian']} "
        f"= {100 * summary['sh_share']:.1f}%",
    ]
    if "file" in summary:
        extra = summary["extra_properties"]
        note = f" (incl. extra properties: {', '.join(extra)})" if extra else ""
        lines.append(f"file size         {summary['file_bytes_per_gaussian']:.1f} B per Gaussian{note}")
    lines.append("attribute ranges  min / max / mean")
    for name, (lo, hi, mean) in summary["ranges"].items():
        lines.append(f"  {name:<22} {lo:>12.5g} {hi:>12.5g} {mean:>12.5g}")
    return "\n".join(lines)


def _ranges(cloud: GaussianCloud) -> dict[str, tuple[float, float, float]]:
    columns: dict[str, np.ndarray] = {}
    for axis, label in enumerate("xyz"):
        columns[f"means.{label}"] = cloud.means[:, axis]
    for axis in range(3):
        columns[f"scales[{axis}] (log)"] = cloud.scales[:, axis]
    columns["|quat|"] = np.linalg.norm(cloud.quats, axis=1)
    columns["opacity (logit)"] = cloud.opacities
    columns["opacity (sigmoid)"] = cloud.activated_opacities()
    for c, label in enumerate("RGB"):
        columns[f"sh_dc.{label}"] = cloud.sh_dc[:, c]
    for l in range(1, cloud.sh_degree + 1):
        band = cloud.sh_rest[:, l * l - 1 : (l + 1) ** 2 - 1]
        columns[f"sh_rest degree {l}"] = band.reshape(-1)
    return {k: (float(v.min()), float(v.max()), float(v.mean())) for k, v in columns.items()}
