"""Paper Table IV on our CPU-trained deformable 3DGS models: size and test quality per D-NeRF scene.

For each trained model directory (``gscodec-shac train-dynamic``) this script measures, on the
scene's test frames (each rendered at its own time, at the training resolution and background),
the mean of per-image PSNR and SSIM against the ground-truth images for:

* ``uncompressed``: the trained model (float32 canonical Gaussians + float32 network);
* ``float_pca``: the paper's Table IV setting: the SH AC part replaced by SHAC-PCA features at
  energy retention 0.96 (float32 features + the stage's side information; no codec);
* ``coded_none``: the ``.gsc`` stream at ``--rate-point`` without an SH stage (``--sh none``);
* ``coded_pca``: the ``.gsc`` stream at the same rate point with SHAC-PCA, ER 0.96;
* ``coded_lst`` (when ``--lst-models`` names models trained with ``--sh lst``): their ``.gsc``.

Each variant's renders are also compared with the uncompressed model's renders (``psnr_vs_uncompressed``):
what coding loses, apart from how good the model is.

Sizes: float32 MB of the models (Gaussians x 59 floats + network weights), the PCA model's
float size (Gaussians x (14 + M) + side information + network) and the ``.gsc`` files' bytes
(with the network's float16 chunk, as ``info`` shows it). Writes ``--json`` and a markdown table
(``--markdown``).

Example::

    python scripts/table_dynamic.py --models ../outputs/dynamic --scenes ../shared/data/scenes/dnerf \\
        --json table_dynamic.json --markdown table_dynamic.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

PAPER = {"uncompressed": {"psnr": 40.09, "ssim": 0.991, "mb": 12.7},
         "pca": {"psnr": 39.99, "ssim": 0.991, "mb": 7.7}, "lst": {"psnr": 40.04, "ssim": 0.991, "mb": 7.7}}
REFERENCE_400 = {"jumpingjacks": 39.10, "mutant": 43.73, "standup": 45.38}
ER = 0.96


def load_test(scene_dir: Path, scale: float, background: list[float]):
    """A DynamicCapture holding only the test frames."""
    from gscodec_shac.io.dnerf import read_dnerf_scene
    from gscodec_shac.train.data import load_images
    from gscodec_shac.train.dynamic import DynamicCapture

    frames = read_dnerf_scene(scene_dir, scale, splits=("test",))["test"]
    cams = [f.camera for f in frames]
    bg = np.asarray(background, dtype=np.float64)
    images = load_images(cams, bg)
    return DynamicCapture(scene_dir.name, [], [], [], cams, [f.time for f in frames], images, bg, 1.0)


def float_pca(model, er: float):
    """(model with PCA-reconstructed SH, PCA float MB, components M)."""
    from gscodec_shac import sh_index
    from gscodec_shac.deform import DynamicModel
    from gscodec_shac.gaussians import GaussianCloud
    from gscodec_shac.shac.base import make_stage

    cloud = model.cloud
    ac = sh_index.ac_matrix(cloud.sh_rest)
    stage = make_stage("pca", energy_retention=er)
    features = stage.fit_transform(ac)
    rebuilt = sh_index.sh_rest_from_ac(np.asarray(stage.inverse_transform(features), dtype=np.float32))
    m = features.shape[1]
    n = cloud.num_gaussians
    mb = (n * (14 + m) * 4 + stage.side_info_bytes() + 4 * model.net.n_params) / 1e6
    new = GaussianCloud(means=cloud.means, scales=cloud.scales, quats=cloud.quats, opacities=cloud.opacities,
                        sh_dc=cloud.sh_dc, sh_rest=rebuilt)
    return DynamicModel(new, model.net), mb, m


def sh_bytes(gsc: Path) -> int:
    """Bytes of the SH AC part of a .gsc (the 'sh' attribute's chunks plus the stage state)."""
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import describe, read_header

    info = describe(read_header(Bitstream.read(gsc)))
    return sum(v["bytes"] for k, v in info["attributes"].items() if k in ("sh", "sh_state"))


def measure(model, capture, reference: list | None = None) -> dict[str, Any]:
    """Mean per-frame PSNR/SSIM against the ground truth; with ``reference`` (the uncompressed model's
    renders) also the mean PSNR against them (``psnr_vs_uncompressed``)."""
    from gscodec_shac.metrics import psnr, ssim
    from gscodec_shac.render import Renderer

    renders, p, s, q = [], [], [], []
    for index, (cam, t, truth) in enumerate(zip(capture.test_cameras, capture.test_times, capture.test_images)):
        image = Renderer(model.at(t)).render(cam, background=capture.background).image
        renders.append(image)
        p.append(psnr(image, truth))
        s.append(ssim(image, truth))
        if reference is not None:
            q.append(psnr(image, reference[index]))
    out: dict[str, Any] = {"psnr": float(np.mean(p)), "ssim": float(np.mean(s)), "renders": renders}
    if reference is not None:
        out["psnr_vs_uncompressed"] = float(np.mean(q))
    return out


def run_scene(model_dir: Path, scene_dir: Path, work: Path, rate_point: str, lst_dir: Path | None) -> dict[str, Any]:
    from gscodec_shac.codec import decode_file, encode_file
    from gscodec_shac.deform import load_dynamic_model

    metrics = json.loads((model_dir / "metrics.json").read_text())
    scale = metrics["width"] / 800.0
    capture = load_test(scene_dir, scale, metrics.get("background", [0.0, 0.0, 0.0]))
    model = load_dynamic_model(model_dir)
    n = model.cloud.num_gaussians
    row: dict[str, Any] = {
        "scene": scene_dir.name, "width": metrics["width"], "height": metrics["height"], "num_gaussians": n,
        "iterations": metrics["iterations_done"], "iterations_planned": metrics["config"]["iterations"],
        "train_seconds": metrics["train_seconds"], "seconds_per_iteration": metrics["seconds_per_iteration"],
        "network": metrics["arch"], "network_weights": model.net.n_params, "rate_point": rate_point,
    }
    tic = time.perf_counter()
    row["uncompressed"] = {"mb": (n * 59 * 4 + 4 * model.net.n_params) / 1e6, **measure(model, capture)}
    reference = row["uncompressed"].pop("renders")
    pca_model, pca_mb, m = float_pca(model, ER)
    row["float_pca"] = {"mb": pca_mb, "components": m, **measure(pca_model, capture, reference)}
    row["float_pca"].pop("renders")
    work.mkdir(parents=True, exist_ok=True)
    for key, sh, params, source in (("coded_none", "none", {}, model_dir),
                                    ("coded_pca", "pca", {"energy_retention": ER}, model_dir),
                                    ("coded_lst", None, {}, lst_dir)):
        if source is None:
            continue
        gsc = work / f"{scene_dir.name}_{key}.gsc"
        summary = encode_file(source, gsc, rate_point, sh=sh, **params)
        out = work / f"{scene_dir.name}_{key}"
        decode_file(gsc, out)
        row[key] = {"mb": summary["bytes"] / 1e6, "sh_bytes": sh_bytes(gsc), "encode_seconds": summary["seconds"],
                    **measure(load_dynamic_model(out), capture, None if key == "coded_lst" else reference)}
        row[key].pop("renders")
    if lst_dir is not None:
        row["lst_uncompressed"] = measure(load_dynamic_model(lst_dir), capture)
        row["lst_uncompressed"].pop("renders")
    row["eval_seconds"] = time.perf_counter() - tic
    return row


def markdown(rows: list[dict[str, Any]]) -> str:
    def fmt(entry: dict[str, Any] | None, digits: int = 2) -> str:
        if not entry:
            return "-"
        return f"{entry['psnr']:.2f} / {entry['ssim']:.4f} / {entry['mb']:.{digits}f}"

    lines = [
        "| scene | res | iterations (planned) | Gaussians | s/it | uncompressed: PSNR / SSIM / MB | float SHAC-PCA ER 0.96 "
        "(M) | .gsc no SH stage | .gsc SHAC-PCA ER 0.96 | .gsc SHAC-LST | PSNR .gsc PCA - none (dB) | "
        "PSNR vs uncompressed render: float PCA / .gsc none / .gsc PCA | "
        "SH part of .gsc: none -> PCA | reference 400x400 PSNR |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sh = delta = fidelity = "-"
        if "coded_none" in r and "coded_pca" in r:
            fidelity = " / ".join(f"{r[k]['psnr_vs_uncompressed']:.2f}" for k in ("float_pca", "coded_none", "coded_pca"))
        if "coded_none" in r and "coded_pca" in r:
            a, b = r["coded_none"]["sh_bytes"], r["coded_pca"]["sh_bytes"]
            sh = f"{a / 1e3:.0f} kB -> {b / 1e3:.0f} kB ({100 * (1 - b / a):.0f}% smaller)"
            delta = f"{r['coded_pca']['psnr'] - r['coded_none']['psnr']:+.3f}"
        lines.append(
            f"| {r['scene']} | {r['width']}x{r['height']} | {r['iterations']} ({r['iterations_planned']}) | "
            f"{r['num_gaussians']:,} | {r['seconds_per_iteration']:.2f} | {fmt(r['uncompressed'])} | "
            f"{fmt(r['float_pca'])} ({r['float_pca']['components']}) | {fmt(r.get('coded_none'), 3)} | "
            f"{fmt(r.get('coded_pca'), 3)} | {fmt(r.get('coded_lst'), 3)} | {delta} | {fidelity} | {sh} | "
            f"{REFERENCE_400.get(r['scene'], float('nan')):.2f} |")
    if rows:
        def mean(key: str, field: str) -> str:
            values = [r[key][field] for r in rows if r.get(key)]
            return f"{np.mean(values):.{4 if field == 'ssim' else 2}f}" if len(values) == len(rows) else "-"

        lines.append(
            f"| **average** | | | {np.mean([r['num_gaussians'] for r in rows]):,.0f} | "
            f"{np.mean([r['seconds_per_iteration'] for r in rows]):.2f} | "
            f"{mean('uncompressed', 'psnr')} / {mean('uncompressed', 'ssim')} / {mean('uncompressed', 'mb')} | "
            f"{mean('float_pca', 'psnr')} / {mean('float_pca', 'ssim')} / {mean('float_pca', 'mb')} | "
            f"{mean('coded_none', 'psnr')} / {mean('coded_none', 'ssim')} / {mean('coded_none', 'mb')} | "
            f"{mean('coded_pca', 'psnr')} / {mean('coded_pca', 'ssim')} / {mean('coded_pca', 'mb')} | "
            f"{mean('coded_lst', 'psnr')} | | | | {np.mean(list(REFERENCE_400.values())):.2f} |")
    lines.append(
        f"| *paper Table IV (GPU, 800x800, average of D-NeRF)* | | | | | {PAPER['uncompressed']['psnr']} / "
        f"{PAPER['uncompressed']['ssim']} / {PAPER['uncompressed']['mb']} | {PAPER['pca']['psnr']} / "
        f"{PAPER['pca']['ssim']} / {PAPER['pca']['mb']} | | | LST: {PAPER['lst']['psnr']} / {PAPER['lst']['ssim']} / "
        f"{PAPER['lst']['mb']} | {PAPER['pca']['psnr'] - PAPER['uncompressed']['psnr']:+.2f} (vs uncompressed) | | | |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=Path, required=True, help="folder with one trained model directory per scene")
    parser.add_argument("--scenes", type=Path, required=True, help="D-NeRF folder (one folder per scene)")
    parser.add_argument("--names", nargs="+", default=["jumpingjacks", "mutant", "standup"])
    parser.add_argument("--lst-models", type=Path, help="folder with models trained with --sh lst (optional)")
    parser.add_argument("--rate-point", default="paper_table3:rp2")
    parser.add_argument("--work", type=Path, default=Path("/tmp/table_dynamic"))
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args(argv)
    from gscodec_shac.atomic import write_atomic

    rows = []
    for name in args.names:
        model_dir = args.models / name
        if not (model_dir / "metrics.json").is_file():
            print(f"skipping {name}: no trained model in {model_dir}", file=sys.stderr)
            continue
        lst = args.lst_models / name if args.lst_models and (args.lst_models / name / "metrics.json").is_file() else None
        print(f"{name} ...", file=sys.stderr, flush=True)
        rows.append(run_scene(model_dir, args.scenes / name, args.work, args.rate_point, lst))
        write_atomic(args.json, json.dumps({"er": ER, "rate_point": args.rate_point, "rows": rows,
                                            "paper": PAPER, "reference_400": REFERENCE_400}, indent=1))
    if args.markdown:
        write_atomic(args.markdown, markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
