"""Dynamic (deformable) 3DGS: D-NeRF reader, deformation network, rendering at time t, training."""

from __future__ import annotations

import gscodec_shac.render  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from gscodec_shac.camera import look_at
from gscodec_shac.deform import (
    DeformArch, DeformNetwork, DynamicModel, deform_tensors, is_dynamic_model, load_dynamic_model,
    positional_encoding, save_dynamic_model,
)
from gscodec_shac.errors import CameraFormatError, ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.dnerf import is_dnerf_scene, read_dnerf_frames, read_dnerf_scene
from gscodec_shac.render import Renderer
from gscodec_shac.render.backward import DiffRenderer

SMALL = DeformArch(depth=3, width=16, xyz_freqs=3, t_freqs=2, time_net=True, time_width=8, time_out=4)


def random_net(arch: DeformArch = SMALL, seed: int = 0, scale: float = 0.05) -> DeformNetwork:
    """A network with non-zero heads (a fresh one starts at the identity)."""
    torch.manual_seed(seed)
    net = DeformNetwork(arch)
    with torch.no_grad():
        for head in (net.head_xyz, net.head_rot, net.head_scale):
            head.weight.normal_(0.0, scale)
            head.bias.normal_(0.0, scale)
    return net


def random_cloud(n: int = 40, seed: int = 0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(
        means=rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32),
        scales=np.log(rng.uniform(0.05, 0.2, (n, 3))).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.normal(1.0, 1.0, n).astype(np.float32),
        sh_dc=rng.normal(0.0, 1.0, (n, 3)).astype(np.float32),
        sh_rest=rng.normal(0.0, 0.2, (n, 15, 3)).astype(np.float32),
    )


def camera(width: int = 40, height: int = 32):
    return look_at("cam", (0.3, -3.0, 0.8), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width, height, 40.0)


# --------------------------------------------------------------------------- network
def test_positional_encoding_layout() -> None:
    x = torch.tensor([[0.5, -1.0, 2.0]], dtype=torch.float64)
    code = positional_encoding(x, 2)
    assert code.shape == (1, 3 + 12)
    assert torch.allclose(code[0, :3], x[0])
    assert torch.allclose(code[0, 3:6], torch.sin(x[0]))
    assert torch.allclose(code[0, 6:9], torch.sin(2 * x[0]))
    assert torch.allclose(code[0, 9:12], torch.cos(x[0]))


def test_reference_network_size() -> None:
    """The reference D-NeRF network (D=8, W=256, time net) has about 0.52 M weights."""
    n = DeformNetwork(DeformArch()).n_params
    assert 500_000 < n < 540_000


def test_fresh_network_is_identity() -> None:
    net = DeformNetwork(SMALL)
    cloud = random_cloud()
    moved = DynamicModel(cloud, net).at(0.3)
    np.testing.assert_allclose(moved.means, cloud.means, atol=1e-7)
    np.testing.assert_allclose(np.exp(moved.scales), np.exp(cloud.scales), rtol=1e-5)
    q = cloud.quats / np.linalg.norm(cloud.quats, axis=1, keepdims=True)
    np.testing.assert_allclose(moved.quats, q, atol=1e-6)


def test_deformation_gradients_match_finite_differences() -> None:
    """torch gradcheck (central differences) of the deformed (means, log-scales, quats) w.r.t. the
    canonical log-scales, quaternions and the network's weights, in float64."""
    net = random_net().double()
    rng = np.random.default_rng(3)
    means = torch.tensor(rng.uniform(-1, 1, (5, 3)))
    scales = torch.tensor(np.log(rng.uniform(0.05, 0.3, (5, 3))), requires_grad=True)
    quats = torch.tensor(rng.normal(size=(5, 4)), requires_grad=True)

    def g(s, q, w_head, w_first):
        """deform_tensors with two weight matrices substituted (so gradcheck can vary them)."""
        dx, dq, ds = torch.func.functional_call(net, {"head_xyz.weight": w_head, "layers.0.weight": w_first},
                                                (means, 0.37))
        qn = q / torch.linalg.norm(q, dim=1, keepdim=True)
        return means + dx, torch.log((torch.exp(s) + ds).abs()), qn + dq

    w_head = net.head_xyz.weight.detach().clone().requires_grad_(True)
    w_first = net.layers[0].weight.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(g, (scales, quats, w_head, w_first), eps=1e-6, atol=1e-5)
    assert torch.autograd.gradcheck(lambda s, q: deform_tensors(net, means, s, q, 0.8), (scales, quats),
                                    eps=1e-6, atol=1e-5)


