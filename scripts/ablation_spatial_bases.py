"""Spatially varying SHAC-PCA bases (paper Sec. IX, future work): one basis per spatial cluster.

    python scripts/ablation_spatial_bases.py SCENE.ply OUT_DIR [--clusters 1,4,8,16,32,64]
        [--components 3,6,...] [--er 0.9,0.95,...] [--bits 10] [--cameras cameras.json --test-every 8]

The Gaussians are split by k-means on their positions (k clusters, seeded;
:func:`gscodec_shac.shac.spatial_pca.cluster_positions`); each cluster
gets its own SHAC-PCA (eq. 23-29: standardise, principal components, project) of its AC
matrix, k = 1 being the paper's global basis. Two ways to choose the ranks:

* ``fixed-M``: the same M in every cluster (swept over ``--components``);
* ``ER``: every cluster keeps the fewest components reaching an energy retention
  (eq. 26, swept over ``--er``), so a simple region may keep fewer than a busy one.

The features are quantised to ``--bits`` per value with a min/max per cluster and
component (the codec's scalar quantiser). The rate counted, in bytes:

* features: sum over clusters of n_c x M_c x bits / 8;
* side information per cluster: P (K' x M_c), mu and sigma (K' each) as float32 and the
  min/max of each feature (2 x M_c float32);
* cluster labels: N x H(labels) / 8 (their zeroth-order entropy, what an ideal entropy
  coder spends), or ``k`` counts (4 bytes each) if the grid order groups the clusters
  (``labels by sort order``; a lower bound, since that order would disturb the grid sorting).

The distortion is the mean squared error of the reconstructed AC coefficients (all N x K'
values) against the input, and with ``--cameras`` also the PSNR of renders against the
uncompressed model's renders of the test views (every ``--test-every``-th camera) for the
configurations listed in ``--render`` (``k:M`` pairs of fixed-M runs).

With ``--codec RATE_POINT`` the bases go through the real codec instead: the SH stage
``pca-spatial`` (:mod:`gscodec_shac.shac.spatial_pca`; k = 1 is the plain ``pca`` stage) codes
the per-cluster PCA features as the ``sh_features`` of the rate point (one set of M_c
channels, zero-padded to the largest rank), and its state carries the k bases and the
cluster label of every Gaussian in grid order (zlib-deflated by the codec, so the rate
counts them as coded). Each
configuration is encoded (one shared grid order), decoded, and scored by the whole file's
bytes, the SH AC MSE and the render PSNR against the uncompressed model on the test views
(``--cameras``). ``--codec-clusters``, ``--codec-components`` and ``--codec-er`` choose the
configurations; ``--preset`` the x265 preset (equal for all).

Equal-rate comparison: for each k, the bytes needed to reach each MSE of the global curve
(log-log interpolation along the curve), summarised as the mean relative byte change over
the MSE range both curves cover (a BD-rate in the MSE domain; negative = spatial bases
need fewer bytes). Writes ``OUT_DIR/spatial_bases.json`` and ``OUT_DIR/spatial_bases.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from gscodec_shac.shac.pca import ShacPCA
from gscodec_shac.shac.spatial_pca import cluster_positions

FLOAT32 = 4


def label_entropy_bytes(labels: np.ndarray) -> float:
    """N x H(labels) / 8: the zeroth-order entropy of the labels, in bytes."""
    counts = np.bincount(labels)
    p = counts[counts > 0] / labels.size
    return float(-(p * np.log2(p)).sum() * labels.size / 8)


def quantise(values: np.ndarray, bits: int) -> np.ndarray:
    """Min/max uniform quantisation per column to ``bits``, returned dequantised."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    levels = (1 << bits) - 1
    return lo + np.rint((values - lo) / span * levels) / levels * span


