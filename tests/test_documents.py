"""Bad rate-point YAML, sweep YAML and camera files: every variant is accepted or refused with
one GscodecError (types checked before use, nesting bounded, image sizes bounded)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import yaml

from gscodec_shac.camera import Camera, orbit_cameras
from gscodec_shac.cli import main
from gscodec_shac.codec.rate_points import load_rate_point
from gscodec_shac.errors import CameraFormatError, GscodecError, MemoryLimitError, RatePointError
from gscodec_shac.io.cameras import load_cameras
from gscodec_shac.io.inria_cameras import write_inria_cameras
from gscodec_shac.io.nerf import read_nerf_transforms
from gscodec_shac.limits import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, MAX_NESTING, MAX_YAML_BYTES
from gscodec_shac.rd.spec import SweepSpecError, load_sweep

#: What a bad value looks like in YAML text (raw, so huge integers and .nan reach the parser).
BAD_YAML = ["x", "-1", "0", "1.0e30", "1" + "0" * 30, ".nan", ".inf", "-.inf", "true", "null", "[]", "{}",
            "9" * 5000, "1e400", "[[[[1]]]]", "'1e9'"]
#: The same for JSON.
BAD_JSON = ['"x"', "-1", "0", "1e30", "1" + "0" * 30, "NaN", "Infinity", "-Infinity", "true", "null", "[]", "{}",
            "9" * 5000, "1e400", "[[[[1]]]]", '"1e9"', "100000", "1000000000", "0.5"]

RATE_POINT = {
    "description": "test", "defaults": {
        "codec": "hevc", "codec_options": {"preset": "slow"}, "bits": 10, "color": "ycbcr",
        "attributes": {"positions": {"bits": 16, "layout": "split8"}},
        "sh": {"stage": "pca", "energy_retention": 0.99},
        "sort": {"method": "plas", "policy": "pad", "multiple": 8, "seed": 0, "weights": {"xyz": 1.0}},
        "prune": {"min_opacity": 0.0},
    },
    "points": {"a": {"qp": {"opacity": 22, "rotation": 17, "scale": 12, "sh_dc": 7, "sh_ac": [32, 37, 42]}}},
}
SWEEP = {
    "name": "t", "rate_points": ["paper_table3:rp1"],
    "settings": {"preset": "ultrafast", "sort": "morton", "retries": 1, "threads": 1},
    "scenes": [{"name": "syn", "synthetic": {"n": 2000, "seed": 0, "n_cameras": 16, "width": 64, "height": 48},
                "test_every": 8, "background": [0, 0, 0]}],
    "methods": ["baseline", {"name": "pca", "recipe": "pca", "energy_retention": 0.99}],
}


def _leaves(value: Any, path: tuple = ()) -> list[tuple]:
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _leaves(v, path + (k,))]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _leaves(v, path + (i,))]
    return [path]


def _variants(document: Any, bad: list[str], dump: Callable[[Any], str]) -> list[tuple[str, str]]:
    """(label, text) with each leaf replaced by each bad value (spliced in as raw text)."""
    out = []
    for path in _leaves(document):
        for value in bad:
            copy = json.loads(json.dumps(document))
            parent = copy
            for key in path[:-1]:
                parent = parent[key]
            parent[path[-1]] = "@@BAD@@"
            out.append((f"{'.'.join(map(str, path))}={value[:12]}", dump(copy).replace('"@@BAD@@"', value)
                        .replace("'@@BAD@@'", value).replace("@@BAD@@", value)))
    return out


def _structural(flow_open: str, flow_close: str) -> list[tuple[str, str]]:
    return [
        ("deep-flow", "points:\n  a: " + flow_open * 10_000 + flow_close * 10_000 + "\n"),
        ("deep-block", "points:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(3000))),
        ("aliases", "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
            f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(9))),
        ("huge", "description: '" + "x" * (MAX_YAML_BYTES + 10) + "'\n"),
        ("not-utf8", "\udcff"),
        ("empty", ""),
        ("scalar", "42\n"),
        ("tabs", "points:\n\ta: {}\n"),
    ]


def _check(load: Callable[[Path], Any], path: Path, label: str) -> str:
    try:
        load(path)
    except GscodecError:
        return "error"
    except Exception as exc:  # noqa: BLE001 - the failure this test looks for
        return f"crash {label}: {type(exc).__name__}: {exc}"
    return "ok"


def _assert_no_crash(kinds: list[str]) -> None:
    crashes = [k for k in kinds if k.startswith("crash")]
    assert not crashes, f"{len(crashes)} variants crash: {crashes[:10]}"


def _write_text(path: Path, text: str) -> None:
    path.write_bytes(text.encode("utf-8", "surrogateescape"))


def test_every_bad_rate_point_variant_is_one_clean_error(tmp_path):
    cases = _variants(RATE_POINT, BAD_YAML, lambda d: yaml.safe_dump(d, sort_keys=False)) + _structural("[", "]")
    kinds = []
    for index, (label, text) in enumerate(cases):
        path = tmp_path / f"p{index}.yaml"
        _write_text(path, text)
        kinds.append(_check(lambda p: load_rate_point(f"{p}:a"), path, label))
    _assert_no_crash(kinds)
    assert kinds.count("error") > len(cases) // 2 and "ok" in kinds, (kinds.count("error"), len(cases))


def test_every_bad_sweep_variant_is_one_clean_error(tmp_path):
    cases = _variants(SWEEP, BAD_YAML, lambda d: yaml.safe_dump(d, sort_keys=False)) + _structural("{a: ", "}")
    kinds = []
    for index, (label, text) in enumerate(cases):
        path = tmp_path / f"s{index}.yaml"
        _write_text(path, text)
        kinds.append(_check(load_sweep, path, label))
    _assert_no_crash(kinds)
    assert kinds.count("error") > len(cases) // 2 and "ok" in kinds


def _camera_files(tmp_path: Path) -> dict[str, Any]:
    cameras = orbit_cameras([0, 0, 0], 4.0, 2, 64, 48, fov_y_deg=45.0)
    write_inria_cameras(tmp_path / "cameras.json", cameras)
    transforms = {"camera_angle_x": 0.8, "w": 64, "h": 48, "frames": [
        {"file_path": "./r_0", "transform_matrix": np.eye(4).tolist()}]}
    return {"cameras.json": json.loads((tmp_path / "cameras.json").read_text()), "transforms.json": transforms}


@pytest.mark.parametrize("name", ["cameras.json", "transforms.json"])
def test_every_bad_camera_file_variant_is_one_clean_error(tmp_path, name):
    document = _camera_files(tmp_path)[name]
    cases = _variants(document, BAD_JSON, json.dumps) + [
        ("deep", "[" * 100_000 + "]" * 100_000), ("not-json", "{"), ("empty", ""), ("scalar", "7"),
        ("not-utf8", "\udcff"),
    ]
    kinds = []
    for index, (label, text) in enumerate(cases):
        folder = tmp_path / f"c{index}"
        folder.mkdir()
        _write_text(folder / name, text)
        kinds.append(_check(load_cameras, folder / name, label))
    _assert_no_crash(kinds)
    assert kinds.count("error") > len(cases) // 3 and "ok" in kinds


@pytest.mark.parametrize(
    "width, height, message",
    [
        (100_000, 100, "image size 100000x100 exceeds the maximum"),
        (10**9, 1, "exceeds the maximum"),
        (1e30, 100, "exceeds the maximum"),
        (10**400, 100, "is not a number"),
        (MAX_IMAGE_SIDE, MAX_IMAGE_SIDE, f"{MAX_IMAGE_PIXELS:,} pixels in all"),
        (float("nan"), 10, "is not a positive integer"),
        (True, 10, "is not a number"),
    ],
)
def test_image_sizes_are_bounded_before_anything_is_allocated(width, height, message):
    with pytest.raises(CameraFormatError, match=message):
        Camera("c", width, height, 100.0, 100.0, 50.0, 50.0, np.eye(3), np.zeros(3))


def test_the_largest_image_is_allowed_and_scaling_past_it_is_not():
    side = int(math.isqrt(MAX_IMAGE_PIXELS))
    camera = Camera("c", side, side, 100.0, 100.0, 50.0, 50.0, np.eye(3), np.zeros(3))
    with pytest.raises(CameraFormatError, match="would exceed"):
        camera.scaled(1e300)
    with pytest.raises(CameraFormatError, match="exceeds the maximum"):
        camera.resized(side + 1, side)


def test_a_huge_camera_in_a_file_fails_at_load(tmp_path):
    _camera_files(tmp_path)
    data = json.loads((tmp_path / "cameras.json").read_text())
    data[0]["width"] = 100_000
    (tmp_path / "cameras.json").write_text(json.dumps(data))
    with pytest.raises(CameraFormatError, match="camera entry 0: camera .* exceeds the maximum"):
        load_cameras(tmp_path / "cameras.json")


def test_render_checks_the_memory_a_view_needs(small_cloud, monkeypatch, tmp_path, capsys):
    from gscodec_shac.io.ply import write_ply
    from gscodec_shac.render import Renderer

    camera = orbit_cameras([0, 0, 0], 4.0, 1, 512, 512, fov_y_deg=45.0)[0]
    monkeypatch.setenv("GSCODEC_MAX_MEMORY", "1M")
    with pytest.raises(MemoryLimitError, match="a 512x512 render needs about 32.0 MiB"):
        Renderer(small_cloud).render(camera)
    write_ply(tmp_path / "s.ply", small_cloud)
    monkeypatch.delenv("GSCODEC_MAX_MEMORY")
    assert main(["render", str(tmp_path / "s.ply"), "--out", str(tmp_path / "r"), "--width", "100000"]) == 2
    assert "exceeds the maximum" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "s.ply"), "--out", str(tmp_path / "r"), "--scale", "1e300"]) == 2


def test_nerf_transforms_with_a_decompression_bomb_image_is_refused(tmp_path):
    from PIL import Image

    (tmp_path / "images").mkdir()
    Image.new("L", (MAX_IMAGE_SIDE + 1, 8)).save(tmp_path / "r_0.png")  # 16k wide, a few hundred bytes
    transforms = {"camera_angle_x": 0.8, "frames": [{"file_path": "./r_0", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    with pytest.raises(CameraFormatError, match="exceeds the maximum"):
        read_nerf_transforms(tmp_path / "transforms.json")


def test_limits_named_in_messages(tmp_path):
    path = tmp_path / "deep.yaml"
    path.write_text("points:\n  a: " + "[" * 1000 + "]" * 1000 + "\n")
    with pytest.raises(RatePointError, match=f"nested more than {MAX_NESTING} levels deep"):
        load_rate_point(f"{path}:a")
    path.write_text("points:\n  a: {qp: {opacity: x}}\n")
    with pytest.raises(RatePointError, match="key 'qp.opacity'"):
        load_rate_point(f"{path}:a")
    path.write_text("name: t\nrate_points: [paper_table3:rp1]\nscenes: [{name: s, synthetic: {n: 1000}}]\n"
                    "methods: [{name: m, recipe: pca, energy_retention: x}]\n")
    with pytest.raises(SweepSpecError, match="energy_retention"):
        load_sweep(path)
