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


# --------------------------------------------------------------------------- training
def moving_capture(n: int = 60, frames: int = 8, size: tuple[int, int] = (32, 24)):
    """A tiny scene whose Gaussians slide along x with time, seen by a few cameras."""
    from gscodec_shac.train.dynamic import DynamicCapture

    cloud = random_cloud(n, seed=8)
    cams, times, images = [], [], []
    for i in range(frames):
        t = (i + 1) / frames  # no frame shows the canonical state exactly
        angle = 2 * np.pi * i / frames
        eye = (3.0 * np.cos(angle), 3.0 * np.sin(angle), 0.8)
        cam = look_at(f"f{i}", eye, (0, 0, 0), (0, 0, 1), size[0], size[1], 30.0)
        moved = GaussianCloud(means=cloud.means + np.float32([0.3 * t, 0.0, 0.0]), scales=cloud.scales,
                              quats=cloud.quats, opacities=cloud.opacities, sh_dc=cloud.sh_dc, sh_rest=cloud.sh_rest)
        cams.append(cam)
        times.append(t)
        images.append(np.clip(Renderer(moved).render(cam).image, 0, 1).astype(np.float32))
    capture = DynamicCapture("moving", cams, times, images, cams, times, images, np.zeros(3), 3.3)
    return capture, cloud


def test_training_steps_reduce_the_loss(tmp_path: Path) -> None:
    from gscodec_shac.train.dynamic import DynamicConfig, DynamicTrainer, evaluate_dynamic
    from gscodec_shac.train.model import GaussianModel

    capture, cloud = moving_capture()
    model = GaussianModel({"means": cloud.means, "scales": cloud.scales, "quats": cloud.quats,
                           "opacities": cloud.opacities, "sh_dc": cloud.sh_dc, "sh_rest": cloud.sh_rest}, 3)
    config = DynamicConfig(iterations=60, warm_up=0, depth=2, width=32, densify_until=0, sh_interval=1000,
                           lr_deform=3e-3, checkpoint_every=1000)
    trainer = DynamicTrainer(capture, config, model=model)
    trainer.active_degree = 3  # the canonical Gaussians come trained: render their full SH from the start
    before = evaluate_dynamic(trainer.dynamic_model()[0], capture)["mean_psnr"]
    losses = [trainer.step().loss for _ in range(60)]
    after = evaluate_dynamic(trainer.dynamic_model()[0], capture)["mean_psnr"]
    assert np.mean(losses[-10:]) < np.mean(losses[:10])
    assert after > before + 1.0
    # checkpoint + resume gives the same state
    trainer.save_checkpoint(tmp_path)
    again = DynamicTrainer.from_checkpoint(capture, tmp_path)
    assert again.iteration == 60
    for a, b in zip(again.net.parameters(), trainer.net.parameters()):
        assert torch.equal(a, b)


# --------------------------------------------------------------------------- .gsc round trip + commands
def test_weight_shapes_match_the_network() -> None:
    from gscodec_shac.deform_arch import weight_count, weight_shapes

    for arch in (SMALL, DeformArch(depth=4, width=32), DeformArch(depth=2, width=8, time_net=False)):
        net = DeformNetwork(arch)
        assert [(k, tuple(v.shape)) for k, v in net.state_dict().items()] == weight_shapes(arch)
        assert weight_count(arch) == net.n_params


@pytest.fixture()
def dynamic_dir(tmp_path: Path) -> Path:
    from gscodec_shac.synthetic import make_synthetic_scene

    cloud = make_synthetic_scene(800, seed=3, n_cameras=2, width=32, height=24).cloud
    return save_dynamic_model(tmp_path / "model", DynamicModel(cloud, random_net(DeformArch(depth=4, width=32))))


