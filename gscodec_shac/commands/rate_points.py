"""``gscodec-shac rate-points [SET]``: the shipped rate-point sets, or one set's points and QPs.

Without SET: every file of ``rate_points/`` with its description and points. With SET (a
shipped name such as ``paper_table3``, a YAML file, or ``SET:POINT`` for one point): a table
of its points with the QP and bit depth of every attribute, the position coding, the SH
stage and how its QPs are allocated; settings all points share are listed above the table.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gscodec_shac.commands._options import add_command, add_json

#: Attributes coded at a QP, in coding order.
COLUMNS = ("opacity", "rotation", "scale", "sh_dc", "sh_ac", "sh_features")
#: Columns a set's table always has (other settings are listed above it when every point shares them).
TABLE = ("positions", *COLUMNS)
#: What the table's cells mean.
LEGEND = ("Cells are QP/bits: the QP of the lossy codec (a list: one QP per SH degree 1, 2, 3) and the "
          "bit depth; lossless/bits: coded without loss. positions: codec, layout (split8: two 8-bit planes; "
          "single: one plane; set: a Morton-sorted set of codes whose order is the grid order) and bits. sh_ac "
          "codes the AC coefficients (SH stages none, trunc), sh_features the features of pca and lst "
          "(allocation waterfill: one QP per feature from this base QP), sh_labels the labels of vq.")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "rate-points",
        help="list the shipped rate-point sets, or the points and QPs of one",
        description="Without SET: the shipped rate-point sets (rate_points/*.yaml) with their description "
        "and points. With SET: a table of its points, the QP and bit depth of every attribute (QP/bits; "
        "'lossless' when coded without loss; an SH ladder gives one QP per SH degree 1, 2, 3), the position "
        "coding, the SH stage and its QP allocation. Use a point as --rate-point SET:POINT.",
        examples=["gscodec-shac rate-points", "gscodec-shac rate-points paper_table3",
                  "gscodec-shac rate-points shac_ladder:rp4 --json"],
    )
    parser.add_argument("set", nargs="?", metavar="SET",
                        help="a shipped set (e.g. paper_table3, mpeg_ctc_video, shac_ladder, shac_auto), a rate-point "
                        "YAML file, or SET:POINT for one point")
    add_json(parser, "the sets or points (every resolved setting)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    if args.set is None:
        sets = list_sets()
        print(json.dumps(sets, indent=2) if args.json else format_sets(sets))
        return 0
    described = describe_set(args.set)
    print(json.dumps(described, indent=2) if args.json else format_set(described))
    return 0


# ------------------------------------------------------------------ data
def list_sets() -> list[dict[str, Any]]:
    """Every shipped rate-point file: name, file, description, source and point names."""
    from gscodec_shac.codec.rate_points import builtin_rate_point_files, load_rate_point_file

    return [{"set": name, "file": str(path), **_file_text(path), "points": list(load_rate_point_file(path))}
            for name, path in builtin_rate_point_files().items()]


def describe_set(reference: str) -> dict[str, Any]:
    """One set (or one point of it): its file's text and every point resolved (``RatePoint.to_json``)."""
    from gscodec_shac.codec.rate_points import builtin_rate_point_files, load_rate_point_file
    from gscodec_shac.errors import RatePointError

    builtin = builtin_rate_point_files()
    path, point = _split(reference, builtin)
    if path is None:
        raise RatePointError(f"unknown rate-point set {reference!r}; shipped: {', '.join(builtin)} (or give a "
                             ".yaml file)")
    points = load_rate_point_file(path)
    if point is not None and point not in points:
        raise RatePointError(f"{path}: no rate point {point!r}; it has {', '.join(points)}")
    name = path.stem if builtin.get(path.stem) == path else str(path)
    chosen = {k: v for k, v in points.items() if point is None or k == point}
    return {"set": name, "file": str(path), **_file_text(path),
            "points": {k: v.to_json() for k, v in chosen.items()}}


def _split(reference: str, builtin: dict[str, Path]) -> tuple[Path | None, str | None]:
    """``SET``, ``SET:POINT``, ``FILE.yaml`` or ``FILE.yaml:POINT`` -> (file, point)."""
    if reference in builtin:
        return builtin[reference], None
    if Path(reference).is_file():
        return Path(reference), None
    head, sep, point = reference.rpartition(":")
    if sep and head in builtin:
        return builtin[head], point
    if sep and Path(head).is_file():
        return Path(head), point
    if Path(reference).suffix in (".yaml", ".yml"):
        from gscodec_shac.errors import RatePointError

        raise RatePointError(f"{reference}: no such rate-point file")
    return None, None


def _file_text(path: Path) -> dict[str, str]:
    """The file-level ``description`` and ``source`` of a rate-point YAML."""
    from gscodec_shac.errors import RatePointError
    from gscodec_shac.yaml_file import read_yaml_file

    data = read_yaml_file(path, "rate-point file", RatePointError)
    data = data if isinstance(data, dict) else {}
    return {key: " ".join(str(data.get(key) or "").split()) for key in ("description", "source")}


