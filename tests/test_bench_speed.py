"""scripts/bench_speed.py: the fixed encode of the settings a target run chose codes the same chunks."""

from gscodec_shac.codec import Encoder, load_rate_point
from gscodec_shac.codec.rate_control import RateController, make_target
from tests.conftest import load_script

bench_speed = load_script("bench_speed")


def test_the_chosen_settings_as_a_rate_point_code_the_target_files_chunks(small_scene, tmp_path):
    cloud = small_scene.cloud
    controller = RateController(cloud, views=small_scene.cameras, workers=1)
    outcome = controller.encode(make_target(cloud.num_gaussians, bpg=60))
    aimed = tmp_path / "aimed.gsc"
    outcome.stream.write(aimed)
    chosen = bench_speed.chosen_rate_point(aimed, tmp_path / "chosen.yaml")
    point = load_rate_point(f"{chosen}:chosen")
    settings = outcome.plan.rate_point
    assert point.attributes["positions"].bits == settings.attributes["positions"].bits
    assert all(point.attributes[name].qp == settings.attributes[name].qp
               for name in ("opacity", "rotation", "scale", "sh_dc", "sh_features"))
    assert (point.min_opacity, point.keep_share) == (settings.min_opacity, settings.keep_share)
    fixed = tmp_path / "fixed.gsc"
    # with cameras the controller fits SHAC-PCA in their view metric (version 18), as `encode --cameras` does
    metric = controller._sh_metric()
    assert metric is not None
    plain = tmp_path / "plain.gsc"
    Encoder(point, workers=1).encode(cloud).write(plain)
    assert any(name.startswith("sh") for name in bench_speed.differing_chunks(aimed, plain))
    Encoder(point, workers=1, sh_metric=metric).encode(cloud).write(fixed)
    assert bench_speed.differing_chunks(aimed, fixed) == []
    assert bench_speed.chosen_rate_point(fixed, tmp_path / "again.yaml") is None  # not a controller's choice
