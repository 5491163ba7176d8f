"""Reading Deformable-3DGS output folders (``point_cloud/iteration_N`` + ``deform/iteration_N``).

The fixture is a state dict with the reference's key names and shapes (its trainer builds the
8 x 256 network, so that is what is tested), random weights, written into the reference's
folder layout. ``reference_deform`` below re-implements the reference's forward pass and its
renderer's use of the outputs with plain torch ops (interleaved sin/cos encoding, time net,
skip concatenation after layer D/2, three heads; ``x + dx``, ``normalize(q) + dq``,
``exp(s) + ds``), independently of ``gscodec_shac.deform``.
"""

from __future__ import annotations

import gscodec_shac.render  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from gscodec_shac.deform import is_dynamic_model, load_dynamic_model
from gscodec_shac.errors import ModelFormatError
from gscodec_shac.gaussians import GaussianCloud
from gscodec_shac.io.ply import read_ply, write_ply

D, W = 8, 256  # the reference trainer's network (scene/deform_model.py uses the defaults)


def reference_state_dict(blender: bool = True, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random weights under the reference's keys: timenet.{0,2}, linear.0..7, three heads."""
    gen = torch.Generator().manual_seed(seed)
    x_ch = 3 + 3 * 2 * 10
    t_ch = 30 if blender else 1 + 2 * 10
    shapes = {}
    if blender:
        shapes |= {"timenet.0": (256, 1 + 2 * 6), "timenet.2": (30, 256)}
    for i in range(D):
        fan_in = x_ch + t_ch if i == 0 else W + (x_ch + t_ch if i == D // 2 + 1 else 0)
        shapes[f"linear.{i}"] = (W, fan_in)
    shapes |= {"gaussian_warp": (3, W), "gaussian_rotation": (4, W), "gaussian_scaling": (3, W)}
    state = {}
    for name, (out, fan_in) in shapes.items():
        bound = 1.0 / fan_in ** 0.5 * (0.2 if name.startswith("gaussian_") else 1.0)
        state[f"{name}.weight"] = (torch.rand(out, fan_in, generator=gen) * 2 - 1) * bound
        state[f"{name}.bias"] = (torch.rand(out, generator=gen) * 2 - 1) * bound
    return state


def embed(v: torch.Tensor, octaves: int) -> torch.Tensor:
    """The reference's encoding: v, then sin and cos of 2^k v per octave k (interleaved)."""
    parts = [v]
    for k in range(octaves):
        parts += [torch.sin(v * 2.0 ** k), torch.cos(v * 2.0 ** k)]
    return torch.cat(parts, dim=-1)


def reference_deform(state: dict[str, torch.Tensor], cloud: GaussianCloud, t: float, blender: bool):
    """Deformed (means, quats, scales) at ``t`` as the reference's network + renderer compute them."""
    def lin(name: str, h: torch.Tensor) -> torch.Tensor:
        return h @ state[f"{name}.weight"].T + state[f"{name}.bias"]

    x = torch.from_numpy(cloud.means).float()
    x_emb = embed(x, 10)
    t_emb = embed(torch.full((x.shape[0], 1), float(t)), 6 if blender else 10)
    if blender:
        t_emb = lin("timenet.2", torch.relu(lin("timenet.0", t_emb)))
    h = torch.cat([x_emb, t_emb], -1)
    for i in range(D):
        h = torch.relu(lin(f"linear.{i}", h))
        if i == D // 2:
            h = torch.cat([x_emb, t_emb, h], -1)
    dx, dq, ds = lin("gaussian_warp", h), lin("gaussian_rotation", h), lin("gaussian_scaling", h)
    q = torch.from_numpy(cloud.quats).float()
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
    scales = torch.exp(torch.from_numpy(cloud.scales).float()) + ds
    return (x + dx).numpy(), (q + dq).numpy(), scales.numpy()


def canonical(n: int = 600, seed: int = 3) -> GaussianCloud:
    from gscodec_shac.synthetic import make_synthetic_scene

    return make_synthetic_scene(n, seed=seed, n_cameras=2, width=32, height=24).cloud


def write_output(root: Path, cloud: GaussianCloud, state: dict, iteration: int) -> Path:
    """The reference's layout for one saved iteration."""
    (root / "point_cloud" / f"iteration_{iteration}").mkdir(parents=True, exist_ok=True)
    (root / "deform" / f"iteration_{iteration}").mkdir(parents=True, exist_ok=True)
    write_ply(root / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply", cloud)
    torch.save(state, root / "deform" / f"iteration_{iteration}" / "deform.pth")
    return root


@pytest.fixture()
def output(tmp_path: Path) -> Path:
    """Two saved iterations, 7000 and 30000 (the newest is not the last in name order)."""
    root = write_output(tmp_path / "out", canonical(seed=1), reference_state_dict(seed=1), 7000)
    return write_output(root, canonical(), reference_state_dict(), 30000)


# --------------------------------------------------------------------------- the network
@pytest.mark.parametrize("blender", [True, False], ids=["dnerf-timenet", "real-scene"])
def test_deformation_matches_the_reference_formula(tmp_path: Path, blender: bool) -> None:
    cloud, state = canonical(), reference_state_dict(blender, seed=5)
    root = write_output(tmp_path / "out", cloud, state, 40000)
    model = load_dynamic_model(root)
    assert (model.arch.depth, model.arch.width, model.arch.time_net) == (D, W, blender)
    assert model.net.n_params == sum(v.numel() for v in state.values())
    for t in (0.0, 0.37, 1.0):
        means, quats, scales = reference_deform(state, cloud, t, blender)
        assert np.abs(means - cloud.means).max() > 1e-3  # the deformation is not the identity
        moved = model.at(t)
        np.testing.assert_allclose(moved.means, means, atol=2e-5)
        np.testing.assert_allclose(moved.quats, quats, atol=2e-5)
        # our log-scale is log |exp(s) + ds| (only the square of the scale enters the covariance)
        np.testing.assert_allclose(np.exp(moved.scales), np.abs(scales), rtol=1e-4, atol=2e-6)
        np.testing.assert_array_equal(moved.sh_rest, cloud.sh_rest)


def test_newest_iteration_unless_one_is_named(output: Path) -> None:
    newest = load_dynamic_model(output)
    np.testing.assert_array_equal(newest.cloud.means, canonical().means)
    named = load_dynamic_model(output / "point_cloud" / "iteration_7000")
    np.testing.assert_array_equal(named.cloud.means, canonical(seed=1).means)
    state = reference_state_dict(seed=1)
    np.testing.assert_array_equal(named.net.weights()["head_xyz.weight"], state["gaussian_warp.weight"].numpy())
    also = load_dynamic_model(output / "deform" / "iteration_7000")
    np.testing.assert_array_equal(also.cloud.means, named.cloud.means)
    assert is_dynamic_model(output) and is_dynamic_model(output / "point_cloud" / "iteration_30000")
    assert not is_dynamic_model(output / "point_cloud")


# --------------------------------------------------------------------------- errors
def _edit(state: dict, change) -> dict:
    state = dict(state)
    change(state)
    return state


@pytest.mark.parametrize("change, message", [
    (lambda s: s.update({"extra.weight": torch.zeros(3)}), r"unknown key\(s\) extra.weight"),
    (lambda s: s.pop("gaussian_scaling.bias"), r"missing key\(s\) gaussian_scaling.bias"),
    (lambda s: s.update({"linear.5.weight": torch.zeros(256, 256 + 63)}),
     r"linear.5.weight has shape \(256, 319\), the reference's 8x256 D-NeRF \(is_blender\) network needs \(256, 349\)"),
    (lambda s: s.update({"timenet.0.weight": torch.zeros(256, 21)}), r"timenet.0.weight has shape \(256, 21\)"),
    (lambda s: s.update({"branch_w.weight": s.pop("gaussian_warp.weight")}), "6-DoF network"),
    (lambda s: s.update({"linear.3.bias": torch.zeros(256, dtype=torch.int64)}), "linear.3.bias has dtype"),
    (lambda s: s.update({"linear.3.bias": torch.full((256,), float("nan"))}), "NaN"),
])
def test_a_state_dict_that_does_not_match_is_one_clear_error(tmp_path: Path, change, message: str) -> None:
    root = write_output(tmp_path / "out", canonical(), _edit(reference_state_dict(), change), 7000)
    with pytest.raises(ModelFormatError, match=message):
        load_dynamic_model(root)


def test_missing_iteration_and_foreign_files(tmp_path: Path, output: Path, capsys) -> None:
    from gscodec_shac.cli import main

    (output / "point_cloud" / "iteration_50000").mkdir()
    write_ply(output / "point_cloud" / "iteration_50000" / "point_cloud.ply", canonical())
    with pytest.raises(ModelFormatError, match=r"iteration 50000 has no deform/iteration_50000/deform.pth "
                                                r"\(saved iterations there: \[7000, 30000\]\)"):
        load_dynamic_model(output)
    # the CLI: one error line, usage exit status, nothing else
    assert main(["info", str(output)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "iteration 50000" in err[0]
    (output / "deform" / "iteration_50000").mkdir()
    (output / "deform" / "iteration_50000" / "deform.pth").write_bytes(b"not a torch file")
    with pytest.raises(ModelFormatError, match="not a readable torch state dict"):
        load_dynamic_model(output)
    torch.save([torch.zeros(3)], output / "deform" / "iteration_50000" / "deform.pth")
    with pytest.raises(ModelFormatError, match="expected a dict of named tensors"):
        load_dynamic_model(output)
    empty = tmp_path / "empty"
    (empty / "point_cloud").mkdir(parents=True)
    (empty / "deform").mkdir()
    with pytest.raises(ModelFormatError, match="no point_cloud/iteration_N/point_cloud.ply"):
        load_dynamic_model(empty)


# --------------------------------------------------------------------------- commands
def test_encode_decode_render_info_rd_on_an_output_folder(tmp_path: Path, output: Path, capsys) -> None:
    """The issue's command on the fixture, then decode to our model directory, render at a time, info, rd's reader."""
    from gscodec_shac.cli import main
    from gscodec_shac.io.models import read_model
    from gscodec_shac.rd.scenes import convert_model_to_ply

    gsc = tmp_path / "out.gsc"
    assert main(["encode", str(output), str(gsc), "--sh", "pca", "--er", "0.96", "-q"]) == 0
    capsys.readouterr()
    assert main(["info", str(gsc), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["deformation"]["arch"]["depth"] == D and info["deformation"]["arch"]["width"] == W
    assert main(["decode", str(gsc), str(tmp_path / "dec"), "-q"]) == 0
    decoded, source = load_dynamic_model(tmp_path / "dec"), load_dynamic_model(output)
    assert (tmp_path / "dec" / "deformation.json").is_file() and decoded.arch == source.arch
    assert decoded.cloud.num_gaussians == source.cloud.num_gaussians
    for key, value in source.net.weights().items():  # the coded network: matrices on their 8-bit row grids
        if value.ndim == 2:  # (the fitted rounding may pick a grid value a few steps away; biases absorb the shift)
            step = np.ptp(value, axis=-1, keepdims=True) / 255.0
            assert np.abs(decoded.net.weights()[key] - value).mean() <= np.mean(step), key
            assert np.all(np.abs(decoded.net.weights()[key] - value) <= 8 * step + 1e-3 * np.abs(value).max()), key
    x = torch.from_numpy(decoded.cloud.means)  # ... and deforms the (reordered) Gaussians as the source does
    with torch.no_grad():
        got, want = decoded.net(x, 0.4)[0], source.net(x, 0.4)[0]
    assert float((got - want).abs().max()) <= 0.02 * float(want.abs().max())
    # render --time on the folder == a static render of the reference formula's Gaussians
    cloud = source.cloud
    means, quats, scales = reference_deform(reference_state_dict(), cloud, 0.6, True)
    moved = GaussianCloud(means=means, scales=np.log(np.abs(scales)), quats=quats, opacities=cloud.opacities,
                          sh_dc=cloud.sh_dc, sh_rest=cloud.sh_rest)
    write_ply(tmp_path / "reference_at.ply", moved)
    common = ["--orbit-views", "2", "--width", "48", "-q"]
    assert main(["render", str(output), str(tmp_path / "r_dyn"), "--time", "0.6", *common]) == 0
    assert main(["render", str(tmp_path / "reference_at.ply"), str(tmp_path / "r_ref"), *common]) == 0
    names = sorted(p.name for p in (tmp_path / "r_ref").glob("*.png"))
    assert names
    for name in names:
        a = cv2.imread(str(tmp_path / "r_dyn" / name), cv2.IMREAD_UNCHANGED).astype(int)
        b = cv2.imread(str(tmp_path / "r_ref" / name), cv2.IMREAD_UNCHANGED).astype(int)
        assert a.std() > 0 and np.abs(a - b).max() <= 1, name
    assert main(["info", str(output)]) == 0
    text = capsys.readouterr().out
    assert "deformation       MLP 8x256 + time net" in text
    ply = output / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    assert f"({ply.stat().st_size + (output / 'deform' / 'iteration_30000' / 'deform.pth').stat().st_size:,} bytes)" \
        in text
    # rd (static): the canonical Gaussians of the newest iteration, with a note
    cloud, notes = read_model(output)
    np.testing.assert_array_equal(cloud.means, read_ply(ply).means)
    assert len(notes) == 1 and "iteration 30000" in notes[0]
    convert_model_to_ply(output, tmp_path / "rd" / "scene.ply")
    np.testing.assert_array_equal(read_ply(tmp_path / "rd" / "scene.ply").means, cloud.means)
