"""Image quality metrics as 3DGS papers report them: PSNR, SSIM and (optionally) LPIPS-VGG.

* :func:`psnr`: data range 1, both images clipped to [0, 1], mean over pixels and channels.
* :func:`ssim`: the 3DGS ``loss_utils.ssim``: an 11x11 Gaussian window (sigma 1.5, the outer
  product of a normalised 1-D window), per-channel filtering with *zero* padding of 5 pixels
  (``F.conv2d(..., padding=5)``: same-size output, borders see zeros), ``C1 = 0.01^2``,
  ``C2 = 0.03^2``, and the SSIM map averaged over channels and pixels. Images clipped to [0, 1].
  (scikit-image's defaults - a uniform 7x7 window, no padding - give different numbers.)
* :func:`lpips`: LPIPS with the VGG16 backbone, computed **only** from a weights file the user
  supplies (argument, or the ``GSCODEC_LPIPS_WEIGHTS`` environment variable); otherwise the value
  is ``None`` with the reason. No other network is ever used under the LPIPS name.

LPIPS weights file: a ``torch.save``-d state dict holding the torchvision VGG16 convolution
weights under their torchvision names ``features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.{weight,bias}``
and the five LPIPS v0.1 linear layers as ``lin{0..4}.weight`` (shapes (1, C, 1, 1), C = 64,
128, 256, 512, 512; the LPIPS release's names ``lin{k}.model.1.weight`` are accepted too).
Built once, on any machine with torchvision and the lpips package, e.g.::

    vgg = torchvision.models.vgg16(weights="IMAGENET1K_V1").state_dict()
    state = {k: v for k, v in vgg.items() if k.startswith("features.")}
    state.update({k.replace(".model.1", ""): v for k, v in torch.load("lpips/weights/v0.1/vgg.pth").items()})
    torch.save(state, "lpips_vgg16.pth")

:func:`load_image` reads 8/16-bit (or float) RGB, gray or RGBA images as float32 RGB in [0, 1],
compositing RGBA over a background colour (NeRF-synthetic is evaluated over white).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from gscodec_shac.errors import GscodecError

#: Environment variable naming the LPIPS-VGG weights file.
LPIPS_ENV = "GSCODEC_LPIPS_WEIGHTS"
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

PathLike = str | os.PathLike


class ImageError(GscodecError):
    """An image file is missing, unreadable or has an unsupported layout."""


class LpipsWeightsError(GscodecError):
    """A supplied LPIPS weights file does not hold the VGG16 + LPIPS layers."""


# --------------------------------------------------------------------------- images


def _pair(a: np.ndarray, b: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise GscodecError(f"{what}: images have different shapes {a.shape} and {b.shape}")
    if a.ndim not in (2, 3) or a.size == 0:
        raise GscodecError(f"{what}: expected (H, W) or (H, W, C) images, got shape {a.shape}")
    return np.clip(a, 0.0, 1.0), np.clip(b, 0.0, 1.0)


def load_image(
    path: PathLike, *, background: Sequence[float] = (0.0, 0.0, 0.0), size: tuple[int, int] | None = None
) -> np.ndarray:
    """An image file as float32 RGB (H, W, 3) in [0, 1].

    8-bit and 16-bit integers are scaled by their maximum; gray images are repeated to RGB;
    RGBA is composited over ``background`` (``rgb * a + background * (1 - a)``). With
    ``size=(width, height)`` the image is resampled with ``cv2.INTER_AREA`` (integer images
    are resized before the conversion to float, as the usual 3DGS data loaders do).
    """
    import cv2

    from gscodec_shac.limits import check_image_file

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such image file")
    check_image_file(path, ImageError)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageError(f"{path}: cannot be decoded as an image")
    if raw.ndim == 3 and raw.shape[2] not in (3, 4) or raw.ndim not in (2, 3):
        raise ImageError(f"{path}: unsupported channel layout {raw.shape}")
    if raw.dtype == np.uint8:
        scale = 255.0
    elif raw.dtype == np.uint16:
        scale = 65535.0
    elif np.issubdtype(raw.dtype, np.floating):
        scale = 1.0
    else:
        raise ImageError(f"{path}: unsupported sample type {raw.dtype}")
    has_alpha = raw.ndim == 3 and raw.shape[2] == 4
    if size is not None and not has_alpha:
        raw = _resize(raw, size, path)
    image = raw.astype(np.float32) / np.float32(scale)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif has_alpha:
        rgb = image[:, :, 2::-1]
        alpha = image[:, :, 3:4]
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        image = rgb * alpha + bg * (1.0 - alpha)
        if size is not None:
            image = _resize(image, size, path)
    else:
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image, dtype=np.float32)


def _resize(image: np.ndarray, size: tuple[int, int], path: Path) -> np.ndarray:
    import cv2

    width, height = (int(v) for v in size)
    if width < 1 or height < 1:
        raise ImageError(f"{path}: cannot resize to {width}x{height}")
    if (image.shape[1], image.shape[0]) == (width, height):
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


# --------------------------------------------------------------------------- PSNR / SSIM


def mse(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean squared error of the images clipped to [0, 1]."""
    a, b = _pair(image, reference, "mse")
    return float(np.mean((a - b) ** 2))


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB, data range 1, on images clipped to [0, 1]; ``inf`` for identical images."""
    error = mse(image, reference)
    return math.inf if error == 0.0 else -10.0 * math.log10(error)


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1-D Gaussian window of 3DGS's SSIM (centre at ``size // 2``)."""
    x = np.arange(size, dtype=np.float64) - size // 2
    window = np.exp(-(x**2) / (2.0 * sigma**2))
    return window / window.sum()


