"""The fast paths of issue 25 give the same results as the plain ones, and a decode stays lean.

* a process that only decodes imports neither numba nor the sorting kernels (checked in a
  fresh interpreter, for every stored legacy stream);
* it imports only the grid codecs and the SH stage its stream names (cv2 alone took 0.2 s);
* the threaded, numpy dequantisation equals the per-value formula;
* the numpy unpacking of set-coded positions equals the compiled packer's inverse,
  across block boundaries;
* a PLY written in row blocks is byte-identical to one written from the whole table.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import plyfile
import pytest

from gscodec_shac.codec import positions
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.grid.base import CODECS
from gscodec_shac.codec.header import read_header
from gscodec_shac.codec.quantize import Quantizer
from gscodec_shac.codec.rate_points import load_rate_point
from gscodec_shac.io.ply import cloud_to_structured, read_ply, write_ply
from gscodec_shac.shac.base import STAGES

ROOT = Path(__file__).resolve().parents[1]
STREAMS = sorted((ROOT / "tests" / "fixtures" / "streams").glob("v*/*.gsc"))
#: Modules a decode has no use for (numba's import and cache loading cost seconds).
NOT_FOR_DECODE = ("numba", "sorting.plas", "sorting._kernels", "sorting.api",
                  "gscodec_shac.render.raster", "gscodec_shac.train.model")


def last_line_printed(script: str) -> str:
    """The last line ``script`` prints, run in a fresh interpreter with this checkout first on the path."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True)
    return done.stdout.strip().splitlines()[-1]


def test_decoding_imports_no_compiled_kernels(tmp_path):
    script = (
        "import json, sys\n"
        "from gscodec_shac.codec import decode_file\n"
        "from gscodec_shac.codec.files import is_dynamic_stream\n"
        f"for i, path in enumerate({[str(p) for p in STREAMS]!r}):\n"  # a dynamic model decodes to a directory
        f"    decode_file(path, {str(tmp_path)!r} + (f'/dir{{i}}/' if is_dynamic_stream(path) else f'/out{{i}}.ply'))\n"
        f"print(json.dumps([m for m in {NOT_FOR_DECODE!r} if m in sys.modules]))\n"
    )
    assert STREAMS and json.loads(last_line_printed(script)) == []
    dynamic = [p for p in STREAMS if "deformation" in Bitstream.read(p).features]
    assert len(list(tmp_path.glob("out*.ply"))) == len(STREAMS) - len(dynamic)
    assert len(list(tmp_path.glob("dir*/point_cloud.ply"))) == len(dynamic)


def test_the_decode_command_imports_no_numba(tmp_path):
    script = (
        "import sys\n"
        "from gscodec_shac.cli import main\n"
        f"assert main(['decode', {str(STREAMS[-1])!r}, {str(tmp_path / 'out.ply')!r}]) == 0\n"
        "print('numba' in sys.modules)\n"
    )
    assert last_line_printed(script) == "False"


