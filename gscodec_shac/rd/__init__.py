"""Rate-distortion sweeps: scenes x methods x rate points -> rows, BD-rates, tables and plots.

Public API::

    from gscodec_shac.rd import load_sweep, run_sweep, write_report, bd_rate, bd_psnr

    spec = load_sweep("sweeps/bonsai.yaml")                 # validated SweepSpec
    outcome = run_sweep(spec, "out/bonsai", workers=2)      # resumable; executor="local"|"serial"|"ray"
    outcome.rows                                            # one dict per run (also OUT/results.csv/.json)
    write_report("out/bonsai")                              # OUT/report/: report.md, bd.json, bd.csv, rd_<scene>.png
    bd_rate(anchor_bytes, anchor_psnr, test_bytes, test_psnr).value   # percent

Modules: :mod:`.spec` (sweep YAML), :mod:`.methods` (recipes), :mod:`.scenes` (inputs,
test views, reference renders), :mod:`.runner` (one run: a pure function -> row),
:mod:`.executors` / :mod:`.ray_executor` (where runs execute), :mod:`.results` (run log,
CSV/JSON), :mod:`.sweep` (the driver), :mod:`.bd` (Bjontegaard), :mod:`.report` and
:mod:`.plots` (tables and figures), :mod:`.external` (splat-transform), :mod:`.sortcache`.
"""

from gscodec_shac.rd.bd import BdResult, bd_psnr, bd_quality, bd_rate
from gscodec_shac.rd.report import bd_table, markdown_report, write_report
from gscodec_shac.rd.results import ResultStore, load_results
from gscodec_shac.rd.spec import EvalSettings, MethodSpec, SceneSpec, SweepSpec, SweepSpecError, load_sweep, parse_sweep
from gscodec_shac.rd.sweep import SweepOutcome, run_sweep

__all__ = [
    "BdResult", "EvalSettings", "MethodSpec", "ResultStore", "SceneSpec", "SweepOutcome", "SweepSpec",
    "SweepSpecError", "bd_psnr", "bd_quality", "bd_rate", "bd_table", "load_results", "load_sweep",
    "markdown_report", "parse_sweep", "run_sweep", "write_report",
]