def test_chain_rule_through_rasteriser_matches_finite_differences() -> None:
    """d(sum(W * image))/d(network weight) via the rasteriser backward + autograd equals central differences."""
    net = random_net(seed=1, scale=0.1).double()
    cloud = random_cloud(30, seed=2)
    cam = camera()
    rng = np.random.default_rng(5)
    weights_img = rng.normal(size=(cam.height, cam.width, 3))
    renderer = DiffRenderer()
    t = 0.6

    def render_loss(deformed):
        m, s, q = (np.ascontiguousarray(x.detach().numpy()) for x in deformed)
        state = renderer.forward(m, s, q, cloud.opacities.astype(np.float64), cloud.sh_dc.astype(np.float64),
                                 cloud.sh_rest.astype(np.float64), cam)
        return float(np.sum(weights_img * state.image)), state

    means = torch.tensor(cloud.means, dtype=torch.float64)
    scales = torch.tensor(cloud.scales, dtype=torch.float64)
    quats = torch.tensor(cloud.quats, dtype=torch.float64)
    deformed = deform_tensors(net, means, scales, quats, t)
    _, state = render_loss(deformed)
    grads = renderer.backward(state, weights_img)
    torch.autograd.backward(list(deformed), [torch.from_numpy(a) for a in (grads.means, grads.log_scales,
                                                                           grads.quats)])
    checked = 0
    for param, index in ((net.head_xyz.bias, (0,)), (net.head_xyz.bias, (2,)), (net.head_scale.bias, (1,)),
                         (net.head_rot.bias, (0,)), (net.layers[0].weight, (3, 5)), (net.time_layers[1].bias, (1,))):
        analytic = float(param.grad[index])
        eps = 1e-5
        with torch.no_grad():
            param[index] += eps
            plus, _ = render_loss(deform_tensors(net, means, scales, quats, t))
            param[index] -= 2 * eps
            minus, _ = render_loss(deform_tensors(net, means, scales, quats, t))
            param[index] += eps
        numeric = (plus - minus) / (2 * eps)
        assert analytic == pytest.approx(numeric, rel=2e-3, abs=1e-4 * (1 + abs(numeric)))
        checked += abs(numeric) > 1e-3
    assert checked >= 3  # the check is not vacuous


# --------------------------------------------------------------------------- model directory
def test_model_directory_round_trip(tmp_path: Path) -> None:
    model = DynamicModel(random_cloud(), random_net())
    save_dynamic_model(tmp_path / "m", model)
    assert is_dynamic_model(tmp_path / "m")
    back = load_dynamic_model(tmp_path / "m")
    assert back.arch == SMALL
    for t in (0.0, 0.5, 1.0):
        a, b = model.at(t), back.at(t)
        np.testing.assert_allclose(a.means, b.means, atol=1e-6)
        np.testing.assert_allclose(a.quats, b.quats, atol=1e-6)


def test_model_directory_errors(tmp_path: Path) -> None:
    model = DynamicModel(random_cloud(), random_net())
    save_dynamic_model(tmp_path / "m", model)
    (tmp_path / "m" / "deformation.npz").unlink()
    with pytest.raises(ModelFormatError, match="no deformation.npz"):
        load_dynamic_model(tmp_path / "m")
    save_dynamic_model(tmp_path / "m", model)
    data = json.loads((tmp_path / "m" / "deformation.json").read_text())
    data["arch"]["width"] = 17
    (tmp_path / "m" / "deformation.json").write_text(json.dumps(data))
    with pytest.raises(ModelFormatError, match="shape"):
        load_dynamic_model(tmp_path / "m")
    data["arch"]["bogus"] = 1
    (tmp_path / "m" / "deformation.json").write_text(json.dumps(data))
    with pytest.raises(ModelFormatError, match="unknown key"):
        load_dynamic_model(tmp_path / "m")


