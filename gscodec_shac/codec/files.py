"""File in, file out: a model file -> ``.gsc`` and ``.gsc`` -> a model file, written atomically, with a summary.

Models are read and written by :mod:`gscodec_shac.io.models` (Inria PLY, SPZ, .splat, SOG,
compressed.ply, gsplat checkpoints; the output format follows the extension)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable

from gscodec_shac.atomic import inputs_protected
from gscodec_shac.codec.container import Bitstream
from gscodec_shac.codec.decoder import Decoder
from gscodec_shac.codec.encoder import Encoder
from gscodec_shac.codec.grid import x265_processes
from gscodec_shac.codec.rate_control import TEMPLATE, RateController, Target, make_target
from gscodec_shac.codec.importance import importance_views
from gscodec_shac.codec.rate_points import RatePoint, load_rate_point
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.errors import GscodecError, OutputError
from gscodec_shac.limits import default_workers
from gscodec_shac.shac.view_metric import cloud_view_metric, metric_applies


def _prestart_x265(rate_point: str | Path | RatePoint) -> None:
    """Start the x265 worker processes while the model is read, when the rate point codes with x265
    (a rate point that does not load is reported where it is used)."""
    try:
        point = load_rate_point(rate_point)
    except GscodecError:
        return
    if any(spec.codec == "hevc" for spec in point.attributes.values()):
        x265_processes.prestart(default_workers())


def encode_file(
    in_ply: str | os.PathLike,
    out_gsc: str | os.PathLike,
    rate_point: str | Path | RatePoint,
    sh: str | None = None,
    *,
    sort: str | None = None,
    seed: int | None = None,
    preset: str | None = None,
    analysis: str | None = None,
    progress: bool = False,
    choose_sh: Callable[[Any], tuple[str, dict[str, Any]]] | None = None,
    network_bits: int | None = None,
    keep_share: float | None = None,
    dc_only_share: float | None = None,
    dc_only_energy: float | None = None,
    dc_only_weight: str | None = None,
    cameras: str | os.PathLike | None = None,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    **stage_params: Any,
) -> dict[str, Any]:
    """Any model file ``read_model`` reads -> ``.gsc`` (written atomically); returns a summary
    (bytes, bits per Gaussian, seconds, the reader's ``notes``).

    ``sh`` picks the SH stage (default: the rate point's), ``stage_params`` its
    parameters (e.g. ``energy_retention=0.99``); ``preset`` sets the lossy
    codecs' speed preset (x265's ``preset`` option), ``analysis`` x265's analysis (``"full"`` or
    ``"preset"``; default: by the scene's size, :mod:`.effort`). ``choose_sh``, when given, picks
    ``(stage, params)`` from the model read (the default encode, :mod:`.defaults`);
    ``network_bits`` how a dynamic model's network is stored (16: float16, 2..8: quantised,
    the output heads at 8 bits below 8; default: the bits of the grid a network trained with
    ``train-dynamic --network-bits`` lies on, else 8, :mod:`.deformation`). ``keep_share`` overrides
    the rate point's importance pruning (:mod:`.importance`), measured on ``cameras`` (any camera
    file) or else orbit views around ``up``; ``dc_only_share`` the rate point's share of DC-only
    Gaussians (or ``dc_only_energy`` its energy bar, ``dc_only_weight`` its weight, :mod:`.sh_degree`);
    a render weight is measured on the same views.
    """
    from gscodec_shac.deform_arch import is_dynamic_model
    from gscodec_shac.io.models import read_model

    tic = time.perf_counter()
    _check_output_dir(out_gsc, in_ply)
    _prestart_x265(rate_point)
    dynamic = None
    if is_dynamic_model(in_ply):  # canonical Gaussians as any model + the network chunk
        from gscodec_shac.codec.deformation import add_deformation
        from gscodec_shac.deform import load_dynamic_model

        dynamic = load_dynamic_model(in_ply)
        cloud, notes = dynamic.cloud, []
    else:
        if network_bits is not None:
            raise GscodecError(f"{in_ply}: network bits apply to a dynamic model, this is a static one")
        cloud, notes = read_model(in_ply)
    if choose_sh is not None:
        sh, chosen = choose_sh(cloud)
        stage_params = {**chosen, **stage_params}
    point = load_rate_point(rate_point).with_overrides(keep_share=keep_share, dc_only_share=dc_only_share,
                                                       dc_only_energy=dc_only_energy,
                                                       dc_only_weight=dc_only_weight)
    views = None
    given = load_cameras(cameras) if cameras is not None else None
    if point.keep_share < 1.0 or (point.dc_only and point.dc_only_weight == "render"):
        views = importance_views(cloud, given, up=up)
    encoder = Encoder(point, sh_stage=sh, sort=sort, seed=seed,
                      sh_params={k: v for k, v in stage_params.items() if v is not None},
                      codec_options=_codec_options(preset, analysis), progress=progress, views=views)
    weighed_by = _view_metric(encoder, cloud, given, notes, measures_importance=views is not None)
    n_input, sh_degree = cloud.num_gaussians, cloud.sh_degree
    means = cloud.means if dynamic is not None else None  # the network's rounding is fitted on them
    stream = encoder.encode(cloud, release_input=True)  # the model is freed once read (memory, issue 25)
    if dynamic is not None:
        from gscodec_shac.codec.deformation import DEFAULT_BITS, encoder_bits, trained_grid

        weights = dynamic.net.weights()
        # a network trained on a coarser grid is coded on it, else at the default
        bits = encoder_bits(dynamic.arch, network_bits) if network_bits is not None else \
            trained_grid(dynamic.arch, weights) or encoder_bits(dynamic.arch, DEFAULT_BITS)
        add_deformation(stream, dynamic.arch, weights, bits, means=means)
    with inputs_protected(in_ply, *([cameras] if cameras is not None else [])):
        size = stream.write(out_gsc)
    return {
        "input": str(in_ply),
        "output": str(out_gsc),
        "rate_point": encoder.rate_point.name,
        "sh_stage": encoder.rate_point.sh_stage,
        "input_gaussians": n_input,
        "sh_degree": sh_degree,
        "num_gaussians": stream.header["num_gaussians"],
        "bytes": size,
        "bits_per_gaussian": 8.0 * size / n_input,
        "seconds": time.perf_counter() - tic,
        "timings": encoder.timings_,
        "sizes": stream.attribute_sizes(),
        "sh_view_metric_cameras": weighed_by,
        "notes": notes,
    }


def _view_metric(encoder: Encoder, cloud: Any, cameras: list | None, notes: list[str], *,
                 measures_importance: bool) -> int | None:
    """With the caller's ``cameras`` and a SHAC-PCA stage that takes one, set the encoder's SH view metric
    (:mod:`gscodec_shac.shac.view_metric`: the SH coefficients weighed by the directions the cameras see
    the Gaussians from; the paper's rank, another basis); returns how many cameras it counts. When the
    metric does not apply, a note says the cameras went unused, unless importance is measured from them."""
    if not cameras:
        return None
    point = encoder.rate_point
    if cloud.sh_degree == 0 or not metric_applies(point.sh_stage, point.sh_params):
        if not measures_importance:
            why = "the model has no view-dependent colour (SH degree 0)" if cloud.sh_degree == 0 else \
                f"the SH stage {point.sh_stage!r} does not weigh the SH by the views (SHAC-PCA over R, G and B does)"
            notes.append(f"the cameras are not used: {why}")
        return None
    encoder.sh_metric = cloud_view_metric(cloud, cameras)
    return len(cameras)


def encode_file_to_target(
    in_ply: str | os.PathLike,
    out_gsc: str | os.PathLike,
    target: Target | None = None,
    *,
    size: str | None = None,
    bpg: float | None = None,
    psnr: float | None = None,
    template: str | RatePoint = TEMPLATE,
    cameras: str | os.PathLike | None = None,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    preset: str | None = None,
    analysis: str | None = None,
    progress: bool = False,
    recover: bool = False,
    recover_steps: int | None = None,
) -> dict[str, Any]:
    """Any model file ``read_model`` reads -> ``.gsc`` at a target (:mod:`.rate_control`): a size (``"2.5MB"``), bits per Gaussian or
    PSNR against the uncompressed model on ``cameras`` (any camera file; default: orbit views).
    ``recover``: also code the model's pruned-and-recovered versions and keep the best file (:mod:`.rate_recover`),
    their recovery ``recover_steps`` fine-tuning steps long (default: the recovery's).

    Nothing is written when the target cannot be reached (:class:`TargetUnreachableError`).
    """
    from gscodec_shac.deform_arch import is_dynamic_model
    from gscodec_shac.io.models import read_model

    tic = time.perf_counter()
    if is_dynamic_model(in_ply):
        raise GscodecError(f"{in_ply}: a dynamic model is encoded at a rate point (--rate-point), not to a target")
    _check_output_dir(out_gsc, in_ply)
    cloud, notes = read_model(in_ply)
    target = target or make_target(cloud.num_gaussians, size=size, bpg=bpg, psnr=psnr)
    views = load_cameras(cameras) if cameras is not None else None
    options = {"up": up, "background": background, "progress": progress,
               "codec_options": _codec_options(preset, analysis)}
    if recover:
        from gscodec_shac.codec.rate_recover import RecoveringController

        controller: Any = RecoveringController(cloud, template, views, iterations=recover_steps,
                                               controller_options=options)
    else:
        controller = RateController(cloud, template, views, **options)
    outcome = controller.encode(target)
    with inputs_protected(in_ply, *([cameras] if cameras is not None else [])):
        written = outcome.stream.write(out_gsc)
    return {
        "input": str(in_ply),
        "output": str(out_gsc),
        "rate_point": outcome.plan.rate_point.name,
        "sh_stage": outcome.plan.rate_point.sh_stage,
        "input_gaussians": cloud.num_gaussians,
        "num_gaussians": outcome.stream.header["num_gaussians"],
        "bytes": written,
        "bits_per_gaussian": 8.0 * written / cloud.num_gaussians,
        "seconds": time.perf_counter() - tic,
        "rate_control": outcome.summary(),
        "sizes": outcome.stream.attribute_sizes(),
        "notes": notes,
    }


def decode_file(in_gsc: str | os.PathLike, out_ply: str | os.PathLike, *, progress: bool = False) -> dict[str, Any]:
    """``.gsc`` -> a model file by extension (.ply, .spz, .splat, .sog, .pt; written atomically); returns a summary."""
    from gscodec_shac.io.models import check_model_extension, write_model

    tic = time.perf_counter()
    stream = Bitstream.read(in_gsc)
    if "deformation" in stream.features:
        return _decode_dynamic(stream, in_gsc, out_ply, tic, progress)
    _check_output_dir(out_ply, in_gsc)
    check_model_extension(out_ply)
    cloud = Decoder(progress=progress).decode(stream)
    with inputs_protected(in_gsc):
        notes = write_model(out_ply, cloud, progress=progress)
    return {
        "input": str(in_gsc),
        "output": str(out_ply),
        "num_gaussians": cloud.num_gaussians,
        "sh_degree": cloud.sh_degree,
        "bytes": Path(in_gsc).stat().st_size,
        "seconds": time.perf_counter() - tic,
        "notes": notes,
    }


def is_dynamic_stream(in_gsc: str | os.PathLike) -> bool:
    """True when the ``.gsc`` file holds a dynamic model (it decodes to a directory)."""
    return "deformation" in Bitstream.read(in_gsc).features


def _decode_dynamic(stream: Bitstream, in_gsc: str | os.PathLike, out_dir: str | os.PathLike, tic: float,
                    progress: bool) -> dict[str, Any]:
    """A dynamic stream -> a model directory (canonical ``point_cloud.ply`` + the network)."""
    from gscodec_shac.codec.header import read_deformation, read_header
    from gscodec_shac.deform import DeformNetwork, DynamicModel, save_dynamic_model
    from gscodec_shac.io.models import WRITE_EXTENSIONS

    out = Path(out_dir)
    if out.suffix.lower() in WRITE_EXTENSIONS or (out.exists() and not out.is_dir()):
        raise OutputError(f"{out}: {in_gsc} holds a dynamic model (canonical Gaussians + deformation network); "
                          "decode it to a directory (e.g. OUT_DIR/)")
    view = read_header(stream)
    cloud = Decoder(progress=progress).decode(stream)
    weights = read_deformation(stream, view)
    net = DeformNetwork(view.deformation.arch)
    net.load_weights(weights, f"{in_gsc}: chunk 'deformation'")
    with inputs_protected(in_gsc):
        save_dynamic_model(out, DynamicModel(cloud, net), {"source": f"gscodec-shac decode {Path(in_gsc).name}"})
    return {
        "input": str(in_gsc),
        "output": str(out),
        "num_gaussians": cloud.num_gaussians,
        "sh_degree": cloud.sh_degree,
        "bytes": Path(in_gsc).stat().st_size,
        "deformation_bytes": view.chunk_bytes.get("deformation", 0),
        "seconds": time.perf_counter() - tic,
        "notes": [],
        "dynamic": True,
    }


def _check_output_dir(path: str | os.PathLike, source: str | os.PathLike) -> None:
    """Fail before the work, not after it, when the output cannot be written (the write checks again)."""
    directory = Path(path).parent
    if not directory.is_dir():
        raise GscodecError(f"{path}: output directory {directory} does not exist")
    if Path(path).is_dir():
        raise OutputError(f"{path}: the output path is a directory; give a file name")
    if Path(path).exists() and Path(source).exists() and os.path.samefile(path, source):
        raise OutputError(f"{path}: is the input {source}; refusing to write over an input (even with --force)")


def _codec_options(preset: str | None, analysis: str | None) -> dict[str, str] | None:
    """The lossy codecs' options a caller set (x265's preset, its analysis), or None."""
    options = {key: value for key, value in (("preset", preset), ("analysis", analysis)) if value}
    return options or None
