"""``tune-network``: a trained dynamic model's network fitted to its coded grid, the Gaussians frozen."""

from __future__ import annotations

import gscodec_shac.render  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gscodec_shac.camera import look_at
from gscodec_shac.deform import DeformArch, DeformNetwork, DynamicModel, load_dynamic_model, save_dynamic_model
from gscodec_shac.render import Renderer

ARCH = DeformArch(depth=2, width=24, xyz_freqs=3, t_freqs=2, time_net=True, time_width=8, time_out=4)


def teacher_model(n: int = 80, seed: int = 4) -> DynamicModel:
    """Random Gaussians (``tests.test_dynamic.random_cloud``) and a float network with non-zero heads:
    the model the images are rendered from."""
    from tests.test_dynamic import random_cloud

    cloud = random_cloud(n, seed)
    torch.manual_seed(seed)
    net = DeformNetwork(ARCH)
    with torch.no_grad():
        for layer in (*net.layers, *net.time_layers):
            layer.weight.mul_(2.0)
        for head in (net.head_xyz, net.head_rot, net.head_scale):
            head.weight.normal_(0.0, 0.08)
            head.bias.normal_(0.0, 0.02)
    return DynamicModel(cloud, net)


def capture_of(model: DynamicModel, frames: int = 12, size: tuple[int, int] = (40, 32)):
    """Views of ``model`` at evenly spread times around it (train = test: the test measures the fit)."""
    from gscodec_shac.train.dynamic import DynamicCapture

    cams, times, images = [], [], []
    for i in range(frames):
        angle = 2 * np.pi * i / frames
        cam = look_at(f"f{i}", (3.0 * np.cos(angle), 3.0 * np.sin(angle), 0.8), (0, 0, 0), (0, 0, 1), *size, 35.0)
        t = (i + 0.5) / frames
        cams.append(cam)
        times.append(t)
        images.append(np.clip(Renderer(model.at(t)).render(cam).image, 0, 1).astype(np.float32))
    return DynamicCapture("teacher", cams, times, images, cams, times, images, np.zeros(3), 3.3)


def test_tuning_recovers_what_snapping_to_the_grid_loses_and_leaves_the_gaussians_alone() -> None:
    from gscodec_shac.codec.deformation import encoder_grid, on_grid
    from gscodec_shac.train.dynamic import evaluate_dynamic
    from gscodec_shac.train.network_tune import NetworkTuneConfig, tune_network

    teacher = teacher_model()
    capture = capture_of(teacher)
    before = teacher.net.weights()
    grid = encoder_grid(ARCH, 2)
    snapped = DeformNetwork(ARCH)
    snapped.load_weights(before)
    snapped.snap_to_grid(grid)
    snapped_psnr = evaluate_dynamic(DynamicModel(teacher.cloud, snapped), capture)["mean_psnr"]

    tuned = tune_network(teacher, capture, NetworkTuneConfig(bits=2, float_iterations=0, iterations=60, lr=3e-3,
                                                                  lr_final=3e-4))
    tuned_psnr = evaluate_dynamic(tuned, capture)["mean_psnr"]
    assert tuned_psnr > snapped_psnr + 1.0, (snapped_psnr, tuned_psnr)
    assert on_grid(tuned.net.weights(), grid)
    assert tuned.cloud is teacher.cloud  # the canonical Gaussians are not trained
    for name, value in teacher.net.weights().items():  # nor is the input network changed
        np.testing.assert_array_equal(value, before[name])


def test_the_float_control_keeps_the_network_off_the_grid() -> None:
    from gscodec_shac.codec.deformation import encoder_grid, on_grid
    from gscodec_shac.train.network_tune import NetworkTuneConfig, tune_network

    teacher = teacher_model()
    tuned = tune_network(teacher, capture_of(teacher, frames=3), NetworkTuneConfig(bits=16, float_iterations=3))
    assert not on_grid(tuned.net.weights(), encoder_grid(ARCH, 7))
    assert any(not np.array_equal(a, b) for a, b in zip(tuned.net.weights().values(), teacher.net.weights().values()))


def test_the_two_phases_are_a_float_tuning_then_a_grid_tuning_of_its_result() -> None:
    """One call equals the float control followed by a grid-only tuning of its network (what the
    two-step measurements in docs/dynamic.md ran as two commands)."""
    from gscodec_shac.train.network_tune import NetworkTuneConfig, tune_network

    teacher = teacher_model()
    capture = capture_of(teacher, frames=4)
    both = tune_network(teacher, capture, NetworkTuneConfig(bits=3, float_iterations=5, iterations=4))
    first = tune_network(teacher, capture, NetworkTuneConfig(bits=16, float_iterations=5))
    second = tune_network(first, capture, NetworkTuneConfig(bits=3, float_iterations=0, iterations=4))
    for name, value in both.net.weights().items():
        np.testing.assert_array_equal(value, second.net.weights()[name])


@pytest.mark.parametrize("setting, message", [
    ({"bits": 8}, "--network-bits must be 2-7"), ({"bits": 1}, "--network-bits must be 2-7"),
    ({"iterations": 0, "float_iterations": 0}, "--float-iterations"), ({"iterations": -1}, "--iterations"),
    ({"lr": 0.0}, "learning rates"), ({"float_lr_final": -1.0}, "learning rates"),
])
def test_bad_tuning_settings_are_refused(setting: dict, message: str) -> None:
    from gscodec_shac.train.network_tune import NetworkTuneConfig, NetworkTuneError

    with pytest.raises(NetworkTuneError, match=message):
        NetworkTuneConfig(**setting).validate()