@pytest.mark.parametrize("bits", [16, 8, 5, 4])
def test_gsc_round_trip_of_a_dynamic_model(tmp_path: Path, dynamic_dir: Path, bits: int) -> None:
    from gscodec_shac.codec import decode_file, encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.deformation import matrix_bits
    from gscodec_shac.codec.header import read_header

    summary = encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png", network_bits=bits)
    static = encode_file(dynamic_dir / "point_cloud.ply", tmp_path / "s.gsc", "gsplat_png")
    stream = Bitstream.read(tmp_path / "d.gsc")
    quantised, mixed = bits < 16, bits < 8
    assert stream.version == ((2, 2) if mixed else (2, 1) if quantised else (2, 0))
    assert stream.features == ({"deformation"} | ({"deformation_quantised"} if quantised else set())
                               | ({"deformation_mixed_bits"} if mixed else set()))
    view = read_header(stream)
    assert view.deformation is not None and view.deformation.arch == DeformArch(depth=4, width=32)
    # below 8 bits the time net's first layer and the three heads (the last three matrices) keep 8,
    # the matrix after the skip (layers.3 at depth 4) gets one bit more
    per_matrix = (8,) + (bits,) * 4 + (bits + 1,) + (8,) * 3 if mixed else bits  # 2 time, 4 hidden, 3 heads
    assert (view.deformation.dtype, view.deformation.bits) == (("uint8", per_matrix) if quantised else ("float16", 16))
    net_bytes = view.chunk_bytes["deformation"]
    assert 0 < net_bytes <= 2 * view.deformation.weights + 64
    # the network counts in the rate: the rest is the static stream (its header deflated in format 2.x)
    assert summary["bytes"] == (tmp_path / "d.gsc").stat().st_size
    assert 0.9 * static["bytes"] < summary["bytes"] - net_bytes <= static["bytes"]
    out = decode_file(tmp_path / "d.gsc", tmp_path / "decoded")
    assert out["dynamic"] and is_dynamic_model(tmp_path / "decoded")
    decode_file(tmp_path / "s.gsc", tmp_path / "static.ply")
    back = load_dynamic_model(tmp_path / "decoded")
    original = load_dynamic_model(dynamic_dir)
    from gscodec_shac.io.ply import read_ply

    static_cloud = read_ply(tmp_path / "static.ply")  # canonical Gaussians exactly as a static stream gives them
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(back.cloud, name), getattr(static_cloud, name))
    for key, value in original.net.weights().items():
        got = back.net.weights()[key]
        if not quantised:
            np.testing.assert_array_equal(got, value.astype(np.float16).astype(np.float32))
            continue
        if value.ndim == 1:  # float16; the fitted rounding moved each bias by its matrix's mean output shift
            assert np.array_equal(got, got.astype(np.float16).astype(np.float32))
            continue
        # per row on a grid of 2^b values spanning the row's range (+ float16 rounding of lo and step); the
        # fitted rounding may pick a farther grid value than the nearest, within the range
        b = dict(zip([k for k, v in original.net.weights().items() if v.ndim == 2],
                     matrix_bits(view.deformation.arch, view.deformation.bits)))[key]
        lo, hi = value.min(axis=1, keepdims=True), value.max(axis=1, keepdims=True)
        step, half = (hi - lo) / (2 ** b - 1), 1e-3 * np.abs(value).max()  # half: float16 rounding of lo, step
        assert np.all((got >= lo - half) & (got <= hi + 1.01 * step + half)), key
        assert np.abs(got - value).mean() <= np.mean(step), key
        assert all(len(np.unique(row)) <= 2 ** b for row in got)


def test_quantised_network_is_smaller_and_its_errors_are_bounded(dynamic_dir: Path) -> None:
    """The coded chunk shrinks with the bits, and the decoded weights' worst error grows as the step."""
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.deformation import add_deformation, decode_weights, raw_size
    import zlib

    model = load_dynamic_model(dynamic_dir)
    weights = model.net.weights()
    sizes, errors = {}, {}
    for bits in (16, 8, 6, 4):
        stream = Bitstream()
        sizes[bits] = add_deformation(stream, model.arch, weights, bits)
        raw = zlib.decompress(stream.chunk("deformation").data)
        dtype = stream.header["deformation"]["dtype"]
        assert len(raw) == raw_size(model.arch, dtype, bits)
        back = decode_weights(raw, model.arch, dtype, bits)
        errors[bits] = max(float(np.abs(back[k] - v).max()) for k, v in weights.items() if v.ndim == 2)
        for key, value in weights.items():  # plain rounding (no centres given): within half a step per row
            if value.ndim == 2 and bits < 16:
                span = value.max(axis=1, keepdims=True) - value.min(axis=1, keepdims=True)
                bound = 0.5 * span / (2 ** bits - 1) * 1.01 + 1e-3 * np.abs(value).max()
                assert np.all(np.abs(back[key] - value) <= bound), key
    assert sizes[16] > sizes[8] > sizes[6] > sizes[4]
    assert errors[16] < errors[8] < errors[6] < errors[4]
    from gscodec_shac.codec.deformation import encoder_bits  # what encode writes: fitted, heads at 8 below 8

    fitted = [add_deformation(Bitstream(), model.arch, weights, encoder_bits(model.arch, b), means=model.cloud.means)
              for b in (8, 4, 3)]
    assert sizes[16] > fitted[0] > fitted[1] > fitted[2] and fitted[1] < sizes[16] / 2.5


