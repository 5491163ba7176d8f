"""Drop-in use inside gsplat-style code: splats dicts in, splats dicts out.

gsplat keeps a model as a dict of tensors::

    means (N, 3)   scales (N, 3) log   quats (N, 4) wxyz   opacities (N,) logits
    sh0 (N, 1, 3)  shN (N, K-1, 3)     (torch tensors; numpy arrays work too)

plus, in some trainings, other per-Gaussian tensors (``features`` and ``colors`` with
appearance optimisation, or a user's own).

:class:`ShacCompression` has the constructor and the two methods of gsplat 1.5's
``PngCompression`` (``ShacCompression(use_sort=True, verbose=True)``,
``compress(compress_dir, splats)`` and ``decompress(compress_dir) -> splats``), our
settings following as keywords. It writes ``splats.gsc`` and, when the splats hold
other keys, ``splats.extra.npz`` beside it: those tensors coded losslessly (numpy's
deflated npz, dtype and shape kept), in the decoded (grid) order, as gsplat's own codec
stores keys it does not know. A gsplat training script swaps it in with one line
(gsplat itself is not needed; docs/formats.md shows the change to simple_trainer.py)::

    from gscodec_shac.gsplat_compat import ShacCompression

    # was: compression_method = PngCompression()
    compression_method = ShacCompression(rate_point="gsplat_png", sh="pca", sh_params={"energy_retention": 0.99})
    compression_method.compress(compress_dir, runner.splats)
    splats = compression_method.decompress(compress_dir)   # dict of CPU tensors, grid order

The SH stages also work on the dict (or on plain (N, K-1, 3) arrays) without
the codec, e.g. to apply SHAC-PCA before gsplat's own k-means::

    stage = fit_sh_stage("pca", splats, energy_retention=0.99)
    features = sh_features(stage, splats)            # (N, M) what a codec would code
    splats["shN"] = sh_from_features(stage, features, like=splats["shN"])
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gscodec_shac import sh_index
from gscodec_shac.atomic import write_atomic
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.errors import GscodecError, ValidationError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.shac.base import ShStage, make_stage

SPLAT_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


# --------------------------------------------------------------- conversions
def to_numpy(value: Any) -> np.ndarray:
    """A torch tensor (any device) or array-like -> numpy float32."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.ascontiguousarray(value, dtype=np.float32)


def splats_to_cloud(splats: Mapping[str, Any]) -> GaussianCloud:
    """A gsplat splats dict -> :class:`GaussianCloud` (same rows, same order; other keys in ``extra``).

    Works on a dict or on the trainer's ``torch.nn.ParameterDict``; ``extra`` keeps the
    other tensors' dtypes and shapes (one row per Gaussian).
    """
    missing = [k for k in SPLAT_KEYS if k not in splats]
    if missing:
        raise ValidationError(f"splats dict lacks {', '.join(missing)} (needs {', '.join(SPLAT_KEYS)})")
    extra = {str(k): _raw_numpy(splats[k]) for k in splats if k not in SPLAT_KEYS}
    sh0 = to_numpy(splats["sh0"])
    if sh0.ndim != 3 or sh0.shape[1:] != (1, 3):
        raise ValidationError(f"sh0 must have shape (N, 1, 3), got {sh0.shape}")
    return GaussianCloud(
        means=to_numpy(splats["means"]),
        scales=to_numpy(splats["scales"]),
        quats=to_numpy(splats["quats"]),
        opacities=to_numpy(splats["opacities"]).reshape(-1),
        sh_dc=sh0[:, 0, :],
        sh_rest=to_numpy(splats["shN"]),
        extra=extra,
    )


def _raw_numpy(value: Any) -> np.ndarray:
    """A tensor or array-like as numpy with its own dtype (no float32 cast)."""
    if hasattr(value, "detach"):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def cloud_to_splats(cloud: GaussianCloud, *, as_torch: bool | None = None) -> dict[str, Any]:
    """:class:`GaussianCloud` -> gsplat splats dict (torch CPU tensors when torch imports, unless ``as_torch=False``).

    ``cloud.extra`` entries follow the six gsplat keys.
    """
    arrays = {
        "means": cloud.means,
        "scales": cloud.scales,
        "quats": cloud.quats,
        "opacities": cloud.opacities,
        "sh0": cloud.sh_dc[:, None, :],
        "shN": cloud.sh_rest,
    }
    arrays.update({k: v for k, v in cloud.extra.items() if k not in arrays})
    if as_torch is None:
        try:
            import torch  # noqa: F401

            as_torch = True
        except ImportError:
            as_torch = False
    if not as_torch:
        return {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    import torch

    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrays.items()}


# ------------------------------------------------------------------ SH stages
def _ac(source: Mapping[str, Any] | Any) -> np.ndarray:
    """AC matrix (N, K') from a splats dict, an (N, K-1, 3) shN array or an (N, K') matrix."""
    sh = source["shN"] if isinstance(source, Mapping) else source
    array = to_numpy(sh)
    if array.ndim == 3:
        return sh_index.ac_matrix(array)
    if array.ndim == 2:
        return array
    raise ValidationError(f"expected shN (N, K-1, 3) or an AC matrix (N, K'), got shape {array.shape}")


