"""Paper Fig. 2: real SH basis functions y_l^m (l = 1..3) on the sphere, laid out by order m, to
show that bases of the same order share the same longitude (azimuthal) frequency |m|.

Each panel is an equirectangular map (longitude phi across, polar angle theta down) of
:func:`gscodec_shac.sh.sh_basis`; a row is a degree l, a column an order m. Along any line of
latitude y_l^m varies as cos(m phi) or sin(|m| phi), whatever l is: the columns are what
SHAC-LST's subset selection keeps one member of (eq. 32).

    python scripts/fig2_sh_basis.py --out docs/figures/fig2_sh_basis.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.sh import sh_basis


def basis_maps(degree: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta, phi, values (H, 2H, (degree+1)^2)) on an equirectangular grid."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(2 * height) + 0.5) / (2 * height) * 2 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    return theta, phi, sh_basis(dirs, degree)


def azimuthal_frequency(values: np.ndarray) -> int:
    """Dominant frequency of a basis map along longitude (FFT of the equator row)."""
    row = values[values.shape[0] // 2 - 1] if np.abs(values[values.shape[0] // 2 - 1]).max() > 1e-9 else values[values.shape[0] // 4]
    spectrum = np.abs(np.fft.rfft(row - row.mean()))
    return int(np.argmax(spectrum)) if spectrum.max() > 1e-9 else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--degree", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true", help="coarser maps")
    args = parser.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    L = args.degree
    _, _, values = basis_maps(L, 24 if args.quick else 64)
    fig, axes = plt.subplots(L, 2 * L + 1, figsize=(1.45 * (2 * L + 1), 0.95 * L + 0.4), squeeze=False)
    for l in range(1, L + 1):
        for m in range(-L, L + 1):
            ax = axes[l - 1][m + L]
            ax.axis("off")
            if abs(m) > l:
                continue
            v = values[..., sh_index.coeff_index(l, m)]
            freq = azimuthal_frequency(v)
            assert freq == abs(m), (l, m, freq)  # the property the figure shows
            ax.imshow(v, cmap="coolwarm", vmin=-np.abs(v).max(), vmax=np.abs(v).max(), aspect="auto")
            ax.set_title(f"l={l}, m={m}", fontsize=7)
    fig.suptitle("real SH bases by order m (columns): same m = same longitude frequency |m|", fontsize=8)
    fig.tight_layout(pad=0.2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=75)
    print(f"wrote {args.out} (every basis checked: its longitude frequency is |m|)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
