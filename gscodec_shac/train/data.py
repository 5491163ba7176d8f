"""Training data: cameras + ground-truth images + initial points of a real capture.

:func:`load_capture` reads any capture folder :func:`gscodec_shac.io.cameras.load_cameras`
understands (COLMAP ``sparse/0``, Inria ``cameras.json``, NeRF ``transforms_*.json``):

* **Split.** NeRF-synthetic folders keep their official ``transforms_train`` /
  ``transforms_test`` split (as the 3DGS Blender loader); everything else holds out every 8th
  camera in name order (:func:`gscodec_shac.camera.test_split`). Test views are never
  trained on.
* **Images.** From ``--images SUBDIR`` (e.g. ``images_8``), else ``images``, else the
  lowest-factor ``images_N`` folder present (NeRF: the paths in the transforms). Cameras are
  first resized to the real image size (``cameras.json`` stores full-resolution intrinsics),
  then to the training size (``resolution_scale`` or ``width``); images are resampled with
  ``cv2.INTER_AREA`` and RGBA is composited over the background (white for NeRF-synthetic).
* **Initial points.** ``init="sfm"``: the first of ``input.ply``, ``points3D_object.ply``,
  ``points3d.ply``, ``sparse/0/points3D.{bin,txt}`` found; ``init="random"`` (and NeRF without
  points): 100k uniform points in the cube [-1.3, 1.3]^3 for NeRF-synthetic (the reference's
  Blender init), else in a ball of half the camera radius around the camera centroid.
  ``random_points`` adds extra random points for scenes whose SfM points cover only the object
  (bonsai): 60% uniform in a ball of 1.1x the camera radius, 40% in a shell out to 3.3x.
  Random points get the median colour of the training pixels they project to.
* **Extent.** ``1.1 x`` the largest distance of a training camera centre from their mean (the
  reference's ``cameras_extent``); it scales the position learning rate and densification.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from gscodec_shac.camera import Camera, test_split
from gscodec_shac.errors import CameraFormatError, GscodecError
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.common import image_size
from gscodec_shac.io.nerf import read_nerf_transforms

PathLike = str | os.PathLike

SFM_FILES = ("input.ply", "points3D_object.ply", "points3d.ply", "points3D.ply")
NERF_RANDOM_POINTS = 100_000
NERF_CUBE = 1.3


class CaptureError(GscodecError):
    """A capture folder cannot be used for training (no cameras, images or points)."""


@dataclass
class Capture:
    """Everything the trainer reads from a capture (images float32 (H, W, 3) in [0, 1])."""

    name: str
    kind: str  # "nerf", "inria" or "colmap"
    train_cameras: list[Camera]
    test_cameras: list[Camera]
    train_images: list[np.ndarray]
    test_images: list[np.ndarray]
    points: np.ndarray  # (P, 3) float64 initial positions
    colors: np.ndarray  # (P, 3) float64 in [0, 1]
    background: np.ndarray  # (3,)
    extent: float
    info: dict = field(default_factory=dict)

    @property
    def all_cameras(self) -> list[Camera]:
        return sorted(self.train_cameras + self.test_cameras, key=lambda c: c.name)


# --------------------------------------------------------------------------- cameras / images
def _image_dir(root: Path, images: str | None) -> Path | None:
    if images is not None:
        path = root / images
        if not path.is_dir():
            raise CaptureError(f"{path}: no such image folder (--images is relative to the capture folder)")
        return path
    if (root / "images").is_dir():
        return root / "images"
    for factor in (2, 4, 8):
        if (root / f"images_{factor}").is_dir():
            return root / f"images_{factor}"
    return None


def target_size(camera: Camera, resolution_scale: float | None, width: int | None) -> tuple[int, int]:
    """Training size of a camera: scaled by ``resolution_scale`` or resized to ``width`` (aspect kept)."""
    if resolution_scale is not None:
        return max(1, round(camera.width * resolution_scale)), max(1, round(camera.height * resolution_scale))
    if width is not None:
        return width, max(1, round(width * camera.height / camera.width))
    return camera.width, camera.height


def load_cameras_split(root: PathLike, images: str | None = None) -> tuple[str, list[Camera], list[Camera]]:
    """``(kind, train, test)`` cameras at the size of their image files (see the module docstring)."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"{root}: no such capture folder")
    if (root / "transforms_train.json").is_file():
        kind = "nerf"
        train = read_nerf_transforms(root / "transforms_train.json")
        test_file = root / "transforms_test.json"
        test = read_nerf_transforms(test_file) if test_file.is_file() else []
        if not test:
            train, test = test_split(train)
    else:
        image_dir = _image_dir(root, images)
        cameras = load_cameras(root, image_dir)
        kind = "inria" if (root / "cameras.json").is_file() and not (root / "sparse").is_dir() else "colmap"
        train, test = test_split(cameras)
    missing = [c.name for c in train + test if c.image_path is None]
    if missing:
        raise CaptureError(
            f"{root}: {len(missing)} camera(s) have no image (first {missing[0]!r}); pass --images SUBDIR"
        )
    sizes: dict[Path, tuple[int, int]] = {}
    out = []
    for group in (train, test):
        resized = []
        for cam in group:
            folder = cam.image_path.parent
            if folder not in sizes:  # captures have one image size per folder
                try:
                    sizes[folder] = image_size(cam.image_path)
                except CameraFormatError as exc:  # a capture's image: the capture's error
                    raise CaptureError(str(exc)) from None
            w, h = sizes[folder]
            resized.append(cam if (cam.width, cam.height) == (w, h) else cam.resized(w, h))
        out.append(resized)
    return kind, out[0], out[1]


