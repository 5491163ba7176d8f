"""Small-scale paper Table VI: encode / decode time of the SH AC part with and without a
low-rank SH stage (docs/paper.md).

The paper times gsplat's SH AC coding (k-means on 45 vs 21 dimensions) on a GPU. Here the SH
part of our codec is timed on its own, exactly as :class:`gscodec_shac.codec.encoder.Encoder`
codes the SH attribute, for one grid order shared by every method (the sort is done once and
not timed):

* **encode** = SH stage (``fit`` + ``transform``; ``none`` passes the 45 AC columns) ->
  YCbCr on triplets where the rate point says so -> min/max quantiser -> one grid-codec chunk
  per QP run (HEVC through x265, one thread, the rate point's preset);
* **decode** = grid decode -> dequantise -> inverse YCbCr -> ``inverse_transform`` -> the
  (N, 45) AC matrix.

Methods: ``none`` (45 AC planes), ``pca`` (SHAC-PCA, ER 0.99 as the paper's Sec. VI-C2),
``lst`` (SHAC-LST post-hoc: ridge fit of T at encode, 21 planes) and ``lst-trained`` (the same
21 planes with T already known, as for a model trained with ``--sh lst``: the encoder only
selects S). Wall time and the process's CPU time, median over ``--repeats``; speedup = time of
``none`` / time of the method.

    python scripts/table6_sh_codec_time.py --json table6.json --md table6.md \\
        --scene bonsai=../shared/data/scenes/bonsai_cpu_sh3/point_cloud.ply --synthetic 500000
    python scripts/table6_sh_codec_time.py --quick
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gscodec_shac.codec import quantize as qz  # noqa: E402
from gscodec_shac.codec.encoder import Encoder  # noqa: E402
from gscodec_shac.codec.grid.base import get_codec  # noqa: E402
from gscodec_shac.codec.layout import kept_rows, occupied, planes, qp_runs  # noqa: E402
from gscodec_shac.codec.rate_points import load_rate_point  # noqa: E402
from gscodec_shac.gaussians import GaussianCloud  # noqa: E402
from gscodec_shac.io.ply import read_ply  # noqa: E402
from gscodec_shac.shac.base import ShStage, make_stage  # noqa: E402

METHODS = {
    "none": ("none", {}),
    "pca": ("pca", {"energy_retention": 0.99}),
    "lst": ("lst", {}),
    "lst-trained": ("lst", {}),
}
#: The paper's Table VI (gsplat on truck, RTX 3090): (N, enc s, enc speedup, dec s, dec speedup).
PAPER = [
    {"method": "gsplat", "n": "0.36M", "enc_s": 30.52, "dec_s": 0.15},
    {"method": "gsplat+SHAC-LST", "n": "0.36M", "enc_s": 9.24, "enc_speedup": 3.3, "dec_s": 0.04, "dec_speedup": 3.8},
    {"method": "gsplat", "n": "1.00M", "enc_s": 85.39, "dec_s": 0.38},
    {"method": "gsplat+SHAC-LST", "n": "1.00M", "enc_s": 46.22, "enc_speedup": 1.8, "dec_s": 0.12, "dec_speedup": 3.2},
]


class Timer:
    def __enter__(self) -> "Timer":
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def encode_sh(ac: np.ndarray, stage: ShStage, fit: bool, rate_point, cell_rows, shape, codec):
    """The encoder's SH path (Encoder._sh_features + _code_sh + the chunk coding)."""
    features = np.asarray(stage.fit_transform(ac) if fit else stage.transform(ac))
    spec = rate_point.attributes[stage.rate_attribute]
    ycbcr = rate_point.color == "ycbcr" and stage.ycbcr_applies(features.shape[1])
    values = qz.triplets_to_ycbcr(features) if ycbcr else features
    quantizer = qz.Quantizer.fit(values, spec.bits)
    q = quantizer.quantize(values)
    qps = [spec.qp_for_degree(d) for d in stage.feature_degrees(features.shape[1])]
    chunks = []
    for start, stop in qp_runs(qps):
        chunks.append(((start, stop), codec.encode(planes(q[:, start:stop], cell_rows, shape), spec.bits, qps[start])))
    return {"quantizer": quantizer, "chunks": chunks, "ycbcr": ycbcr, "bits": spec.bits,
            "n_features": int(features.shape[1]), "bytes": sum(len(c) for _, c in chunks)}


def decode_sh(coded: dict, stage: ShStage, cells, shape, codec) -> np.ndarray:
    """The decoder's SH path: grid decode, dequantise, inverse YCbCr, inverse transform."""
    parts = []
    for (start, stop), data in coded["chunks"]:
        decoded = codec.decode(data, (stop - start, *shape), coded["bits"])
        parts.append(occupied(decoded.reshape(stop - start, -1), cells))
    values = coded["quantizer"].dequantize(np.concatenate(parts, axis=1))
    features = qz.triplets_from_ycbcr(values) if coded["ycbcr"] else values
    return stage.inverse_transform(features)


