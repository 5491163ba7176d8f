"""The fast fuzz suite (every CI run): damaged streams never crash ``decode`` or ``info``.

Every truncation offset of a small stream, and a few thousand seeded mutations of one
stream per SH stage plus the legacy fixtures (byte edits, re-signed edits, structured
header and stage-state edits, consistent size lies), each through both targets. Each
outcome must be a valid result or one clean :class:`GscodecError`; a failure names the
case, which ``gscodec_shac.fuzz.make_case(family, seed, seed_index, index)`` rebuilds.
The long run is ``scripts/fuzz.py`` (docs/reliability.md).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from tests.fuzzlib import gsc as fuzz

FIXTURES = Path(__file__).parent / "fixtures" / "streams"
#: Mutated streams per family (each through decode and info): 2,500 in all.
PER_FAMILY = 500
CASE_SECONDS = 10.0


@pytest.fixture(scope="module")
def seeds() -> list[tuple[str, bytes]]:
    return list(fuzz.seed_streams(200, fixtures=FIXTURES).items())


def _check(outcomes: list[tuple[str, str, int, fuzz.Outcome]]) -> Counter:
    kinds = Counter(outcome.kind for *_, outcome in outcomes)
    crashes = [f"{target} of {where} case {index}: {o.detail}" for target, where, index, o in outcomes
               if o.kind not in ("valid", "error")]
    assert not crashes, f"{len(crashes)} crashes, first: {crashes[:5]}"
    slow = [(target, where, index, o.seconds) for target, where, index, o in outcomes if o.seconds > CASE_SECONDS]
    assert not slow, f"cases slower than {CASE_SECONDS} s: {slow[:5]}"
    return kinds


def test_every_truncation_of_a_small_stream_is_one_clean_error(seeds):
    name, data = next((n, d) for n, d in seeds if n == "stage_pca")
    outcomes = [(target, name, cut, fuzz.run_case(target, data[:cut]))
                for cut in range(len(data)) for target in fuzz.TARGETS]
    kinds = _check(outcomes)
    assert kinds == {"error": 2 * len(data)}  # no prefix is a whole stream
    assert fuzz.run_case("decode", data).kind == fuzz.run_case("info", data).kind == "valid"


@pytest.mark.parametrize("family", [f for f in fuzz.FAMILIES if f != "truncate"])
def test_seeded_mutations_never_crash(seeds, family):
    outcomes = []
    for index in range(PER_FAMILY):
        seed_index = index % len(seeds)
        name, data = seeds[seed_index]
        case = fuzz.make_case(family, data, seed_index, index)
        for target in fuzz.TARGETS:
            outcomes.append((target, f"{family}/{name}", index, fuzz.run_case(target, case)))
    kinds = _check(outcomes)
    assert kinds["error"] > 0  # the mutations do reach the checks


def test_cases_are_reproducible(seeds):
    name, data = seeds[0]
    for family in fuzz.FAMILIES[1:]:
        assert fuzz.make_case(family, data, 0, 7) == fuzz.make_case(family, data, 0, 7)
        assert fuzz.make_case(family, data, 0, 7) != fuzz.make_case(family, data, 0, 8)


def test_seeds_cover_every_sh_stage(seeds):
    from gscodec_shac.codec.container import Bitstream

    stages = {Bitstream.from_bytes(data).header["sh"]["stage"] for name, data in seeds if name.startswith("stage_")}
    assert stages == set(fuzz.SEED_STAGES)
