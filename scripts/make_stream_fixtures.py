"""Write the legacy-stream fixtures: small ``.gsc`` files and the arrays they decode to.

Files users already have must keep opening. This script encodes two small input PLYs
(``tests/fixtures/streams/input_sh3.ply``, ``input_sh0.ply``; written once from the seeded
synthetic scene when absent) with a spread of settings (every SH stage, every lossless
layout, each grid codec that needs no external binary) and stores, per case,

* ``<version>/<case>.gsc``  the stream written by this version of the codec,
* ``<version>/<case>.npz``  the arrays it decodes to (float32, grid order),

plus ``<version>/manifest.json`` (the settings, the SHA-256 of each stream and the codec
versions that made it). ``tests/test_legacy_streams.py`` decodes every stream of every
version to exactly the stored arrays and, for the current version, re-encodes the inputs
and compares the hashes (golden hashes). Run it once per container version, never to
"fix" a failing test (an intended change of the encoder's output records new golden hashes
beside the stored streams with ``--record-encoder-change "REASON"``):

    python scripts/make_stream_fixtures.py --version 1.0
    python scripts/make_stream_fixtures.py --version 2.0
    python scripts/make_stream_fixtures.py --version 2.1
    python scripts/make_stream_fixtures.py --version 2.2
    python scripts/make_stream_fixtures.py --version 2.3
    python scripts/make_stream_fixtures.py --version 2.4
    python scripts/make_stream_fixtures.py --version 2.5
    python scripts/make_stream_fixtures.py --version 2.6

(v2.4's ``ladder_rp5_pca_spatial`` was added later, written by the code of commit 99e3bb0, the last
before format 2.5 changed what the ``pca-spatial`` stage writes by default.)
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "streams"

#: Container 1.0 cases: case -> (input, rate point, SH stage, stage parameters, sort override)
CASES_V1: dict[str, dict] = {
    "table3_rp2_none": {"input": "input_sh3.ply", "rate_point": "paper_table3:rp2", "sh": "none", "params": {}},
    "table3_rp1_pca": {"input": "input_sh3.ply", "rate_point": "paper_table3:rp1", "sh": "pca",
                       "params": {"energy_retention": 0.95}},
    "table3_rp3_pca_dc": {"input": "input_sh3.ply", "rate_point": "paper_table3:rp3", "sh": "pca",
                          "params": {"n_components": 12, "include_dc": True}},
    "recommended_rp3_lst": {"input": "input_sh3.ply", "rate_point": "shac_recommended:rp3", "sh": "lst",
                            "params": {}},
    "mpeg_rp01_trunc_morton": {"input": "input_sh3.ply", "rate_point": "mpeg_ctc_video:rp01", "sh": "trunc",
                               "params": {"degree": 1}, "sort": "morton"},
    "gsplat_png_vq": {"input": "input_sh3.ply", "rate_point": "gsplat_png:default", "sh": "vq",
                      "params": {"n_clusters": 32}},
    "gscodec_studio_rp0_sh0": {"input": "input_sh0.ply", "rate_point": "gscodec_studio:rp0", "sh": None,
                               "params": {}, "sort": "random"},
    "custom_lossless_drop": {"input": "input_sh3.ply", "rate_point": "custom_points.yaml:lossless_drop", "sh": None,
                             "params": {}},
}
#: Container 2.0 cases: set-coded positions (feature positions_set), pruning, water-filled SH QPs,
#: a deflated header.
CASES_V2: dict[str, dict] = {
    "ladder_rp1_none": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp1", "sh": "none", "params": {}},
    "ladder_rp6_pca": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp6", "sh": "pca",
                       "params": {"energy_retention": 0.97}},
    "auto_template_waterfill": {"input": "input_sh3.ply", "rate_point": "shac_auto:template", "sh": None, "params": {}},
    "ladder_rp4_sh0": {"input": "input_sh0.ply", "rate_point": "shac_ladder:rp4", "sh": None, "params": {}},
}
#: Container 2.1 cases: a dynamic model (canonical Gaussians + the small network of
#: ``network_small.npz``, architecture :data:`SMALL_ARCH`), network quantised to 8 bits per row
#: (feature deformation_quantised).
SMALL_ARCH = {"depth": 3, "width": 24, "xyz_freqs": 2, "t_freqs": 2, "time_net": True, "time_width": 16,
              "time_out": 6}
CASES_V21: dict[str, dict] = {
    "dynamic_rp2_net8": {"input": "input_sh3.ply", "rate_point": "paper_table3:rp2", "sh": "none", "params": {},
                         "network": "network_small.npz", "arch": SMALL_ARCH, "network_bits": 8},
}
#: Container 2.2 cases: the same network at 4 bits with the heads at 8 (feature deformation_mixed_bits),
#: codes picked by quantisation-aware rounding.
CASES_V22: dict[str, dict] = {
    "dynamic_rp2_net4_heads8": {"input": "input_sh3.ply", "rate_point": "paper_table3:rp2", "sh": "none",
                                "params": {}, "network": "network_small.npz", "arch": SMALL_ARCH, "network_bits": 4},
}
#: Container 2.3 cases: per-Gaussian SH degree (feature sh_dc_only; ``dc_only_share`` overrides the
#: rate point's): the coded Gaussians' SH on a Z-ordered grid (set-coded positions) and on a raster one.
CASES_V23: dict[str, dict] = {
    "ladder_rp4_pca_dc_only": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp4", "sh": "pca",
                               "params": {"energy_retention": 0.97}, "dc_only_share": 0.5},
    "custom_lossless_drop_dc_only": {"input": "input_sh3.ply", "rate_point": "custom_points.yaml:lossless_drop",
                                     "sh": None, "params": {}, "dc_only_share": 0.3},
}
#: Container 2.4 cases: the rotation coded as a rotation vector (feature rotation_vector; the SHAC-auto
#: template since controller version 19) and the HEVC parameter sets stored once (feature hevc_parameter_sets,
#: every stream that needs format 2).
CASES_V24: dict[str, dict] = {
    "auto_template_rotation_vector": {"input": "input_sh3.ply", "rate_point": "shac_auto:template", "sh": None,
                                      "params": {}},
    "ladder_rp5_pca_parameter_sets": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp5", "sh": "pca",
                                      "params": {"energy_retention": 0.99}},
    "ladder_rp5_pca_spatial": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp5", "sh": "pca-spatial",
                               "params": {"energy_retention": 0.99, "spatial_clusters": 2}},
}
#: Container 2.5 cases: the pca-spatial stage's features scaled per region to unit weights (feature
#: sh_spatial_unit_weights), its bases in float16.
CASES_V25: dict[str, dict] = {
    "ladder_rp5_pca_spatial_unit_weights": {"input": "input_sh3.ply", "rate_point": "shac_ladder:rp5",
                                            "sh": "pca-spatial", "params": {"energy_retention": 0.99,
                                                                            "spatial_clusters": 2,
                                                                            "side_dtype": "float16"}},
}
#: Container 2.6 cases: importance tiers (feature tiers; ``tiers`` adds them to the rate point), SHAC-PCA's
#: state shared by the tiers, the second tier keeping fewer features.
CASES_V26: dict[str, dict] = {
    "auto_template_tiers": {"input": "input_sh3.ply", "rate_point": "shac_auto:template", "sh": None, "params": {},
                            "tiers": {"shares": [0.5, 0.5], "qp_offsets": [-2, 8]}},
}
CASES = {"1.0": CASES_V1, "2.0": CASES_V2, "2.1": CASES_V21, "2.2": CASES_V22, "2.3": CASES_V23, "2.4": CASES_V24,
         "2.5": CASES_V25, "2.6": CASES_V26}


def write_inputs() -> None:
    """The two input PLYs (only when absent: they are fixtures, not outputs)."""
    from gscodec_shac.gaussians import GaussianCloud
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    sh3 = FIXTURES / "input_sh3.ply"
    if not sh3.exists():
        write_ply(sh3, make_synthetic_scene(300, seed=7, n_cameras=2, width=32, height=24).cloud)
    sh0 = FIXTURES / "input_sh0.ply"
    if not sh0.exists():
        c = make_synthetic_scene(200, seed=8, n_cameras=2, width=32, height=24).cloud
        write_ply(sh0, GaussianCloud(means=c.means, scales=c.scales, quats=c.quats, opacities=c.opacities,
                                     sh_dc=c.sh_dc, sh_rest=np.zeros((c.num_gaussians, 0, 3), np.float32)))


def write_network() -> None:
    """``network_small.npz``: seeded weights of :data:`SMALL_ARCH` (only when absent), each matrix
    uniform in +-1/sqrt(fan-in) as PyTorch initialises it, the heads included."""
    from gscodec_shac.deform_arch import DeformArch, weight_shapes

    path = FIXTURES / "network_small.npz"
    if path.exists():
        return
    rng = np.random.default_rng(11)
    shapes = weight_shapes(DeformArch(**SMALL_ARCH))
    bound = {name.rsplit(".", 1)[0]: 1.0 / np.sqrt(shape[1]) for name, shape in shapes if len(shape) == 2}
    np.savez_compressed(path, **{name: rng.uniform(-1, 1, shape).astype(np.float32) * bound[name.rsplit(".", 1)[0]]
                                 for name, shape in shapes})


def network_inputs(case: dict) -> tuple:
    """(architecture, weights) of a dynamic case."""
    from gscodec_shac.deform_arch import DeformArch

    with np.load(FIXTURES / case["network"]) as data:
        return DeformArch(**case["arch"]), {k: data[k] for k in data.files}


def encode_case(case: dict, workers: int = 1) -> bytes:
    """The stream of one case, encoded by the current code (no progress)."""
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.codec import Encoder, load_rate_point

    cloud = read_ply(FIXTURES / case["input"])
    rate_point = case["rate_point"]
    if rate_point.startswith("custom_points.yaml"):
        rate_point = str(FIXTURES / rate_point)
    if "dc_only_share" in case:
        rate_point = load_rate_point(rate_point).with_overrides(dc_only_share=case["dc_only_share"])
    if "tiers" in case:
        rate_point = load_rate_point(rate_point).with_overrides(tiers=case["tiers"])
    encoder = Encoder(rate_point, sh_stage=case["sh"], sort=case.get("sort"),
                      sh_params=case["params"] or None, workers=workers)
    stream = encoder.encode(cloud)
    if "network" in case:
        from gscodec_shac.codec.deformation import add_deformation, encoder_bits

        arch, weights = network_inputs(case)
        add_deformation(stream, arch, weights, encoder_bits(arch, case["network_bits"]), means=cloud.means)
    return stream.to_bytes()


def decoded_arrays(data: bytes) -> dict[str, np.ndarray]:
    from gscodec_shac.codec import Decoder

    from gscodec_shac.codec import Bitstream
    from gscodec_shac.codec.header import read_deformation, read_header

    cloud = Decoder(workers=1).decode(data)
    arrays = {"means": cloud.means, "scales": cloud.scales, "quats": cloud.quats, "opacities": cloud.opacities,
              "sh_dc": cloud.sh_dc, "sh_rest": cloud.sh_rest}
    stream = Bitstream.from_bytes(data)
    if "deformation" in stream.features:  # a dynamic stream: its network's weights too
        arrays.update({f"network/{k}": v for k, v in read_deformation(stream, read_header(stream)).items()})
    return arrays


def record_encoder_change(reason: str) -> None:
    """After an intended change of the encoder's output: encode every case of every version again
    (one and two workers, which must agree) and record the new golden hash as ``encoder_sha256``
    with ``reason`` in ``encoder_change`` wherever it moved. The stored streams and arrays stay:
    old files must still decode to them."""
    for manifest_path in sorted(FIXTURES.glob("v*/manifest.json")):
        manifest = json.loads(manifest_path.read_text())
        for name, case in manifest["cases"].items():
            hashes = {hashlib.sha256(encode_case(case, workers)).hexdigest() for workers in (1, 2)}
            if len(hashes) != 1:
                raise SystemExit(f"{manifest_path.parent.name}/{name}: one and two workers wrote different bytes")
            new = hashes.pop()
            if new == case.get("encoder_sha256", case["sha256"]):
                continue
            earlier = case.get("encoder_change")
            case["encoder_sha256"] = new
            case["encoder_change"] = reason + (f"; before that: {earlier}" if earlier else "")
            print(f"{manifest_path.parent.name}/{name}: new golden hash {new[:16]}")
        manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")


def main() -> None:
    from gscodec_shac.codec import Bitstream

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--version", help="container version folder, e.g. 1.0")
    group.add_argument("--record-encoder-change", metavar="REASON",
                       help="re-encode every version's cases and record the new golden hashes with REASON")
    args = parser.parse_args()
    if args.record_encoder_change:
        record_encoder_change(args.record_encoder_change)
        return
    out = FIXTURES / f"v{args.version}"
    out.mkdir(parents=True, exist_ok=True)
    write_inputs()
    write_network()
    manifest = {"container_version": args.version, "cases": {}}
    for name, case in CASES[args.version].items():
        data = encode_case(case)
        (out / f"{name}.gsc").write_bytes(data)
        np.savez_compressed(out / f"{name}.npz", **decoded_arrays(data))
        header = Bitstream.from_bytes(data).header
        codecs = header.get("codecs") or [c for tier in header.get("tiers", []) for c in tier["codecs"]]
        manifest["cases"][name] = {**case, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data),
                                   "codecs": [c["version"] for c in codecs]}
        print(f"{name}: {len(data):,} bytes")
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


if __name__ == "__main__":
    main()
