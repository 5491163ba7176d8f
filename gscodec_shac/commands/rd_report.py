"""``gscodec-shac rd-report RESULTS [OUT_DIR]``: tables, BD-rates and RD plots from a sweep's results."""

from __future__ import annotations

import argparse

from gscodec_shac.commands._options import add_command, add_force, add_output


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "rd-report",
        help="tables, BD-rates and RD plots from the results of 'gscodec-shac rd'",
        description="Read RESULTS/results.json (or the run log) and write report.md (RD and BD tables), "
        "bd.json, bd.csv, one rd_<scene>.png per scene and report.html (one self-contained page with the plots, "
        "the BD table and decoded renders to compare) into OUT_DIR (default: RESULTS/report).",
        examples=["gscodec-shac rd-report runs/bonsai",
                  "gscodec-shac rd-report runs/bonsai bonsai_report/ --x-axis bpg"],
    )
    parser.add_argument("results", metavar="RESULTS", help="a sweep output folder (or its results.json)")
    add_output(parser, "OUT_DIR", "report folder (default: RESULTS/report)", required=False)
    parser.add_argument("--anchor", default=None, metavar="METHOD",
                        help="method the BD-rates are measured against (default: the sweep's)")
    parser.add_argument("--x-axis", choices=("mb", "bpg"), default="mb",
                        help="plot size in MB or bits per Gaussian (default mb)")
    parser.add_argument("--title", default=None, help="report title (default: \"RD results: <sweep name>\")")
    parser.add_argument("--prefix", default="rd_", help="figure file prefix (default rd_)")
    add_force(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from gscodec_shac.atomic import check_outputs
    from gscodec_shac.rd.report import bd_label, bd_table, write_report
    from gscodec_shac.rd.results import load_results

    results = Path(args.results)
    out = Path(args.out) if args.out else (results if results.is_dir() else results.parent) / "report"
    if out.exists() and not out.is_dir():
        from gscodec_shac.errors import OutputError

        raise OutputError(f"{out}: the report folder is a file")
    # a report this command wrote before is regenerated in place; other files need --force
    check_outputs([out / "report.md", out / "report.html", out / "bd.json", out / "bd.csv"],
                  force=args.force or _own_report(out), what="report")
    paths = write_report(args.results, args.out, anchor=args.anchor, x_axis=args.x_axis, title=args.title,
                         figure_prefix=args.prefix)
    rows = load_results(args.results)
    settings = _settings(args.results)
    anchor = args.anchor or settings.get("anchor") or "baseline"
    table = bd_table(rows, anchor, settings.get("compare"))
    for entry in table:
        if entry["metric"] in ("psnr_gt", "psnr_ref"):
            rate = f"{entry['bd_rate_pct']:+.1f}%" if entry["bd_rate_pct"] is not None else "n/a"
            gain = f"{entry['bd_quality']:+.3f} dB" if entry["bd_quality"] is not None else "n/a"
            print(f"{entry['scene']}\t{bd_label(entry)}\t{entry['metric']}\tBD-rate {rate}\tBD-PSNR {gain}")
    print(f"report: {paths['markdown']}; page with renders: {paths['html']}")
    return 0


def _settings(results: str) -> dict:
    """The sweep's settings (anchor, compare) from RESULTS/sweep.json; empty without one."""
    import json
    from pathlib import Path

    sweep = Path(results) / "sweep.json"
    if sweep.is_file():
        return json.loads(sweep.read_text()).get("settings") or {}
    return {}


def _own_report(out) -> bool:
    """True when ``out`` holds a report rd-report wrote: report.md plus a bd.json of BD rows."""
    import json

    if not (out / "report.md").is_file() or not (out / "bd.json").is_file():
        return False
    try:
        table = json.loads((out / "bd.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(table, list) and all(isinstance(r, dict) and "bd_rate_pct" in r for r in table)
