"""PSNR, SSIM (3DGS flavour), LPIPS plumbing (never a substitute network) and image loading."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gscodec_shac import metrics
from gscodec_shac.metrics import (
    LPIPS_ENV,
    ImageError,
    LpipsVGG,
    LpipsWeightsError,
    image_metrics,
    load_image,
    lpips,
    lpips_state_shapes,
    psnr,
    ssim,
)


def _images(seed: int = 0, shape=(24, 20, 3)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.0, 1.0, shape)
    b = np.clip(a + rng.normal(0.0, 0.1, shape), 0.0, 1.0)
    return a, b


def test_psnr_identical_is_infinite():
    a, _ = _images()
    assert psnr(a, a) == math.inf


def test_psnr_of_known_noise_matches_the_formula():
    rng = np.random.default_rng(1)
    a = np.full((32, 32, 3), 0.5)
    noise = rng.choice([-0.05, 0.05], size=a.shape)  # every squared error is exactly 0.0025
    assert psnr(a + noise, a) == pytest.approx(-10 * math.log10(0.0025), abs=1e-9)
    # values outside [0, 1] are clipped first: 1.5 counts as 1.0
    assert psnr(np.full((4, 4, 3), 1.5), np.full((4, 4, 3), 0.9)) == pytest.approx(20.0, abs=1e-9)


def test_ssim_identical_is_one():
    a, _ = _images()
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_matches_an_independent_torch_conv2d_computation():
    import torch
    import torch.nn.functional as F

    a, b = _images(2, (17, 23, 3))
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    g /= g.sum()
    window = torch.from_numpy(np.outer(g, g)).expand(3, 1, 11, 11).contiguous()
    t1 = torch.from_numpy(a).permute(2, 0, 1)[None]
    t2 = torch.from_numpy(b).permute(2, 0, 1)[None]

    def conv(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=5, groups=3)

    mu1, mu2 = conv(t1), conv(t2)
    s1 = conv(t1 * t1) - mu1**2
    s2 = conv(t2 * t2) - mu2**2
    s12 = conv(t1 * t2) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    expected = (((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))).mean().item()
    assert ssim(a, b) == pytest.approx(expected, abs=1e-12)
    assert ssim(a, b) < 0.99


def test_lpips_is_unavailable_without_weights(monkeypatch):
    monkeypatch.delenv(LPIPS_ENV, raising=False)
    a, b = _images()
    value, reason = lpips(a, b)
    assert value is None and LPIPS_ENV in reason and "no other network" in reason
    row = image_metrics(a, b)
    assert row["lpips"] is None and row["lpips_note"]
    assert row["psnr"] == psnr(a, b)


def _random_lpips_file(tmp_path, *, drop: str | None = None):
    """A weights file of the right layout filled with RANDOM values: tests plumbing only, not LPIPS."""
    import torch

    gen = torch.Generator().manual_seed(0)
    state = {k: torch.rand(shape, generator=gen) * 0.1 for k, shape in lpips_state_shapes().items()}
    if drop is not None:
        del state[drop]
    path = tmp_path / "random_lpips_layout.pth"
    torch.save(state, path)
    return path


def test_lpips_plumbing_with_random_weights(tmp_path, monkeypatch):
    path = _random_lpips_file(tmp_path)
    a, b = _images(3, (37, 29, 3))  # odd sizes go through the pooling stack
    model = LpipsVGG.from_file(path)
    assert model(a, a) == 0.0
    distance = model(a, b)
    assert math.isfinite(distance) and distance > 0.0
    monkeypatch.setenv(LPIPS_ENV, str(path))
    value, reason = lpips(a, b)
    assert reason is None and value == pytest.approx(distance, rel=1e-6)


def test_lpips_refuses_incomplete_weights_instead_of_using_another_network(tmp_path):
    with pytest.raises(LpipsWeightsError, match="lin4"):
        LpipsVGG.from_file(_random_lpips_file(tmp_path, drop="lin4.weight"))
    with pytest.raises(LpipsWeightsError, match="no such"):
        lpips(*_images(), weights=tmp_path / "missing.pth")
    bad = tmp_path / "not_torch.pth"
    bad.write_bytes(b"junk")
    with pytest.raises(LpipsWeightsError, match="not a torch state dict"):
        LpipsVGG.from_file(bad)


def test_lpips_accepts_the_lpips_release_layer_names(tmp_path):
    import torch

    state = {k: torch.zeros(s) for k, s in lpips_state_shapes().items()}
    renamed = {k.replace(".weight", ".model.1.weight") if k.startswith("lin") else k: v for k, v in state.items()}
    model = LpipsVGG(renamed)
    assert model(*_images()) == 0.0  # zero linear layers: plumbing only


def test_load_image_8_16_bit_gray_and_rgba(tmp_path):
    import cv2

    rgb = np.zeros((4, 5, 3), dtype=np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 255, 128, 0  # R, G, B
    cv2.imwrite(str(tmp_path / "a.png"), rgb[:, :, ::-1])
    image = load_image(tmp_path / "a.png")
    assert image.dtype == np.float32 and image.shape == (4, 5, 3)
    assert np.allclose(image[0, 0], [1.0, 128 / 255, 0.0])

    deep = np.full((4, 5, 3), 65535, dtype=np.uint16)
    deep[..., 2] = 0  # stored B channel = 0 -> R = 0
    cv2.imwrite(str(tmp_path / "b.png"), deep)
    assert np.allclose(load_image(tmp_path / "b.png")[0, 0], [0.0, 1.0, 1.0])

    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 5), 51, dtype=np.uint8))
    assert np.allclose(load_image(tmp_path / "g.png")[1, 1], [0.2, 0.2, 0.2])

    rgba = np.zeros((4, 5, 4), dtype=np.uint8)
    rgba[..., 2] = 255  # red in BGRA
    rgba[..., 3] = 0
    rgba[0, 0, 3] = 255
    cv2.imwrite(str(tmp_path / "c.png"), rgba)
    white = load_image(tmp_path / "c.png", background=(1.0, 1.0, 1.0))
    assert np.allclose(white[0, 0], [1.0, 0.0, 0.0]) and np.allclose(white[1, 1], [1.0, 1.0, 1.0])
    assert np.allclose(load_image(tmp_path / "c.png")[1, 1], [0.0, 0.0, 0.0])

    small = load_image(tmp_path / "a.png", size=(2, 2))
    assert small.shape == (2, 2, 3)


def test_load_image_errors(tmp_path):
    with pytest.raises(ImageError, match="no such"):
        load_image(tmp_path / "none.png")
    (tmp_path / "x.png").write_bytes(b"not an image")
    with pytest.raises(ImageError, match="cannot be decoded"):
        load_image(tmp_path / "x.png")


def test_metrics_reject_mismatched_shapes():
    with pytest.raises(metrics.GscodecError, match="different shapes"):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
