"""Is a size target's plan the best allocation on held-out views? One step of each attribute around it.

Fits the rate controller (SHAC-auto) on a scene and its cameras, codes a size target, then codes the
target's plan again with one attribute one step finer and one step coarser: a QP by one step of the
controller's choices (the SH features' base QP by two, half a QP), the positions by one bit; the
pruning and the DC-only bar stay the plan's. Each move's bytes and the rendered MSE it adds or removes
are measured on the controller's views and on held-out views (``--judge-cameras``), against the
uncompressed model, beside what the controller's models predicted for it (the models as the
target's encodes left them). ``--codec-options`` also codes the plan, at its QPs, with other x265
options (a preset, the loop filters).

With ``--judge-images`` the held-out views are judged against their photos too (``photos_*``
columns, a best exchange on the photos); ``--structure-moves`` adds the plan coded with each other
pruning choice and DC-only bar of the controller; ``--ac-gains`` renders the model and the plan's
file with their view-dependent colour (the AC SH) scaled by each gain, against the photos and the
model: whether the model itself has too little view-dependent colour for its photos, so that the
coding's shrinkage of it costs more against the photos than against the model
(docs/rate_control.md, "The chair against its photos, measured again").

At the best allocation no finer step gains more MSE per byte than the cheapest coarser step loses.
The best pair of one finer and one coarser step of two attributes, spending the bytes one saves on the
other, shows what reallocating single steps would buy, in dB at equal size (:func:`best_swap`;
docs/rate_control.md, "Is the plan the best allocation on held-out views?").

    python scripts/plan_marginals.py ../outputs/train/chair_train_l3_d45/point_cloud.ply \\
        --cameras ../outputs/train/chair_train_l3_d45/cameras.json \\
        --judge-cameras ../outputs/train/chair_train_l3_d45/cameras_test.json --judge-every 4 \\
        --background 1,1,1 --bpg 100 --codec-options preset=placebo --out plan_marginals_chair100
    python scripts/plan_marginals.py ../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply \\
        --cameras ../shared/data/scenes/bonsai_cpu_sh3/cameras.json --test-every 8 --bpg 100 \\
        --out plan_marginals_bonsai100
    python scripts/plan_marginals.py ../outputs/train/chair_train_l3_d45/point_cloud.ply \\
        --cameras ../outputs/train/chair_train_l3_d45/cameras.json \\
        --judge-cameras ../outputs/train/chair_train_l3_d45/cameras_test.json --judge-every 4 \\
        --judge-images ../shared/data/scenes/nerf_synthetic/chair/test --background 1,1,1 --bpg 104 \\
        --structure-moves --ac-gains 1.03,1.06,1.1 --out plan_marginals_chair104_photos
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

FIELDS = ["move", "attribute", "direction", "setting", "bytes", "d_bytes", "model_d_mse", "views_d_mse",
          "judges_d_mse", "views_psnr", "judges_psnr", "photos_d_mse", "photos_psnr"]


def moves(controller: Any, settings: dict[str, Any]) -> list[tuple[str, str, str, dict[str, Any]]]:
    """(label, attribute, "finer" or "coarser", settings) of one step of each attribute around ``settings``."""
    from gscodec_shac.codec.rate_control import _setting

    out = []
    for name, model in controller.models_.items():
        choices = list(model.choices)
        index = int(np.searchsorted(model.choices, settings[name]))
        step = 2 if name == "sh" else 1
        # positions: more bits is finer; a QP: a lower one is finer
        finer_delta = step if name == "positions" else -step
        for direction, delta in (("finer", finer_delta), ("coarser", -finer_delta)):
            j = index + delta
            if 0 <= j < len(choices):
                out.append((f"{name} {direction}", name, direction, {**settings, name: _setting(choices[j])}))
    return out


def structure_moves(controller: Any, settings: dict[str, Any]) -> list[tuple[str, str, str, dict[str, Any]]]:
    """(label, "prune" or "dc_only", "other", settings) of each pruning choice and DC-only bar the plan
    did not take (these choices are not ordered by fineness: each is one variant)."""
    out = []
    for name, count in (("prune", len(controller.prune_)), ("dc_only", len(controller.dc_only_))):
        for index in range(count):
            if index != settings.get(name, 0):
                label = f"{name} {index}"
                if name == "prune":
                    label += " (" + ", ".join(f"{k} {v:g}" for k, v in controller.prune_[index][0].items()) + ")"
                out.append((label, name, "other", {**settings, name: index}))
    return out


def with_ac_gain(cloud: Any, gain: float) -> Any:
    """``cloud`` with its AC SH coefficients (the view-dependent colour) multiplied by ``gain``."""
    return cloud.replace(sh_rest=cloud.sh_rest * np.float32(gain))


def best_swap(rows: Sequence[dict[str, Any]], key: str, base_mse: float) -> dict[str, Any] | None:
    """The pair (finer step of one attribute, coarser step of another) whose exchange lowers ``key``'s MSE
    most at equal bytes, or None when no pair gains.

    A finer step gains ``g = -d_mse / d_bytes`` per byte spent, a coarser one loses ``l = d_mse / -d_bytes``
    per byte saved; spending ``B = min(d_bytes_finer, -d_bytes_coarser)`` bytes (each step taken in
    proportion) removes ``(g - l) B`` of MSE, added to ``base_mse`` as the PSNR gained at equal size."""
    best = None
    finer = [r for r in rows if r["direction"] == "finer" and r["d_bytes"] > 0]
    coarser = [r for r in rows if r["direction"] == "coarser" and r["d_bytes"] < 0]
    for f in finer:
        gain = -f[key] / f["d_bytes"]
        for c in coarser:
            if c["attribute"] == f["attribute"]:
                continue
            loss = c[key] / -c["d_bytes"]
            spent = min(f["d_bytes"], -c["d_bytes"])
            removed = (gain - loss) * spent
            if removed > 0 and (best is None or removed > best["mse_removed"]):
                best = {"finer": f["move"], "coarser": c["move"], "gain_per_byte": gain, "loss_per_byte": loss,
                        "bytes_moved": spent, "mse_removed": removed,
                        "db_at_equal_size": 10 * math.log10(base_mse / max(base_mse - removed, 1e-30))}
    return best


def codec_options(text: str) -> dict[str, Any]:
    """``"preset=placebo,loop_filters=false"`` -> ``{"preset": "placebo", "loop_filters": False}`` (YAML values)."""
    import yaml

    out = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--codec-options: {item!r} is not KEY=VALUE")
        out[key.strip()] = yaml.safe_load(value)
    return out


def add_scene_arguments(parser: argparse.ArgumentParser, judged: str) -> None:
    """The model, the controller's cameras, the held-out views that judge ``judged`` and the size target."""
    parser.add_argument("model", help="a static model file (PLY, or any format the codec reads)")
    parser.add_argument("--cameras", required=True, help="the controller's cameras (its views and importance)")
    held_out = parser.add_mutually_exclusive_group(required=True)
    held_out.add_argument("--judge-cameras", help=f"held-out cameras the {judged} are judged on")
    held_out.add_argument("--test-every", type=int, help="hold out every k-th of --cameras in name order (as "
                          f"`gscodec-shac rd`): the controller gets the others, the {judged} are judged on them")
    parser.add_argument("--judge-every", type=int, default=1, help="every k-th held-out camera (default: all)")
    parser.add_argument("--judge-images", help="the held-out views' photos (a folder the camera file names them "
                        "in): judged against them too")
    parser.add_argument("--background", default="0,0,0", help="r,g,b in [0, 1] (1,1,1 for NeRF-synthetic)")
    goal = parser.add_mutually_exclusive_group(required=True)
    goal.add_argument("--bpg", type=float, help="a size target in bits per Gaussian")
    goal.add_argument("--size", help="a size target (e.g. 600kB)")