# --------------------------------------------------------------------------- rendering at time t
def test_training_render_equals_static_render_of_deformed_gaussians() -> None:
    """The trainer's differentiable render of the deformed arrays equals rendering ``model.at(t)`` as
    an ordinary static model."""
    net = random_net(seed=4, scale=0.1)
    cloud = random_cloud(50, seed=6)
    cam = camera(48, 36)
    for t in (0.1, 0.9):
        m, s, q = deform_tensors(net, torch.from_numpy(cloud.means), torch.from_numpy(cloud.scales),
                                 torch.from_numpy(cloud.quats), t)
        state = DiffRenderer().forward(m.detach().numpy(), s.detach().numpy(), q.detach().numpy(), cloud.opacities,
                                       cloud.sh_dc, cloud.sh_rest, cam)
        static = Renderer(DynamicModel(cloud, net).at(t)).render(cam).image
        np.testing.assert_allclose(state.image, static, atol=1e-5)
    a = Renderer(DynamicModel(cloud, net).at(0.1)).render(cam).image
    b = Renderer(DynamicModel(cloud, net).at(0.9)).render(cam).image
    assert np.abs(a - b).max() > 1e-3  # time matters


# --------------------------------------------------------------------------- reader
def write_scene(root: Path, frames: int = 3, size: tuple[int, int] = (8, 6), *, times: bool = True,
                skip_image: int | None = None, odd_size: int | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for split in ("train", "test"):
        (root / split).mkdir(exist_ok=True)
        entries = []
        for i in range(frames):
            w, h = size if i != odd_size else (size[0] + 2, size[1])
            if i != skip_image:
                rgba = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
                rgba[0, 0, 3] = 0
                cv2.imwrite(str(root / split / f"r_{i:03d}.png"), rgba)
            frame = {"file_path": f"./{split}/r_{i:03d}", "transform_matrix": np.eye(4).tolist()}
            frame["transform_matrix"][2][3] = 4.0
            if times:
                frame["time"] = i / max(1, frames - 1)
            entries.append(frame)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": entries}))
    return root


def test_reader_fixture(tmp_path: Path) -> None:
    root = write_scene(tmp_path / "scene")
    assert is_dnerf_scene(root)
    frames = read_dnerf_frames(root / "transforms_train.json")
    assert [f.time for f in frames] == [0.0, 0.5, 1.0]
    assert (frames[0].camera.width, frames[0].camera.height) == (8, 6)
    half = read_dnerf_scene(root, 0.5)
    assert (half["test"][2].camera.width, half["test"][2].camera.height) == (4, 3)
    assert half["test"][2].time == 1.0


def test_reader_background_composite(tmp_path: Path) -> None:
    from gscodec_shac.train.dynamic import load_dnerf_capture

    root = write_scene(tmp_path / "scene")
    black = load_dnerf_capture(root, resolution_scale=1.0)
    white = load_dnerf_capture(root, resolution_scale=1.0, background=(1.0, 1.0, 1.0))
    assert np.all(black.train_images[0][0, 0] == 0.0)  # alpha 0 pixel
    assert np.all(white.train_images[0][0, 0] == 1.0)
    assert black.train_times == [0.0, 0.5, 1.0]


@pytest.mark.parametrize("case, message", [
    ({"times": False}, "no 'time' key"),
    ({"skip_image": 1}, "absent"),
    ({"odd_size": 2}, "all frames must have one size"),
])
def test_reader_bad_cases(tmp_path: Path, case: dict, message: str) -> None:
    root = write_scene(tmp_path / "bad", **case)
    assert not is_dnerf_scene(root) if case.get("times") is False else True
    with pytest.raises(CameraFormatError, match=message):
        read_dnerf_scene(root)


def test_reader_non_numeric_time(tmp_path: Path) -> None:
    root = write_scene(tmp_path / "scene")
    data = json.loads((root / "transforms_train.json").read_text())
    data["frames"][1]["time"] = "soon"
    (root / "transforms_train.json").write_text(json.dumps(data))
    with pytest.raises(CameraFormatError, match="finite number"):
        read_dnerf_frames(root / "transforms_train.json")