def time_scene(name: str, cloud: GaussianCloud, args: argparse.Namespace) -> list[dict]:
    rate_point = load_rate_point(args.rate_point)
    encoder = Encoder(rate_point, sort=args.sort)
    with Timer() as sort_time:
        grid = encoder.grid_order(cloud)
    cells = grid.cells()
    cell_rows = grid.cell_rows(cells)
    kept = kept_rows(cloud, rate_point.min_opacity)  # what the encoder prunes before sorting
    work = cloud.select(kept).select(grid.order[cells])
    ac = work.ac_matrix()
    spec = rate_point.attributes["sh_ac"]
    codec = get_codec(spec.codec, **{**spec.options, "threads": 1} if spec.codec == "hevc" else spec.options)
    print(f"{name}: N = {work.num_gaussians:,}, grid {grid.shape}, sort {sort_time.wall:.1f} s", flush=True)
    rows = []
    fitted_lst = make_stage("lst").fit(ac)
    for method in args.methods:
        stage_name, params = METHODS[method]
        enc_wall, enc_cpu, dec_wall, dec_cpu = [], [], [], []
        coded = None
        for _ in range(args.repeats):
            stage = copy.deepcopy(fitted_lst) if method == "lst-trained" else make_stage(stage_name, **params)
            with Timer() as t:
                coded = encode_sh(ac, stage, method != "lst-trained", rate_point, cell_rows, grid.shape, codec)
            enc_wall.append(t.wall)
            enc_cpu.append(t.cpu)
            with Timer() as t:
                decoded = decode_sh(coded, stage, cells, grid.shape, codec)
            dec_wall.append(t.wall)
            dec_cpu.append(t.cpu)
        rel = float(np.linalg.norm(decoded - ac) / max(np.linalg.norm(ac), 1e-30))
        row = {"scene": name, "n": work.num_gaussians, "method": method, "features": coded["n_features"],
               "bytes": coded["bytes"], "rel_error": rel, "repeats": args.repeats,
               "enc_wall_s": statistics.median(enc_wall), "enc_cpu_s": statistics.median(enc_cpu),
               "dec_wall_s": statistics.median(dec_wall), "dec_cpu_s": statistics.median(dec_cpu),
               "enc_wall_all": enc_wall, "dec_wall_all": dec_wall}
        rows.append(row)
        print(f"  {method:12s} D={row['features']:2d} enc {row['enc_wall_s']:.2f} s ({row['enc_cpu_s']:.2f} CPU) "
              f"dec {row['dec_wall_s']:.2f} s ({row['dec_cpu_s']:.2f} CPU) {row['bytes']:,} B rel {rel:.3f}", flush=True)
    base = next((r for r in rows if r["method"] == "none"), None)
    for r in rows:
        if base is not None:
            for key in ("enc_wall_s", "enc_cpu_s", "dec_wall_s", "dec_cpu_s"):
                r[key.replace("_s", "_speedup")] = base[key] / r[key] if r[key] > 0 else None
    return rows


def markdown(rows: list[dict], setup: dict) -> str:
    lines = [f"Rate point `{setup['rate_point']}` (SH QP {setup['sh_qp']}), x265 one thread, sort `{setup['sort']}` "
             f"(not timed), median of {setup['repeats']} runs, load average {setup['load'][0]:.1f} at the start. "
             "Speedup = `none` / method (wall; CPU in brackets).", "",
             "| scene | N | method | D | bytes | rel. error | enc. [s] | speedup | dec. [s] | speedup |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        sp = (lambda k: "-" if r["method"] == "none" or r.get(k + "_wall_speedup") is None else
              f"{r[k + '_wall_speedup']:.1f}x ({r[k + '_cpu_speedup']:.1f}x)")
        lines.append(f"| {r['scene']} | {r['n']:,} | {r['method']} | {r['features']} | {r['bytes']:,} | "
                     f"{r['rel_error']:.3f} | {r['enc_wall_s']:.2f} ({r['enc_cpu_s']:.2f}) | {sp('enc')} | "
                     f"{r['dec_wall_s']:.3f} ({r['dec_cpu_s']:.3f}) | {sp('dec')} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", action="append", default=[], metavar="NAME=PLY", help="a PLY to time (repeatable)")
    parser.add_argument("--synthetic", type=int, action="append", default=[], metavar="N",
                        help="also a seeded synthetic scene (gscodec-shac synthetic) of N Gaussians (repeatable)")
    parser.add_argument("--rate-point", default="paper_table3:rp2")
    parser.add_argument("--sort", default=None, help="override the rate point's sort (e.g. morton for large scenes)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--quick", action="store_true", help="smoke test: a 5,000-Gaussian synthetic scene, 1 repeat")
    args = parser.parse_args(argv)
    if args.quick:
        args.scene, args.synthetic, args.repeats = [], [5000], 1
    scenes: list[tuple[str, GaussianCloud]] = []
    for item in args.scene:
        name, _, path = item.partition("=")
        scenes.append((name, read_ply(path)))
    for n in args.synthetic:
        from gscodec_shac.synthetic import make_synthetic_scene

        scenes.append((f"synthetic-{n // 1000}k", make_synthetic_scene(n, seed=0).cloud))
    if not scenes:
        parser.error("give --scene NAME=PLY and/or --synthetic N (or --quick)")
    rate_point = load_rate_point(args.rate_point)
    setup = {"rate_point": args.rate_point, "sh_qp": rate_point.attributes["sh_ac"].qp, "repeats": args.repeats,
             "sort": args.sort or rate_point.sort.method, "load": list(os.getloadavg()), "quick": args.quick}
    rows: list[dict] = []
    for name, cloud in scenes:
        rows += time_scene(name, cloud, args)
        setup["load_end"] = list(os.getloadavg())
        text = markdown(rows, setup)  # written after every scene, so a stopped run keeps what it measured
        if args.json:
            args.json.write_text(json.dumps({"setup": setup, "paper": PAPER, "rows": rows}, indent=1) + "\n")
        if args.md:
            args.md.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
