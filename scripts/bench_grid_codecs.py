"""Benchmark the grid codecs on realistic attribute grids.

Gaussians from a real scene (bonsai, 75k, SH degree 3) and the synthetic
generator are placed on a 2-D grid (Morton order of positions in 2-D Z-order
layout; PLAS-like sorting by xyz + DC where ``sorting`` provides it), each
attribute is quantised per channel (min/max; positions 16 bit, the rest 10 bit)
and coded with every grid codec. Reported: bytes, bits per sample, encode and
decode time (medians), PSNR (peak 1023) for lossy HEVC.

    python scripts/bench_grid_codecs.py --out /tmp/bench_codecs \
        --markdown docs/benchmarks_codecs.md

Results (JSON rows) and cached grid orders go to ``--out``; only the markdown
tables go into the repository.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from gscodec_shac.codec.grid import get_codec
from gscodec_shac.io.ply import read_ply
from gscodec_shac.synthetic import make_synthetic_scene

BONSAI = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "scenes" / "bonsai_cpu_sh3" / "point_cloud.ply"
LOSSY_QPS = (7, 12, 17, 22)
SECTIONS = ["position", "lossless", "lossy"]
RAW = ("raw", {"entropy": "none"})
LOSSLESS_CODECS = [
    ("png", {}), ("jpegls", {}), RAW, ("raw", {"entropy": "zlib"}), ("raw", {"entropy": "lzma"}),
    ("hevc", {"layout": "gray"}), ("hevc", {"layout": "frames"}),
]  # fmt: skip


# ------------------------------------------------------------------- grids
def load_scene(name: str, n: int):
    if name == "bonsai":
        if not BONSAI.exists():
            raise SystemExit(f"real scene not found: {BONSAI}")
        return read_ply(BONSAI)
    return make_synthetic_scene(n, seed=0, n_cameras=2).cloud


def grid_order(cloud, method: str, cache: Path) -> tuple[np.ndarray, tuple[int, int]]:
    """(order, shape) from the project's sorter, cached per scene and method."""
    import sorting

    shape = sorting.grid_shape(len(cloud))
    if cache.exists():
        return np.load(cache), shape
    start = time.perf_counter()
    if method == "morton":
        order = sorting.morton_order(cloud.means, shape)
    else:
        features = sorting.prepare_features({"xyz": cloud.means, "dc": cloud.sh_dc})
        order = sorting.sort_to_grid(features, shape, method="plas", progress=True)
    log(f"  {method} order {shape[0]}x{shape[1]} in {time.perf_counter() - start:.1f} s")
    np.save(cache, order)
    return order, shape