def write_dnerf_scene(root: Path, frames: int = 3, size: tuple[int, int] = (16, 12)) -> Path:
    """A D-NeRF folder: random RGBA PNGs seen from (0, 0, 4) towards the origin, a time per frame."""
    import cv2

    rng = np.random.default_rng(0)
    for split in ("train", "test"):
        (root / split).mkdir(parents=True)
        entries = []
        for i in range(frames):
            cv2.imwrite(str(root / split / f"r_{i}.png"), rng.integers(0, 256, (size[1], size[0], 4), dtype=np.uint8))
            pose = np.eye(4)
            pose[2, 3] = 4.0
            entries.append({"file_path": f"./{split}/r_{i}", "time": i / (frames - 1), "transform_matrix": pose.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": entries}))
    return root


def test_the_command_writes_a_model_that_encode_codes_on_its_grid(tmp_path: Path, capsys) -> None:
    from gscodec_shac.cli import main
    from gscodec_shac.codec.container import Bitstream
    from gscodec_shac.codec.deformation import encoder_bits, matrix_bits
    from gscodec_shac.codec.header import read_header

    teacher = teacher_model(n=40)
    model_dir = save_dynamic_model(tmp_path / "model", teacher)
    scene = write_dnerf_scene(tmp_path / "scene")
    out = tmp_path / "tuned"
    assert main(["tune-network", str(model_dir), str(scene), str(out), "--network-bits", "3", "--float-iterations", "2",
                 "--iterations", "4",
                 "--resolution-scale", "1", "-q"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["bits"] == 3 and len(metrics["input_test"]["views"]) == 3
    assert "test PSNR" in capsys.readouterr().out
    assert main(["info", str(out)]) == 0  # info names the grid the network lies on
    expected = ",".join(map(str, matrix_bits(ARCH, encoder_bits(ARCH, 3))))
    assert f"on a coded grid, bits per matrix {expected}" in capsys.readouterr().out
    assert main(["info", str(model_dir)]) == 0 and "coded grid" not in capsys.readouterr().out
    assert main(["encode", str(out), str(tmp_path / "t.gsc"), "-q"]) == 0
    view = read_header(Bitstream.read(tmp_path / "t.gsc"))
    assert view.deformation.bits == matrix_bits(ARCH, encoder_bits(ARCH, 3))
    np.testing.assert_array_equal(load_dynamic_model(out).cloud.means, load_dynamic_model(model_dir).cloud.means)
    # a second run does not write over the first without --force
    assert main(["tune-network", str(model_dir), str(scene), str(out), "--iterations", "1", "-q"]) != 0
    assert "pass --force to replace it" in capsys.readouterr().err


def test_a_static_model_or_a_folder_without_frames_is_one_clear_error(tmp_path: Path, capsys) -> None:
    from gscodec_shac.cli import main
    from gscodec_shac.io.ply import write_ply

    teacher = teacher_model(n=20)
    write_ply(tmp_path / "static.ply", teacher.cloud)
    model_dir = save_dynamic_model(tmp_path / "model", teacher)
    scene = write_dnerf_scene(tmp_path / "scene")
    assert main(["tune-network", str(tmp_path / "static.ply"), str(scene), str(tmp_path / "a"), "-q"]) == 2
    assert "not a dynamic model directory" in capsys.readouterr().err
    assert main(["tune-network", str(model_dir), str(tmp_path), str(tmp_path / "b"), "-q"]) == 2
    assert "transforms" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_deformable_3dgs_output_folder_is_tuned_into_our_model_directory(tmp_path: Path, capsys) -> None:
    """A model trained elsewhere (the reference's output layout, its 8 x 256 network): tuned for 4 bits,
    it becomes our model directory with the reference's architecture, its network on the 4-bit grid
    and its canonical Gaussians unchanged."""
    from gscodec_shac.cli import main
    from gscodec_shac.codec.deformation import encoder_grid, on_grid
    from tests.test_deformable3dgs import canonical, reference_state_dict, write_output

    cloud = canonical(n=200)
    folder = write_output(tmp_path / "reference", cloud, reference_state_dict(), 30000)
    scene = write_dnerf_scene(tmp_path / "scene")
    out = tmp_path / "tuned"
    assert main(["tune-network", str(folder), str(scene), str(out), "--float-iterations", "1", "--iterations", "2",
                 "--resolution-scale", "1", "--no-eval", "-q"]) == 0
    given, tuned = load_dynamic_model(folder), load_dynamic_model(out)
    assert tuned.arch == given.arch and (tuned.arch.depth, tuned.arch.width) == (8, 256)
    assert on_grid(tuned.net.weights(), encoder_grid(tuned.arch, 4))
    np.testing.assert_array_equal(tuned.cloud.means, given.cloud.means)
    np.testing.assert_array_equal(tuned.cloud.sh_rest, given.cloud.sh_rest)


@pytest.mark.parametrize("command", ["tune-network", "train-dynamic", "train"])
def test_threads_below_one_are_refused_by_every_trainer(tmp_path: Path, capsys, command: str) -> None:
    from gscodec_shac.cli import main

    positional = [str(tmp_path / "m"), str(tmp_path / "s"), str(tmp_path / "o")] if command == "tune-network" \
        else [str(tmp_path / "s"), str(tmp_path / "o")]
    assert main([command, *positional, "--threads", "0", "-q"]) == 2
    assert "--threads must be at least 1, got 0" in capsys.readouterr().err