@pytest.mark.parametrize("bits", [4, 3])
def test_fitted_rounding_keeps_the_deformation_closer_than_plain_rounding(dynamic_dir: Path, bits: int) -> None:
    """Quantisation-aware rounding (the encoder has the centres) deforms the model's own Gaussians closer
    to the float network than rounding each weight to its nearest grid value, and decodes as the same form."""
    import zlib

    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.deformation import add_deformation, decode_weights

    model = load_dynamic_model(dynamic_dir)
    x = torch.from_numpy(model.cloud.means.astype(np.float32))
    with torch.no_grad():
        want = [torch.cat(model.net(x, t), 1) for t in (0.1, 0.45, 0.9)]
    errors = {}
    for fit in (False, True):
        stream = Bitstream()
        add_deformation(stream, model.arch, model.net.weights(), bits, means=model.cloud.means if fit else None)
        entry = stream.header["deformation"]
        net = DeformNetwork(model.arch)
        net.load_weights(decode_weights(zlib.decompress(stream.chunk("deformation").data), model.arch,
                                        entry["dtype"], entry["bits"]))
        with torch.no_grad():
            errors[fit] = float(sum(((torch.cat(net(x, t), 1) - w) ** 2).mean() for t, w in zip((0.1, 0.45, 0.9), want)))
    assert errors[True] < 0.8 * errors[False]


def test_old_decoder_refuses_a_dynamic_stream(tmp_path: Path, dynamic_dir: Path, monkeypatch) -> None:
    """A decoder whose container knows no 'deformation' feature (the release before this one) refuses it."""
    from gscodec_shac.codec import container, encode_file
    from gscodec_shac.errors import BitstreamError

    encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png")
    monkeypatch.delitem(container.FEATURES, "deformation")
    with pytest.raises(BitstreamError, match="needs deformation.*update gscodec-shac"):
        container.Bitstream.read(tmp_path / "d.gsc")


def test_a_2_0_decoder_refuses_a_quantised_network(tmp_path: Path, dynamic_dir: Path, monkeypatch) -> None:
    """The release that wrote float16 networks (format 2.0) knows 'deformation' but not the quantised form."""
    from gscodec_shac.codec import container, encode_file
    from gscodec_shac.errors import BitstreamError

    encode_file(dynamic_dir, tmp_path / "q.gsc", "gsplat_png", network_bits=8)
    encode_file(dynamic_dir, tmp_path / "f.gsc", "gsplat_png", network_bits=16)
    monkeypatch.delitem(container.FEATURES, "deformation_quantised")
    with pytest.raises(BitstreamError, match="needs deformation_quantised, which this version"):
        container.Bitstream.read(tmp_path / "q.gsc")
    assert container.Bitstream.read(tmp_path / "f.gsc").version == (2, 0)


def test_a_2_1_decoder_refuses_mixed_network_bits(tmp_path: Path, dynamic_dir: Path, monkeypatch, capsys) -> None:
    """The release that wrote uniform quantised networks (format 2.1) does not know per-matrix bits."""
    from gscodec_shac.codec import container, encode_file
    from gscodec_shac.errors import BitstreamError

    from gscodec_shac.cli import main

    encode_file(dynamic_dir, tmp_path / "m.gsc", "gsplat_png", network_bits=4)
    encode_file(dynamic_dir, tmp_path / "u.gsc", "gsplat_png", network_bits=8)
    assert main(["info", str(tmp_path / "m.gsc")]) == 0
    assert "per-row quantised, bits per matrix 8,4,4,4,4,5,8,8,8)" in capsys.readouterr().out
    monkeypatch.delitem(container.FEATURES, "deformation_mixed_bits")
    with pytest.raises(BitstreamError, match="needs deformation_mixed_bits, which this version"):
        container.Bitstream.read(tmp_path / "m.gsc")
    assert container.Bitstream.read(tmp_path / "u.gsc").version == (2, 1)


