"""How well the rate controller's rate curves interpolate between the probe's QPs.

Fits a :class:`~gscodec_shac.codec.rate_control.RateController` on a scene, then codes its probe at more
QPs (every QP attribute at each of ``--qps``, the water-filled SH features each at its own QP for that
base QP) and compares what curves through the fitted probe's points alone predict there with what
was coded: for the QP attributes the mean absolute log error and the sum of predicted over coded bytes,
for the SH features (each on its own curve) the sum of predicted over coded bytes and the mean absolute
error per byte. Curves: PCHIP in log (the controller's), straight segments in log, Akima and a natural
cubic spline in log (docs/rate_control.md, "Controller version 16"). Writes the table as JSON.

    python scripts/rate_curve_check.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --out curves.json
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gscodec_shac.codec.rate_control import QP_ATTRIBUTES, RateController, _interpolate_log, make_target  # noqa: E402
from gscodec_shac.io.cameras import load_cameras  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402

Curve = Callable[[list[int], np.ndarray, np.ndarray], np.ndarray]
#: Base QPs the probe is coded at beyond its own (6, 18, 30, 42).
DEFAULT_QPS = (3, 10, 14, 22, 26, 34, 38)


def curves() -> dict[str, Curve]:
    from scipy.interpolate import Akima1DInterpolator, CubicSpline

    return {
        "pchip (used)": _interpolate_log,
        "straight segments": partial(_interpolate_log, inner=lambda xs, logs, g: np.interp(g, xs, logs)),
        "akima": partial(_interpolate_log, inner=lambda xs, logs, g: Akima1DInterpolator(xs, logs)(g)),
        "natural cubic spline": partial(_interpolate_log,
                                        inner=lambda xs, logs, g: CubicSpline(xs, logs, bc_type="natural")(g)),
    }


def coded_points(controller: RateController, qps: tuple[int, ...]) -> tuple[dict, dict, dict, dict]:
    """The fitted probe's points and the points after coding the probe at ``qps`` (QP attributes, SH features)."""
    fitted = {name: dict(points) for name, points in controller._probe_rates.items()}
    fitted_sh = {feature: dict(points) for feature, points in controller._sh_points.items()}
    start = controller._first_plan(make_target(controller.cloud.num_gaussians, bpg=100))
    for qp in qps:
        settings = {**start.settings, **{name: qp for name in QP_ATTRIBUTES if name in start.settings}}
        controller._probe_at(controller._predict(settings))
    return fitted, fitted_sh, controller._probe_rates, controller._sh_points


def _compare(curve: Curve, fitted: dict[int, float], coded: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
    new = sorted(q for q in coded if q not in fitted)
    known = sorted(fitted)
    return curve(known, np.array([fitted[q] for q in known]), np.array(new)), np.array([coded[q] for q in new])


def measure(controller: RateController, qps: tuple[int, ...] = DEFAULT_QPS) -> dict[str, dict[str, float]]:
    """Per curve: the QP attributes' mean absolute log error and sum ratio, the SH features' sum ratio and
    mean absolute error per coded byte (predicted from the fitted points, against the bytes coded)."""
    fitted, fitted_sh, rates, sh_points = coded_points(controller, qps)
    out = {}
    for label, curve in curves().items():
        errors, predicted, coded = [], 0.0, 0.0
        for name, points in rates.items():
            if name == "sh" and controller._waterfilled:
                continue  # the features' own curves below
            p, c = _compare(curve, fitted[name], points)
            errors += list(np.abs(np.log(p / c)))
            predicted, coded = predicted + p.sum(), coded + c.sum()
        row = {"qp_attributes_mean_abs_log_error": float(np.mean(errors)), "qp_attributes_sum_ratio": predicted / coded}
        p_sum = c_sum = abs_sum = 0.0
        for feature, points in sh_points.items():
            if feature < 0 or len(fitted_sh.get(feature, {})) < 2:
                continue
            p, c = _compare(curve, fitted_sh[feature], points)
            p_sum, c_sum, abs_sum = p_sum + p.sum(), c_sum + c.sum(), abs_sum + np.abs(p - c).sum()
        if c_sum:
            row |= {"sh_features_sum_ratio": p_sum / c_sum, "sh_features_abs_error_per_byte": abs_sum / c_sum}
        out[label] = row
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ply")
    parser.add_argument("--cameras", help="the scene's cameras (else orbit views)")
    parser.add_argument("--background", default="0,0,0", help="R,G,B in [0, 1]")
    parser.add_argument("--out", type=Path, help="write the table here as JSON")
    args = parser.parse_args(argv)
    cloud, _ = read_model(args.ply)
    views = load_cameras(args.cameras) if args.cameras else None
    background = tuple(float(v) for v in args.background.split(","))
    controller = RateController(cloud, views=views, background=background).fit()
    if controller._probe_rows.size >= cloud.num_gaussians:
        parser.error(f"the probe is the whole cloud ({cloud.num_gaussians:,} Gaussians): its curves are never "
                     "interpolated; give a scene of more than 20,000 Gaussians")
    table = measure(controller)
    for label, row in table.items():
        print(f"{label:22s} " + "  ".join(f"{key} {value:.3f}" for key, value in row.items()))
    if args.out:
        args.out.write_text(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
