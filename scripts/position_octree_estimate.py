"""How far the set coder of positions is from a context-modelled octree (issue 29, a lead measured).

Set coding (``gscodec_shac/codec/positions.py``) codes the sorted Morton codes of the quantised
log-positions as gaps. An octree coder (G-PCC style) codes, level by level, which of each occupied
node's eight children are occupied, each bit under an adaptive model of its context. This script
estimates the bytes of such a coder without writing one: the ideal code length of every occupancy
bit under adaptive counts (both starting at 1) per context = (depth, occupied neighbours of the
parent among its 6 face neighbours, child index, children of the node found occupied before it).
Duplicate points (equal codes, which the set coder codes as zero gaps) are counted, not coded, so
the estimate is a lower bound for an octree coder. Prints one line per bit depth.

    python scripts/position_octree_estimate.py ../outputs/train/lego_train_l3_d45/point_cloud.ply \\
        --bits 12,13,14 --min-opacity 0.05
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscodec_shac.codec import quantize as qz  # noqa: E402
from gscodec_shac.codec.positions import encode_sorted_codes, morton_encode  # noqa: E402

NEIGHBOURS = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
MAX_DEPTH_CONTEXT = 16


def adaptive_code_length(contexts: np.ndarray, bits: np.ndarray, n_contexts: int) -> float:
    """Bits to code ``bits`` in order, each with the adaptive probability of its context."""
    zeros, ones = np.ones(n_contexts), np.ones(n_contexts)
    total = 0.0
    for context, bit in zip(contexts.tolist(), bits.tolist()):
        count = ones[context] if bit else zeros[context]
        total -= math.log2(count / (zeros[context] + ones[context]))
        if bit:
            ones[context] += 1
        else:
            zeros[context] += 1
    return total


def octree_bits(points: np.ndarray, depth: int) -> float:
    """The estimated code length (bits) of the distinct integer ``points`` (M, 3) in an octree of ``depth``."""
    total = 0.0
    n_contexts = MAX_DEPTH_CONTEXT * 7 * 8 * 9
    for level in range(depth):
        shift = depth - level - 1
        parents = np.unique(points >> (shift + 1), axis=0)
        children = np.unique(points >> shift, axis=0)
        index = {tuple(p): i for i, p in enumerate(parents.tolist())}
        masks = np.zeros(len(parents), np.int64)
        for child in children.tolist():
            slot = (child[0] & 1) << 2 | (child[1] & 1) << 1 | (child[2] & 1)
            masks[index[(child[0] >> 1, child[1] >> 1, child[2] >> 1)]] |= 1 << slot
        neighbours = np.array([sum((x + dx, y + dy, z + dz) in index for dx, dy, dz in NEIGHBOURS)
                               for x, y, z in parents.tolist()])
        occupied_before = np.zeros(len(parents), np.int64)
        contexts, bits = [], []
        for slot in range(8):
            bit = (masks >> slot) & 1
            contexts.append(((min(level, MAX_DEPTH_CONTEXT - 1) * 7 + neighbours) * 8 + slot) * 9 + occupied_before)
            bits.append(bit)
            occupied_before = occupied_before + bit
        total += adaptive_code_length(np.stack(contexts, 1).ravel(), np.stack(bits, 1).ravel(), n_contexts)
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--bits", default="12,13,14", help="comma-separated bits per axis")
    parser.add_argument("--min-opacity", type=float, default=0.0, help="keep the Gaussians at or above this opacity")
    args = parser.parse_args(argv)
    from gscodec_shac.io.models import read_model

    cloud, _ = read_model(args.model)
    if args.min_opacity > 0:
        cloud = cloud.select(np.flatnonzero(cloud.activated_opacities() >= args.min_opacity))
    values = qz.log_transform(cloud.means)
    n = cloud.num_gaussians
    for bits in (int(b) for b in args.bits.split(",")):
        quantizer = qz.Quantizer.fit(values, bits)
        quantized = quantizer.quantize(values)
        set_bytes = len(encode_sorted_codes(np.sort(morton_encode(quantized))))
        distinct = np.unique(quantized.astype(np.int64), axis=0)
        octree_bytes = octree_bits(distinct, bits) / 8
        print(f"{n:,} Gaussians at {bits} bits: set coder {set_bytes:,} B ({8 * set_bytes / n:.2f} bits/G), "
              f"octree estimate {octree_bytes:,.0f} B ({8 * octree_bytes / n:.2f} bits/G; "
              f"{n - len(distinct):,} duplicates not counted): {octree_bytes / set_bytes:.3f} of the set coder",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
