"""``gscodec-shac analyze SCENE.ply ...``: the low-rank analysis of paper Table I and Fig. 1.

For each scene: rank needed for ``--er`` energy and energy captured by ``--k``
components, for the SVD of the standardised AC matrix (eq. 23-26) and for
degree-order truncation (raw, centred and standardised energy; see
:mod:`gscodec_shac.shac.analysis`), plus one average row per SH degree present. With ``--out DIR`` it
writes ``table.json``, ``table.csv``, one correlation heatmap per scene
(``correlation_<scene>.png``) and ``er_curves.png``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

from gscodec_shac.commands._options import add_command, add_force, add_quiet

#: Columns of the printed table: (header, TableRow field, is a fraction).
PRINTED = (
    ("SVD rank", "svd_rank", False),
    ("trunc rank raw", "trunc_raw_rank", False),
    ("trunc rank ctr", "trunc_centred_rank", False),
    ("SVD E@k", "svd_energy", True),
    ("trunc E@k raw", "trunc_raw_energy", True),
    ("trunc E@k ctr", "trunc_centred_energy", True),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "analyze",
        help="low-rank analysis of SH AC coefficients (paper Table I, Fig. 1)",
        description="Rank at an energy-retention target and energy at k components of the SH AC matrix, "
        "for the SVD of the standardised matrix and for degree truncation, per scene and averaged per SH degree "
        "(paper Table I); with --out, correlation heatmaps (Fig. 1) and ER curves as PNG. Several "
        "scenes go in, so the output folder stays an option.",
        examples=["gscodec-shac analyze a.ply b.ply --er 0.95 --k 24 --out analysis/",
                  "gscodec-shac analyze --synthetic 100000 --seeds 0 1 2"],
    )
    parser.add_argument("scenes", nargs="*", metavar="SCENE", help="models with SH degree >= 1 (Inria .ply, .spz, "
                        ".sog, compressed.ply, gsplat .pt, a .gsc, ...)")
    parser.add_argument("--er", type=float, default=0.95, help="energy retention target (default 0.95)")
    parser.add_argument("--k", type=int, default=24, help="components / columns for the energy column (default 24)")
    parser.add_argument("--out", metavar="DIR",
                        help="directory for table.json, table.csv and the PNGs (default: print only)")
    parser.add_argument("--synthetic", type=int, metavar="N", help="also analyse a generated N-Gaussian SH-3 scene")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="SEED",
                        help="seeds of the synthetic scenes (default 0)")
    parser.add_argument(
        "--drop-untouched", action="store_true",
        help="drop Gaussians whose AC coefficients (f_rest) are all zero before analysing",
    )
    add_quiet(parser)
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscodec_shac.errors import ValidationError
    from gscodec_shac.shac.analysis import average_rows, check_energy_target

    check_energy_target(args.er)
    if not args.scenes and args.synthetic is None:
        raise ValidationError("give at least one SCENE.ply or --synthetic N")
    if args.synthetic is not None and not 1_000 <= args.synthetic <= 20_000_000:
        raise ValidationError(f"--synthetic must be between 1,000 and 20,000,000 Gaussians, got {args.synthetic}")
    if args.out:
        from gscodec_shac.atomic import check_outputs, protect_inputs

        protect_inputs(*args.scenes)
        if Path(args.out).exists() and not Path(args.out).is_dir():
            raise ValidationError(f"{args.out}: --out must be a directory, this is a file")
        check_outputs([Path(args.out) / name for name in ("table.json", "table.csv", "er_curves.png")],
                      force=args.force)
    from tqdm import tqdm

    total = len(args.scenes) + (len(args.seeds) if args.synthetic is not None else 0)
    results = [_analyse(name, ac, args) for name, ac in tqdm(_load_scenes(args), total=total, desc="analyze",
                                                             unit="scene", disable=args.quiet, leave=False)]
    rows = [row for row, _ in results]
    averages = average_rows(rows)  # one per SH degree: ranks of different degrees do not mix
    print(format_table(rows, averages))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_outputs(out, rows, averages, [extra for _, extra in results])
        print(f"wrote {out / 'table.json'}, {out / 'table.csv'} and {len(rows) + 1} PNGs in {out}")
    return 0


def _load_scenes(args: argparse.Namespace):
    """Yield (name, AC matrix) for every PLY and synthetic scene asked for."""
    from gscodec_shac.errors import ValidationError
    from gscodec_shac.io.models import read_model, report_notes
    from gscodec_shac.synthetic import make_synthetic_scene

    for path in args.scenes:
        cloud, notes = read_model(path)
        report_notes(notes)
        if cloud.sh_degree < 1:
            raise ValidationError(f"{path}: SH degree 0 has no AC coefficients to analyse")
        yield scene_name(Path(path)), cloud.ac_matrix()
    if args.synthetic is not None:
        for seed in args.seeds:
            cloud = make_synthetic_scene(args.synthetic, seed=seed, progress=not args.quiet).cloud
            yield f"synthetic_{args.synthetic}_s{seed}", cloud.ac_matrix()


def scene_name(path: Path) -> str:
    """Directory name for ``.../NAME/point_cloud.ply`` (Inria layout), else the file stem."""
    if path.stem == "point_cloud":
        parents = [p.name for p in path.resolve().parents if p.name and p.name != "point_cloud"
                   and not p.name.startswith("iteration_")]
        return parents[0] if parents else path.stem
    return path.stem


def _analyse(name: str, ac, args: argparse.Namespace):
    from gscodec_shac.errors import ValidationError
    from gscodec_shac.shac import analysis

    untouched = analysis.untouched_mask(ac)
    n_untouched = int(untouched.sum())
    if args.drop_untouched:
        ac = ac[~untouched]
        name = f"{name} (touched)"
        if ac.shape[0] < 2:
            raise ValidationError(f"{name}: fewer than 2 Gaussians have non-zero AC coefficients")
    if args.k > ac.shape[1]:
        raise ValidationError(f"{name}: --k {args.k} exceeds its {ac.shape[1]} AC columns")
    moments = analysis.column_moments(ac)
    row = analysis.table_row(name, ac, args.er, args.k, n_untouched=n_untouched)
    extra = {
        "correlation": analysis.correlation_matrix(ac, moments),
        "svd_curve": analysis.svd_energy_curve(ac, "standardized", moments),
        "trunc_raw_curve": analysis.truncation_energy_curve(ac, "raw", moments),
    }
    return row, extra


def format_table(rows, averages: list[dict]) -> str:
    """Plain-text Table I: ranks, then energies in percent."""
    width = max(12, *(len(r.scene) for r in rows))
    k, er = rows[0].k, rows[0].er
    header = f"{'scene':<{width}} {'N':>9} " + " ".join(f"{h:>14}" for h, _, _ in PRINTED)
    lines = [f"rank at ER={er:g}; energy at k={k} (E@k, %); raw/ctr = truncation on raw/mean-centred coefficients",
             header, "-" * len(header)]
    for item in [r.to_dict() for r in rows] + averages:
        cells = [_cell(item[f], pct) for _, f, pct in PRINTED]
        lines.append(f"{item['scene']:<{width}} {int(round(item['n_gaussians'])):>9,} " + " ".join(cells))
    return "\n".join(lines)


def _cell(value, percent: bool) -> str:
    if percent:
        return f"{value * 100:14.1f}"
    return f"{value:14.1f}" if isinstance(value, float) else f"{value:14d}"


def write_outputs(out: Path, rows, averages: list[dict], extras: list[dict]) -> None:
    """table.json, table.csv, correlation_<scene>.png per scene and er_curves.png."""
    from gscodec_shac import sh_index
    from gscodec_shac.atomic import write_atomic

    write_atomic(out / "table.json", json.dumps({"rows": [r.to_dict() for r in rows], "averages": averages,
                                                     "average": averages[0] if len(averages) == 1 else None}, indent=2))
    fields = [f for f in rows[0].to_dict() if f not in ("degree_energy_raw", "mean_abs_correlation")]
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    for item in [r.to_dict() for r in rows] + averages:
        writer.writerow({f: item.get(f, "") for f in fields})
    write_atomic(out / "table.csv", text.getvalue())
    for row, extra in zip(rows, extras):
        degree = sh_index.degree_from_rest_count(row.n_ac_columns // 3)
        plot_correlation(extra["correlation"], sh_index.ac_column_labels(degree), row.scene,
                         out / f"correlation_{slug(row.scene)}.png")
    plot_er_curves(rows, extras, out / "er_curves.png")


def slug(name: str) -> str:
    """A file-name-safe version of a scene name."""
    keep = [c if c.isalnum() or c in "-_." else "_" for c in name.replace(" (touched)", "_touched")]
    return "".join(keep).strip("_") or "scene"


def plot_correlation(corr, labels: list[str], title: str, path: Path) -> None:
    """Fig. 1 style heatmap of the Pearson correlation matrix (eq. 24)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(labels)
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=100)
    image = ax.imshow(corr, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    ax.set_xticks(range(n), labels, rotation=90, fontsize=4)
    ax.set_yticks(range(n), labels, fontsize=4)
    start, l = 0, 1
    while start + 3 * (2 * l + 1) < n:  # separators between degrees
        start += 3 * (2 * l + 1)
        ax.axhline(start - 0.5, color="k", lw=0.5)
        ax.axvline(start - 0.5, color="k", lw=0.5)
        l += 1
    ax.set_title(f"Pearson correlation of SH AC coefficients: {title}", fontsize=8)
    fig.colorbar(image, ax=ax, fraction=0.046, pad=0.03)
    fig.tight_layout()
    _save_figure(fig, path)
    plt.close(fig)


def plot_er_curves(rows, extras: list[dict], path: Path) -> None:
    """ER(r) of the standardised SVD (solid) and of raw degree truncation (dashed) per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=100)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (row, extra) in enumerate(zip(rows, extras)):
        colour = colours[i % len(colours)]
        r = np.arange(1, row.n_ac_columns + 1)
        ax.plot(r, 100 * extra["svd_curve"], color=colour, lw=1.4, label=f"{row.scene}: SVD of A'")
        ax.plot(r, 100 * extra["trunc_raw_curve"], color=colour, lw=1.0, ls="--",
                label=f"{row.scene}: truncation (raw)")
    ax.axhline(100 * rows[0].er, color="0.4", lw=0.6, ls=":")
    ax.axvline(rows[0].k, color="0.4", lw=0.6, ls=":")
    ax.set_xlabel("components r (SVD) / AC columns kept in degree order (truncation)")
    ax.set_ylabel("energy retention ER(r) [%]")
    ax.set_ylim(0, 101)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    _save_figure(fig, path)
    plt.close(fig)


def _save_figure(fig, path: Path) -> None:
    """A matplotlib figure as a PNG, written atomically."""
    from gscodec_shac.atomic import atomic_output

    with atomic_output(path) as handle:
        fig.savefig(handle, format="png")
