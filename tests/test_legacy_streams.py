"""Files users already have keep opening: every committed stream decodes to its stored arrays.

``tests/fixtures/streams/v<version>/`` holds streams written by each container version
(``scripts/make_stream_fixtures.py``) with the arrays they decoded to when written. They
stay forever: a decoder change that alters one value of one of them fails here. For the
version, re-encoding the same inputs with the same settings must still give the same
bytes (golden hashes: the encoder writes each stream with the oldest version that holds it),
unless a grid codec library of a different version is installed
(the test then says so and skips the hash comparison). Where the encoder was changed on
purpose after a fixture was written, the case's ``encoder_sha256`` is the golden hash of
today's encoder and ``encoder_change`` says why (the fixture itself still must decode):
SHAC-PCA's projection moved from a float32 to a float64-accumulated product so that the
bytes no longer depend on the CPU's BLAS kernel or thread count.

Every decoded value is compared bit for bit, except the outputs of an SH stage's float32
matrix product (SHAC-PCA's inverse), which must agree to within 4 float32 units in the
last place of the array's largest value: a BLAS may sum the products in another order
(another CPU, another memory layout), and the decoder is free to choose the fastest one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from gscodec_shac.codec.deformation import add_deformation, encoder_bits
from gscodec_shac.codec.grid.base import get_codec
from gscodec_shac.codec.header import read_deformation, read_header
from gscodec_shac.deform_arch import DeformArch
from gscodec_shac.io.ply import read_ply
from gscodec_shac.codec import Bitstream, Decoder, Encoder, load_rate_point

FIXTURES = Path(__file__).parent / "fixtures" / "streams"
VERSIONS = sorted((p for p in FIXTURES.glob("v*") if p.is_dir()), key=lambda p: tuple(map(int, p.name[1:].split("."))))
CASES = [(folder, name) for folder in VERSIONS for name in json.loads((folder / "manifest.json").read_text())["cases"]]
ARRAYS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
#: Arrays that come out of a stage's matrix product, by SH stage.
PRODUCTS = {"pca": ("sh_rest", "sh_dc"), "pca-spatial": ("sh_rest",)}


def network_inputs(case: dict) -> tuple[DeformArch, dict[str, np.ndarray]]:
    """(architecture, weights) of a dynamic case (``scripts/make_stream_fixtures.py``)."""
    with np.load(FIXTURES / case["network"]) as data:
        return DeformArch(**case["arch"]), {k: data[k] for k in data.files}


def _manifest(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())


@pytest.mark.parametrize("folder, name", CASES, ids=[f"{f.name}-{n}" for f, n in CASES])
def test_legacy_stream_decodes_to_the_stored_arrays(folder, name):
    data = (folder / f"{name}.gsc").read_bytes()
    assert hashlib.sha256(data).hexdigest() == _manifest(folder)["cases"][name]["sha256"]
    cloud = Decoder(workers=2).decode(data)
    header = Bitstream.from_bytes(data).header
    sh = header.get("sh") or next((tier.get("sh") for tier in header.get("tiers", []) if tier.get("sh")), None)
    products = PRODUCTS.get((sh or {}).get("stage"), ())
    with np.load(folder / f"{name}.npz") as expected:
        for key in ARRAYS:
            got, want = getattr(cloud, key), expected[key]
            assert got.dtype == want.dtype and got.shape == want.shape, key
            if key in products:
                ulp = np.spacing(np.float32(np.abs(want).max()))
                assert np.abs(got - want).max() <= 4 * ulp, f"{name}: {key} changed beyond float32 rounding"
            else:
                assert got.tobytes() == want.tobytes(), f"{name}: {key} changed"
        stored = sorted(k for k in expected.files if k.startswith("network/"))
        if stored:  # a dynamic stream: the network's weights too, bit for bit
            stream = Bitstream.from_bytes(data)
            weights = read_deformation(stream, read_header(stream))
            assert sorted(f"network/{k}" for k in weights) == stored
            for key in stored:
                assert weights[key[len("network/"):]].tobytes() == expected[key].tobytes(), f"{name}: {key} changed"


@pytest.mark.parametrize("folder, name", CASES, ids=[f"{f.name}-{n}" for f, n in CASES])
def test_encoding_the_fixture_inputs_gives_the_golden_bytes(folder, name):
    case = _manifest(folder)["cases"][name]
    rate_point = case["rate_point"]
    if rate_point.startswith("custom_points.yaml"):
        rate_point = str(FIXTURES / rate_point)
    header = Bitstream.from_bytes((folder / f"{name}.gsc").read_bytes()).header
    codecs = header.get("codecs") or [c for tier in header.get("tiers", []) for c in tier["codecs"]]
    installed = [get_codec(c["name"], **c["options"]).version() for c in codecs]
    if installed != case["codecs"]:
        pytest.skip(f"codec libraries differ from the fixture's ({installed} vs {case['codecs']}): bytes may differ")
    if "dc_only_share" in case:
        rate_point = load_rate_point(rate_point).with_overrides(dc_only_share=case["dc_only_share"])
    if "tiers" in case:
        rate_point = load_rate_point(rate_point).with_overrides(tiers=case["tiers"])
    cloud = read_ply(FIXTURES / case["input"])
    for workers in (1, 2):
        encoder = Encoder(rate_point, sh_stage=case["sh"], sort=case.get("sort"), sh_params=case["params"] or None,
                          workers=workers)
        stream = encoder.encode(cloud)
        if "network" in case:
            arch, weights = network_inputs(case)
            add_deformation(stream, arch, weights, encoder_bits(arch, case["network_bits"]), means=cloud.means)
        data = stream.to_bytes()
        golden = case.get("encoder_sha256", case["sha256"])
        assert hashlib.sha256(data).hexdigest() == golden, f"{name}: encoding changed (workers={workers})"