def check_scene_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.judge_every < 1 or (args.test_every is not None and args.test_every < 2):
        parser.error("--judge-every must be at least 1 and --test-every at least 2")


def fitted_scene(args: argparse.Namespace) -> tuple[Any, Any, Any, list, tuple[float, ...]]:
    """(model, the rate controller fitted on its cameras, the size target, the judging views, background)."""
    from gscodec_shac.camera import test_split
    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.models import read_model

    cloud, _ = read_model(args.model)
    background = tuple(float(v) for v in args.background.split(","))
    if args.judge_cameras:
        cameras, judges = load_cameras(args.cameras), load_cameras(args.judge_cameras, args.judge_images)
    else:  # the photos' folder names the held-out views' images (the others are never read)
        cameras, judges = test_split(load_cameras(args.cameras, args.judge_images), args.test_every)
    controller = rc.RateController(cloud, views=cameras, background=background, progress=True)
    controller.fit()
    target = rc.make_target(cloud.num_gaussians, bpg=args.bpg) if args.bpg is not None else \
        rc.make_target(cloud.num_gaussians, size=args.size)
    return cloud, controller, target, judges[:: args.judge_every], background


def judged_photos(views: Sequence[Any], background: tuple[float, ...]) -> list[np.ndarray]:
    """The photos of ``views`` at their resolution (as `gscodec-shac rd` loads them)."""
    from gscodec_shac.metrics import load_image

    missing = [view.name for view in views if view.image_path is None]
    if missing:
        raise SystemExit(f"--judge-images: no photo for camera(s) {', '.join(missing[:3])}")
    return [load_image(view.image_path, background=background, size=(view.width, view.height)) for view in views]