@pytest.mark.parametrize("name", ["v2.0/ladder_rp6_pca.gsc", "v1.0/recommended_rp3_lst.gsc", "v1.0/gsplat_png_vq.gsc"])
def test_decoding_imports_only_the_codecs_and_stage_the_stream_names(tmp_path, name):
    path = ROOT / "tests" / "fixtures" / "streams" / name
    header = read_header(Bitstream.read(path))
    script = (
        "import json, sys\n"
        "from gscodec_shac.codec import decode_file\n"
        f"decode_file({str(path)!r}, {str(tmp_path / 'out.ply')!r})\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    imported = set(json.loads(last_line_printed(script)))
    codecs = {m for m in CODECS.modules.values() if f"gscodec_shac.codec.grid.{m}" in imported}
    stages = {m for m in STAGES.modules.values() if f"gscodec_shac.shac.{m}" in imported}
    assert codecs == {CODECS.modules[c.name] for c in header.codecs}
    assert stages == {STAGES.modules[header.sh.stage]}
    assert ("cv2" in imported) == ("png" in codecs)


def test_each_builtin_name_is_registered_by_the_module_named_for_it():
    for registry, package in ((CODECS, "gscodec_shac.codec.grid"), (STAGES, "gscodec_shac.shac")):
        registered = dict(registry.items())  # imports every built-in module
        assert sorted(registered) == sorted(registry.modules)
        for name, module in registry.modules.items():
            assert registered[name].__module__ == f"{package}.{module}"


@pytest.mark.parametrize("bits", [1, 10, 12])
def test_dequantize_cells_matches_dequantize_for_any_thread_count(bits):
    rng = np.random.default_rng(bits)
    channels, cells_total = 7, 5000
    lo = rng.normal(size=channels).astype(np.float32)
    quantizer = Quantizer(bits, lo, lo + rng.uniform(0, 3, size=channels).astype(np.float32))
    planes = rng.integers(0, 1 << bits, size=(channels, cells_total)).astype(np.uint16)
    planes[0, :10] = (1 << bits) + 5  # above the last code: clipped, as np.take does
    cells = rng.permutation(cells_total)[:3000]
    want = quantizer.dequantize(planes[:, cells].T)
    for workers in (1, 2, 4):
        got = quantizer.dequantize_cells(planes, cells, workers)
        assert got.dtype == np.float32 and got.tobytes() == np.ascontiguousarray(want).tobytes()


@pytest.mark.parametrize("block", [1, 3, 1 << 20])
def test_position_gaps_unpack_as_packed(monkeypatch, block):
    rng = np.random.default_rng(block)
    lengths_drawn = rng.integers(0, 64, size=2000)  # every bit length 0..63
    gaps = np.where(lengths_drawn > 0, np.uint64(1) << np.maximum(lengths_drawn - 1, 0).astype(np.uint64), 0)
    gaps = gaps.astype(np.uint64) | (rng.integers(0, 1 << 62, size=gaps.size, dtype=np.uint64) & (gaps - np.uint64(1)))
    gaps[lengths_drawn == 0] = 0
    lengths = positions._bit_lengths(gaps)
    assert np.array_equal(lengths, lengths_drawn)
    packed = positions._pack_mantissas(gaps, lengths)
    monkeypatch.setattr(positions, "_UNPACK_BLOCK", block)
    assert np.array_equal(positions._unpack_mantissas(packed, lengths), gaps)


def test_position_gaps_pack_as_a_plain_bit_string():
    """The encoder's compiled packer (gscodec_shac/codec/gap_packing.py) writes each gap's bits below
    its leading one, most significant first, exactly as a bit string built in Python would."""
    rng = np.random.default_rng(7)
    lengths = rng.integers(0, 64, size=3000)
    gaps = np.where(lengths > 0, np.uint64(1) << np.maximum(lengths - 1, 0).astype(np.uint64), 0).astype(np.uint64)
    gaps |= rng.integers(0, 1 << 62, size=gaps.size, dtype=np.uint64) & (gaps - np.uint64(1))
    gaps[lengths == 0] = 0
    bits = "".join(format(int(g) & ((1 << (int(k) - 1)) - 1), f"0{int(k) - 1}b") for g, k in zip(gaps, lengths) if k > 1)
    bits += "0" * (-len(bits) % 8)
    assert positions._pack_mantissas(gaps, lengths) == int(bits, 2).to_bytes(len(bits) // 8, "big")
    assert positions._pack_mantissas(np.zeros(3, np.uint64), np.zeros(3, np.int64)) == b""


@pytest.mark.parametrize("block_rows", [1, 7, 64, 1 << 16])
def test_ply_written_in_blocks_equals_the_whole_table(tmp_path, block_rows):
    cloud = read_ply(ROOT / "tests" / "fixtures" / "streams" / "input_sh3.ply")
    cloud.extra["custom"] = np.arange(cloud.num_gaussians, dtype=np.int32)
    whole = tmp_path / "whole.ply"
    with open(whole, "wb") as handle:
        plyfile.PlyData([plyfile.PlyElement.describe(cloud_to_structured(cloud), "vertex")], text=False,
                        byte_order="<").write(handle)
    blocked = tmp_path / "blocked.ply"
    write_ply(blocked, cloud, block_rows=block_rows)
    assert blocked.read_bytes() == whole.read_bytes()


def test_encodes_sharing_a_cache_give_the_bytes_of_fresh_encodes():
    from gscodec_shac.codec import Encoder
    from gscodec_shac.shac import make_stage

    cloud = read_ply(ROOT / "tests" / "fixtures" / "streams" / "input_sh3.ply")
    stage = make_stage("pca", energy_retention=0.97).fit(cloud.ac_matrix())
    cache: dict = {}
    points = ["shac_ladder:rp4", "shac_ladder:rp2", "shac_ladder:rp4", "paper_table3:rp2"]
    # gray layout: x265's multi-frame streams of pictures this small (16 x 24 for 300 Gaussians) were
    # not reproducible from one encode to the next in one process (found here; the cache is not involved).
    gray = {"layout": "gray"}
    for point in points:
        shared = Encoder(point, sh_stage=stage, fit_stage=False, chunk_cache=cache, codec_options=gray)
        fresh = Encoder(point, sh_stage=stage, fit_stage=False, codec_options=gray)
        assert shared.encode(cloud).to_bytes() == fresh.encode(cloud).to_bytes(), point
    assert any(key[0] == "__work__" for key in cache)


def test_given_stage_features_give_the_bytes_of_features_computed_by_the_encoder():
    """The rate controller hands its trial encodes the whole cloud's SHAC-PCA features (issue 25):
    gathered in grid order, pruned or DC-only, they must code to the same bytes."""
    from gscodec_shac.codec import Encoder
    from gscodec_shac.shac import make_stage

    cloud = read_ply(ROOT / "tests" / "fixtures" / "streams" / "input_sh3.ply")
    stage = make_stage("pca", energy_retention=0.97).fit(cloud.ac_matrix())
    features = stage.transform(cloud.ac_matrix())
    gray = {"layout": "gray"}
    for point in ["shac_ladder:rp4", "paper_table3:rp2"]:
        for extra in ({}, {"keep_share": 0.6}, {"dc_only_energy": 0.01}):
            rate_point = load_rate_point(point).with_overrides(**extra) if extra else point
            given = Encoder(rate_point, sh_stage=stage, fit_stage=False, codec_options=gray, stage_features=features)
            own = Encoder(rate_point, sh_stage=stage, fit_stage=False, codec_options=gray)
            assert given.encode(cloud).to_bytes() == own.encode(cloud).to_bytes(), (point, extra)
    wrong = Encoder("shac_ladder:rp4", sh_stage=stage, fit_stage=False, stage_features=features[:-1])
    with pytest.raises(ValueError, match="rows for a cloud of 300"):
        wrong.encode(cloud)


def test_scheduler_runs_the_costliest_pending_piece_first():
    import threading

    from gscodec_shac.codec.encoder import _Scheduler

    scheduler, started, order = _Scheduler(2), threading.Event(), []  # one thread, then the caller's
    gate = threading.Event()
    first = scheduler.submit(0, lambda: (started.set(), gate.wait(10)))
    started.wait(10)  # the one thread is busy: the next pieces wait in the queue
    futures = [scheduler.submit(cost, lambda cost=cost: order.append(cost)) for cost in (1, 5, 3, 5)]
    scheduler.work_until(futures)  # the caller runs them, costliest first, while the thread is busy
    gate.set()
    first.result(10)
    scheduler.close()
    assert order == [5, 5, 3, 1]
    serial = _Scheduler(1)  # no thread: every piece runs in the caller's thread, in cost order
    ran = []
    futures = [serial.submit(cost, lambda cost=cost: ran.append((cost, threading.get_ident()))) for cost in (2, 9)]
    serial.work_until(futures)
    serial.close()
    assert ran == [(9, threading.get_ident()), (2, threading.get_ident())]


def test_hevc_stream_pieces_in_any_order_join_to_the_encode():
    from concurrent.futures import ThreadPoolExecutor

    from gscodec_shac.codec.grid.base import get_codec

    planes = np.random.default_rng(3).integers(0, 1024, size=(8, 24, 80)).astype(np.uint16)
    codec = get_codec("hevc", layout="yuv444", preset="ultrafast")
    parts, join = codec.encode_parts(planes, 10, 30)
    assert len(parts) == 4  # two 4:4:4 streams and two gray ones
    with ThreadPoolExecutor(2) as pool:  # last piece first, two at a time
        outputs = list(reversed(list(pool.map(lambda part: part[1](), reversed(parts)))))
    assert join(outputs) == codec.encode(planes, 10, 30)
    got = np.zeros_like(planes)
    seen = []

    def sink(first, decoded):
        seen.append((first, len(decoded)))
        got[first : first + len(decoded)] = decoded

    codec.decode_into(join(outputs), planes.shape, 10, sink)
    assert sorted(seen) == [(0, 3), (3, 3), (6, 1), (7, 1)] and np.array_equal(got, codec.decode(join(outputs), planes.shape, 10))


@pytest.mark.parametrize("point", ["paper_table3:rp2", "shac_ladder:rp4"])
def test_serial_and_parallel_encodes_give_the_same_bytes(point):
    # paper_table3: yuv444 chunks of many streams coded as separate pieces; shac_ladder: one
    # multi-frame stream per chunk and the position set, all coded while the SH stage is fitted
    from gscodec_shac.codec import Decoder, Encoder

    cloud = read_ply(ROOT / "tests" / "fixtures" / "streams" / "input_sh3.ply")
    fast = {"preset": "ultrafast", "layout": "gray"} if point.startswith("shac") else {"preset": "ultrafast"}
    streams = {workers: Encoder(point, sh_stage="pca", sh_params={"energy_retention": 0.97}, workers=workers,
                                codec_options=fast).encode(cloud).to_bytes() for workers in (1, 2, 5)}
    assert streams[1] == streams[2] == streams[5]
    assert Decoder(workers=1).decode(streams[1]).num_gaussians == cloud.num_gaussians