# ------------------------------------------------------------------ text
def format_sets(sets: list[dict[str, Any]]) -> str:
    """One line per shipped set: name, points, description."""
    width = max(len(s["set"]) for s in sets)
    lines = [f"{'set':<{width}}  points / description"]
    for entry in sets:
        lines.append(f"{entry['set']:<{width}}  {', '.join(entry['points'])}")
        lines.append(f"{'':<{width}}    {entry['description']}")
    lines.append("")
    lines.append("A set's points and QPs: gscodec-shac rate-points SET; use a point: "
                 "gscodec-shac encode IN OUT --rate-point SET:POINT")
    return "\n".join(lines)


def format_set(described: dict[str, Any]) -> str:
    """The set's text, the settings its points share, and a table with one row per point."""
    import textwrap

    points = described["points"]
    lines = [f"{described['set']}: {described['description']}" if described["description"] else described["set"]]
    if described["source"]:
        lines.append(f"source: {described['source']}")
    lines.append(f"file:   {described['file']}")
    cells = {name: _cells(point) for name, point in points.items()}
    first = next(iter(cells.values()))
    shared = {key: first[key] for key in first
              if key not in TABLE and len({str(c[key]) for c in cells.values()}) == 1}
    lines.append("")
    lines += [f"{key + ':':<15} {value}" for key, value in shared.items() if value is not None]
    columns = ["point", *[k for k in first if k not in shared]]
    rows = [[name, *[str(cell[k]) for k in columns[1:]]] for name, cell in cells.items()]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(columns)]
    lines.append("")
    lines.append("  ".join(h.ljust(w) for h, w in zip(columns, widths)).rstrip())
    for row in rows:
        lines.append("  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip())
    lines.append("")
    lines += textwrap.wrap(LEGEND, 100)
    return "\n".join(lines)


def _cells(point: dict[str, Any]) -> dict[str, Any]:
    """The displayed settings of one resolved point (``RatePoint.to_json``)."""
    from gscodec_shac.shac.base import STAGES

    attributes = point["attributes"]
    codec = attributes["opacity"]["codec"]
    out: dict[str, Any] = {
        "codec": f"{codec} ({_options(attributes['opacity']['options'])})" if attributes["opacity"]["options"]
        else codec,
        "positions": _positions(attributes["positions"]),
    }
    for name in COLUMNS:
        out[name] = _qp_bits(attributes[name], codec)
    sh = dict(point["sh"])
    stage = sh.pop("stage")
    labelled = stage in STAGES and STAGES.get(stage).rate_attribute == "sh_labels"  # vq, vq-pca
    out["sh_labels"] = _qp_bits(attributes["sh_labels"], codec) if labelled else None
    out["SH stage"] = " ".join([stage, *(f"{k}={v}" for k, v in sh.items())])
    out["SH allocation"] = attributes["sh_features"].get("allocation", "degree")
    out["colour"] = point["color"]
    set_coded = attributes["positions"]["layout"] == "set"
    out["sort"] = "morton order of the positions" if set_coded else _sort(point["sort"])
    out["prune"] = _prune(point["prune"])
    out["tiers"] = _tiers(point.get("tiers"))
    return out


def _tiers(tiers: dict[str, list] | None) -> str | None:
    """``by importance: 50% QP -3, then 50% QP +8`` (and ``, the offsets scaled by the scene's importance``
    with ``spread``), or None without tiers (codec/tiers.py)."""
    if not tiers:
        return None
    parts = [f"{100 * share:g}% QP {offset:+d}" for share, offset in zip(tiers["shares"], tiers["qp_offsets"])]
    spread = ", the offsets scaled by the scene's importance" if tiers.get("spread") == "importance" else ""
    return "by importance: " + ", then ".join(parts) + spread


def _prune(prune: dict[str, float]) -> str:
    """``opacity < 0.01, keep the most important 60%`` or ``none``."""
    parts = [f"opacity < {prune['min_opacity']:g}"] if prune["min_opacity"] else []
    if prune.get("keep_share", 1.0) < 1.0:
        parts.append(f"keep the most important {100 * prune['keep_share']:g}%")
    return ", ".join(parts) or "none"


def _qp_bits(spec: dict[str, Any], codec: str) -> str:
    qp = spec["qp"]
    text = "lossless" if qp is None else ",".join(map(str, qp)) if isinstance(qp, list) else str(qp)
    prefix = "" if spec["codec"] == codec else f"{spec['codec']} "
    return f"{prefix}{text}/{spec['bits']}"


def _positions(spec: dict[str, Any]) -> str:
    """How positions are coded: a Morton-sorted set, or a lossless grid codec and layout."""
    if spec["layout"] == "set":
        return f"set lossless/{spec['bits']}"
    return f"{spec['codec']} {spec['layout']} lossless/{spec['bits']}"


def _sort(sort: dict[str, Any]) -> str:
    weights = " ".join(f"{k}={v:g}" for k, v in sort["weights"].items() if v)
    return (f"{sort['method']} (weights {weights}; grid sides a multiple of {sort['multiple']}, "
            f"policy {sort['policy']}, seed {sort['seed']})")


def _options(options: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v}" for k, v in options.items())
