"""Importance tiers against one grid, at a size target's plan: the bytes saved at equal held-out PSNR.

Fits the rate controller (SHAC-auto) on a scene and its cameras, codes a size target and takes its
plan without tiers. That plan is coded again with every lossy QP moved together by each of
``--curve``'s steps (one grid: the curve the tiers are read against), then with each ``--tiers``
setting (the plan's QPs moved per tier, :mod:`gscodec_shac.codec.tiers`). Every file is decoded and
rendered on held-out views against the uncompressed model. A tiered file's saving is
``1 - bytes / B`` with ``B`` the one-grid size at its PSNR (log-size interpolated along the curve,
extrapolated from the nearest two points beyond its ends).

    python scripts/tier_check.py ../outputs/train/chair_train_l3_d45/point_cloud.ply \\
        --cameras ../outputs/train/chair_train_l3_d45/cameras.json \\
        --judge-cameras ../outputs/train/chair_train_l3_d45/cameras_test.json --judge-every 4 \\
        --background 1,1,1 --bpg 100 --tiers "0.5,0.5@-3,8;0.5,0.5@-4,10" --out tiers_chair100
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_speed import write_results  # noqa: E402
from plan_marginals import add_scene_arguments, check_scene_arguments, fitted_scene  # noqa: E402

from gscodec_shac.codec.rate_points import TIER_SPREADS  # noqa: E402

FIELDS = ["kind", "setting", "bytes", "psnr", "one_grid_bytes", "saving"]


def parse_tiers(text: str) -> list[tuple[tuple[float, ...], tuple[int, ...], str | None]]:
    """``"0.5,0.5@-3,8;0.3,0.7@-3,5@importance"`` -> [(shares, QP offsets, spread), ...] (a third field:
    the offsets scaled by the scene's importance, ``tiers.spread``)."""
    out = []
    for item in filter(None, (part.strip() for part in text.split(";"))):
        shares, offsets, *spread = item.split("@")
        if len(spread) > 1 or (spread and spread[0] not in TIER_SPREADS):
            raise ValueError(f"{item!r}: SHARES@OFFSETS, or SHARES@OFFSETS@SPREAD with SPREAD one of "
                             f"{', '.join(TIER_SPREADS)}")
        out.append((tuple(float(v) for v in shares.split(",")), tuple(int(v) for v in offsets.split(",")),
                    spread[0] if spread else None))
    return out


def one_grid_bytes(curve: Sequence[tuple[int, float]], psnr: float) -> float:
    """The one-grid size at ``psnr`` on ``curve`` ((bytes, PSNR) points): log-size interpolated, or
    extrapolated from the two points nearest the end it lies beyond."""
    points = sorted((q, math.log(b)) for b, q in curve)
    qs, logs = np.array([q for q, _ in points]), np.array([v for _, v in points])
    if qs[0] <= psnr <= qs[-1]:
        return float(np.exp(np.interp(psnr, qs, logs)))
    i = 0 if psnr < qs[0] else len(qs) - 2
    slope = (logs[i + 1] - logs[i]) / (qs[i + 1] - qs[i])
    return float(np.exp(logs[i] + (psnr - qs[i]) * slope))


def moved(point: Any, step: int) -> Any:
    """``point`` with every single lossy QP moved by ``step`` (within 0-51)."""
    attributes = {name: spec if spec.qp is None or isinstance(spec.qp, tuple)
                  else dataclasses.replace(spec, qp=type(spec.qp)(min(51, max(0, spec.qp + step))))
                  for name, spec in point.attributes.items()}
    return dataclasses.replace(point, attributes=attributes)


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser, "files")
    parser.add_argument("--tiers", required=True, help='tier settings "SHARES@OFFSETS[@importance];..." e.g. '
                        '"0.5,0.5@-3,8" (@importance: the offsets scaled by the scene\'s importance)')
    parser.add_argument("--curve", default="-2,-1,0,1,2", help="QP steps of the one-grid curve (default -2..2; "
                        "write --curve=-1,1 for a list that starts with a minus)")
    parser.add_argument("--out", required=True, type=Path, help="results stem: OUT.json and OUT.csv")
    args = parser.parse_args(argv)
    check_scene_arguments(parser, args)
    try:
        settings = parse_tiers(args.tiers)
        steps = [int(v) for v in args.curve.split(",") if v.strip()]
    except ValueError as exc:
        parser.error(f"--tiers / --curve: {exc}")
    if len(steps) < 2:
        parser.error("--curve needs at least two steps")

    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.codec.encoder import Encoder
    from gscodec_shac.codec.rate_points import TierSpec
    from gscodec_shac.render import Renderer

    cloud, controller, target, judges, background = fitted_scene(args)
    plan = controller._encode_to(target).plan.rate_point  # the controller's plan, one grid (its template's tiers off)
    plan = dataclasses.replace(plan, tiers=None)
    references = [Renderer(cloud).render(view, background=background).image for view in judges]

    def coded(point: Any) -> tuple[int, float]:
        encoder = Encoder(point, sh_stage=controller.stage_, fit_stage=False, importance=controller.importance_,
                          stage_features=controller._stage_features)
        stream = encoder.encode(cloud)
        renderer = Renderer(rc._decoded(stream, controller.workers))
        mse = np.mean([np.mean((renderer.render(view, background=background).image - reference) ** 2)
                       for view, reference in zip(judges, references)])
        return stream.total_bytes(), rc._psnr(float(mse))

    rows: list[dict[str, Any]] = []
    for step in steps:
        size, psnr = coded(moved(plan, step))
        rows.append({"kind": "one grid", "setting": f"{step:+d}", "bytes": size, "psnr": psnr})
        print(f"one grid {step:+d}: {size:,} bytes, {psnr:.2f} dB", flush=True)
    curve = [(row["bytes"], row["psnr"]) for row in rows]
    for shares, offsets, spread in settings:
        size, psnr = coded(dataclasses.replace(plan, tiers=TierSpec(shares, offsets, spread)))
        reference = one_grid_bytes(curve, psnr)
        label = f"{','.join(f'{v:g}' for v in shares)}@{','.join(f'{v:+d}' for v in offsets)}" + \
            (f"@{spread}" if spread else "")
        rows.append({"kind": "tiers", "setting": label, "bytes": size, "psnr": psnr,
                     "one_grid_bytes": round(reference), "saving": 1.0 - size / reference})
        print(f"tiers {label}: {size:,} bytes, {psnr:.2f} dB; one grid there {reference:,.0f}: "
              f"{100 * rows[-1]['saving']:.1f}% saved", flush=True)
    write_results(args.out, {"scene": str(args.model), "bpg": args.bpg, "size": args.size, "rows": rows}, rows, FIELDS)
    return rows


if __name__ == "__main__":
    main()
