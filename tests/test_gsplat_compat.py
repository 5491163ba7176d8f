"""gsplat drop-in: splats dicts (torch or numpy) through the SH stages and the codec."""

import numpy as np
import pytest
import torch

from gscodec_shac.errors import ValidationError
from gscodec_shac.gsplat_compat import (
    ShacCompression,
    cloud_to_splats,
    fit_sh_stage,
    sh_features,
    sh_from_features,
    splats_to_cloud,
)
from gscodec_shac.shac.base import make_stage


@pytest.fixture()
def splats(small_cloud):
    return {k: v.clone() for k, v in cloud_to_splats(small_cloud, as_torch=True).items()}


def test_dict_conversion_round_trip(small_cloud, splats):
    assert splats["sh0"].shape == (2000, 1, 3) and splats["shN"].shape == (2000, 15, 3)
    assert all(isinstance(v, torch.Tensor) and v.dtype == torch.float32 for v in splats.values())
    assert splats_to_cloud(splats).equals(small_cloud)
    arrays = cloud_to_splats(small_cloud, as_torch=False)
    assert all(isinstance(v, np.ndarray) for v in arrays.values())
    assert splats_to_cloud(arrays).equals(splats_to_cloud(splats))


def test_bad_dicts(splats):
    missing = dict(splats)
    missing.pop("quats")
    with pytest.raises(ValidationError, match="lacks quats"):
        splats_to_cloud(missing)
    with pytest.raises(ValidationError, match="extra property 'features' has shape"):
        splats_to_cloud({**splats, "features": splats["means"][:5]})
    with pytest.raises(ValidationError, match="sh0"):
        splats_to_cloud({**splats, "sh0": splats["sh0"][:, 0]})


def test_compress_decompress_like_png_compression(tmp_path, splats):
    codec = ShacCompression(rate_point="paper_table3:rp4", sh="pca", sh_params={"energy_retention": 0.999}, verbose=False)
    codec.compress(str(tmp_path / "c"), splats)
    assert (tmp_path / "c" / "splats.gsc").is_file()
    out = codec.decompress(str(tmp_path / "c"))
    assert set(out) == set(splats)
    for key, value in out.items():
        assert isinstance(value, torch.Tensor) and value.shape == splats[key].shape and value.dtype == torch.float32
    # grid order: compare sorted positions, which are coded losslessly at 16 bit
    original = np.sort(splats["means"].numpy(), axis=0)
    decoded = np.sort(out["means"].numpy(), axis=0)
    assert np.abs(original - decoded).max() < 1e-3
    assert abs(out["shN"].std().item() - splats["shN"].std().item()) < 0.1 * splats["shN"].std().item()


def test_numpy_splats_and_no_sort(tmp_path, small_cloud):
    codec = ShacCompression(False, False, rate_point="gsplat_png", sh_params={"n_clusters": 256})  # use_sort, verbose
    codec.compress(tmp_path, cloud_to_splats(small_cloud, as_torch=False))
    out = codec.decompress(tmp_path)
    assert np.abs(out["means"].numpy() - small_cloud.means).max() < 1e-3  # raster order = input order


def test_extra_keys_are_carried_losslessly_in_decoded_order(tmp_path, splats):
    n = splats["means"].shape[0]
    extra = {"features": torch.randn(n, 6), "colors": torch.randn(n, 3), "ids": torch.arange(n, dtype=torch.int64)}
    given = {**splats, **extra}
    before = {k: v.clone() for k, v in given.items()}
    codec = ShacCompression(rate_point="paper_table3:rp4", verbose=False)
    codec.compress(tmp_path, given)
    assert all(torch.equal(given[k], before[k]) for k in given)  # the caller's dict is left alone
    assert (tmp_path / "splats.extra.npz").is_file()
    out = codec.decompress(tmp_path)
    assert set(out) == set(given)
    rows = out["ids"].numpy()  # which input row each decoded row came from
    assert out["ids"].dtype == torch.int64 and sorted(rows) == list(range(n))
    for key in ("features", "colors"):
        assert out[key].dtype == torch.float32 and torch.equal(out[key], extra[key][rows])
    assert np.abs(out["means"].numpy() - splats["means"].numpy()[rows]).max() < 1e-3
    # a later compress without extras removes the side file, so nothing stale is attached
    codec.compress(tmp_path, splats)
    assert not (tmp_path / "splats.extra.npz").exists() and set(codec.decompress(tmp_path)) == set(splats)


def test_sh_stages_on_dicts_and_arrays(splats):
    stage = fit_sh_stage("pca", splats, n_components=10)
    features = sh_features(stage, splats)
    assert features.shape == (2000, 10)
    rebuilt = sh_from_features(stage, features, like=splats["shN"])
    assert isinstance(rebuilt, torch.Tensor) and rebuilt.shape == splats["shN"].shape
    array = splats["shN"].numpy()
    same = fit_sh_stage(make_stage("pca", n_components=10), array)
    assert np.allclose(sh_features(same, array), features)
    plain = sh_from_features(same, features)
    assert isinstance(plain, np.ndarray) and np.allclose(plain, rebuilt.numpy())
    error = float(((plain - array) ** 2).mean())
    assert error < 0.5 * float(array.var())


def test_decompress_warns_when_pruning_returns_fewer_gaussians(tmp_path, splats):
    from gscodec_shac.gsplat_compat import FewerGaussiansWarning

    splats = {k: v.clone() for k, v in splats.items()}
    splats["opacities"][:100] = -8.0  # alpha 0.0003: below shac_ladder:rp1's pruning threshold (0.02)
    codec = ShacCompression(rate_point="shac_ladder:rp1", verbose=False)
    codec.compress(tmp_path, splats)
    with pytest.warns(FewerGaussiansWarning, match=r"of the 2,000 compressed .* bits per input Gaussian"):
        back = codec.decompress(tmp_path)
    assert back["means"].shape[0] <= 1900
    codec = ShacCompression(rate_point="paper_table3:rp4", verbose=False)  # no pruning: no warning
    codec.compress(tmp_path / "b", splats)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", FewerGaussiansWarning)
        assert codec.decompress(tmp_path / "b")["means"].shape[0] == 2000
