"""Test-PSNR cost of coding a dynamic model's deformation network, the canonical Gaussians left uncompressed.

In one process: the network is coded by the encoder's own ``add_deformation`` (the bits
``encode --network-bits B`` writes, or one matrix at a time at fewer bits with the rest at 8),
decoded by ``decode_weights``, and the scene's test frames are rendered at their times and
compared with the ground truth. Isolates the network's share of the loss that
``scripts/network_bits.py`` measures on whole ``.gsc`` files.

    python scripts/network_sensitivity.py ../outputs/dynamic_s7/standup ../shared/data/scenes/dnerf/standup \\
        --bits 8 7 6 5 4 --per-matrix 3 4 6 --matrix-bits 8,4,4,3,3,6,8,8,8 --json standup_network.json
"""

from __future__ import annotations

import argparse
import json
import sys
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table_dynamic import load_test  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="dynamic model directory")
    parser.add_argument("scene", type=Path, help="D-NeRF scene folder (transforms_test.json)")
    parser.add_argument("--bits", nargs="+", type=int, default=[8, 7, 6, 5, 4], help="--network-bits values")
    parser.add_argument("--per-matrix", nargs="*", type=int, default=[],
                        help="also code each matrix alone at these bits, the others at 8")
    parser.add_argument("--matrix-bits", nargs="*", default=[],
                        help="also these allocations: one comma-separated list of bits per matrix, in order")
    parser.add_argument("--resolution-scale", type=float, default=0.5)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args()

    from gscodec_shac.codec import deformation as coding
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.deform import DeformNetwork, DynamicModel, load_dynamic_model
    from gscodec_shac.train.dynamic import evaluate_dynamic

    capture = load_test(args.scene, args.resolution_scale, [0.0, 0.0, 0.0])
    model = load_dynamic_model(args.model)
    arch = model.arch
    weights = {k: v.detach().numpy().copy() for k, v in model.net.state_dict().items()}
    matrices = list(coding._matrices(arch))

    def measure(bits) -> dict:
        stream = Bitstream()
        size = coding.add_deformation(stream, arch, weights, bits=bits, means=model.cloud.means)
        header = stream.header[coding.CHUNK]
        written = header.get("bits", 16)
        decoded = coding.decode_weights(zlib.decompress(stream.chunk(coding.CHUNK).data), arch, header["dtype"],
                                        tuple(written) if isinstance(written, list) else written)
        net = DeformNetwork(arch)
        net.load_weights(decoded)
        return {"chunk_bytes": size, "psnr": evaluate_dynamic(DynamicModel(model.cloud, net), capture)["mean_psnr"]}

    reference = measure(16)
    rows = [{"variant": "float16", **reference}]
    variants = [(f"{b} bits", coding.encoder_bits(arch, b)) for b in args.bits]
    variants += [(f"{name} at {b} bits", tuple(b if other == name else 8 for other in matrices))
                 for name in matrices for b in args.per_matrix]
    variants += [(f"bits {text}", tuple(int(b) for b in text.split(","))) for text in args.matrix_bits]
    for label, bits in variants:
        row = {"variant": label, **measure(bits)}
        row["vs_float16"] = reference["chunk_bytes"] / row["chunk_bytes"]
        row["psnr_change_db"] = row["psnr"] - reference["psnr"]
        rows.append(row)
        print(f"{label}: {row['chunk_bytes']:,} B, {row['vs_float16']:.2f}x smaller, {row['psnr_change_db']:+.3f} dB",
              flush=True)
    args.json.write_text(json.dumps({"model": str(args.model), "scene": str(args.scene), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
