"""Another SH stage at a size target's plan: the same QPs, the same pruning, the SH coded otherwise.

Fits the rate controller (SHAC-auto) on a scene and its cameras and codes a size target. Then it
codes the target's plan, with its SH features' base QP moved by ``--sh-offsets`` (a short RD curve
through the plan), once with the template's SH stage and once per ``--stage`` variant, every file by
a fresh :class:`~gscodec_shac.codec.encoder.Encoder` with the controller's importance (the same
Gaussians kept) and, where the stage takes one, the controller's view metric (``--no-view-metric``:
none, every stage in the paper's metric). Each file is judged on
held-out views against the uncompressed model; each variant's BD-rate against the template's curve
says what the stage would buy at that plan, with its side information (the ``sh_state`` chunk)
counted. Made for the spatial bases of ``pca-spatial`` (docs/ablations.md, "Spatially varying bases",
"At the rate controller's plans").

    python scripts/sh_stage_at_plan.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8 --bpg 100 \\
        --stage pca-spatial:spatial_clusters=2,side_dtype=float16 \\
        --stage pca-spatial:spatial_clusters=4,side_dtype=float16 --out sh_stage_bonsai100
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_speed import write_results  # noqa: E402
from plan_marginals import (add_scene_arguments, check_scene_arguments, codec_options,  # noqa: E402
                            fitted_scene)

FIELDS = ["stage", "params", "sh_offset", "sh", "bytes", "sh_state_bytes", "judges_psnr"]


def stage_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME[:KEY=VALUE,...]`` -> (stage name, parameters; values read as YAML scalars)."""
    name, _, rest = text.partition(":")
    if not name:
        raise ValueError(f"{text!r} names no SH stage")
    return name, codec_options(rest) if rest else {}


def bd_against(anchor: Sequence[dict[str, Any]], rows: Sequence[dict[str, Any]]) -> float:
    """BD-rate (%) of ``rows`` against ``anchor`` (bytes against held-out PSNR); NaN where they do not overlap."""
    from gscodec_shac.rd.bd import bd_rate

    def curve(points: Sequence[dict[str, Any]]) -> tuple[list[float], list[float]]:
        ordered = sorted(points, key=lambda r: r["bytes"])
        return [r["bytes"] for r in ordered], [r["judges_psnr"] for r in ordered]

    return float(bd_rate(*curve(anchor), *curve(rows)).value)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser, "files")
    parser.add_argument("--stage", action="append", default=[], metavar="NAME[:KEY=VALUE,...]",
                        help="an SH stage to code the plan with (repeatable), e.g. pca-spatial:spatial_clusters=4")
    parser.add_argument("--sh-offsets", default="-1.5,0,1.5",
                        help="the SH features' base QP around the plan's, comma-separated "
                        "(give it as --sh-offsets=-2,0,2)")
    parser.add_argument("--no-view-metric", action="store_true",
                        help="fit every stage in the paper's metric, not the cameras' view metric")
    parser.add_argument("--out", required=True, type=Path, help="results stem: OUT.json and OUT.csv")
    args = parser.parse_args(argv)
    check_scene_arguments(parser, args)
    try:
        variants = [stage_variant(text) for text in args.stage]
        offsets = [float(v) for v in args.sh_offsets.split(",")]
    except ValueError as exc:
        parser.error(str(exc))
    if not variants or len(offsets) < 2:
        parser.error("give at least one --stage and two --sh-offsets")

    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.codec.encoder import Encoder
    from gscodec_shac.render import Renderer
    from gscodec_shac.shac.view_metric import metric_applies

    cloud, controller, target, judges, background = fitted_scene(args)
    plan = controller._encode_to(target).plan
    metric = None if args.no_view_metric else controller._sh_metric()
    references = [Renderer(cloud).render(view, background=background).image for view in judges]

    def coded(stage: str, params: dict[str, Any], offset: float) -> dict[str, Any]:
        point = plan.point_of(dict(plan.settings, sh=plan.settings["sh"] + offset))
        point = point.with_overrides(sh_stage=stage, sh_params=params)
        weighed = metric if metric_applies(stage, params) else None
        stream = Encoder(point, importance=controller.importance_, workers=controller.workers,
                         sh_metric=weighed).encode(cloud)
        renderer = Renderer(rc._decoded(stream, controller.workers))
        mse = float(np.mean([np.mean((renderer.render(view, background=background).image - reference) ** 2)
                             for view, reference in zip(judges, references)]))
        row = {"stage": stage, "params": params, "sh_offset": offset, "sh": float(plan.settings["sh"] + offset),
               "bytes": stream.total_bytes(), "sh_state_bytes": stream.sizes().get("sh_state", 0),
               "judges_psnr": rc._psnr(mse)}
        print(f"{stage} {params} SH base QP {row['sh']}: {row['bytes']:,} bytes "
              f"(sh_state {row['sh_state_bytes']:,}), {row['judges_psnr']:.3f} dB", flush=True)
        return row

    template = plan.rate_point
    anchor = [coded(template.sh_stage, dict(template.sh_params), offset) for offset in offsets]
    rows, summary = list(anchor), []
    for stage, params in variants:
        curve = [coded(stage, {**template.sh_params, **params} if stage == template.sh_stage else params, offset)
                 for offset in offsets]
        rows += curve
        summary.append({"stage": stage, "params": params, "bd_rate_percent": bd_against(anchor, curve)})
        print(f"{stage} {params}: BD-rate {summary[-1]['bd_rate_percent']:+.2f}% against "
              f"{template.sh_stage} {dict(template.sh_params)}", flush=True)
    document = {"model": str(args.model), "target": {"kind": target.kind, "value": target.value},
                "plan": dict(plan.settings), "template_stage": template.sh_stage,
                "template_params": dict(template.sh_params), "view_metric": metric is not None,
                "judges": len(judges), "rows": rows, "bd_rates": summary}
    write_results(args.out, document, [{**row, "params": str(row["params"])} for row in rows], FIELDS)
    return document


if __name__ == "__main__":
    main()