def quantise(values: np.ndarray, bits: int) -> np.ndarray:
    """(N, C) floats -> (N, C) integers, each column min/max-scaled to ``bits`` bits."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.rint((values - lo) / span * (2**bits - 1)).astype(np.uint16)


def attribute_grids(cloud, order: np.ndarray, shape: tuple[int, int]) -> dict[str, tuple[np.ndarray, int]]:
    """name -> ((C, H, W) uint16 planes, bits); empty cells repeat the previous filled cell."""
    n = len(cloud)
    attributes = {
        "position": (cloud.means, 16),
        "opacity": (cloud.opacities.reshape(n, 1), 10),
        "scale": (cloud.scales, 10),
        "rotation": (cloud.normalized_quats(), 10),
        "dc": (cloud.sh_dc.reshape(n, 3), 10),
        "sh_rest": (cloud.sh_rest.reshape(n, -1), 10),  # coefficient-major: RGB of one (l, m) adjacent
    }
    filled = np.maximum.accumulate(np.where(order >= 0, np.arange(order.size), 0))
    rows = order[filled]
    grids = {}
    for name, (values, bits) in attributes.items():
        q = quantise(np.asarray(values, dtype=np.float64), bits)
        grids[name] = (np.ascontiguousarray(q[rows].T.reshape(-1, *shape)), bits)
    return grids


def split_hi_lo(planes: np.ndarray) -> np.ndarray:
    """16-bit planes -> 8-bit planes [hi_0, lo_0, hi_1, lo_1, ...]."""
    return np.stack([planes >> 8, planes & 0xFF], axis=1).reshape(-1, *planes.shape[1:])


# ------------------------------------------------------------------ timing
def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def measure(codec_name: str, options: dict, planes: np.ndarray, bits: int, qp: int | None, repeats: int) -> dict:
    codec = get_codec(codec_name, **options)
    enc, dec = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        data = codec.encode(planes, bits, qp)
        enc.append(time.perf_counter() - start)
        start = time.perf_counter()
        decoded = codec.decode(data, planes.shape, bits)
        dec.append(time.perf_counter() - start)
    row = {"codec": codec_name, "options": options, "qp": qp, "bits": bits, "channels": planes.shape[0],
           "bytes": len(data), "enc_s": statistics.median(enc), "dec_s": statistics.median(dec)}  # fmt: skip
    error = decoded.astype(np.float64) - planes
    mse = float(np.mean(error**2))
    row["exact"] = mse == 0.0
    row["psnr"] = None if mse == 0 else 10 * np.log10((2**bits - 1) ** 2 / mse)
    return row


def label(row: dict) -> str:
    opts = ",".join(f"{v}" for k, v in row["options"].items() if k not in ("threads",))
    return f"{row['codec']}({opts})" if opts else row["codec"]


# ----------------------------------------------------------------- benchmark
def run(args: argparse.Namespace) -> list[dict]:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    if args.reuse:  # keep the rows of sections not measured this time
        rows = [r for r in json.loads(Path(args.reuse).read_text()) if r["section"] not in args.sections]
    for scene in args.scenes:
        log(f"scene {scene}")
        cloud = load_scene(scene, args.synthetic_n)
        for method in args.orders:
            order, shape = grid_order(cloud, method, out / f"order_{scene}_{len(cloud)}_{method}.npy")
            grids = attribute_grids(cloud, order, shape)
            base = {"scene": scene, "n": len(cloud), "order": method, "grid": f"{shape[0]}x{shape[1]}"}

            def add(section: str, attribute: str, form: str, codec: tuple, planes, bits, qp=None, repeats=args.repeats):
                row = {**base, "section": section, "attribute": attribute, "form": form,
                       **measure(codec[0], codec[1], planes, bits, qp, repeats)}  # fmt: skip
                row["samples"] = int(grids[attribute][0].size)
                row["bits_per_sample"] = 8 * row["bytes"] / row["samples"]
                rows.append(row)
                psnr = "lossless" if row["exact"] else f"{row['psnr']:.2f} dB"
                log(f"  {method:6s} {attribute:8s} {form:9s} {label(row):28s} qp={qp!s:4s} "
                    f"{row['bytes']:9d} B {row['bits_per_sample']:6.2f} b/s {psnr:>9s} "
                    f"enc {row['enc_s'] * 1e3:8.1f} ms dec {row['dec_s'] * 1e3:7.1f} ms")  # fmt: skip

            # 1. positions: one 16-bit plane per axis vs two 8-bit planes (hi/lo)
            pos, _ = grids["position"]
            for codec in [("png", {}), ("jpegls", {}), RAW, ("raw", {"entropy": "lzma"})]:
                if "position" in args.sections:
                    add("position", "position", "16-bit", codec, pos, 16)
            for codec in [("png", {}), ("jpegls", {}), ("raw", {"entropy": "lzma"}), ("hevc", {"layout": "gray"})]:
                if "position" in args.sections:
                    add("position", "position", "hi/lo 8", codec, split_hi_lo(pos), 8)

            # 2. 10-bit attributes, lossless
            for attribute in ("opacity", "scale", "rotation", "dc", "sh_rest") if "lossless" in args.sections else ():
                planes, bits = grids[attribute]
                for codec in LOSSLESS_CODECS:
                    if codec[0] == "hevc" and codec[1]["layout"] == "frames" and planes.shape[0] < 3:
                        continue
                    reps = 1 if (codec[0] == "hevc" and attribute == "sh_rest") else args.repeats
                    add("lossless", attribute, "10-bit", codec, planes, bits, repeats=reps)

            # 3. HEVC lossy: layouts x presets x QPs
            if method not in args.lossy_orders or "lossy" not in args.sections:
                continue
            for attribute in ("dc", "scale", "sh_rest"):
                planes, bits = grids[attribute]
                reps = 1 if attribute == "sh_rest" else args.repeats
                for preset in ("slow", "medium"):
                    for layout in ("gray", "yuv444", "frames"):
                        for qp in LOSSY_QPS:
                            add("lossy", attribute, "10-bit", ("hevc", {"layout": layout, "preset": preset}), planes, bits, qp, reps)
                for qp in LOSSY_QPS:  # does tune=psnr matter? (default tune is psnr)
                    add("lossy", attribute, "10-bit", ("hevc", {"layout": "yuv444", "preset": "slow", "tune": None}), planes, bits, qp, reps)
    return rows


# ------------------------------------------------------------------ markdown
ANCHOR = "hevc(gray,slow)"
LOSSY_LABELS = ["hevc(yuv444,slow)", "hevc(frames,slow)", "hevc(gray,medium)", "hevc(yuv444,medium)",
                "hevc(frames,medium)", "hevc(yuv444,slow,None)"]  # fmt: skip


def bd_rate(anchor: list[tuple[float, float]], test: list[tuple[float, float]]) -> float:
    """Bjontegaard rate difference: mean log-rate gap over the common PSNR range (PCHIP fits)."""
    from scipy.interpolate import PchipInterpolator

    def fit(points):
        points = sorted(points, key=lambda p: p[1])
        return PchipInterpolator([p[1] for p in points], np.log([p[0] for p in points]))

    lo = max(min(p[1] for p in anchor), min(p[1] for p in test))
    hi = min(max(p[1] for p in anchor), max(p[1] for p in test))
    if hi <= lo:
        return float("nan")
    a, t = fit(anchor), fit(test)
    gap = (t.integrate(lo, hi) - a.integrate(lo, hi)) / (hi - lo)
    return float(np.exp(gap) - 1)


def markdown(rows: list[dict], command: str) -> str:
    versions = {label(r).split("(")[0]: None for r in rows}
    lines = [
        "# Grid codec benchmark",
        "",
        f"Command: `{command}`  ",
        f"Machine: {platform.machine()}, {platform.processor() or 'unknown CPU'}, Python {platform.python_version()}; "
        "timings are medians on a shared 2-core machine (orders of magnitude).  ",
        "Codec versions: " + "; ".join(f"{name}: {get_codec(name).version()}" for name in sorted(versions)) + ".",
        "",
        "bits/s = bits per grid sample of the attribute (one channel of one cell; positions count 16-bit samples, "
        "so the hi/lo split is directly comparable). Times in ms for the whole attribute grid.",
        "",
    ]
    groups = sorted({(r["scene"], r["n"], r["order"], r["grid"]) for r in rows}, key=lambda g: (g[0], g[2]))
    for scene, n, order, grid in groups:
        sub = [r for r in rows if (r["scene"], r["n"], r["order"]) == (scene, n, order)]
        lines += [f"## {scene} ({n:,} Gaussians), {order} order, {grid} grid", ""]
        lines += ["### Positions (16 bit, 3 axes): one 16-bit plane vs two 8-bit planes", "",
                  "| form | codec | bytes | bits/s | enc ms | dec ms |", "|---|---|---:|---:|---:|---:|"]  # fmt: skip
        for r in sorted((r for r in sub if r["section"] == "position"), key=lambda r: r["bytes"]):
            lines.append(f"| {r['form']} | {label(r)} | {r['bytes']:,} | {r['bits_per_sample']:.2f} | {r['enc_s'] * 1e3:.0f} | {r['dec_s'] * 1e3:.0f} |")
        lossless = [r for r in sub if r["section"] == "lossless"]
        attributes = list(dict.fromkeys(r["attribute"] for r in lossless))
        codecs = list(dict.fromkeys(label(r) for r in lossless))
        lines += ["", "### 10-bit attributes, lossless: bits/s (enc ms / dec ms)", "",
                  "| codec | " + " | ".join(attributes) + " | total bytes |",
                  "|---|" + "---:|" * (len(attributes) + 1)]  # fmt: skip
        for codec in codecs:
            cells, total = [], 0
            for attribute in attributes:
                match = [r for r in lossless if label(r) == codec and r["attribute"] == attribute]
                if match:
                    r = match[0]
                    total += r["bytes"]
                    cells.append(f"{r['bits_per_sample']:.2f} ({r['enc_s'] * 1e3:.0f} / {r['dec_s'] * 1e3:.0f})")
                else:
                    cells.append("-")
            complete = all(c != "-" for c in cells)
            lines.append(f"| {codec} | " + " | ".join(cells) + f" | {total:,}{'' if complete else ' (partial)'} |")
        lossy = [r for r in sub if r["section"] == "lossy"]
        if lossy:
            lines += ["", "### HEVC lossy (10 bit): bytes / PSNR dB (peak 1023); encode s at QP 17", "",
                      "| attribute | codec | " + " | ".join(f"QP {q}" for q in LOSSY_QPS) + " | enc s QP17 | dec ms QP17 |",
                      "|---|---|" + "---:|" * (len(LOSSY_QPS) + 2)]  # fmt: skip
            for attribute in dict.fromkeys(r["attribute"] for r in lossy):
                for codec in dict.fromkeys(label(r) for r in lossy if r["attribute"] == attribute):
                    by_qp = {r["qp"]: r for r in lossy if r["attribute"] == attribute and label(r) == codec}
                    cells = [f"{by_qp[q]['bytes']:,} / {by_qp[q]['psnr']:.2f}" for q in LOSSY_QPS]
                    r17 = by_qp[17]
                    lines.append(f"| {attribute} | {codec} | " + " | ".join(cells) + f" | {r17['enc_s']:.2f} | {r17['dec_s'] * 1e3:.0f} |")
            lines += ["", f"BD-rate (bytes at equal PSNR, QP {LOSSY_QPS[0]}-{LOSSY_QPS[-1]}) against `{ANCHOR}`; "
                      "negative = smaller:", "", "| attribute | " + " | ".join(LOSSY_LABELS) + " |",
                      "|---|" + "---:|" * len(LOSSY_LABELS)]  # fmt: skip
            for attribute in dict.fromkeys(r["attribute"] for r in lossy):
                curves = {}
                for r in lossy:
                    if r["attribute"] == attribute:
                        curves.setdefault(label(r), []).append((r["bytes"], r["psnr"]))
                cells = [f"{bd_rate(curves[ANCHOR], curves[c]):+.1%}" if c in curves else "-" for c in LOSSY_LABELS]
                lines.append(f"| {attribute} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="/tmp/bench_codecs", help="folder for results.json and cached orders")
    parser.add_argument("--markdown", help="write the markdown tables here (e.g. docs/benchmarks_codecs.md)")
    parser.add_argument("--scenes", nargs="+", default=["bonsai", "synthetic"], choices=["bonsai", "synthetic"])
    parser.add_argument("--orders", nargs="+", default=["morton", "plas"], choices=["morton", "plas"])
    parser.add_argument("--lossy-orders", nargs="+", default=["morton", "plas"], choices=["morton", "plas"])
    parser.add_argument("--synthetic-n", type=int, default=75_000)
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (1 for HEVC on the 45 SH channels)")
    parser.add_argument("--sections", nargs="+", default=SECTIONS, choices=SECTIONS, help="what to measure")
    parser.add_argument("--reuse", help="a previous results.json whose rows of the other sections are kept")
    args = parser.parse_args()
    command = "python scripts/bench_grid_codecs.py " + " ".join(sys.argv[1:])
    rows = run(args)
    (Path(args.out) / "results.json").write_text(json.dumps(rows, indent=1, default=float))
    text = markdown(rows, command)
    if args.markdown:
        Path(args.markdown).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
