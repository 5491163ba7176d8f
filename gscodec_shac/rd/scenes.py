"""Scenes of a sweep: preparing their inputs once (driver) and the evaluation views (runs).

The driver turns each :class:`SceneSpec` into a :class:`PreparedScene` whose inputs are
plain files under ``OUT/scenes/``: the built-in synthetic scene is generated and written
as a PLY + cameras.json; a deployed-format input (meta.json, .sog, .spz, .splat,
compressed.ply, gsplat .pt) is converted to a PLY with the native readers
(:func:`gscodec_shac.io.models.read_model`; splat-transform only for what they do not
read, e.g. .ksplat); a scene without cameras gets orbit cameras written as cameras.json. Runs then read everything by path.

A run's evaluation data (:func:`evaluation_views`): the test cameras (every
``test_every``-th camera in name order, as 3DGS holds out every 8th view; optionally
capped to ``max_views`` evenly spaced ones), the ground-truth images where the scene has
them (resized to the camera with ``cv2.INTER_AREA``) and the renders of the uncompressed
model, cached per scene in ``OUT/cache/<scene>/`` together with the uncompressed model's
own scores against the ground truth.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscodec_shac.camera import Camera, orbit_cameras, test_split
from gscodec_shac.errors import GscodecError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.atomic import write_json, write_npz
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.inria_cameras import write_inria_cameras
from gscodec_shac.rd.cache import DURABLE, file_lock
from gscodec_shac.rd.spec import OrbitSpec, SceneSpec, file_fingerprint, stable_hash


class SceneError(GscodecError):
    """A scene's inputs cannot be prepared or read."""


@dataclass(frozen=True)
class PreparedScene:
    """A scene whose model and cameras are files (what runs receive)."""

    spec: SceneSpec
    ply: str
    cameras: str
    fingerprint: str  # changes when the model, cameras or evaluation setup change
    ply_bytes: int
    images: str | None = None  # ground-truth folder (given, or rendered for the synthetic scene)

    def cache_dir(self, out_dir: str | Path) -> Path:
        return Path(out_dir) / "cache" / f"{self.spec.name}-{self.fingerprint}"

    def to_json(self) -> dict[str, Any]:
        return {"spec": self.spec.to_json(), "ply": self.ply, "cameras": self.cameras, "images": self.images,
                "fingerprint": self.fingerprint, "ply_bytes": self.ply_bytes}


# --------------------------------------------------------------------------- driver side
def prepare_scene(spec: SceneSpec, out_dir: str | Path) -> PreparedScene:
    """Materialise a scene's inputs as files under ``out_dir/scenes`` (idempotent)."""
    out_dir = Path(out_dir)
    images = spec.images
    if spec.synthetic is not None:
        folder = out_dir / "scenes" / f"{spec.name}-{stable_hash(asdict(spec.synthetic), 10)}"
        ply, cameras, gt = folder / "scene.ply", folder / "cameras.json", folder / "ground_truth"
        with file_lock(folder / ".lock"):
            if not (ply.is_file() and cameras.is_file() and (gt / "done").is_file() == spec.synthetic.ground_truth):
                _write_synthetic(spec, ply, cameras, gt)
        images = str(gt) if spec.synthetic.ground_truth else None
    else:
        ply = Path(spec.ply)  # type: ignore[arg-type]
        if not ply.exists():
            raise SceneError(f"scene {spec.name!r}: {ply} does not exist")
        if spec.needs_conversion:
            folder = out_dir / "scenes" / f"{spec.name}-{file_fingerprint(ply)[:10]}"
            converted = folder / "scene.ply"
            with file_lock(folder / ".lock"):
                if not converted.is_file():
                    convert_model_to_ply(ply, converted)
            ply = converted
        if spec.cameras is not None:
            cameras = Path(spec.cameras)
        else:
            orbit = spec.orbit or OrbitSpec()
            folder = out_dir / "scenes" / f"{spec.name}-{file_fingerprint(ply)[:10]}-{stable_hash(asdict(orbit), 8)}"
            cameras = folder / "cameras.json"
            with file_lock(folder / ".lock"):
                if not cameras.is_file():
                    from gscodec_shac.io.ply import read_ply

                    write_inria_cameras(cameras, auto_orbit(read_ply(ply), orbit))
    # ground truth by identity: a user folder by its path, the synthetic one by what generated it
    images_id = f"synthetic:{stable_hash(asdict(spec.synthetic))}" if spec.synthetic is not None and images else images
    setup = {
        "ply": file_fingerprint(ply), "cameras": file_fingerprint(cameras), "images": images_id,
        "background": spec.background, "test_every": spec.test_every, "max_views": spec.max_views,
    }
    if spec.calibration is not None:  # only when given: the fingerprints of scenes without stay the same
        setup["calibration"] = file_fingerprint(spec.calibration)
    fingerprint = stable_hash(setup)
    return PreparedScene(spec, str(ply), str(cameras), fingerprint, Path(ply).stat().st_size, images)


