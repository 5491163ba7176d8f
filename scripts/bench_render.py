"""Benchmark the CPU renderer; writes JSON and a markdown table (docs/benchmarks_render.md).

Rows (each measured in its own subprocess, so peak memory is per row):

* synthetic 1M Gaussians at 1280x800 and 100k at 800x600 (gscodec_shac.synthetic, cached as
  PLYs under --cache-dir), orbit views;
* the real bonsai_cpu_sh3 (75k, SH 3) at 200x133 and at 800x533 (cameras resized), test views.

Per row: median / min seconds per view after a warm-up render (wall clock and process CPU
time, all threads), a stage breakdown (projection, SH colours, sort+binning, blend), peak RSS.
Also: numba compilation from an empty cache vs a cached start (``import + warmup()`` in fresh
processes with a private NUMBA_CACHE_DIR), and the bonsai quality check (PSNR / SSIM of the 37
held-out views at 200x133, black background, against the INTER_AREA-downscaled photos).

    python scripts/bench_render.py                      # everything (about 5-10 minutes)
    python scripts/bench_render.py --rows bonsai_200 --no-compile
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO.parent / "shared" / "data" / "scenes"
BONSAI = SCENES / "bonsai_cpu_sh3"
BONSAI_IMAGES = SCENES / "mipnerf360_bonsai" / "images"

ROWS = {
    "synthetic_1m": {"kind": "synthetic", "n": 1_000_000, "width": 1280, "height": 800, "target_s": 1.5},
    "synthetic_100k": {"kind": "synthetic", "n": 100_000, "width": 800, "height": 600, "target_s": 0.3},
    "bonsai_200": {"kind": "bonsai", "width": 200, "height": 133, "target_s": None},
    "bonsai_800": {"kind": "bonsai", "width": 800, "height": 533, "target_s": None},
}


# ----------------------------------------------------------------------------- one row (child)


def _synthetic_cloud(n: int, cache_dir: Path):
    from gscodec_shac.io.ply import read_ply, write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    path = cache_dir / f"synthetic_{n}_seed0.ply"
    if not path.is_file():
        cache_dir.mkdir(parents=True, exist_ok=True)
        write_ply(path, make_synthetic_scene(n, seed=0, n_cameras=1).cloud)
    return read_ply(path)


def _row_cameras(spec: dict, views: int) -> list:
    from gscodec_shac.camera import orbit_cameras, test_split
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.synthetic import ORBIT_RADIUS, SCENE_CENTER

    if spec["kind"] == "synthetic":
        return orbit_cameras(SCENE_CENTER, ORBIT_RADIUS, views + 1, spec["width"], spec["height"],
                             fov_y_deg=45.0, elevation_deg=28.0, up=(0.0, 0.0, 1.0))
    _, test = test_split(load_cameras(BONSAI / "cameras.json"))
    return [c.resized(spec["width"], spec["height"]) for c in test[: views + 1]]


def run_row(name: str, views: int, cache_dir: Path) -> dict:
    import numba

    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.render import Renderer, warmup
    from gscodec_shac.render.raster import rasterize

    spec = ROWS[name]
    warmup()
    if spec["kind"] == "synthetic":
        cloud = _synthetic_cloud(spec["n"], cache_dir)
    else:
        cloud = read_ply(BONSAI / "point_cloud.ply")
    cameras = _row_cameras(spec, views)
    start = time.perf_counter()
    renderer = Renderer(cloud)
    setup_s = time.perf_counter() - start
    renderer.render(cameras[0])  # warm-up: workspace allocation, page faults
    walls, cpus, stages, counts = [], [], [], []
    for camera in cameras[1:]:
        w0, c0 = time.perf_counter(), time.process_time()
        result = renderer.render(camera)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
        counts.append((result.n_visible, result.n_pairs))
        # stage breakdown, measured on a second pass of the same view
        t0 = time.perf_counter()
        frame = renderer.prepare(camera)
        t1 = time.perf_counter()
        rasterize(frame.bins, camera.width, camera.height)
        t2 = time.perf_counter()
        stages.append({"prepare_s": t1 - t0, "blend_s": t2 - t1})
    return {
        "row": name,
        "gaussians": cloud.num_gaussians,
        "sh_degree": cloud.sh_degree,
        "width": cameras[0].width,
        "height": cameras[0].height,
        "views": len(walls),
        "threads": numba.get_num_threads(),
        "median_s": statistics.median(walls),
        "min_s": min(walls),
        "median_cpu_s": statistics.median(cpus),
        "prepare_median_s": statistics.median(s["prepare_s"] for s in stages),
        "blend_median_s": statistics.median(s["blend_s"] for s in stages),
        "visible_median": int(statistics.median(c[0] for c in counts)),
        "tile_pairs_median": int(statistics.median(c[1] for c in counts)),
        "renderer_setup_s": setup_s,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "target_s": spec["target_s"],
        "load_avg_1min_after": os.getloadavg()[0],
    }


def stage_breakdown(views: int, cache_dir: Path) -> dict:
    """Per-stage medians for the 1M row: projection, colours, sort + binning, blend."""
    import numpy as np

    from gscodec_shac.render import Renderer, warmup
    from gscodec_shac.render.binning import bin_gaussians
    from gscodec_shac.render.projection import P_R
    from gscodec_shac.render.raster import rasterize
    from gscodec_shac.render.shading import view_colors

    warmup()
    spec = ROWS["synthetic_1m"]
    cloud = _synthetic_cloud(spec["n"], cache_dir)
    renderer = Renderer(cloud)
    cameras = _row_cameras(spec, views)
    renderer.render(cameras[0])
    rows = []
    for camera in cameras[1:]:
        ws = renderer._workspace()
        t = [time.perf_counter()]
        proj = renderer._project(camera)
        t.append(time.perf_counter())
        view_colors(renderer.means, cloud.sh_dc, cloud.sh_rest, camera.center, proj.radii > 0, ws.pack_n, P_R)
        t.append(time.perf_counter())
        bins = bin_gaussians(ws.keys, ws.pack_n, ws.rects_n, camera.width, camera.height, ws.order, ws.pack, ws.rects)
        t.append(time.perf_counter())
        rasterize(bins, camera.width, camera.height, ws.pixels)
        t.append(time.perf_counter())
        rows.append(np.diff(t))
    med = np.median(np.array(rows), axis=0)
    return dict(zip(("projection_s", "sh_colours_s", "sort_and_binning_s", "blend_s"), (float(v) for v in med)))


def bonsai_quality() -> dict:
    import numpy as np

    from gscodec_shac.camera import test_split
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import load_image, psnr, ssim
    from gscodec_shac.render import Renderer

    cloud = read_ply(BONSAI / "point_cloud.ply")
    _, test = test_split(load_cameras(BONSAI / "cameras.json", BONSAI_IMAGES))
    renderer = Renderer(cloud)
    psnrs, ssims = [], []
    for camera in test:
        image = renderer.render(camera, background=(0.0, 0.0, 0.0)).image
        truth = load_image(camera.image_path, size=(camera.width, camera.height))
        psnrs.append(psnr(image, truth))
        ssims.append(ssim(image, truth))
    trainer = json.loads((BONSAI / "train_summary.json").read_text())
    ref = np.array(trainer["test_psnr_list"])
    return {
        "views": len(test),
        "psnr_mean": float(np.mean(psnrs)),
        "ssim_mean": float(np.mean(ssims)),
        "trainer_psnr_mean": float(trainer["test_psnr"]),
        "max_abs_view_psnr_diff_db": float(np.max(np.abs(np.array(psnrs) - ref))),
    }


def compile_times() -> dict:
    """``import + warmup()`` in fresh processes: empty numba cache, then the filled one."""
    code = (
        "import time; t = time.perf_counter(); from gscodec_shac.render import warmup; warmup(); "
        "print(time.perf_counter() - t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        cold = float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                    check=True).stdout.split()[-1])
        warm = float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                    check=True).stdout.split()[-1])
    return {"first_call_empty_cache_s": cold, "cached_start_s": warm}


# ----------------------------------------------------------------------------- parent


def _child(task: str, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--child", task, "--views", str(args.views), "--cache-dir", str(args.cache_dir)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{task} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def markdown(report: dict) -> str:
    lines = [
        "# Renderer benchmarks (CPU)",
        "",
        f"Machine: {report['machine']}; numba threads {report['threads']}. 1-minute load average before / after "
        f"the run: {report['load_before']:.1f} / {report['load_after']:.1f}. The machine is shared with other jobs: "
        "wall-clock times under load overstate an idle machine, so the CPU time of the process (all threads "
        "together) is reported too.",
        "",
        "Command: `python scripts/bench_render.py` (add `--json PATH` for the JSON; it is also at the end of "
        "this file). Median and minimum over the timed views, after one warm-up view; `prepare` = projection + "
        "SH colours + sort + tile lists, `blend` = the per-pixel pass; peak RSS includes reading the PLY.",
        "",
        "| scene | Gaussians | size | views | median s/view | min s/view | CPU s/view | prepare s | blend s "
        "| tile pairs | peak RSS MB | target | met (median) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in report["rows"]:
        target = f"<= {row['target_s']} s" if row["target_s"] else "-"
        met = "-" if not row["target_s"] else ("yes" if row["median_s"] <= row["target_s"] else "**no**")
        lines.append(
            f"| {row['row']} | {row['gaussians']:,} | {row['width']}x{row['height']} | {row['views']} | "
            f"{row['median_s']:.3f} | {row['min_s']:.3f} | {row['median_cpu_s']:.3f} | {row['prepare_median_s']:.3f} | "
            f"{row['blend_median_s']:.3f} | {row['tile_pairs_median']:,} | {row['peak_rss_mb']:.0f} | {target} | {met} |"
        )
    if "stages_1m" in report:
        s = report["stages_1m"]
        total = sum(s.values())
        lines += ["", "Stages of the 1M row (median wall s, share): " + ", ".join(
            f"{k[:-2].replace('_', ' ')} {v:.3f} ({100 * v / total:.0f}%)" for k, v in s.items())]
    if "compile" in report:
        c = report["compile"]
        lines += ["", f"Numba compilation (`import` + `warmup()` in a fresh process): empty cache "
                  f"{c['first_call_empty_cache_s']:.1f} s, cached start {c['cached_start_s']:.1f} s "
                  "(kernels use `cache=True`; the cache lives in `gscodec_shac/render/__pycache__`, or under "
                  "`NUMBA_CACHE_DIR`)."]
    if "quality" in report:
        q = report["quality"]
        lines += ["", f"Quality check, bonsai_cpu_sh3: {q['views']} held-out views (every 8th) at 200x133, black "
                  f"background, against the photos downscaled with INTER_AREA: **PSNR {q['psnr_mean']:.3f} dB** "
                  f"(the trainer's independent exact 3DGS renderer: {q['trainer_psnr_mean']:.3f} dB; largest "
                  f"per-view difference {q['max_abs_view_psnr_diff_db']:.1e} dB), SSIM {q['ssim_mean']:.4f}."]
    lines += ["", NOTES, "", "```json", json.dumps(report, indent=1), "```", ""]
    return "\n".join(lines)


NOTES = """## Notes