def _corrupt(stream, edit) -> None:
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import read_header

    copy = Bitstream.from_bytes(stream.to_bytes())
    edit(copy)
    copy = Bitstream.from_bytes(copy.to_bytes())
    read_header(copy)


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.header["deformation"]["arch"].update(width=4096), "too large"),
    (lambda s: s.header["deformation"]["arch"].update(depth="8"), "positive integer"),
    (lambda s: s.header["deformation"].update(dtype="float64"), "deformation.dtype"),
    (lambda s: s.header["deformation"].update(dtype="uint8" if "bits" not in s.header["deformation"] else "float16"),
     "deformation.dtype.*come together"),
    (lambda s: s.header.pop("deformation"), "come together"),
    (lambda s: s.features.discard("deformation") or s.header.pop("deformation"), "belongs to no attribute"),
    (lambda s: s.chunk("deformation").meta.update(raw_size=10), "raw_size"),
    (lambda s: s.header["deformation"]["arch"].update(width=33), "raw_size"),
])
@pytest.mark.parametrize("bits", [16, 8, 4])
def test_header_validates_the_deformation_chunk(tmp_path: Path, dynamic_dir: Path, edit, message: str,
                                                bits: int) -> None:
    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.errors import BitstreamError

    encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png", network_bits=bits)
    if bits < 16 and message == "belongs to no attribute":
        message = "'deformation_quantised' feature needs a deformation entry"
    stream = Bitstream.read(tmp_path / "d.gsc")
    with pytest.raises(BitstreamError, match=message):
        _corrupt(stream, edit)


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.header["deformation"].update(bits=s.header["deformation"]["bits"][:-1]), "8 values for the .* 9"),
    (lambda s: s.header["deformation"].update(bits=s.header["deformation"]["bits"][:-1] + [9]), "in 2..8"),
    (lambda s: s.header["deformation"].update(bits=s.header["deformation"]["bits"][:-1] + ["8"]), "in 2..8"),
    (lambda s: s.header["deformation"].update(bits=4), "list of bits and the 'deformation_mixed_bits'"),
    (lambda s: s.features.discard("deformation_mixed_bits"), "list of bits and the 'deformation_mixed_bits'"),
    (lambda s: s.header["deformation"].update(bits=[4] * 6 + [2] * 3), "raw_size"),
    (lambda s: s.header["deformation"].update(dtype="float16") or s.features.discard("deformation_quantised"),
     "'deformation_mixed_bits' feature needs the quantised form"),
])
def test_header_validates_mixed_network_bits(tmp_path: Path, dynamic_dir: Path, edit, message: str) -> None:
    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.errors import BitstreamError

    encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png", network_bits=4)
    with pytest.raises(BitstreamError, match=message):
        _corrupt(Bitstream.read(tmp_path / "d.gsc"), edit)