def ssim(image: np.ndarray, reference: np.ndarray) -> float:
    """SSIM as 3DGS computes it (see the module docstring); 1 for identical images."""
    from scipy.ndimage import correlate1d

    a, b = _pair(image, reference, "ssim")
    if a.ndim == 2:
        a, b = a[:, :, None], b[:, :, None]
    window = gaussian_window()

    def blur(x: np.ndarray) -> np.ndarray:  # zero padding, same-size output, per channel
        x = correlate1d(x, window, axis=0, mode="constant", cval=0.0)
        return correlate1d(x, window, axis=1, mode="constant", cval=0.0)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    ssim_map = ((2.0 * mu_a * mu_b + SSIM_C1) * (2.0 * cov + SSIM_C2)) / (
        (mu_a**2 + mu_b**2 + SSIM_C1) * (var_a + var_b + SSIM_C2)
    )
    return float(ssim_map.mean())


# --------------------------------------------------------------------------- LPIPS

#: (torchvision index, in channels, out channels) of VGG16's convolutions; ``None`` = max-pool.
_VGG16 = (
    (0, 3, 64), (2, 64, 64), None,
    (5, 64, 128), (7, 128, 128), None,
    (10, 128, 256), (12, 256, 256), (14, 256, 256), None,
    (17, 256, 512), (19, 512, 512), (21, 512, 512), None,
    (24, 512, 512), (26, 512, 512), (28, 512, 512),
)
#: LPIPS taps VGG16 after these convolutions' ReLUs (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).
_TAPS = (2, 7, 14, 21, 28)
LPIPS_CHANNELS = (64, 128, 256, 512, 512)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def lpips_state_shapes() -> dict[str, tuple[int, ...]]:
    """Every key of the LPIPS-VGG weights file and its tensor shape (see the module docstring)."""
    shapes: dict[str, tuple[int, ...]] = {}
    for layer in _VGG16:
        if layer is not None:
            index, cin, cout = layer
            shapes[f"features.{index}.weight"] = (cout, cin, 3, 3)
            shapes[f"features.{index}.bias"] = (cout,)
    for k, channels in enumerate(LPIPS_CHANNELS):
        shapes[f"lin{k}.weight"] = (1, channels, 1, 1)
    return shapes