class ClusterBases:
    """A full-rank SHAC-PCA per cluster, truncated on demand."""

    def __init__(self, ac: np.ndarray, labels: np.ndarray) -> None:
        self.ac, self.labels = ac, labels
        self.k = int(labels.max()) + 1
        self.rows = [np.flatnonzero(labels == c) for c in range(self.k)]
        self.pcas = [ShacPCA(n_components=ac.shape[1]).fit(ac[r].astype(np.float64)) for r in self.rows]
        self.features = [p.transform(ac[r].astype(np.float64)) for p, r in zip(self.pcas, self.rows)]

    def ranks_for_energy(self, er: float) -> list[int]:
        return [int(np.searchsorted(p.energy_, er - 1e-12) + 1) for p in self.pcas]

    def reconstruct(self, ranks: list[int], bits: int) -> np.ndarray:
        out = np.empty_like(self.ac, dtype=np.float64)
        for p, r, f, m in zip(self.pcas, self.rows, self.features, ranks):
            q = quantise(f[:, :m], bits)
            back = (p.components_[:, :m] * p.scale_[:, None])  # eq. 29
            out[r] = q @ back.T + p.mean_
        return out

    def rate(self, ranks: list[int], bits: int) -> dict[str, float]:
        kp = self.ac.shape[1]
        features = sum(r.size * m for r, m in zip(self.rows, ranks)) * bits / 8
        side = sum((kp * m + 2 * kp + 2 * m) * FLOAT32 for m in ranks)
        labels = label_entropy_bytes(self.labels) if self.k > 1 else 0.0
        return {"features": features, "side": float(side), "labels_entropy": labels,
                "labels_sorted": float(FLOAT32 * self.k if self.k > 1 else 0),
                "bytes": features + side + labels, "bytes_sorted": features + side + (FLOAT32 * self.k if self.k > 1 else 0)}