def fit_sh_stage(stage: str | ShStage, source: Mapping[str, Any] | Any, **params: Any) -> ShStage:
    """Fit an SH stage (by name with ``params``, or an instance) on a splats dict or an SH array."""
    stage = make_stage(stage, **params) if isinstance(stage, str) else stage
    return stage.fit(_ac(source))


def sh_features(stage: ShStage, source: Mapping[str, Any] | Any) -> np.ndarray:
    """Features (N, D) a codec would code for ``source``'s SH AC coefficients."""
    return np.asarray(stage.transform(_ac(source)))


def sh_from_features(stage: ShStage, features: np.ndarray, *, like: Any = None) -> Any:
    """Reconstructed shN (N, K-1, 3) from features; a torch tensor when ``like`` is one."""
    sh_rest = sh_index.sh_rest_from_ac(np.ascontiguousarray(stage.inverse_transform(np.asarray(features)), dtype=np.float32))
    if like is not None and hasattr(like, "detach"):
        import torch

        return torch.from_numpy(sh_rest).to(device=like.device, dtype=like.dtype)
    return sh_rest


# --------------------------------------------------------------------- codec
@dataclass
class ShacCompression:
    """gsplat ``PngCompression``-shaped codec writing ``compress_dir/splats.gsc`` (+ ``splats.extra.npz``).

    ``use_sort``: sort onto the grid with the rate point's method (else raster order,
    as gsplat's ``use_sort=False``); ``verbose``: progress bars (as gsplat: on by
    default). Ours, by keyword: ``rate_point`` (default ``"gsplat_png"``: 8-bit PNG +
    k-means SH, as gsplat), ``sh``/``sh_params`` (SH stage override), ``filename`` and
    ``extra_filename`` (the side file of the other splat keys). ``decompress`` warns
    (:class:`FewerGaussiansWarning`) when the rate point pruned Gaussians, so it returns fewer
    than ``compress`` was given; sizes are bits per input Gaussian, as everywhere.
    """

    use_sort: bool = True
    verbose: bool = True
    rate_point: str = "gsplat_png"
    sh: str | None = None
    sh_params: dict[str, Any] = field(default_factory=dict)
    filename: str = "splats.gsc"
    extra_filename: str = "splats.extra.npz"

    def compress(self, compress_dir: str | os.PathLike, splats: Mapping[str, Any]) -> None:
        """Encode ``splats`` into ``compress_dir`` (created); ``splats`` is not modified."""
        from gscodec_shac.codec import Encoder

        directory = Path(compress_dir)
        cloud = splats_to_cloud(splats)
        encoder = Encoder(
            self.rate_point, sh_stage=self.sh, sh_params=dict(self.sh_params),
            sort=None if self.use_sort else "none", progress=self.verbose,
        )
        stream = encoder.encode(cloud)
        directory.mkdir(parents=True, exist_ok=True)
        extra_path = directory / self.extra_filename
        if cloud.extra:  # the decoded rows are encoder.order_ of the input: store the extras that way
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **{k: v[encoder.order_] for k, v in cloud.extra.items()})
            write_atomic(extra_path, buffer.getvalue())
        else:
            extra_path.unlink(missing_ok=True)  # never pair this .gsc with an older run's extras
        stream.write(directory / self.filename)

    def decompress(self, compress_dir: str | os.PathLike) -> dict[str, Any]:
        """Decode ``compress_dir`` into a splats dict (Gaussians in grid order, extra keys included)."""
        from gscodec_shac.codec import Decoder

        directory = Path(compress_dir)
        stream = Bitstream.read(directory / self.filename)
        splats = cloud_to_splats(Decoder(progress=self.verbose).decode(stream))
        _warn_if_fewer(stream, splats["means"].shape[0], directory / self.filename)
        extra_path = directory / self.extra_filename
        if extra_path.is_file():
            import torch

            n = splats["means"].shape[0]
            try:
                with np.load(extra_path, allow_pickle=False) as data:
                    extra = {key: data[key] for key in data.files}
            except (OSError, ValueError) as exc:
                raise GscodecError(f"{extra_path}: unreadable extra splat keys ({exc})") from None
            for key, value in extra.items():
                if value.ndim < 1 or value.shape[0] != n:
                    raise GscodecError(f"{extra_path}: {key!r} has {value.shape[0] if value.ndim else 0} rows, "
                                       f"the decoded splats {n}: the side file belongs to another compression")
                splats[key] = torch.from_numpy(np.ascontiguousarray(value))
        return splats


class FewerGaussiansWarning(UserWarning):
    """The decoded splats hold fewer Gaussians than were compressed (the rate point prunes)."""


def _warn_if_fewer(stream: Bitstream, decoded: int, path: Path) -> None:
    """Warn when pruning left fewer Gaussians than ``compress`` was given (header ``input_gaussians``)."""
    import warnings

    from gscodec_shac.codec.header import read_header

    from gscodec_shac.codec import tiers

    given = stream.header.get("input_gaussians") if tiers.is_tiered(stream) else read_header(stream).input_gaussians
    if given is not None and decoded < given:
        warnings.warn(FewerGaussiansWarning(
            f"{path}: returns {decoded:,} Gaussians of the {given:,} compressed ({given - decoded:,} pruned by the "
            f"rate point; {8.0 * stream.total_bytes() / given:.2f} bits per input Gaussian)"), stacklevel=3)