def load_images(
    cameras: Sequence[Camera], background: np.ndarray, *, progress: bool = False, desc: str = "images"
) -> list[np.ndarray]:
    """Ground-truth images at each camera's size (INTER_AREA, RGBA over ``background``)."""
    from tqdm import tqdm

    from gscodec_shac.metrics import load_image

    return [
        load_image(c.image_path, background=tuple(background), size=(c.width, c.height))
        for c in tqdm(cameras, desc=desc, unit="img", disable=not progress, leave=False)
    ]


def camera_extent(cameras: Sequence[Camera]) -> tuple[np.ndarray, float]:
    """``(centroid, radius)``: the reference's ``cameras_extent`` = 1.1 x max distance from the centroid."""
    centers = np.stack([c.center for c in cameras])
    centroid = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - centroid, axis=1).max()) * 1.1
    return centroid, max(radius, 1e-6)


# --------------------------------------------------------------------------- points
def read_point_ply(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz (P, 3), rgb (P, 3) in [0, 1])`` of a point-cloud PLY (grey where it has no colours)."""
    import plyfile

    try:
        vertex = plyfile.PlyData.read(str(path))["vertex"].data
        xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    except Exception as exc:  # plyfile raises many types
        raise CaptureError(f"{path}: not a readable point-cloud PLY ({exc})") from None
    names = vertex.dtype.names
    if all(k in names for k in ("red", "green", "blue")):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.float64)
        rgb = rgb / (255.0 if rgb.max() > 1.0 else 1.0)
    else:
        rgb = np.full_like(xyz, 0.5)
    return xyz, rgb


def read_colmap_points(sparse_dir: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz, rgb in [0, 1])`` from COLMAP ``points3D.bin`` or ``points3D.txt``."""
    sparse_dir = Path(sparse_dir)
    binary, text = sparse_dir / "points3D.bin", sparse_dir / "points3D.txt"
    xyz, rgb = [], []
    if binary.is_file():
        data = binary.read_bytes()
        try:
            (count,) = struct.unpack_from("<Q", data, 0)
            offset = 8
            record = struct.calcsize("<QdddBBBdQ")
            for _ in range(count):
                _, x, y, z, r, g, b, _, track = struct.unpack_from("<QdddBBBdQ", data, offset)
                offset += record + 8 * track
                xyz.append((x, y, z))
                rgb.append((r, g, b))
        except struct.error:
            raise CaptureError(f"{binary}: truncated COLMAP points3D.bin") from None
    elif text.is_file():
        for number, line in enumerate(text.read_text().splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            try:
                xyz.append(tuple(float(v) for v in parts[1:4]))
                rgb.append(tuple(float(v) for v in parts[4:7]))
            except (ValueError, IndexError):
                raise CaptureError(f"{text}: line {number} is not a COLMAP point") from None
    else:
        raise CaptureError(f"{sparse_dir}: no points3D.bin or points3D.txt")
    if not xyz:
        raise CaptureError(f"{sparse_dir}: the COLMAP model has no 3D points")
    return np.asarray(xyz, dtype=np.float64), np.asarray(rgb, dtype=np.float64) / 255.0


def find_sfm_points(root: Path) -> Path | None:
    """The SfM point file of a capture folder (see :data:`SFM_FILES`), or None."""
    for name in SFM_FILES:
        if (root / name).is_file():
            return root / name
    for sparse in (root / "sparse" / "0", root / "sparse", root / "colmap" / "sparse" / "0"):
        if (sparse / "points3D.bin").is_file() or (sparse / "points3D.txt").is_file():
            return sparse
    return None


def project_colors(
    points: np.ndarray, cameras: Sequence[Camera], images: Sequence[np.ndarray], max_views: int = 32
) -> np.ndarray:
    """Median colour of the pixels each point projects to over up to ``max_views`` views (0.5 if none)."""
    n = points.shape[0]
    step = max(1, len(cameras) // max_views)
    samples = []
    for cam, image in list(zip(cameras, images))[::step][:max_views]:
        pc = points @ cam.R.T + cam.t
        z = pc[:, 2]
        ok = z > 0.2
        u = np.full(n, -1, dtype=np.int64)
        v = np.full(n, -1, dtype=np.int64)
        u[ok] = np.floor(cam.fx * pc[ok, 0] / z[ok] + cam.cx).astype(np.int64)
        v[ok] = np.floor(cam.fy * pc[ok, 1] / z[ok] + cam.cy).astype(np.int64)
        ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        col = np.full((n, 3), np.nan)
        col[ok] = image[v[ok], u[ok]]
        samples.append(col)
    if not samples:
        return np.full((n, 3), 0.5)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            median = np.nanmedian(np.stack(samples), axis=0)
    return np.where(np.isfinite(median), median, 0.5)


def random_background_points(n: int, centroid: np.ndarray, radius: float, rng: np.random.Generator) -> np.ndarray:
    """60% uniform in a ball of 1.1 ``radius``, 40% uniform in the shell 1.1-3.3 ``radius``."""
    inner = int(round(0.6 * n))
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = np.empty(n)
    r[:inner] = 1.1 * radius * np.cbrt(rng.random(inner))
    lo, hi = 1.1 * radius, 3.3 * radius
    r[inner:] = np.cbrt(lo**3 + (hi**3 - lo**3) * rng.random(n - inner))
    return centroid + dirs * r[:, None]


# --------------------------------------------------------------------------- capture
def load_capture(
    root: PathLike,
    *,
    images: str | None = None,
    resolution_scale: float | None = None,
    width: int | None = None,
    background: Sequence[float] | None = None,
    init: str = "sfm",
    random_points: int = 0,
    seed: int = 0,
    progress: bool = False,
) -> Capture:
    """Read a capture for training; see the module docstring."""
    root = Path(root)
    if resolution_scale is not None and not (np.isfinite(resolution_scale) and resolution_scale > 0):
        raise CaptureError(f"--resolution-scale must be a positive number, got {resolution_scale}")
    if width is not None and width < 1:
        raise CaptureError(f"--width must be a positive integer, got {width}")
    if init not in ("sfm", "random"):
        raise CaptureError(f"--init must be 'sfm' or 'random', got {init!r}")
    if random_points < 0:
        raise CaptureError(f"--random-points must be >= 0, got {random_points}")
    kind, train, test = load_cameras_split(root, images)
    if not train:
        raise CaptureError(f"{root}: no training cameras")
    train = [c.resized(*target_size(c, resolution_scale, width)) for c in train]
    test = [c.resized(*target_size(c, resolution_scale, width)) for c in test]
    bg = np.asarray(background if background is not None else ((1.0, 1.0, 1.0) if kind == "nerf" else (0.0,) * 3),
                    dtype=np.float64)
    train_images = load_images(train, bg, progress=progress, desc="train images")
    test_images = load_images(test, bg, progress=progress, desc="test images")
    centroid, extent = camera_extent(train)
    rng = np.random.default_rng(seed)
    info: dict = {"root": str(root), "kind": kind}
    source = find_sfm_points(root) if init == "sfm" else None
    if init == "sfm" and source is None and kind != "nerf":
        raise CaptureError(f"{root}: no SfM points found (looked for {', '.join(SFM_FILES)}, sparse/0/points3D.*); "
                           "use --init random")
    if source is not None:
        points, colors = read_colmap_points(source) if source.is_dir() else read_point_ply(source)
        info["init"] = f"sfm:{source.name if source.is_file() else source}"
    elif kind == "nerf":
        points = rng.uniform(-NERF_CUBE, NERF_CUBE, (NERF_RANDOM_POINTS, 3))
        colors = project_colors(points, train, train_images)
        info["init"] = f"random cube +-{NERF_CUBE} ({NERF_RANDOM_POINTS} points)"
    else:
        count = NERF_RANDOM_POINTS
        dirs = rng.normal(size=(count, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        points = centroid + dirs * (0.5 * extent / 1.1 * np.cbrt(rng.random(count)))[:, None]
        colors = project_colors(points, train, train_images)
        info["init"] = f"random ball ({count} points)"
    if random_points:
        extra = random_background_points(random_points, centroid, extent / 1.1, rng)
        points = np.concatenate([points, extra])
        colors = np.concatenate([colors, project_colors(extra, train, train_images)])
        info["random_points"] = random_points
    return Capture(
        name=root.name, kind=kind, train_cameras=train, test_cameras=test, train_images=train_images,
        test_images=test_images, points=points, colors=np.clip(colors, 0.0, 1.0), background=bg, extent=extent,
        info=info,
    )


def synthetic_capture(
    n_gaussians: int = 2_000,
    *,
    n_cameras: int = 24,
    width: int = 64,
    height: int = 48,
    init_points: int | None = None,
    init_noise: float = 0.02,
    seed: int = 0,
    background: Sequence[float] = (0.0, 0.0, 0.0),
) -> Capture:
    """A capture rendered from :func:`gscodec_shac.synthetic.make_synthetic_scene` (tests, benchmarks).

    Ground truth = the CPU renderer's images of the synthetic model from orbit cameras (every 8th
    held out); the initial points are ``init_points`` of its means (default: all) jittered by
    ``init_noise`` scene units, coloured by their true DC colour.
    """
    from gscodec_shac.render import Renderer
    from gscodec_shac.sh import sh_dc_to_rgb
    from gscodec_shac.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(n_gaussians, seed=seed, n_cameras=n_cameras, width=width, height=height)
    renderer = Renderer(scene.cloud)
    bg = np.asarray(background, dtype=np.float64)
    train, test = test_split(scene.cameras)
    render = [np.ascontiguousarray(renderer.render(c, background=bg).image) for c in train + test]
    rng = np.random.default_rng(seed + 1)
    count = n_gaussians if init_points is None else min(init_points, n_gaussians)
    index = np.sort(rng.choice(n_gaussians, count, replace=False))
    points = scene.cloud.means[index].astype(np.float64) + rng.normal(0.0, init_noise, (count, 3))
    colors = np.clip(sh_dc_to_rgb(scene.cloud.sh_dc[index].astype(np.float64)), 0.0, 1.0)
    _, extent = camera_extent(train)
    return Capture(
        name=f"synthetic_{n_gaussians}_{seed}", kind="synthetic", train_cameras=train, test_cameras=test,
        train_images=render[: len(train)], test_images=render[len(train):], points=points, colors=colors,
        background=bg, extent=extent, info={"synthetic": True},
    )
