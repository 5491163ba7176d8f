"""Per-Gaussian SH degree (rate point ``sh.dc_only_share``, codec/sh_degree.py): DC-only Gaussians
decode with zero AC coefficients, the others as the stage codes them; bad streams are one error."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from gscodec_shac.codec import Bitstream, Decoder, Encoder, load_rate_point
from gscodec_shac.codec.header import read_header
from gscodec_shac.codec.rate_points import load_rate_point_file
from gscodec_shac.codec.sh_degree import CHUNK, FEATURE, ac_energy, dc_only_flags, flags_chunk
from gscodec_shac.errors import BitstreamError, RatePointError, ValidationError

POINT = "shac_ladder:rp6"


def _encode(cloud, share: float, stage: str = "none", point: str = POINT, **params) -> tuple[Encoder, bytes]:
    rate_point = load_rate_point(point).with_overrides(dc_only_share=share)
    encoder = Encoder(rate_point, sh_stage=stage, sh_params=params or None, workers=2)
    return encoder, encoder.encode(cloud).to_bytes()


@pytest.mark.parametrize("stage, params, point", [("none", {}, POINT), ("pca", {"energy_retention": 0.97}, POINT),
                                                  ("none", {}, "paper_table3:rp2")])
def test_dc_only_gaussians_decode_with_zero_ac_and_the_others_as_before(small_cloud, stage, params, point):
    share = 0.4
    plain, plain_bytes = _encode(small_cloud, 0.0, stage, point, **params)
    encoder, data = _encode(small_cloud, share, stage, point, **params)
    stream, before = Bitstream.from_bytes(data), Bitstream.from_bytes(plain_bytes)
    # 2.3 for the flags; 2.4 because a format-2 stream's HEVC chunks share their parameter sets
    assert stream.version == (2, 4) and FEATURE in stream.features and FEATURE not in before.features
    decoded, reference = Decoder().decode(data), Decoder().decode(plain_bytes)
    np.testing.assert_array_equal(encoder.order_, plain.order_)  # the same grid order ...
    for name in ("means", "scales", "quats", "opacities", "sh_dc"):  # ... and the same other attributes
        np.testing.assert_array_equal(getattr(decoded, name), getattr(reference, name))
    # the DC-only Gaussians are the share with the least alpha-weighted AC energy of the input
    ac = small_cloud.ac_matrix()[encoder.order_]
    expected = dc_only_flags(ac_energy(ac, small_cloud.activated_opacities()[encoder.order_]), share)
    zero = ~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1)
    np.testing.assert_array_equal(zero, expected)
    assert zero.sum() == round(share * decoded.num_gaussians) == read_header(stream).sh.dc_only
    # the others keep their view-dependent colour: as close to the input as without the feature
    error = np.abs(decoded.sh_rest[~zero] - small_cloud.sh_rest[encoder.order_][~zero]).mean()
    plain_error = np.abs(reference.sh_rest[~zero] - small_cloud.sh_rest[plain.order_][~zero]).mean()
    assert error <= 1.5 * plain_error + 1e-3
    # fewer SH bytes: the SH planes hold the coded Gaussians only
    assert stream.attribute_sizes()["sh"] < before.attribute_sizes()["sh"]


def test_share_zero_changes_nothing(small_cloud):
    _, plain = _encode(small_cloud, 0.0)
    assert Encoder(POINT, sh_stage="none", workers=2).encode(small_cloud).to_bytes() == plain


def test_a_stage_that_codes_the_dc_refuses(small_cloud):
    with pytest.raises(ValidationError, match="DC-only"):
        _encode(small_cloud, 0.5, "pca", n_components=8, include_dc=True)


def _edited(data: bytes, edit) -> bytes:
    stream = Bitstream.from_bytes(data)
    edit(stream)
    return stream.to_bytes()


def _set_flags(stream: Bitstream, flags: np.ndarray) -> None:
    packed, raw = flags_chunk(flags)
    stream.chunk(CHUNK).data = packed
    stream.chunk(CHUNK).meta["raw_size"] = raw


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.header["sh"].update(dc_only=s.header["sh"]["dc_only"] + 1), "flags .* the header says"),
    (lambda s: _set_flags(s, np.ones(s.header["num_gaussians"], bool)), "flags .* the header says"),
    (lambda s: s.header["sh"].pop("dc_only"), "sh.dc_only"),
    (lambda s: s.features.discard(FEATURE), "sh.dc_only"),
    (lambda s: s.header["sh"].pop("grid"), "sh.grid"),
    (lambda s: s.header["sh"]["grid"].update(height=1), "sh.grid"),
    (lambda s: s.header["sh"]["grid"].update(padding="mask"), "sh.grid.padding"),
    (lambda s: s.chunks.remove(s.chunk(CHUNK)), CHUNK),
    (lambda s: s.chunk(CHUNK).meta.update(raw_size=3), CHUNK),
])
def test_bad_dc_only_streams_are_one_clear_error(small_cloud, edit, message):
    _, data = _encode(small_cloud, 0.5)
    with pytest.raises(BitstreamError, match=message):
        Decoder().decode(_edited(data, edit))


@pytest.mark.parametrize("value", [1, 1.5, -0.1, "half", True, float("nan")])
def test_bad_dc_only_share_is_one_clear_error(tmp_path, value):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"points": {"a": {"sh": {"stage": "none", "dc_only_share": value}}}}))
    with pytest.raises(RatePointError, match=r"sh\.dc_only_share.*\[0, 1\)"):
        load_rate_point_file(path)
    with pytest.raises(RatePointError, match=r"\[0, 1\)"):
        load_rate_point(POINT).with_overrides(dc_only_share=value)


def test_dc_only_settings_round_trip_through_yaml(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"points": {"a": {"sh": {"stage": "pca", "dc_only_share": 0.25,
                                                            "dc_only_weight": "render"}}}}))
    point = load_rate_point_file(path)["a"]
    assert (point.dc_only_share, point.dc_only_weight, point.sh_stage) == (0.25, "render", "pca")
    assert point.to_json()["sh"] == {"stage": "pca", "dc_only_share": 0.25, "dc_only_weight": "render",
                                     **point.sh_params}
    assert "dc_only_share" not in load_rate_point(POINT).to_json()["sh"]  # absent: the header is unchanged


def test_render_weight_ranks_by_importance(small_scene):
    cloud = small_scene.cloud
    rate_point = load_rate_point(POINT).with_overrides(dc_only_share=0.5)
    importance = np.linspace(0.0, 1.0, cloud.num_gaussians)  # a given importance wins over a measured one
    import dataclasses

    encoder = Encoder(dataclasses.replace(rate_point, dc_only_weight="render"), sh_stage="none", workers=2,
                      importance=importance)
    decoded = Decoder().decode(encoder.encode(cloud).to_bytes())
    zero = ~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1)
    ac = cloud.ac_matrix()[encoder.order_]
    np.testing.assert_array_equal(zero, dc_only_flags(ac_energy(ac, importance[encoder.order_]), 0.5))


def test_cli_sh_dc_only(tmp_path, small_scene, capsys):
    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import write_ply

    ply, out = tmp_path / "in.ply", tmp_path / "out.gsc"
    write_ply(ply, small_scene.cloud)
    assert main(["encode", str(ply), str(out), "--sh-dc-only", "1", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "[0, 1)" in err and "Traceback" not in err and not out.exists()
    assert main(["encode", str(ply), str(out), "--sh-dc-only", "0.5", "--target-bpg", "100"]) == 2
    assert "--sh-dc-only cannot be combined with a target" in capsys.readouterr().err
    assert main(["encode", str(ply), str(out), "--sh-dc-only", "0.5", "-q"]) == 0
    decoded = Decoder().decode(out.read_bytes())
    zero = ~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1)
    assert zero.sum() == round(0.5 * decoded.num_gaussians)
    assert main(["info", str(out), "--json"]) == 0
    assert '"sh_dc_only": %d' % zero.sum() in capsys.readouterr().out
    assert main(["info", str(out)]) == 0
    assert f"{zero.sum():,} DC-only" in capsys.readouterr().out


def test_energy_bar_drops_at_most_that_fraction_of_the_energy():
    energy = np.array([3.0, 0.0, 4.0, 1.0, 0.0, 2.0])  # total 10
    assert np.flatnonzero(dc_only_flags(energy, 0.0, 0.1)).tolist() == [1, 3, 4]  # 0 + 0 + 1 <= 1
    assert np.flatnonzero(dc_only_flags(energy, 0.0, 0.05)).tolist() == [1, 4]
    assert np.flatnonzero(dc_only_flags(energy, 0.5)).tolist() == [1, 3, 4]  # a share: the 3 weakest
    assert dc_only_flags(np.zeros(4), 0.0, 0.5).sum() == 3  # never all of them


def test_energy_bar_and_share_are_one_or_the_other(tmp_path, small_cloud, capsys):
    path = tmp_path / "both.yaml"
    path.write_text(yaml.safe_dump({"points": {"a": {"sh": {"dc_only_share": 0.2, "dc_only_energy": 0.02}}}}))
    with pytest.raises(RatePointError, match="not both"):
        load_rate_point_file(path)
    with pytest.raises(RatePointError, match=r"energy bar .*\[0, 1\)"):
        load_rate_point(POINT).with_overrides(dc_only_energy=1.0)
    point = load_rate_point(POINT).with_overrides(dc_only_energy=0.02)
    assert point.dc_only and point.to_json()["sh"]["dc_only_energy"] == 0.02
    encoder = Encoder(point, sh_stage="none", workers=2)
    decoded = Decoder().decode(encoder.encode(small_cloud).to_bytes())
    zero = ~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1)
    ac = small_cloud.ac_matrix()[encoder.order_]
    energy = ac_energy(ac, small_cloud.activated_opacities()[encoder.order_])
    np.testing.assert_array_equal(zero, dc_only_flags(energy, 0.0, 0.02))
    assert 0 < zero.sum() and energy[zero].sum() <= 0.02 * energy.sum()

    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import write_ply

    ply = tmp_path / "in.ply"
    write_ply(ply, small_cloud)
    assert main(["encode", str(ply), str(tmp_path / "o.gsc"), "--sh-dc-only", "0.2", "--sh-dc-energy", "0.02"]) == 2
    assert "give one of them" in capsys.readouterr().err


def test_cli_render_weight_uses_the_cameras(tmp_path, capsys):
    from gscodec_shac.cli import main
    from gscodec_shac.codec.importance import importance_views
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply

    ply, cameras = tmp_path / "scene.ply", tmp_path / "cameras.json"
    assert main(["synthetic", str(ply), "-n", "1500", "--views", "4"]) == 0
    alpha, render = tmp_path / "alpha.gsc", tmp_path / "render.gsc"
    point = ["-r", POINT, "--sh", "none", "--sh-dc-only", "0.5", "-q"]
    assert main(["encode", str(ply), str(alpha), "--cameras", str(cameras), *point]) == 2
    assert "--sh-dc-weight render" in capsys.readouterr().err
    assert main(["encode", str(ply), str(alpha), *point]) == 0
    assert main(["encode", str(ply), str(render), "--cameras", str(cameras), "--sh-dc-weight", "render", *point]) == 0
    cloud = read_ply(ply)
    rate_point = load_rate_point(POINT).with_overrides(dc_only_share=0.5, dc_only_weight="render")
    expected = Encoder(rate_point, sh_stage="none", views=importance_views(cloud, load_cameras(cameras))).encode(cloud)

    def dc_only(data: bytes) -> np.ndarray:
        decoded = Decoder().decode(data)
        return ~decoded.sh_rest.reshape(decoded.num_gaussians, -1).any(axis=1)

    # the renderer's threads sum the blending weights in any order: near-ties may rank either way
    wanted = dc_only(expected.to_bytes())
    assert np.mean(dc_only(render.read_bytes()) != wanted) <= 0.01
    assert np.mean(dc_only(alpha.read_bytes()) != wanted) > 0.05


def test_a_2_2_decoder_refuses_dc_only_streams(small_cloud, monkeypatch):
    """The release before format 2.3 does not know the feature: it refuses the stream, naming it."""
    from gscodec_shac.codec import container

    _, data = _encode(small_cloud, 0.5)
    monkeypatch.delitem(container.FEATURES, FEATURE)
    with pytest.raises(BitstreamError, match="needs sh_dc_only.*update gscodec-shac"):
        Bitstream.from_bytes(data)


def test_a_stage_without_features_needs_no_flags(small_cloud):
    """Truncation to degree 0 codes no AC at all: no flags, the chunks of the stream without DC-only Gaussians."""
    _, data = _encode(small_cloud, 0.5, "trunc", degree=0)
    _, plain = _encode(small_cloud, 0.0, "trunc", degree=0)
    stream, before = Bitstream.from_bytes(data), Bitstream.from_bytes(plain)
    assert FEATURE not in stream.features and "dc_only" not in stream.header["sh"]
    assert [(c.name, c.data) for c in stream.chunks] == [(c.name, c.data) for c in before.chunks]
    assert not Decoder().decode(data).sh_rest.any()
