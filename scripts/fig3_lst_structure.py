"""Paper Fig. 3: the structure of SHAC-LST's transformation T (d x K', eq. 32-34).

Draws which entries of T are fixed to 1 (the subset passes through), learnable (the blocks t_l
of eq. 34, joint RGB) or fixed to 0, for the paper's layout and the ablation layouts of Table
VII / IX (highest-degree subset, dense structure), from :func:`gscodec_shac.shac.lst.lst_layout`,
and prints d, K' and P_T (eq. 34: 306 for L = 3).

    python scripts/fig3_lst_structure.py --out docs/figures/fig3_lst_structure.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gscodec_shac.shac.lst import lst_layout


def pattern(degree: int, subset: str, structure: str) -> tuple[np.ndarray, int, int]:
    layout = lst_layout(degree, subset, structure)
    image = np.zeros((layout.d, layout.n_ac_columns))
    image[np.arange(layout.d), layout.subset_columns] = 1.0  # identity part
    for b in layout.blocks:
        image[np.ix_(b.input_rows, b.output_columns)] = 0.5  # learnable
    return image, layout.d, layout.n_params


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--degree", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true", help="(no effect: the figure is instant)")
    args = parser.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cases = [("lowest", "block", "paper: lowest l per m, block-diagonal"),
             ("highest", "block", "Table VII: highest l per m"), ("lowest", "dense", "Table IX: dense T")]
    fig, axes = plt.subplots(len(cases), 1, figsize=(7.5, 2.0 * len(cases)))
    cmap = ListedColormap(["#f2f2f2", "#e6862a", "#1f4e9a"])
    for ax, (subset, structure, title) in zip(axes, cases):
        image, d, p_t = pattern(args.degree, subset, structure)
        ax.imshow(image, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"{title}: d = {d}, K' = {image.shape[1]}, learnable P_T = {p_t} "
                     "(blue 1 = subset passes through, orange = learnable, grey = 0)", fontsize=7)
        ax.set_xlabel("AC column (paper order: degree, order, RGB)", fontsize=7)
        ax.set_ylabel("subset row", fontsize=7)
        ax.tick_params(labelsize=6)
        print(f"{subset}/{structure}: d = {d}, K' = {image.shape[1]}, P_T = {p_t}")
    fig.tight_layout(pad=0.3)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
