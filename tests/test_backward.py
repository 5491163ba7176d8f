"""The CPU backward pass against torch autograd of a dense reference and finite differences."""

from __future__ import annotations

import gscodec_shac.render  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import numba
import numpy as np
import pytest
import torch

from gscodec_shac.camera import Camera, look_at
from gscodec_shac.geometry import covariances
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.render import render
from gscodec_shac.render.backward import DiffRenderer, covariances_upper, sigmoid
from gscodec_shac.render.projection import camera_limits
from gscodec_shac.render.torch_reference import render_torch
from gscodec_shac.sh import sh_basis

GROUPS = ("means", "log_scales", "quats", "logits", "sh_dc", "sh_rest")
BACKGROUND = (0.2, 0.3, 0.4)


def random_params(seed: int, n: int = 30, degree: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {
        "means": rng.uniform(-1.0, 1.0, (n, 3)),
        "log_scales": np.log(rng.uniform(0.04, 0.35, (n, 3))),
        "quats": rng.normal(size=(n, 4)),
        "logits": rng.normal(0.5, 2.5, n),
        "sh_dc": rng.normal(0.0, 1.0, (n, 3)),
        "sh_rest": rng.normal(0.0, 0.3, (n, k, 3)),
    }


def with_off_frustum(params: dict[str, np.ndarray], camera: Camera) -> dict[str, np.ndarray]:
    """Append 3 large Gaussians just outside the frustum (x/z or y/z beyond the Jacobian clamp)
    whose footprints still reach the image, so that the clamped branch is exercised."""
    lx_neg, lx_pos, ly_neg, ly_pos = camera_limits(camera)
    z = np.array([0.9, 1.0, 1.1])  # distinct depths: equal ones would swap order under perturbation
    cam_points = np.array([[1.15 * lx_pos * z[0], 0.1, z[0]], [-1.15 * lx_neg * z[1], -0.1, z[1]],
                           [0.0, 1.15 * ly_pos * z[2], z[2]]])
    world = (cam_points - camera.t) @ camera.R  # R^T (x - t), row-wise
    rng = np.random.default_rng(11)
    k = params["sh_rest"].shape[1]
    extra = {
        "means": world, "log_scales": np.log(np.full((3, 3), 0.45)), "quats": rng.normal(size=(3, 4)),
        "logits": np.full(3, 1.0), "sh_dc": rng.normal(0.0, 1.0, (3, 3)), "sh_rest": rng.normal(0.0, 0.3, (3, k, 3)),
    }
    return {g: np.concatenate([params[g], extra[g]]) for g in GROUPS}


def clamped_visible(params: dict[str, np.ndarray], camera: Camera, visible: np.ndarray) -> int:
    pc = params["means"] @ camera.R.T + camera.t
    lx_neg, lx_pos, ly_neg, ly_pos = camera_limits(camera)
    rx, ry = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    clamped = (rx > lx_pos) | (rx < -lx_neg) | (ry > ly_pos) | (ry < -ly_neg)
    return int(np.count_nonzero(clamped & visible))


def off_centre(name: str, eye, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> Camera:
    base = look_at(name, eye, np.zeros(3), np.array([0.0, 0.0, 1.0]), width, height, fx)
    return Camera(name, width, height, fx, fy, cx, cy, base.R, base.t)


CAMERAS = {
    "centred": look_at("centred", np.array([0.3, -3.5, 0.8]), np.zeros(3), np.array([0.0, 0.0, 1.0]), 40, 34, 40.0),
    "off_centre": off_centre("off_centre", np.array([2.8, 1.5, 1.2]), 37, 29, 30.0, 34.0, 11.3, 19.7),
    "wide_close": off_centre("wide_close", np.array([-1.2, -1.6, 0.4]), 33, 40, 14.0, 15.5, 20.0, 22.5),
}


def numba_grads(params: dict[str, np.ndarray], camera: Camera, weights: np.ndarray):
    renderer = DiffRenderer()
    state = renderer.forward(*(params[g] for g in GROUPS), camera, BACKGROUND)
    return state, renderer.backward(state, weights)


def torch_grads(params: dict[str, np.ndarray], camera: Camera, weights: np.ndarray):
    tensors = {k: torch.tensor(v, requires_grad=True) for k, v in params.items()}
    extra: dict[str, torch.Tensor] = {}
    image = render_torch(*(tensors[g] for g in GROUPS), camera, BACKGROUND, intermediates=extra)
    (image * torch.as_tensor(weights)).sum().backward()
    return image.detach().numpy(), {k: t.grad.numpy() for k, t in tensors.items()}, extra["means2d"].grad.numpy()


@pytest.mark.parametrize("camera", list(CAMERAS))
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_gradients_match_torch_autograd(camera: str, degree: int) -> None:
    cam = CAMERAS[camera]
    params = with_off_frustum(random_params(7 + degree, degree=degree), cam)
    weights = np.random.default_rng(1).normal(size=(cam.height, cam.width, 3))
    state, grads = numba_grads(params, cam, weights)
    image, reference, means2d_grad = torch_grads(params, cam, weights)
    assert np.abs(state.image - image).max() < 1e-10
    assert clamped_visible(params, cam, state.visible) >= 1
    for group, attr in zip(GROUPS, ("means", "log_scales", "quats", "logits", "sh_dc", "sh_rest")):
        ours = getattr(grads, attr)
        scale = max(np.abs(reference[group]).max(initial=0.0), 1e-12)
        assert ours.shape == reference[group].shape
        assert np.abs(ours - reference[group]).max(initial=0.0) <= 1e-9 * scale, group
        assert np.abs(reference[group]).max(initial=0.0) > 0.0 or ours.size == 0, f"{group}: no gradient to compare"
    # densification statistic: |dL/d(mean2d)| in NDC units (pixel gradient x W/2, H/2)
    ndc = np.hypot(means2d_grad[:, 0] * cam.width / 2, means2d_grad[:, 1] * cam.height / 2)
    assert np.allclose(grads.means2d_ndc_norm, ndc, rtol=1e-9, atol=1e-12)


def test_the_scenes_exercise_every_clamp() -> None:
    """The random scenes above hit the alpha cap, the colour clamp and the Jacobian clamp."""
    cam = CAMERAS["wide_close"]
    params = with_off_frustum(random_params(10), cam)
    opacity = sigmoid(params["logits"])
    assert np.count_nonzero(opacity > 0.99) >= 2
    renderer = DiffRenderer()
    state = renderer.forward(*(params[g] for g in GROUPS), cam, BACKGROUND)
    assert clamped_visible(params, cam, state.visible) >= 1
    # some contributions are capped at alpha = 0.99: G = o exp(power) > 0.99 at a pixel
    _, screen = renderer.screen_gradients(state, np.ones((cam.height, cam.width, 3)))
    assert screen.shape[1] == 9
    assert state.last.max() >= 3
    dirs = params["means"] - cam.center
    raw = np.einsum("nk,nkc->nc", sh_basis(dirs, 3), np.concatenate([params["sh_dc"][:, None], params["sh_rest"]], 1))
    assert np.count_nonzero((raw + 0.5 < 0) & state.visible[:, None]) >= 3


@pytest.mark.parametrize("camera", ["centred", "wide_close"])
def test_gradients_match_finite_differences(camera: str) -> None:
    cam = CAMERAS[camera]
    params = with_off_frustum(random_params(3), cam)
    weights = np.random.default_rng(2).normal(size=(cam.height, cam.width, 3))
    renderer = DiffRenderer()

    def loss(p: dict[str, np.ndarray]) -> float:
        return float((renderer.forward(*(p[g] for g in GROUPS), cam, BACKGROUND).image * weights).sum())

    state = renderer.forward(*(params[g] for g in GROUPS), cam, BACKGROUND)
    grads = renderer.backward(state, weights)
    rng = np.random.default_rng(5)
    eps = 1e-6
    for group, attr in zip(GROUPS, ("means", "log_scales", "quats", "logits", "sh_dc", "sh_rest")):
        analytic = getattr(grads, attr)
        flat = np.argsort(-np.abs(analytic).ravel())[:12]
        for index in rng.choice(flat, 4, replace=False):
            where = np.unravel_index(index, analytic.shape)
            plus = {k: v.copy() for k, v in params.items()}
            minus = {k: v.copy() for k, v in params.items()}
            plus[group][where] += eps
            minus[group][where] -= eps
            numeric = (loss(plus) - loss(minus)) / (2 * eps)
            assert abs(numeric - analytic[where]) <= 1e-5 * max(1.0, abs(analytic[where])), (group, where)


def test_forward_equals_the_renderer() -> None:
    params = random_params(4)
    cloud = GaussianCloud(means=params["means"], scales=params["log_scales"], quats=params["quats"],
                          opacities=params["logits"], sh_dc=params["sh_dc"], sh_rest=params["sh_rest"])
    f32 = {g: getattr(cloud, a) for g, a in zip(GROUPS, ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"))}
    for cam in CAMERAS.values():
        state = DiffRenderer().forward(*(f32[g] for g in GROUPS), cam, BACKGROUND)
        expected = render(cloud, cam, background=BACKGROUND).image
        assert np.abs(state.image - expected).max() < 1e-5


def test_covariances_match_geometry() -> None:
    params = random_params(6, n=50)
    full = covariances(params["log_scales"], params["quats"])
    upper = covariances_upper(params["log_scales"], params["quats"])
    rows, cols = np.triu_indices(3)
    assert np.allclose(upper, full[:, rows, cols], rtol=1e-12, atol=1e-15)


def test_backward_is_deterministic_across_thread_counts() -> None:
    params = random_params(8, n=200)
    cam = CAMERAS["centred"]
    weights = np.random.default_rng(3).normal(size=(cam.height, cam.width, 3))
    _, first = numba_grads(params, cam, weights)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        _, single = numba_grads(params, cam, weights)
    finally:
        numba.set_num_threads(previous)
    for attr in ("means", "log_scales", "quats", "logits", "sh_dc", "sh_rest", "means2d_ndc_norm"):
        assert np.array_equal(getattr(first, attr), getattr(single, attr)), attr


def test_invisible_gaussians_get_zero_gradients() -> None:
    params = random_params(9, n=10)
    params["means"][0] = (0.3, -6.0, 0.8)  # behind the "centred" camera (at y = -3.5, looking along +y)
    cam = CAMERAS["centred"]
    state, grads = numba_grads(params, cam, np.ones((cam.height, cam.width, 3)))
    assert not state.visible[0]
    for attr in ("means", "log_scales", "quats", "logits", "sh_dc", "sh_rest"):
        assert not np.any(getattr(grads, attr)[0])