def test_a_truncated_network_chunk_is_refused(tmp_path: Path, dynamic_dir: Path) -> None:
    """A network chunk cut short or with flipped bytes: one clear error, from the library and the CLI."""
    from gscodec_shac.cli import main
    from gscodec_shac.codec import decode_file, encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.errors import BitstreamError

    encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png", network_bits=4)
    for name, cut in (("short", lambda d: d[: len(d) // 2]), ("flipped", lambda d: d[:10] + bytes(b ^ 0x5A for b in d[10:]))):
        stream = Bitstream.read(tmp_path / "d.gsc")
        chunk = stream.chunk("deformation")
        chunk.data = cut(chunk.data)
        stream.write(tmp_path / f"{name}.gsc")
        with pytest.raises(BitstreamError, match="corrupt .gsc file.*deformation"):
            decode_file(tmp_path / f"{name}.gsc", tmp_path / f"{name}_out")
        assert not (tmp_path / f"{name}_out").exists()
        assert main(["decode", str(tmp_path / f"{name}.gsc"), str(tmp_path / f"{name}_cli")]) != 0
    data = (tmp_path / "d.gsc").read_bytes()
    (tmp_path / "cut.gsc").write_bytes(data[: len(data) - 40])  # the file itself cut: the container refuses it
    with pytest.raises(BitstreamError):
        decode_file(tmp_path / "cut.gsc", tmp_path / "cut_out")


def test_commands_accept_a_model_directory(tmp_path: Path, dynamic_dir: Path, capsys) -> None:
    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import write_ply

    assert main(["info", str(dynamic_dir)]) == 0
    assert "deformation       MLP 4x32" in capsys.readouterr().out
    assert main(["encode", str(dynamic_dir), str(tmp_path / "d.gsc"), "-r", "gsplat_png", "-q"]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "d.gsc"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["deformation"]["weights"] == DeformNetwork(DeformArch(depth=4, width=32)).n_params
    assert info["attributes"]["deformation"]["bytes"] == info["deformation"]["bytes"] > 0
    assert main(["decode", str(tmp_path / "d.gsc"), str(tmp_path / "bad.ply")]) != 0
    assert "decode it to a directory" in capsys.readouterr().err
    assert main(["decode", str(tmp_path / "d.gsc"), str(tmp_path / "dec"), "-q"]) == 0
    assert is_dynamic_model(tmp_path / "dec")
    # render at time t == render of the deformed Gaussians as a static model
    model = load_dynamic_model(tmp_path / "dec")
    write_ply(tmp_path / "at.ply", model.at(0.25))
    common = ["--orbit-views", "2", "--width", "40", "-q"]
    assert main(["render", str(tmp_path / "dec"), str(tmp_path / "r_dyn"), "--time", "0.25", *common]) == 0
    assert main(["render", str(tmp_path / "at.ply"), str(tmp_path / "r_static"), *common]) == 0
    for name in sorted(p.name for p in (tmp_path / "r_static").glob("*.png")):
        a = cv2.imread(str(tmp_path / "r_dyn" / name))
        b = cv2.imread(str(tmp_path / "r_static" / name))
        assert a is not None and np.abs(a.astype(int) - b.astype(int)).max() <= 1
    assert main(["render", str(tmp_path / "dec"), str(tmp_path / "r_none"), *common]) != 0
    assert "needs --time" in capsys.readouterr().err


def test_render_uses_each_frames_time(tmp_path: Path, dynamic_dir: Path) -> None:
    """Without --time, each D-NeRF frame is rendered at its own time."""
    from gscodec_shac.cli import main

    root = write_scene(tmp_path / "scene", frames=2, size=(16, 12))
    assert main(["render", str(dynamic_dir), str(tmp_path / "r"), "--cameras",
                 str(root / "transforms_test.json"), "-q"]) == 0
    rows = json.loads((tmp_path / "r" / "metrics.json").read_text())["views"]
    assert [r["time"] for r in rows] == [0.0, 1.0]


def test_damaged_dynamic_streams_are_clean_errors(tmp_path: Path, dynamic_dir: Path) -> None:
    """Seeded mutations of a dynamic stream (every fuzz family) through the whole dynamic decode:
    each is a valid decode or one GscodecError, never a crash."""
    from tests.fuzzlib import gsc as fuzz
    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.decoder import Decoder
    from gscodec_shac.codec.header import read_deformation, read_header
    from gscodec_shac.errors import GscodecError

    encode_file(dynamic_dir, tmp_path / "d.gsc", "gsplat_png")
    data = (tmp_path / "d.gsc").read_bytes()

    def decode(blob: bytes) -> None:
        stream = Bitstream.from_bytes(blob)
        view = read_header(stream)
        Decoder(workers=1).decode(stream)
        if view.deformation is not None:
            DeformNetwork(view.deformation.arch).load_weights(read_deformation(stream, view))

    kinds = {"valid": 0, "error": 0}
    for family in fuzz.FAMILIES:
        for index in range(40):
            case = data[: index * len(data) // 40] if family == "truncate" else fuzz.make_case(family, data, 0, index)
            try:
                decode(case)
                kinds["valid"] += 1
            except GscodecError:
                kinds["error"] += 1
    assert kinds["error"] > 0
    decode(data)


def test_network_bits_need_a_dynamic_model(tmp_path: Path, dynamic_dir: Path, capsys) -> None:
    from gscodec_shac.cli import main

    assert main(["encode", str(dynamic_dir / "point_cloud.ply"), str(tmp_path / "s.gsc"), "-r", "gsplat_png",
                 "--network-bits", "8", "-q"]) == 2
    assert "network bits apply to a dynamic model" in capsys.readouterr().err
    assert not (tmp_path / "s.gsc").exists()


@pytest.mark.parametrize("value", [0.0, -1e-5, 1e-3])
def test_a_deformation_learning_rate_floor_outside_its_range_is_refused(value: float) -> None:
    """``train-dynamic --deform-lr-final``: positive and at most the starting rate (8e-4), else one error naming it."""
    from gscodec_shac.train.dynamic import DynamicConfig, DynamicTrainError

    with pytest.raises(DynamicTrainError, match="--deform-lr-final"):
        DynamicConfig(lr_deform_final=value).validate()


def test_the_command_line_sets_the_deformation_learning_rate_floor() -> None:
    """``--deform-lr-final`` parses to the value ``train-dynamic`` hands to ``DynamicConfig.lr_deform_final``, the
    rate the network's learning rate decays to (docs/dynamic.md: a 1,500-iteration jumpingjacks run learned the
    motion better with a floor of 8e-5); the default is the reference's 1.6e-6."""
    from gscodec_shac.cli import build_parser

    args = build_parser().parse_args(["train-dynamic", "scene", "out", "--deform-lr-final", "8e-5"])
    assert args.deform_lr_final == 8e-5
    assert build_parser().parse_args(["train-dynamic", "scene", "out"]).deform_lr_final == 1.6e-6


def test_a_bad_training_setting_is_one_error_before_anything_is_read_or_made(tmp_path: Path, capsys) -> None:
    """``train-dynamic`` refuses a setting its config rejects before it reads the scene or creates OUT_DIR:
    one ``error:`` line, the usage status, no folder left behind."""
    from gscodec_shac.cli import main

    out = tmp_path / "run"
    for bad in (["--deform-lr-final", "0"], ["--iterations", "0"], ["--network-bits", "9"]):
        assert main(["train-dynamic", str(tmp_path / "no-scene"), str(out), "-q", *bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and bad[0] in err and "Traceback" not in err and not out.exists()


# --------------------------------------------------------------------------- quantisation-aware training
def test_fake_quantised_rows_are_the_coded_grid_with_a_straight_through_gradient() -> None:
    """Training's grid is ``encode --network-bits``' per-row grid (``lo`` = row minimum, ``step`` = range / (2^B - 1),
    nearest point), and its gradient is the identity (straight-through)."""
    from gscodec_shac.deform import fake_quantised_rows

    w = torch.from_numpy(np.random.default_rng(3).normal(size=(6, 40))).requires_grad_(True)
    q = fake_quantised_rows(w, 4)
    values = w.detach().numpy()
    lo, hi = values.min(axis=1, keepdims=True), values.max(axis=1, keepdims=True)
    step = (hi - lo) / 15
    expected = lo + np.rint((values - lo) / step) * step
    np.testing.assert_allclose(q.detach().numpy(), expected, rtol=0, atol=1e-12)
    assert all(len(np.unique(row)) <= 16 for row in q.detach().numpy())
    q.sum().backward()
    np.testing.assert_array_equal(w.grad.numpy(), np.ones_like(values))


def test_quantisation_aware_training_saves_a_network_its_coding_keeps(tmp_path: Path) -> None:
    """``network_bits``: only the last ``network_grid_fraction`` of the iterations train through the grid; the saved
    network is on it, so coding it at those bits changes it by far less than coding the float network does."""
    from gscodec_shac.codec import deformation as coding
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.train.dynamic import DynamicConfig, DynamicTrainer
    from gscodec_shac.train.model import GaussianModel

    capture, cloud = moving_capture()
    model = GaussianModel({"means": cloud.means, "scales": cloud.scales, "quats": cloud.quats,
                           "opacities": cloud.opacities, "sh_dc": cloud.sh_dc, "sh_rest": cloud.sh_rest}, 3)
    config = DynamicConfig(iterations=20, warm_up=0, depth=2, width=32, densify_until=0, sh_interval=1000,
                           lr_deform=3e-3, checkpoint_every=1000, network_bits=4, network_grid_fraction=0.5)
    trainer = DynamicTrainer(capture, config, model=model)
    seen = []
    for _ in range(20):
        trainer.step()
        seen.append(trainer.net.grid_bits)
    assert all(g is None for g in seen[:10]) and all(g == coding.encoder_grid(trainer.net.arch, 4) for g in seen[10:])
    saved = trainer.dynamic_model()[0].net.weights()
    trained = trainer.net.weights()  # the float weights the optimiser holds

    def coding_change(weights: dict) -> float:
        stream = Bitstream()
        coding.add_deformation(stream, trainer.net.arch, weights, bits=coding.encoder_bits(trainer.net.arch, 4),
                               means=cloud.means)
        header = stream.header[coding.CHUNK]
        raw = coding.zlib.decompress(stream.chunk(coding.CHUNK).data)
        back = coding.decode_weights(raw, trainer.net.arch, header["dtype"], tuple(header["bits"]))
        return max(float(np.abs(back[k] - weights[k]).max()) for k in weights if weights[k].ndim == 2)

    for name, bits in coding.encoder_grid(trainer.net.arch, 4).items():
        assert all(len(np.unique(row)) <= 1 << bits for row in saved[name])
    assert coding_change(saved) < 0.05 * coding_change(trained)


def test_network_bits_for_training_outside_2_to_8_are_refused() -> None:
    from gscodec_shac.train.dynamic import DynamicConfig, DynamicTrainError

    for bits in (1, 9, 16):
        with pytest.raises(DynamicTrainError, match="--network-bits"):
            DynamicConfig(network_bits=bits).validate()


def test_encode_codes_a_network_trained_on_a_grid_at_its_bits(tmp_path: Path, dynamic_dir: Path) -> None:
    """Without ``--network-bits``, ``encode`` codes a network whose matrices lie on the 4-bit grid (what
    ``train-dynamic --network-bits 4`` saves) on that grid (:func:`encoder_grid`), exactly; a float network at the default 8."""
    from gscodec_shac.codec import decode_file, encode_file
    from gscodec_shac.codec import deformation as coding
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import read_header
    from gscodec_shac.deform import load_dynamic_model

    model = load_dynamic_model(dynamic_dir)
    arch = model.arch
    float_bits = read_header(Bitstream.read(Path(encode_file(dynamic_dir, tmp_path / "f.gsc", "gsplat_png")["output"])))
    assert float_bits.deformation.bits == 8
    model.net.snap_to_grid(coding.encoder_grid(arch, 4))
    gridded = save_dynamic_model(tmp_path / "gridded", model)
    encode_file(gridded, tmp_path / "g.gsc", "gsplat_png")
    view = read_header(Bitstream.read(tmp_path / "g.gsc"))
    assert view.deformation.bits == coding.matrix_bits(arch, coding.encoder_bits(arch, 4))
    decode_file(tmp_path / "g.gsc", tmp_path / "back")
    back = load_dynamic_model(tmp_path / "back").net.weights()
    for name, value in model.net.weights().items():
        if value.ndim == 2:  # on the grid up to the float16 rounding of each row's lo and step
            step = (value.max(axis=1) - value.min(axis=1)) / 255
            assert np.all(np.abs(back[name] - value) <= np.maximum(step, 1e-6)[:, None])


def test_encode_codes_a_network_trained_on_the_earlier_heads_only_grid_on_that_grid(tmp_path: Path,
                                                                                     dynamic_dir: Path) -> None:
    """Networks trained with `--network-bits 4` before the time layer and the matrix after the skip
    were kept finer lie on the heads-only grid: `encode` still finds it and codes them on it."""
    from gscodec_shac.codec import deformation as coding
    from gscodec_shac.codec import encode_file
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.header import read_header
    from gscodec_shac.deform import load_dynamic_model

    model = load_dynamic_model(dynamic_dir)
    old = coding.heads_only_grid(model.arch, 4)
    assert old != coding.encoder_grid(model.arch, 4)
    model.net.snap_to_grid(old)
    gridded = save_dynamic_model(tmp_path / "old", model)
    assert coding.trained_grid(model.arch, model.net.weights()) == tuple(old.values())
    encode_file(gridded, tmp_path / "o.gsc", "gsplat_png")
    assert read_header(Bitstream.read(tmp_path / "o.gsc")).deformation.bits == tuple(old.values())
    rough = load_dynamic_model(dynamic_dir)  # a float network lies on no grid: the default 8 bits
    assert coding.trained_grid(rough.arch, rough.net.weights()) is None
