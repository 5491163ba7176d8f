"""The rotation coded as a rotation vector (rate point ``attributes.rotation.form: vector``, format 2.4):
the transform and its inverse, the rate point's rules, the stream it writes and the header's checks."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from gscodec_shac.codec import Decoder, Encoder, load_rate_point
from gscodec_shac.codec import quantize as qz
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.errors import BitstreamError, RatePointError
from gscodec_shac.synthetic import make_synthetic_scene


def _random_quaternions(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 4))


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle (radians) of the rotation taking quaternion ``a`` to ``b`` (unit, either sign)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return 2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0, 1))


def test_rotation_vectors_invert_to_the_canonical_quaternions():
    quats = _random_quaternions(10_000, 0)
    vectors = qz.rotation_vectors(quats)
    assert vectors.shape == (10_000, 3)
    assert np.linalg.norm(vectors, axis=1).max() <= np.pi + 1e-12
    back = qz.quaternions_from_rotation_vectors(vectors)
    np.testing.assert_allclose(back, qz.canonical_quaternions(quats), atol=1e-12)


def test_the_identity_and_tiny_rotations_are_exact():
    tiny = np.array([[1.0, 0, 0, 0], [1.0, 1e-15, 0, 0], [1.0, 0, -3e-9, 0], [-1.0, 0, 0, 0], [0, 0, 0, 0]])
    vectors = qz.rotation_vectors(tiny)
    np.testing.assert_allclose(vectors, [[0, 0, 0], [2e-15, 0, 0], [0, -6e-9, 0], [0, 0, 0], [0, 0, 0]], atol=1e-20)
    np.testing.assert_allclose(qz.quaternions_from_rotation_vectors(vectors), qz.canonical_quaternions(tiny),
                               atol=1e-15)


def test_a_step_of_the_vector_turns_the_rotation_by_at_most_its_length():
    """What makes the form worth coding: a quantiser's step of the vector is a bounded turn,
    the same bound for every rotation (a quaternion's step turns by up to twice its length)."""
    rng = np.random.default_rng(1)
    vectors = qz.rotation_vectors(_random_quaternions(20_000, 2))
    steps = rng.normal(size=vectors.shape) * 1e-3
    turned = _angle_between(qz.quaternions_from_rotation_vectors(vectors),
                            qz.quaternions_from_rotation_vectors(vectors + steps))
    assert np.all(turned <= np.linalg.norm(steps, axis=1) * (1 + 1e-6))
    assert np.median(turned / np.linalg.norm(steps, axis=1)) > 0.5  # not a degenerate map either


def _points(tmp_path, rotation: dict, qp) -> str:
    path = tmp_path / "points.yaml"
    path.write_text(yaml.safe_dump({"points": {"p": {"attributes": {"rotation": rotation},
                                                     "qp": {"opacity": 20, "rotation": qp, "scale": 20,
                                                            "sh_dc": 20, "sh_ac": 30}}}}))
    return f"{path}:p"


def test_the_rate_point_names_the_form(tmp_path):
    point = load_rate_point(_points(tmp_path, {"form": "vector"}, 20))
    assert point.rotation_form == "vector"
    assert point.attributes["rotation"].to_json()["form"] == "vector"
    assert load_rate_point(_points(tmp_path, {}, [20, 30])).rotation_form == "quaternion"
    assert "form" not in load_rate_point("shac_ladder:rp4").attributes["rotation"].to_json()
    assert load_rate_point("shac_auto:template").rotation_form == "vector"


@pytest.mark.parametrize("rotation, qp, message", [
    ({"form": "euler"}, 20, "attributes.rotation.form"),
    ({"form": "vector"}, [20, 30], "a rotation vector takes one QP"),
])
def test_bad_forms_are_one_clear_error(tmp_path, rotation, qp, message):
    with pytest.raises(RatePointError, match=message):
        load_rate_point(_points(tmp_path, rotation, qp))


def test_only_the_rotation_has_a_form(tmp_path):
    path = tmp_path / "points.yaml"
    path.write_text(yaml.safe_dump({"points": {"p": {"attributes": {"scale": {"form": "vector"}}}}}))
    with pytest.raises(RatePointError, match="only the rotation has a form"):
        load_rate_point(f"{path}:p")


@pytest.fixture(scope="module")
def cloud():
    return make_synthetic_scene(400, seed=5, n_cameras=1, width=32, height=24).cloud


def _encode(cloud, point):
    encoder = Encoder(point, sh_stage="pca", sh_params={"energy_retention": 0.97},
                      codec_options={"preset": "ultrafast"})
    stream = encoder.encode(cloud)
    return encoder, stream.to_bytes()


def test_a_vector_stream_is_format_2_4_with_three_rotation_channels(tmp_path, cloud):
    encoder, data = _encode(cloud, _points(tmp_path, {"form": "vector"}, 6))
    stream = Bitstream.from_bytes(data)
    assert data[8:12] == b"\x02\x00\x04\x00"
    assert "rotation_vector" in stream.features
    entry = stream.header["attributes"]["rotation"]
    assert (entry["transform"], entry["channels"], entry["chunks"]) == ("rotation_vector", 3, ["rotation"])
    decoded = Decoder().decode(data)
    assert decoded.quats.shape == (cloud.num_gaussians, 4) and decoded.quats.dtype == np.float32
    turned = _angle_between(cloud.quats[encoder.order_].astype(np.float64), decoded.quats.astype(np.float64))
    assert np.degrees(turned).max() < 3.0  # QP 6 of 10-bit samples over +-pi


def test_the_vector_form_codes_the_rotation_in_fewer_bytes_at_an_equal_error(tmp_path, cloud):
    """On a grid of random rotations (no spatial correlation to exploit), fewer channels must still
    pay: at QPs giving the vector form at most the quaternion's mean turn, fewer rotation bytes."""
    turns, sizes = {}, {}
    for form, rotation, qp in (("quaternion", {}, 12), ("vector", {"form": "vector"}, 6)):
        encoder, data = _encode(cloud, _points(tmp_path, rotation, qp))
        decoded = Decoder().decode(data)
        turns[form] = float(np.mean(_angle_between(cloud.quats[encoder.order_].astype(np.float64),
                                                   decoded.quats.astype(np.float64))))
        sizes[form] = Bitstream.from_bytes(data).attribute_sizes()["rotation"]
    assert turns["vector"] <= turns["quaternion"]
    assert sizes["vector"] < sizes["quaternion"]


def test_the_header_ties_the_transform_to_the_feature_and_its_channels(tmp_path, cloud):
    _, data = _encode(cloud, _points(tmp_path, {"form": "vector"}, 6))

    def edited(edit) -> bytes:
        stream = Bitstream.from_bytes(data)
        edit(stream)
        return stream.to_bytes()

    without_feature = edited(lambda s: s.features.discard("rotation_vector"))
    with pytest.raises(BitstreamError, match="rotation vectors and the rotation_vector feature come together"):
        Decoder().decode(without_feature)
    four_channels = edited(lambda s: s.header["attributes"]["rotation"].update(channels=4))
    with pytest.raises(BitstreamError, match="key 'attributes.rotation.channels': must be 3"):
        Decoder().decode(four_channels)
    unknown = edited(lambda s: s.header["attributes"]["rotation"].update(transform="euler_angles"))
    with pytest.raises(BitstreamError, match="key 'attributes.rotation.transform'"):
        Decoder().decode(unknown)