- **What dominates.** The per-pixel blend (see the stage shares), then sorting + binning;
  projection and SH colours are cheap. The synthetic 1M scene at 1280x800 walks ~1.3M
  (tile, Gaussian) pairs, ~7M row segments and ~19M contributions (~18 per pixel). Single-thread
  experiments on the blend: removing the per-row `exp` (a 2-D recurrence), branch-free pixel
  updates or dropping the depth accumulation each changed it by less than 5%; storing the
  parameter rows in tile-list order (sequential reads) saved ~20% of the blend but costs about as
  much extra in binning, so it was not kept.
- **Exact shortcuts** (the image is unchanged; the dense reference in the tests agrees to ~3e-8):
  a Gaussian is listed only for tiles its alpha >= 1/255 ellipse reaches (inside the reference's
  3-sigma rectangle), only pixels in that ellipse and not yet stopped are visited, `exp` along a
  row is a multiplicative recurrence, buffers are reused between views (fresh 100 MB arrays per
  view cost page faults), and a 64-bit key sort (float32 depth bits, index) replaces a stable
  argsort (20 ms instead of 150 ms at 1M).
- **Threads.** numba's OpenMP layer; importing `gscodec_shac.render` sets `OMP_WAIT_POLICY=PASSIVE`
  unless set, because spinning threads multiplied the CPU time of short parallel stages on this
  shared machine.
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", nargs="*", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--views", type=int, default=5, help="timed views per row (after one warm-up view)")
    parser.add_argument("--cache-dir", type=Path, default=Path(tempfile.gettempdir()) / "gscodec_bench")
    parser.add_argument("--no-compile", action="store_true", help="skip the compilation timing")
    parser.add_argument("--no-quality", action="store_true", help="skip the bonsai PSNR check")
    parser.add_argument("--json", type=Path, help="also write the JSON report here")
    parser.add_argument("--markdown", type=Path, default=REPO / "docs" / "benchmarks_render.md")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.child:
        if args.child == "stages":
            result = stage_breakdown(args.views, args.cache_dir)
        elif args.child == "quality":
            result = bonsai_quality()
        else:
            result = run_row(args.child, args.views, args.cache_dir)
        print(json.dumps(result))
        return 0

    import numba

    from gscodec_shac.render import warmup

    warmup()  # fills the on-disk cache before the timed children start
    report: dict = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {platform.python_version()}",
        "threads": numba.get_num_threads(),
        "load_before": os.getloadavg()[0],
        "rows": [],
    }
    for name in args.rows:
        print(f"row {name} ...", file=sys.stderr)
        report["rows"].append(_child(name, args))
    if "synthetic_1m" in args.rows:
        print("stages ...", file=sys.stderr)
        report["stages_1m"] = _child("stages", args)
    if not args.no_quality:
        print("quality ...", file=sys.stderr)
        report["quality"] = _child("quality", args)
    if not args.no_compile:
        print("compile ...", file=sys.stderr)
        report["compile"] = compile_times()
    report["load_after"] = os.getloadavg()[0]
    text = markdown(report)
    args.markdown.parent.mkdir(parents=True, exist_ok=True)
    args.markdown.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
