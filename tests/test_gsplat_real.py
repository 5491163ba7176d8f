"""The gsplat drop-in against the real ``gsplat`` package (the ``[gsplat]`` extra; CPU is enough).

Skips with the reason where gsplat is not installed (``pip install -e ".[gsplat]"``;
``make test`` installs it).
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch

gsplat = pytest.importorskip("gsplat", reason="gsplat is not installed: pip install -e '.[gsplat]' (make test installs it)")

from gsplat.compression import PngCompression  # noqa: E402
from gsplat.exporter import export_splats  # noqa: E402

from gscodec_shac.gsplat_compat import ShacCompression  # noqa: E402
from gscodec_shac.io.gsplat_ckpt import write_gsplat_checkpoint  # noqa: E402
from gscodec_shac.io.models import read_model  # noqa: E402
from gscodec_shac.gsplat_compat import splats_to_cloud  # noqa: E402

SH_C0 = 0.28209479177387814


def _trainer_splats(n: int = 1500, sh_degree: int = 3, feature_dim: int | None = None) -> torch.nn.ParameterDict:
    """A splats ParameterDict shaped as gsplat 1.5's simple_trainer.create_splats_with_optimizers makes it."""
    g = torch.Generator().manual_seed(0)
    points = torch.rand((n, 3), generator=g) * 4 - 2
    rgbs = torch.rand((n, 3), generator=g)
    params = {
        "means": points,
        "scales": torch.log(torch.rand((n, 1), generator=g) * 0.05 + 0.01).repeat(1, 3),
        "quats": torch.rand((n, 4), generator=g),
        "opacities": torch.logit(torch.rand(n, generator=g) * 0.9 + 0.05),
    }
    if feature_dim is None:
        colors = torch.randn((n, (sh_degree + 1) ** 2, 3), generator=g) * 0.2
        colors[:, 0, :] = (rgbs - 0.5) / SH_C0
        params["sh0"], params["shN"] = colors[:, :1, :], colors[:, 1:, :]
    else:
        params["features"] = torch.rand(n, feature_dim, generator=g)
        params["colors"] = torch.logit(rgbs)
        params["sh0"] = ((rgbs - 0.5) / SH_C0)[:, None, :]
        params["shN"] = torch.zeros((n, 15, 3))
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in params.items()})


def test_same_call_signatures_as_png_compression():
    ours, theirs = inspect.signature(ShacCompression), inspect.signature(PngCompression)
    assert list(ours.parameters)[:2] == list(theirs.parameters) == ["use_sort", "verbose"]
    assert all(ours.parameters[k].default == theirs.parameters[k].default for k in theirs.parameters)
    for method in ("compress", "decompress"):
        assert list(inspect.signature(getattr(ShacCompression, method)).parameters) == \
            list(inspect.signature(getattr(PngCompression, method)).parameters)


@pytest.mark.parametrize("feature_dim", [None, 8])
def test_compress_decompress_as_simple_trainer_does(tmp_path, feature_dim):
    splats = _trainer_splats(feature_dim=feature_dim)
    original = {k: v.detach().clone() for k, v in splats.items()}
    method = ShacCompression(True, False, rate_point="paper_table3:rp2")  # use_sort, verbose as gsplat's
    method.compress(str(tmp_path), splats)  # simple_trainer passes self.splats, a ParameterDict
    splats_c = method.decompress(str(tmp_path))
    assert set(splats_c) == set(splats)
    for k in splats_c.keys():  # simple_trainer.run_compression
        splats[k].data = splats_c[k].to("cpu")
    for key, value in splats.items():
        assert value.dtype == original[key].dtype and value.shape == original[key].shape, key
    # decoded rows are a permutation of the input: match them by the (16-bit coded) positions
    order = torch.cdist(splats["means"].data, original["means"]).argmin(dim=1)
    assert torch.equal(torch.sort(order).values, torch.arange(len(order)))
    assert (splats["means"].data - original["means"][order]).abs().max() < 1e-3
    assert (splats["sh0"].data - original["sh0"][order]).abs().max() < 0.05
    if feature_dim is not None:  # extra keys come back bit-exact, in the decoded order
        assert torch.equal(splats["features"].data, original["features"][order])
        assert torch.equal(splats["colors"].data, original["colors"][order])


def test_our_checkpoint_loads_as_simple_trainer_loads_ckpt(tmp_path):
    splats = _trainer_splats(200)
    write_gsplat_checkpoint(tmp_path / "ckpt_6999_rank0.pt", splats_to_cloud(splats), step=6999)
    ckpt = torch.load(tmp_path / "ckpt_6999_rank0.pt", map_location="cpu", weights_only=True)
    runner_splats = _trainer_splats(200)
    for k in runner_splats.keys():
        runner_splats[k].data = torch.cat([ckpt["splats"][k]])
        assert torch.equal(runner_splats[k].data, splats[k].data)
    assert ckpt["step"] == 6999


def test_we_read_gsplat_exports(tmp_path):
    splats = {k: v.detach() for k, v in _trainer_splats(600).items()}
    args = [splats[k] for k in ("means", "scales", "quats", "opacities", "sh0", "shN")]
    export_splats(*args, format="ply", save_to=str(tmp_path / "g.ply"))
    cloud, _ = read_model(tmp_path / "g.ply")
    assert np.array_equal(cloud.means, splats["means"].numpy()) and np.array_equal(cloud.sh_rest, splats["shN"].numpy())
    for fmt, name, tolerance in (("splat", "g.splat", 1e-6), ("ply_compressed", "g.compressed.ply", 2e-3)):
        export_splats(*args, format=fmt, save_to=str(tmp_path / name))
        cloud, _ = read_model(tmp_path / name)
        assert cloud.num_gaussians == 600
        means = torch.from_numpy(cloud.means)
        order = torch.cdist(means, splats["means"]).argmin(dim=1)  # both exporters sort along a Morton curve
        assert torch.equal(torch.sort(order).values, torch.arange(600)), fmt
        assert (means - splats["means"][order]).abs().max() <= tolerance, fmt
        colour = 0.5 + SH_C0 * cloud.sh_dc
        expected = (0.5 + SH_C0 * splats["sh0"][order, 0]).clamp(0, 1).numpy()
        assert np.abs(colour - expected).max() <= 1.01 / 255, fmt