def convert_model_to_ply(source: Path, target: Path) -> None:
    """A model in another format as an Inria PLY: read natively, else through splat-transform."""
    from gscodec_shac.errors import ModelFormatError
    from gscodec_shac.io.models import read_model
    from gscodec_shac.io.ply import write_ply

    try:
        cloud, _ = read_model(source)
    except ModelFormatError as native:
        from gscodec_shac.rd.external import convert_to_ply, unavailable_reason

        if unavailable_reason() is not None:
            raise SceneError(f"{native} (and splat-transform cannot convert it: {unavailable_reason()})") from None
        convert_to_ply(source, target)
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    write_ply(target, cloud)


def _write_synthetic(spec: SceneSpec, ply: Path, cameras: Path, gt: Path) -> None:
    """The synthetic model, its cameras and (optionally) ground-truth images.

    The ground truth is the same scene generated without the white SH noise that mimics
    optimisation noise (identical geometry and DC; only the AC coefficients differ),
    rendered from every camera and stored as 16-bit PNGs.
    """
    import shutil

    import cv2

    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.synthetic import make_synthetic_scene

    syn = spec.synthetic
    assert syn is not None
    kwargs = {"seed": syn.seed, "n_cameras": syn.n_cameras, "width": syn.width, "height": syn.height}
    scene = make_synthetic_scene(syn.n, **kwargs)
    ply.parent.mkdir(parents=True, exist_ok=True)
    write_ply(ply, scene.cloud)  # atomic in io.ply
    write_inria_cameras(cameras, scene.cameras)
    shutil.rmtree(gt, ignore_errors=True)
    if syn.ground_truth:
        clean = make_synthetic_scene(syn.n, noise=0.0, **kwargs)
        gt.mkdir(parents=True)
        for camera, image in zip(clean.cameras, render_all(clean.cloud, clean.cameras, spec.background)):
            pixels = np.clip(np.rint(np.clip(image, 0.0, 1.0) * 65535.0), 0, 65535).astype(np.uint16)
            if not cv2.imwrite(str(gt / f"{camera.name}.png"), np.ascontiguousarray(pixels[:, :, ::-1])):
                raise SceneError(f"cannot write {gt / camera.name}.png")
        (gt / "done").write_text("noise-free synthetic renders\n")


def auto_orbit(cloud: GaussianCloud, orbit: OrbitSpec) -> list[Camera]:
    """Orbit cameras around the bulk of a cloud.

    Centre: the median of the means of the Gaussians with opacity >= 0.1; up: the world
    axis along which they spread least (right for a flat capture with a ground, wrong for
    a tall object, and its sign is a guess: give ``up`` explicitly, e.g. ``[0, -1, 0]`` for
    the y-down COLMAP/3DGS convention); radius: far enough that the sphere holding 80% of
    them fills the view. Explicit ``center``, ``up`` and ``radius`` in the spec win.
    """
    means = cloud.means.astype(np.float64)
    solid = cloud.activated_opacities() >= 0.1
    points = means[solid] if solid.sum() >= 16 else means
    center = np.asarray(orbit.center, float) if orbit.center is not None else np.median(points, axis=0)
    if orbit.up is not None:
        up = np.asarray(orbit.up, float)
    else:
        spread = np.percentile(points, 90, axis=0) - np.percentile(points, 10, axis=0)
        up = np.eye(3)[int(np.argmin(spread))]
    if orbit.radius is not None:
        radius = orbit.radius
    else:
        extent = float(np.percentile(np.linalg.norm(points - center, axis=1), 80)) or 1.0
        radius = 1.15 * extent / np.sin(np.radians(orbit.fov_y) / 2.0)
    return orbit_cameras(center, radius, orbit.n, orbit.width, orbit.height, orbit.fov_y, orbit.elevation, up)


