"""The test tiers: `make test` (everything) and `make test-fast` (without tests/slow_tests.txt)."""

import re
import sys

from tests.conftest import REPO_ROOT, slow_entries

sys.path.insert(0, str(REPO_ROOT / "scripts"))
import slow_tests  # noqa: E402


def test_every_slow_entry_names_an_existing_test():
    entries = slow_entries()
    assert entries, "tests/slow_tests.txt is empty: make test-fast would run everything"
    for entry in entries:
        module, _, name = entry.partition("::")
        path = REPO_ROOT / module
        assert path.is_file(), entry
        if name:
            function = re.sub(r"\[.*\]$", "", name.split("::")[-1])
            assert re.search(rf"def {re.escape(function)}\(", path.read_text()), entry


def test_make_targets_show_skip_reasons_and_split_on_the_marker():
    makefile = (REPO_ROOT / "Makefile").read_text()
    full = re.search(r"^test:.*\n\t(.*)$", makefile, re.M).group(1)
    fast = re.search(r"^test-fast:.*\n\t(.*)$", makefile, re.M).group(1)
    assert "-rs" in full and "not slow" not in full
    assert "-rs" in fast and '-m "not slow"' in fast


def test_the_longest_tests_go_until_the_rest_fits_the_share():
    times = {"tests/test_a.py::x": 50.0, "tests/test_a.py::y": 1.0, "tests/test_b.py::p[1]": 30.0,
             "tests/test_b.py::p[2]": 9.0, "tests/test_c.py::q": 10.0}
    entries = dict(slow_tests.slow_set(times, share=0.25))  # total 100: at most 25 s stay
    # a's slow test is 98% of its time: the whole module; b's is 77%: that test alone
    assert entries == {"tests/test_a.py": 51.0, "tests/test_b.py::p[1]": 30.0}