def bd_rate_mse(ref: list[tuple[float, float]], test: list[tuple[float, float]]) -> float | None:
    """Mean relative byte change of ``test`` against ``ref`` at equal MSE (log-log, piecewise linear)."""
    def curve(points):
        pts = sorted((np.log(m), np.log(b)) for b, m in points)  # by log MSE
        lm, lb = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
        keep = np.concatenate([[True], np.diff(lm) > 1e-9])
        return lm[keep], lb[keep]

    rm, rb = curve(ref)
    tm, tb = curve(test)
    lo, hi = max(rm.min(), tm.min()), min(rm.max(), tm.max())
    if hi <= lo:
        return None
    grid = np.linspace(lo, hi, 200)
    diff = np.interp(grid, tm, tb) - np.interp(grid, rm, rb)
    return float(np.expm1(diff.mean()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("ply")
    parser.add_argument("out_dir")
    parser.add_argument("--clusters", default="1,4,8,16,32,64")
    parser.add_argument("--components", default="3,5,7,9,12,15,18,21,24,30,36,45")
    parser.add_argument("--er", default="0.8,0.9,0.95,0.97,0.99,0.995,0.999")
    parser.add_argument("--bits", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cameras", help="cameras.json: also render PSNR vs the uncompressed model")
    parser.add_argument("--test-every", type=int, default=8)
    parser.add_argument("--render", default="", help="k:M pairs to render, e.g. 1:9,16:9")
    parser.add_argument("--codec", help="also code through this rate point, e.g. paper_table3:rp2")
    parser.add_argument("--codec-clusters", default="1,4,16,64")
    parser.add_argument("--codec-components", default="6,9,12,18")
    parser.add_argument("--codec-er", default="0.9,0.95,0.97,0.99")
    parser.add_argument("--preset", default="veryfast")
    parser.add_argument("--replot", action="store_true", help="with --codec: report again from OUT_DIR's JSON")
    args = parser.parse_args(argv)

    from gscodec_shac.io.ply import read_ply

    if args.codec and args.replot:  # tables and figure again from the JSON of an earlier run
        data = json.loads((Path(args.out_dir) / "spatial_bases_codec.json").read_text())
        rows = data.pop("rows")
        data.pop("bd_rate", None)
        _codec_report(rows, data, Path(args.out_dir))
        return 0
    cloud = read_ply(args.ply)
    if args.codec:
        return codec_experiment(cloud, args)
    ac = cloud.ac_matrix().astype(np.float64)
    n = ac.shape[0]
    ks = [int(v) for v in args.clusters.split(",")]
    ms = [int(v) for v in args.components.split(",")]
    ers = [float(v) for v in args.er.split(",")]
    rows, curves = [], {}
    for k in ks:
        tic = time.perf_counter()
        bases = ClusterBases(ac, cluster_positions(cloud.means, k, args.seed))
        sizes = [r.size for r in bases.rows]
        for mode, settings in (("fixed-M", ms), ("ER", ers)):
            for s in settings:
                ranks = [min(int(s), ac.shape[1])] * bases.k if mode == "fixed-M" else bases.ranks_for_energy(s)
                recon = bases.reconstruct(ranks, args.bits)
                mse = float(((recon - ac) ** 2).mean())
                rate = bases.rate(ranks, args.bits)
                row = {"k": k, "mode": mode, "setting": s, "mean_rank": float(np.dot(sizes, ranks) / n),
                       "mse": mse, **rate, "bits_per_gaussian": 8 * rate["bytes"] / n}
                rows.append(row)
                curves.setdefault((k, mode), []).append((rate["bytes"], mse))
                curves.setdefault((k, mode + "/sorted"), []).append((rate["bytes_sorted"], mse))
        print(f"k={k}: clusters of {min(sizes)}-{max(sizes)} Gaussians, {time.perf_counter() - tic:.1f} s", file=sys.stderr)

    summary = []
    for k in ks[1:] if ks[0] == 1 else []:
        for mode in ("fixed-M", "ER", "fixed-M/sorted", "ER/sorted"):
            base = curves[(1, "fixed-M")]  # the global basis at every rank: its full RD curve
            summary.append({"k": k, "mode": mode, "bd_rate_vs_global": bd_rate_mse(base, curves[(k, mode)])})

    renders = []
    if args.cameras and args.render:
        from gscodec_shac.io.cameras import load_cameras
        from gscodec_shac.metrics import psnr
        from gscodec_shac.render import Renderer

        cameras = sorted(load_cameras(args.cameras), key=lambda c: c.name)[:: args.test_every]
        reference = [Renderer(cloud).render(c).image for c in cameras]
        for pair in args.render.split(","):
            k, m = (int(v) for v in pair.split(":"))
            bases = ClusterBases(ac, cluster_positions(cloud.means, k, args.seed))
            recon = bases.reconstruct([m] * bases.k, args.bits)
            renderer = Renderer(cloud.with_ac_matrix(recon.astype(np.float32)))
            value = float(np.mean([psnr(renderer.render(c).image, ref) for c, ref in zip(cameras, reference)]))
            rate = bases.rate([m] * bases.k, args.bits)
            renders.append({"k": k, "M": m, "psnr_vs_uncompressed": value, "bytes": rate["bytes"],
                            "mse": float(((recon - ac) ** 2).mean()), "views": len(cameras)})
            print(f"render k={k} M={m}: {value:.2f} dB", file=sys.stderr)

    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = {"scene": os.path.abspath(args.ply), "n_gaussians": n, "bits": args.bits, "seed": args.seed,
              "rows": rows, "bd_rate_vs_global": summary, "renders": renders}
    (out / "spatial_bases.json").write_text(json.dumps(result, indent=1))
    _plot(curves, ks, out / "spatial_bases.png", n)
    for s in summary:
        value = "n/a" if s["bd_rate_vs_global"] is None else f"{100 * s['bd_rate_vs_global']:+.1f}%"
        print(f"k={s['k']:3d} {s['mode']:15s} bytes at equal SH MSE vs global: {value}")
    return 0


# ------------------------------------------------------------------ real codec
def codec_experiment(cloud, args) -> int:
    """Encode, decode and score every (k, ranks) configuration through the rate point ``args.codec``."""
    import zlib

    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.shac.base import StageState, stage_from_state
    from gscodec_shac.metrics import psnr
    from gscodec_shac.render import Renderer

    ac = cloud.ac_matrix()
    cameras = sorted(load_cameras(args.cameras), key=lambda c: c.name)[:: args.test_every] if args.cameras else []
    reference = [Renderer(cloud).render(c).image for c in cameras]
    grid = Encoder(args.codec, sh_stage="pca").grid_order(cloud)
    rows = []
    for k in [int(v) for v in args.codec_clusters.split(",")]:
        settings = [("fixed-M", int(m)) for m in args.codec_components.split(",")]
        settings += [("ER", float(e)) for e in args.codec_er.split(",")]
        for mode, value in settings:
            params = {"n_components": value} if mode == "fixed-M" else {"energy_retention": value}
            if k > 1:  # the regions' fitted scores, as when docs/ablations.md's table was measured (before format 2.5)
                params.update(spatial_clusters=k, seed=args.seed, unit_weights=False)
            encoder = Encoder(args.codec, sh_stage="pca" if k == 1 else "pca-spatial", sh_params=params,
                              codec_options={"preset": args.preset}, workers=1)
            data = encoder.encode(cloud, grid=grid).to_bytes()
            decoded = Decoder(workers=1).decode(data)
            mse = float(((decoded.ac_matrix() - ac[encoder.order_]) ** 2).mean())
            renderer = Renderer(decoded)
            value_psnr = float(np.mean([psnr(renderer.render(c).image, r) for c, r in zip(cameras, reference)])) \
                if cameras else None
            stream = Bitstream.from_bytes(data)
            chunks = stream.sizes()
            fitted = stage_from_state(StageState.from_bytes(zlib.decompress(stream.chunk("sh_state").data)))
            ranks = fitted.ranks() if k > 1 else [fitted.n_components_]
            counts = np.bincount(fitted.labels_, minlength=len(ranks)) if k > 1 else np.array([len(ac)])
            row = {"k": k, "mode": mode, "setting": value, "bytes": len(data), "bits_per_gaussian": 8 * len(data) / len(ac),
                   "sh_bytes": sum(v for key, v in chunks.items() if key.startswith("sh") and key != "sh_dc"),
                   "sh_state_bytes": chunks.get("sh_state", 0), "mse": mse, "psnr_vs_uncompressed": value_psnr,
                   "coded_channels": max(ranks), "mean_rank": float(np.dot(counts, ranks) / counts.sum())}
            rows.append(row)
            print(f"k={k} {mode} {value}: {len(data):,} B, SH {row['sh_bytes']:,} B (state {row['sh_state_bytes']:,}), "
                  f"MSE {mse:.3e}, PSNR {value_psnr if value_psnr is None else round(value_psnr, 3)}", file=sys.stderr)
    meta = {"scene": os.path.abspath(args.ply), "rate_point": args.codec, "preset": args.preset, "views": len(cameras)}
    _codec_report(rows, meta, Path(args.out_dir))
    return 0


def _global_curve(rows: list[dict]) -> list[dict]:
    """The k = 1 rows (fixed M and ER alike: the same stage), one per rank, by size."""
    by_rank = {r["mean_rank"]: r for r in rows if r["k"] == 1}
    return sorted(by_rank.values(), key=lambda r: r["bytes"])


def _codec_report(rows: list[dict], meta: dict, out: Path) -> None:
    """BD-rates against the global basis, the JSON and the figure."""
    from gscodec_shac.rd.bd import bd_rate

    summary = []
    base = [(r["bytes"], r["psnr_vs_uncompressed"]) for r in _global_curve(rows)]
    if meta["views"] and len(base) >= 2:
        for k in sorted({r["k"] for r in rows} - {1}):
            for mode in ("fixed-M", "ER"):
                test = [(r["bytes"], r["psnr_vs_uncompressed"]) for r in rows if r["k"] == k and r["mode"] == mode]
                res = bd_rate([b for b, _ in base], [q for _, q in base], [b for b, _ in test], [q for _, q in test])
                summary.append({"k": k, "mode": mode, "bd_rate_pct_vs_global": res.value, "note": res.reason})
                print(f"k={k:3d} {mode:8s} BD-rate (render PSNR vs uncompressed) vs global basis: {res.value:+.1f}% "
                      f"{res.reason or ''}")
    out.mkdir(parents=True, exist_ok=True)
    (out / "spatial_bases_codec.json").write_text(json.dumps({**meta, "rows": rows, "bd_rate": summary}, indent=1))
    _plot_codec(rows, out / "spatial_bases_codec.png", meta["rate_point"])


def _plot_codec(rows: list[dict], path: Path, rate_point: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    glob = [(r["bits_per_gaussian"], r["psnr_vs_uncompressed"]) for r in _global_curve(rows)
            if r["psnr_vs_uncompressed"] is not None]
    ax.plot([p[0] for p in glob], [p[1] for p in glob], "k-", marker="o", markersize=3, label="global basis (k=1)")
    for k in sorted({r["k"] for r in rows} - {1}):
        for mode, style in (("fixed-M", "o-"), ("ER", "s--")):
            pts = sorted((r["bits_per_gaussian"], r["psnr_vs_uncompressed"]) for r in rows
                         if r["k"] == k and r["mode"] == mode and r["psnr_vs_uncompressed"] is not None)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, markersize=3, label=f"k={k} {mode}")
    ax.set_xlabel("bits per Gaussian (whole file)")
    ax.set_ylabel("PSNR vs uncompressed (dB)")
    ax.set_title(f"spatial PCA bases through the codec ({rate_point})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot(curves: dict, ks: list[int], path: Path, n: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    from matplotlib.ticker import NullFormatter

    for ax, mode in zip(axes, ("fixed-M", "ER")):
        for k in ks:
            if k == 1 and mode == "ER":
                continue
            pts = sorted(curves[(k, mode)])
            ax.plot([8 * b / n for b, _ in pts], [m for _, m in pts], marker=".", label=f"k={k}" + (" (global)" if k == 1 else ""))
        if mode == "ER" and 1 in ks:  # the reference of the comparison: the global basis at every rank
            pts = sorted(curves[(1, "fixed-M")])
            ax.plot([8 * b / n for b, _ in pts], [m for _, m in pts], "k--", lw=1, label="global, every M")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_yscale("log")
        ax.set_xlabel("bits per Gaussian (SH features + bases + labels)")
        ax.set_title(f"one basis per spatial cluster, ranks: {mode}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("SH AC MSE")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
