"""Importance pruning against opacity pruning at a fixed rate point, and the ranking's stability.

For each keep share, two encodes at the same rate point: the ``share`` most important Gaussians
(rate point ``prune.keep_share``, :mod:`gscodec_shac.codec.importance`) and, as the comparison,
the same number of Gaussians with the highest opacity (``prune.min_opacity`` at the opacity of the
last one kept). Reported: Gaussians kept, bits per input Gaussian, PSNR of the decoded model
against the uncompressed model's renders (and against the photos with ``--images``), and the PSNR
of the pruned model before coding. Importance comes from the training cameras (every
``--test-every``-th camera in name order is held out for the PSNR) or, without cameras, from the
orbit views of :func:`importance_views`; the PSNR of orbit scenes is measured on other orbit views
(another ring offset, wider). ``--stability`` measures how the ranking moves with the render width,
``--view-counts`` how it moves with the number of views (a capture's cameras, ``importance.MAX_VIEWS`` of them at most).

    python scripts/measure_prune.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json \\
        --images ../shared/data/scenes/mipnerf360_bonsai/images --out bonsai.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gscodec_shac.camera import orbit_views, spread_views, test_split  # noqa: E402
from gscodec_shac.codec import Decoder, Encoder, load_rate_point  # noqa: E402
from gscodec_shac.codec.defaults import DEFAULT_RATE_POINT, choose_default_sh  # noqa: E402
from gscodec_shac.codec.importance import gaussian_importance, importance_views, keep_count, most_important  # noqa: E402
from gscodec_shac.io.cameras import load_cameras  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402
from gscodec_shac.metrics import load_image, psnr  # noqa: E402
from gscodec_shac.render import Renderer  # noqa: E402

SHARES = (1.0, 0.8, 0.6, 0.45, 0.3)


def renders(cloud, views) -> list[np.ndarray]:
    renderer = Renderer(cloud)
    return [renderer.render(v).image for v in views]


def mean_psnr(images, references) -> float:
    return float(np.mean([psnr(np.clip(a, 0, 1), np.clip(b, 0, 1)) for a, b in zip(images, references)]))


def scene_views(cloud, cameras: str | None, images: str | None, test_every: int, up=(0.0, 0.0, 1.0),
                n_eval: int = 12, eval_width: int = 320) -> tuple[list | None, list, list | None]:
    """(training cameras or None, evaluation views, their photos or None): every ``test_every``-th
    camera in name order held out; without cameras, orbit views (two rings, 0 and 25 degrees)."""
    if cameras:
        loaded = load_cameras(cameras, images) if images else load_cameras(cameras)
        train, test = test_split(loaded, test_every)
        gt = [load_image(c.image_path, size=(c.width, c.height)) for c in test] if images else None
        return train, test, gt
    views = orbit_views(cloud.means, n_eval, eval_width, up=up, elevations=(0.0, 25.0),
                        opacities=cloud.activated_opacities())
    return None, views, None


def record(result: dict, row: dict, images, gt) -> None:
    """Add the PSNR against the photos (when there are photos), keep and print ``row``."""
    if gt is not None:
        row["psnr_gt"] = mean_psnr(images, gt)
    result["rows"].append(row)
    print(json.dumps(row), flush=True)


def save(result: dict, out: str) -> None:
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(result, indent=2))


def rankings(cloud, view_sets: dict[int, list], key: str) -> tuple[list[dict], dict[int, np.ndarray]]:
    """The importance from each of ``view_sets`` (by a width or a count), with its CPU seconds: the rows
    ``{key: ..., "cpu_s": ...}`` and the rankings by the same keys."""
    out, ranks = [], {}
    for value, views in view_sets.items():
        tic = time.process_time()
        ranks[value] = gaussian_importance(cloud, views)
        out.append({key: value, "cpu_s": time.process_time() - tic})
    return out, ranks


def agreement(rank: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """How far ``rank`` agrees with the ``reference`` ranking: the share of the reference's most important
    half that ``rank`` also puts in its top half, and the rank correlation (Spearman)."""
    from scipy.stats import spearmanr

    n = rank.size
    best = set(most_important(reference, np.arange(n), n // 2).tolist())
    mine = set(most_important(rank, np.arange(n), n // 2).tolist())
    return {"top_half_overlap": len(best & mine) / len(best), "spearman": float(spearmanr(rank, reference).statistic)}


def pruned_psnr(cloud, rank: np.ndarray, count: int, eval_views, reference) -> float:
    """PSNR (against the uncompressed model's ``reference`` renders) of ``cloud`` pruned to the ``count``
    Gaussians ``rank`` puts first."""
    kept = cloud.select(most_important(rank, np.arange(cloud.num_gaussians), count))
    return mean_psnr(renders(kept, eval_views), reference)


def stability(cloud, views, widths: list[int], eval_views, reference) -> list[dict]:
    """Top-half overlap and rank correlation of the importance at each width with the widest, and the
    PSNR (against the uncompressed model) of the cloud pruned to its most important half by it."""
    out, ranks = rankings(cloud, {width: [v.resized(width, max(1, round(v.height * width / v.width)))
                                          for v in views] for width in widths}, "width")
    for row in out:
        rank = ranks[row["width"]]
        row.update(agreement(rank, ranks[widths[-1]]))
        row["psnr_ref_half"] = pruned_psnr(cloud, rank, cloud.num_gaussians // 2, eval_views, reference)
    return out


def view_count_stability(cloud, views, counts: list[int], eval_views, reference,
                         shares: tuple[float, ...] = (0.6, 0.45)) -> list[dict]:
    """The importance from ``count`` of ``views`` (spread evenly in name order, as :func:`importance_views`
    spreads a scene's cameras) against the importance from all of them: the top-half overlap, the rank
    correlation, and the PSNR (against the uncompressed model) of the cloud pruned to each of ``shares``."""
    counts = sorted({min(c, len(views)) for c in counts} | {len(views)})
    out, ranks = rankings(cloud, {count: spread_views(views, count) for count in counts}, "views")
    for row in out:
        rank = ranks[row["views"]]
        row.update(agreement(rank, ranks[len(views)]))
        for share in shares:
            row[f"psnr_ref_keep_{share:g}"] = pruned_psnr(cloud, rank, keep_count(cloud.num_gaussians, share),
                                                          eval_views, reference)
    return out


def scene_arguments(ap: argparse.ArgumentParser) -> None:
    """The model, its cameras and photos, the held-out split, and where the results go."""
    ap.add_argument("model")
    ap.add_argument("--cameras")
    ap.add_argument("--images")
    ap.add_argument("--test-every", type=int, default=8)
    ap.add_argument("--out", required=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    scene_arguments(ap)
    ap.add_argument("--up", default="0,0,1")
    ap.add_argument("--eval-views", type=int, default=12, help="orbit views for the PSNR without cameras")
    ap.add_argument("--eval-width", type=int, default=320)
    ap.add_argument("--shares", default=",".join(map(str, SHARES)))
    ap.add_argument("--rate-point", default=DEFAULT_RATE_POINT)
    ap.add_argument("--stability", default="", help="comma-separated widths, e.g. 50,100,200")
    ap.add_argument("--view-counts", default="", help="comma-separated numbers of importance views, e.g. 16,32,64: "
                    "each ranking against the one from every view")
    args = ap.parse_args()
    up = tuple(float(v) for v in args.up.split(","))
    cloud, _ = read_model(args.model)
    n = cloud.num_gaussians
    result: dict = {"model": args.model, "n": n, "rate_point": args.rate_point, "rows": []}
    train, eval_views, gt = scene_views(cloud, args.cameras, args.images, args.test_every, up, args.eval_views,
                                        args.eval_width)
    views = importance_views(cloud, train, up=up)
    result["importance_views"] = {"n": len(views), "width": views[0].width, "height": views[0].height}
    result["eval_views"] = {"n": len(eval_views), "width": eval_views[0].width}
    tic = time.process_time()
    importance = gaussian_importance(cloud, views)
    result["importance_cpu_s"] = time.process_time() - tic
    print(f"importance: {len(views)} views in {result['importance_cpu_s']:.1f} s CPU", flush=True)
    reference = renders(cloud, eval_views)
    if args.stability:
        result["stability"] = stability(cloud, views, [int(w) for w in args.stability.split(",")], eval_views,
                                        reference)
        print(json.dumps(result["stability"]), flush=True)
    if args.view_counts:
        result["view_counts"] = view_count_stability(cloud, views, [int(c) for c in args.view_counts.split(",")],
                                                     eval_views, reference)
        for row in result["view_counts"]:
            print(json.dumps(row), flush=True)
    if gt is not None:
        result["uncompressed_psnr_gt"] = mean_psnr(reference, gt)
    base = load_rate_point(args.rate_point)
    stage, params = choose_default_sh(cloud)  # the default encode's SH stage
    result["sh_stage"] = {"stage": stage, **params}
    opacity = np.sort(cloud.activated_opacities())[::-1]
    for share in (float(s) for s in args.shares.split(",") if s):
        count = keep_count(n, share)
        methods = {"importance": {"keep_share": share}} if share < 1 else {"none": {}}
        if share < 1:
            methods["opacity"] = {"min_opacity": max(base.min_opacity, float(opacity[count - 1]))}
        for method, prune in methods.items():
            point = dataclasses.replace(base, **prune)
            encoder = Encoder(point, sh_stage=stage, sh_params=params, importance=importance)
            tic = time.perf_counter()
            stream = encoder.encode(cloud)
            encode_s = time.perf_counter() - tic
            decoded = Decoder().decode(stream.to_bytes())
            images = renders(decoded, eval_views)
            kept = cloud.select(np.sort(encoder.order_))
            row = {"share": share, "method": method, "kept": decoded.num_gaussians, "bytes": stream.total_bytes(),
                   "bpg": 8 * stream.total_bytes() / n, "psnr_ref": mean_psnr(images, reference),
                   "psnr_ref_pruned_only": mean_psnr(renders(kept, eval_views), reference), "encode_s": encode_s,
                   **prune}
            record(result, row, images, gt)
    save(result, args.out)


if __name__ == "__main__":
    main()