def mean_mse(images: Sequence[np.ndarray], references: Sequence[np.ndarray]) -> float:
    return float(np.mean([np.mean((image - reference) ** 2) for image, reference in zip(images, references)]))


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser, "moves")
    parser.add_argument("--codec-options", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                        help="code the plan again with these lossy-codec options, at its QPs (repeatable; e.g. "
                        "preset=placebo or loop_filters=false): bytes and held-out PSNR against the plan's file")
    parser.add_argument("--no-moves", action="store_true", help="only the plan and its --codec-options variants")
    parser.add_argument("--structure-moves", action="store_true",
                        help="also code the plan with each other pruning choice and DC-only bar")
    parser.add_argument("--ac-gains", default="", metavar="G[,G...]",
                        help="render the model and the plan's file with the AC SH scaled by each gain (needs --judge-images)")
    parser.add_argument("--out", required=True, type=Path, help="results stem: OUT.json and OUT.csv")
    args = parser.parse_args(argv)
    check_scene_arguments(parser, args)
    try:
        option_sets = [codec_options(text) for text in args.codec_options]
        gains = [float(g) for g in args.ac_gains.split(",") if g.strip()]
    except ValueError as exc:
        parser.error(str(exc))
    if gains and not args.judge_images:
        parser.error("--ac-gains needs --judge-images (the gains are judged against the photos)")

    from gscodec_shac.codec import rate_control as rc
    from gscodec_shac.render.renderer import render_views

    cloud, controller, target, judges, background = fitted_scene(args)
    # _encode_to, not encode: the variants are predicted with the models as the target's encodes corrected them
    outcome = controller._encode_to(target)
    base = dict(outcome.plan.settings)
    variants = [] if args.no_moves else moves(controller, base)
    if args.structure_moves:
        variants += structure_moves(controller, base)
    predicted = {label: controller._predict(settings).predicted_mse for label, _, _, settings in variants}
    base_predicted = controller._predict(base).predicted_mse

    photos = judged_photos(judges, background) if args.judge_images else None
    references = render_views(cloud, judges, background=background, progress=False)

    def judged(decoded: Any) -> tuple[float, float]:
        """MSE on the held-out views against the model and against the photos (NaN without them)."""
        images = render_views(decoded, judges, background=background, progress=False)
        return mean_mse(images, references), mean_mse([np.clip(i, 0, 1) for i in images], photos) if photos else math.nan

    def coded(settings: dict[str, Any]) -> tuple[int, float, float, float, Any]:
        stream = controller._encode(controller._predict(settings), target)
        decoded = rc._decoded(stream, controller.workers)
        return (stream.total_bytes(), controller._rendered_mse(decoded), *judged(decoded), decoded)

    base_bytes, base_views, base_judges, base_photos, base_decoded = coded(base)
    rows = []
    for label, name, direction, settings in variants:
        size, views_mse, judges_mse, photos_mse, _ = coded(settings)
        rows.append({"move": label, "attribute": name, "direction": direction, "setting": settings[name],
                     "bytes": size, "d_bytes": size - base_bytes, "model_d_mse": predicted[label] - base_predicted,
                     "views_d_mse": views_mse - base_views, "judges_d_mse": judges_mse - base_judges,
                     "views_psnr": rc._psnr(views_mse), "judges_psnr": rc._psnr(judges_mse),
                     "photos_d_mse": photos_mse - base_photos if photos else None,
                     "photos_psnr": rc._psnr(photos_mse) if photos else None})
        print(f"{label:18s} {size - base_bytes:+8d} bytes  MSE x1e9: model {1e9 * rows[-1]['model_d_mse']:+8.1f}  "
              f"views {1e9 * rows[-1]['views_d_mse']:+8.1f}  judges {1e9 * rows[-1]['judges_d_mse']:+8.1f}"
              + (f"  photos {1e9 * rows[-1]['photos_d_mse']:+8.1f}" if photos else ""), flush=True)
    gain_rows = []
    for gain in gains:
        for source, model in (("model", cloud), ("file", base_decoded)):
            judges_mse, photos_mse = judged(with_ac_gain(model, gain))
            gain_rows.append({"source": source, "gain": gain, "judges_psnr": rc._psnr(judges_mse),
                              "photos_psnr": rc._psnr(photos_mse)})
            print(f"AC x {gain:g} on the {source}: {gain_rows[-1]['photos_psnr']:.4f} dB against the photos, "
                  f"{gain_rows[-1]['judges_psnr']:.3f} dB against the model", flush=True)
    recoded = []
    plan = controller._predict(base)
    for options in option_sets:
        # the controller's own encode (its cache: the placement is reused, the chunks coded with these options)
        variant = dataclasses.replace(plan, point_of=lambda settings, options=options:
                                      plan.point_of(settings).with_overrides(codec_options=options))
        stream = controller._encode(variant, target)
        judges_mse, _ = judged(rc._decoded(stream, controller.workers))
        recoded.append({"codec_options": options, "bytes": stream.total_bytes(), "judges_psnr": rc._psnr(judges_mse),
                        "d_judges_psnr": rc._psnr(judges_mse) - rc._psnr(base_judges)})
        print(f"codec options {options}: {stream.total_bytes() / base_bytes - 1:+.2%} bytes, "
              f"{recoded[-1]['d_judges_psnr']:+.3f} dB on the held-out views", flush=True)
    keys = [("views", base_views), ("judges", base_judges)] + ([("photos", base_photos)] if photos else [])
    swaps = {key: best_swap([r for r in rows if r["direction"] != "other"], f"{key}_d_mse", mse) for key, mse in keys}
    document = {"model": str(args.model), "target": {"kind": target.kind, "value": target.value},
                "plan": base, "target_bytes": outcome.stream.total_bytes(), "bytes": base_bytes,
                "views_psnr": rc._psnr(base_views), "judges_psnr": rc._psnr(base_judges), "judges": len(judges),
                "photos_psnr": rc._psnr(base_photos) if photos else None,
                "model_photos_psnr": rc._psnr(mean_mse([np.clip(i, 0, 1) for i in references], photos)) if photos else None,
                "rows": rows, "best_swap": swaps, "codec_options": recoded, "ac_gains": gain_rows}
    print(f"plan {base}: {base_bytes:,} bytes, {document['views_psnr']:.2f} dB on the controller's views, "
          f"{document['judges_psnr']:.2f} dB on {len(judges)} held-out views"
          + (f", {document['photos_psnr']:.4f} dB against their photos (the model: "
             f"{document['model_photos_psnr']:.4f} dB)" if photos else ""))
    for key, swap in swaps.items():
        print(f"best single-step exchange on the {key}: " + (
            "none gains" if swap is None else
            f"{swap['finer']} paid by {swap['coarser']}: +{swap['db_at_equal_size']:.3f} dB at equal size"))
    write_results(args.out, document, rows, FIELDS)
    return document


if __name__ == "__main__":
    main()
