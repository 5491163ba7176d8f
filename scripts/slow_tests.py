"""Write tests/slow_tests.txt, the list of tests ``make test-fast`` leaves out, from measured durations.

Reads pytest JUnit XML files (``pytest --junitxml=...``; each test's time includes its setup
and teardown) and marks slow the longest tests until the remaining ones take at most
``--share`` of the measured total. A module whose tests are mostly slow is listed whole.

    nice -n 5 python -m pytest -p no:cacheprovider --junitxml=/tmp/dur/all.xml
    python scripts/slow_tests.py /tmp/dur/*.xml --share 0.35 > tests/slow_tests.txt

The list is applied by tests/conftest.py (marker ``slow``); ``make test`` runs everything.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

#: A module is listed whole when its slow tests hold this share of its time.
WHOLE_MODULE = 0.9


def read_durations(paths: list[Path]) -> dict[str, float]:
    """Seconds per test node id (``tests/test_x.py::name[param]``) over all files."""
    times: dict[str, float] = {}
    for path in paths:
        for case in ET.parse(path).getroot().iter("testcase"):
            module = case.get("classname", "").replace(".", "/")
            parts = module.split("/")
            # classname is tests.test_x or tests.test_x.TestClass
            if len(parts) > 2:
                node = f"{'/'.join(parts[:2])}.py::{'::'.join(parts[2:])}::{case.get('name')}"
            else:
                node = f"{module}.py::{case.get('name')}"
            times[node] = times.get(node, 0.0) + float(case.get("time", 0.0))
    return times


def slow_set(times: dict[str, float], share: float) -> list[tuple[str, float]]:
    """The longest tests until the rest take at most ``share`` of the total; modules folded in."""
    total = sum(times.values())
    remaining = total
    slow: dict[str, float] = {}
    for node, seconds in sorted(times.items(), key=lambda item: -item[1]):
        if remaining <= share * total:
            break
        slow[node] = seconds
        remaining -= seconds
    by_module: dict[str, list[str]] = defaultdict(list)
    for node in times:
        by_module[node.split("::")[0]].append(node)
    entries: list[tuple[str, float]] = []
    for module, nodes in sorted(by_module.items()):
        module_time = sum(times[n] for n in nodes)
        slow_time = sum(slow.get(n, 0.0) for n in nodes)
        if slow_time and slow_time >= WHOLE_MODULE * module_time:
            entries.append((module, module_time))
        else:
            entries += [(n, slow[n]) for n in nodes if n in slow]
    return entries


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("xml", nargs="+", type=Path, help="pytest --junitxml files")
    parser.add_argument("--share", type=float, default=0.35, help="time share left to the fast tier (default 0.35)")
    args = parser.parse_args(argv)
    times = read_durations(args.xml)
    entries = slow_set(times, args.share)
    total, slow = sum(times.values()), sum(t for _, t in entries)
    print(f"# Tests `make test-fast` leaves out (marker `slow`, applied in tests/conftest.py).\n"
          f"# Made by scripts/slow_tests.py --share {args.share} from {len(times)} measured tests: "
          f"{total:.0f} s in all, {slow:.0f} s listed here, {total - slow:.0f} s left to the fast tier.\n"
          f"# One node id or module per line; the number is the measured seconds (under load).")
    for node, seconds in entries:
        print(f"{node}  # {seconds:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