# --------------------------------------------------------------------------- run side
@dataclass
class EvalViews:
    """Test cameras, ground truth (or None) and the uncompressed model's renders and scores."""

    cameras: list[Camera]
    ground_truth: list[np.ndarray] | None
    reference: list[np.ndarray]
    uncompressed: dict[str, Any]  # psnr_gt / ssim_gt / lpips_gt of the uncompressed model, n_gaussians


def test_cameras(scene: PreparedScene) -> list[Camera]:
    """Every ``test_every``-th camera in name order, at most ``max_views`` of them (evenly spaced)."""
    spec = scene.spec
    cameras = load_cameras(scene.cameras, scene.images) if scene.images else load_cameras(scene.cameras)
    _, test = test_split(cameras, spec.test_every)
    if spec.max_views is not None and len(test) > spec.max_views:
        index = np.unique(np.linspace(0, len(test) - 1, spec.max_views).round().astype(int))
        test = [test[i] for i in index]
    if not test:
        raise SceneError(f"scene {spec.name!r}: no test cameras")
    return test


def calibration_views(scene: PreparedScene) -> list[Camera]:
    """The scene's calibration cameras when it names them, else its cameras that are not test views
    (all of them when every camera is a test view)."""
    if scene.spec.calibration is not None:
        return load_cameras(scene.spec.calibration)
    train, test = test_split(load_cameras(scene.cameras), scene.spec.test_every)
    return train or test


def ground_truth(scene: PreparedScene, cameras: list[Camera]) -> list[np.ndarray] | None:
    """The test views' images, resized to the cameras (INTER_AREA); None without an image folder."""
    from gscodec_shac.metrics import load_image

    if scene.images is None:
        return None
    missing = [c.name for c in cameras if c.image_path is None]
    if missing:
        raise SceneError(f"scene {scene.spec.name!r}: no image for test camera(s) {', '.join(missing[:3])} in {scene.images}")
    return [load_image(c.image_path, background=scene.spec.background, size=(c.width, c.height)) for c in cameras]


def render_all(cloud: GaussianCloud, cameras: list[Camera], background: tuple[float, float, float]) -> list[np.ndarray]:
    from gscodec_shac.render import Renderer

    renderer = Renderer(cloud)
    return [renderer.render(c, background=background).image for c in cameras]


def evaluation_views(scene: PreparedScene, out_dir: str | Path, lpips_model: Any = None) -> EvalViews:
    """Test views, ground truth and the cached renders of the uncompressed model."""
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import psnr, ssim

    cameras = test_cameras(scene)
    gt = ground_truth(scene, cameras)
    cache = scene.cache_dir(out_dir)
    renders_path, info_path = cache / "reference.npz", cache / "reference.json"
    with file_lock(cache / "reference.lock"):
        if renders_path.is_file() and info_path.is_file():
            with np.load(renders_path, allow_pickle=False) as data:
                reference = [data[f"view{i}"] for i in range(len(cameras))]
            info = json.loads(info_path.read_text())
        else:
            cloud = read_ply(scene.ply)
            tic = time.perf_counter()
            reference = render_all(cloud, cameras, scene.spec.background)
            info: dict[str, Any] = {"n_gaussians": cloud.num_gaussians, "sh_degree": cloud.sh_degree,
                                    "bytes": scene.ply_bytes, "render_s": time.perf_counter() - tic,
                                    "views": [c.name for c in cameras]}
            if gt is not None:
                info["psnr_gt"] = float(np.mean([psnr(r, g) for r, g in zip(reference, gt)]))
                info["ssim_gt"] = float(np.mean([ssim(r, g) for r, g in zip(reference, gt)]))
            write_npz(renders_path, {f"view{i}": im for i, im in enumerate(reference)}, **DURABLE)
            write_json(info_path, info, **DURABLE)
    if gt is not None and lpips_model is not None and "lpips_gt" not in info:
        info["lpips_gt"] = float(np.mean([lpips_model(r, g) for r, g in zip(reference, gt)]))
    return EvalViews(cameras, gt, reference, info)