class LpipsVGG:
    """LPIPS (v0.1, VGG16 backbone) built in plain torch from a user-supplied state dict."""

    def __init__(self, state: dict[str, Any], source: str = "state dict") -> None:
        import torch

        state = {k.replace(".model.1.", "."): v for k, v in state.items()}
        self.params: dict[str, Any] = {}
        for key, shape in lpips_state_shapes().items():
            if key not in state:
                raise LpipsWeightsError(f"{source}: LPIPS weights lack {key!r} (need VGG16 features and lin0-lin4)")
            tensor = torch.as_tensor(state[key]).detach().to(torch.float32)
            if tuple(tensor.shape) != shape:
                raise LpipsWeightsError(f"{source}: {key!r} has shape {tuple(tensor.shape)}, expected {shape}")
            if not bool(torch.isfinite(tensor).all()):
                raise LpipsWeightsError(f"{source}: {key!r} holds non-finite values")
            self.params[key] = tensor
        self.source = source

    @classmethod
    def from_file(cls, path: PathLike) -> "LpipsVGG":
        import torch

        path = Path(path)
        if not path.is_file():
            raise LpipsWeightsError(f"{path}: no such LPIPS weights file")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types for foreign files
            raise LpipsWeightsError(f"{path}: not a torch state dict ({type(exc).__name__})") from None
        if not isinstance(state, dict):
            raise LpipsWeightsError(f"{path}: expected a state dict, found {type(state).__name__}")
        return cls(state, str(path))

    def _features(self, x: Any) -> list[Any]:
        import torch.nn.functional as F

        taps = []
        for layer in _VGG16:
            if layer is None:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
                continue
            index = layer[0]
            weight, bias = self.params[f"features.{index}.weight"], self.params[f"features.{index}.bias"]
            x = F.relu(F.conv2d(x, weight, bias, padding=1))
            if index in _TAPS:
                taps.append(x)
        return taps

    def __call__(self, image: np.ndarray, reference: np.ndarray) -> float:
        """LPIPS distance of two RGB images in [0, 1] (clipped), shape (H, W, 3)."""
        import torch
        import torch.nn.functional as F

        a, b = _pair(image, reference, "lpips")
        if a.ndim != 3 or a.shape[2] != 3:
            raise GscodecError(f"lpips: expected (H, W, 3) RGB images, got shape {a.shape}")
        shift = torch.tensor(_SHIFT, dtype=torch.float32).view(1, 3, 1, 1)
        scale = torch.tensor(_SCALE, dtype=torch.float32).view(1, 3, 1, 1)
        with torch.no_grad():
            batch = torch.from_numpy(np.stack([a, b]).astype(np.float32)).permute(0, 3, 1, 2)
            batch = ((batch * 2.0 - 1.0) - shift) / scale
            total = 0.0
            for k, feats in enumerate(self._features(batch)):
                unit = feats / (torch.sqrt((feats**2).sum(dim=1, keepdim=True)) + 1e-10)
                diff = (unit[0:1] - unit[1:2]) ** 2
                total += float(F.conv2d(diff, self.params[f"lin{k}.weight"]).mean())
        return total


def resolve_lpips_weights(weights: PathLike | None = None) -> tuple[Path | None, str | None]:
    """``(path, None)`` for the weights to use, or ``(None, reason)`` when none was supplied."""
    if weights is not None:
        return Path(weights), None
    env = os.environ.get(LPIPS_ENV, "").strip()
    if env:
        return Path(env), None
    return None, (
        f"LPIPS unavailable: no LPIPS-VGG weights file given (pass a path or set {LPIPS_ENV}); "
        "no other network is substituted"
    )


def load_lpips(weights: PathLike | None = None) -> tuple[LpipsVGG | None, str | None]:
    """``(model, None)`` from the supplied weights, or ``(None, reason)`` when none are supplied.

    A supplied file that is missing or malformed raises :class:`LpipsWeightsError`.
    """
    path, reason = resolve_lpips_weights(weights)
    if path is None:
        return None, reason
    return LpipsVGG.from_file(path), None


def lpips(
    image: np.ndarray, reference: np.ndarray, *, weights: PathLike | None = None, model: LpipsVGG | None = None
) -> tuple[float | None, str | None]:
    """``(distance, None)``, or ``(None, reason)`` when no LPIPS-VGG weights were supplied."""
    if model is None:
        model, reason = load_lpips(weights)
        if model is None:
            return None, reason
    return model(image, reference), None


def image_metrics(
    image: np.ndarray, reference: np.ndarray, *, lpips_model: LpipsVGG | None = None, lpips_reason: str | None = None
) -> dict[str, Any]:
    """``{"psnr", "ssim", "lpips", "lpips_note"}`` for one image pair (LPIPS None without a model)."""
    result: dict[str, Any] = {"psnr": psnr(image, reference), "ssim": ssim(image, reference)}
    if lpips_model is not None:
        result["lpips"], result["lpips_note"] = lpips_model(image, reference), None
    else:
        result["lpips"] = None
        result["lpips_note"] = lpips_reason or "LPIPS not computed: no LPIPS-VGG model was given"
    return result
