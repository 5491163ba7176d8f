"""What a Gaussian left by each of the rate controller's pruning choices costs, per attribute.

Codes the whole cloud and, for each pruning choice of :class:`~gscodec_shac.codec.rate_control.RateController`
(opacity thresholds, importance shares) the Gaussians kept, and a random subset of as many, all at
the same QPs of the SHAC-auto template; prints each QP attribute's bytes per kept Gaussian over the
whole cloud's per Gaussian (the factor version 14 measures on the probe, docs/rate_control.md
"Controller version 14") and writes the rows as JSON.

    python scripts/prune_cost.py ../outputs/train/chair_train_l3_d45/point_cloud.ply \\
        --cameras ../outputs/train/chair_train_l3_d45/cameras_test.json --out prune_cost.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gscodec_shac.codec.encoder import Encoder  # noqa: E402
from gscodec_shac.codec.rate_control import QP_ATTRIBUTES, RateController, _model_sizes, fitted_stage  # noqa: E402
from gscodec_shac.gaussians import GaussianCloud  # noqa: E402
from gscodec_shac.io.cameras import load_cameras  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402

#: The QPs every attribute is coded at (the chair's 55 bits/G plan of version 13, after its probe).
DEFAULT_QPS = "opacity=11,rotation=16,scale=9,sh_dc=16,sh=25"


def parse_qps(text: str) -> dict[str, int]:
    """``name=QP,...`` over the controller's QP attributes (every one must be given)."""
    try:
        qps = {name.strip(): int(value) for name, value in (item.split("=") for item in text.split(","))}
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected NAME=QP pairs, got {text!r}") from exc
    if set(qps) != set(QP_ATTRIBUTES) or not all(0 <= q <= 51 for q in qps.values()):
        raise argparse.ArgumentTypeError(f"give a QP 0-51 for each of {', '.join(QP_ATTRIBUTES)}")
    return qps


def per_gaussian_bytes(cloud: GaussianCloud, encoder: Encoder) -> dict[str, float]:
    """Each QP attribute's bytes per Gaussian of ``cloud`` (the SH side information with the features)."""
    stream = encoder.encode(cloud)
    sizes = _model_sizes(stream)
    return {name: sizes.get(name, 0) / cloud.num_gaussians for name in QP_ATTRIBUTES if name in sizes}


def measure(cloud: GaussianCloud, views: list | None, qps: dict[str, int], seed: int = 0) -> list[dict]:
    """One row per pruning choice: the share kept, each attribute's factor, and the same for a random
    subset of as many Gaussians (what the grid's sparser sampling alone costs)."""
    controller = RateController(cloud, views=views)
    encoder = Encoder(controller._rate_point({**qps, "positions": 16}), sh_stage=fitted_stage(controller.template, cloud),
                      fit_stage=False)
    whole = per_gaussian_bytes(cloud, encoder)
    rng = np.random.default_rng(seed)
    out = []
    for settings, keep in controller._prune_candidates():
        rows = np.flatnonzero(keep)
        random_rows = np.sort(rng.choice(cloud.num_gaussians, rows.size, replace=False))
        kept, random = (per_gaussian_bytes(cloud.select(r), encoder) for r in (rows, random_rows))
        out.append({"pruning": settings, "kept": rows.size / cloud.num_gaussians,
                    "factors": {a: kept[a] / whole[a] for a in whole if whole[a] > 0},
                    "random_factors": {a: random[a] / whole[a] for a in whole if whole[a] > 0}})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ply", help="the model (any format gscodec-shac reads)")
    parser.add_argument("--cameras", help="camera file for the importance renders (default: orbit views)")
    parser.add_argument("--qps", type=parse_qps, default=parse_qps(DEFAULT_QPS), help=f"default {DEFAULT_QPS}")
    parser.add_argument("--out", help="write the rows as JSON here")
    args = parser.parse_args(argv)
    cloud, _ = read_model(args.ply)
    rows = measure(cloud, load_cameras(args.cameras) if args.cameras else None, args.qps)
    if not rows:
        print("no pruning choice applies to this model (no opacity threshold prunes 0-80%, no importance share)")
    for row in rows:
        pruning = ", ".join(f"{k} {v:g}" for k, v in row["pruning"].items())
        for label, key in (("", "factors"), ("  random, as many", "random_factors")):
            factors = "  ".join(f"{a} {f:.3f}" for a, f in row[key].items())
            print(f"{pruning + label:45s} kept {row['kept']:.3f}  {factors}")
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
