"""scripts/measure_prune.py --view-counts: the importance ranking from fewer views against all of them."""

import numpy as np

from tests.conftest import load_script


def test_view_counts_rank_against_every_view(small_scene):
    script = load_script("measure_prune")
    cloud, views = small_scene.cloud, small_scene.cameras  # 8 cameras
    eval_views = views[:2]
    reference = script.renders(cloud, eval_views)
    rows = script.view_count_stability(cloud, views, [2, 4, 50], eval_views, reference, shares=(0.5,))
    assert [row["views"] for row in rows] == [2, 4, 8]  # capped at the views there are, all of them added
    every = rows[-1]
    assert every["top_half_overlap"] == 1.0 and np.isclose(every["spearman"], 1.0)
    for row in rows:
        assert 0.0 <= row["top_half_overlap"] <= 1.0 and np.isfinite(row["psnr_ref_keep_0.5"])
    assert rows[0]["top_half_overlap"] < 1.0  # two views rank the cloud otherwise than eight
