"""The fast fuzz suite (every CI run): damaged inputs never crash a reader.

``.gsc``: every truncation offset of a small stream, and seeded mutations of one stream per
SH stage plus the legacy fixtures (byte edits, re-signed edits, structured header and
stage-state edits, consistent size lies), each through ``decode`` and ``info``. Models: for
every format (dynamic directory, SPZ v1-v4, .splat, SOG bundle and folder, compressed.ply,
gsplat .pt) truncations, byte edits and every kind of hostile value, read in-process, and
one hostile case of each format through ``gscodec-shac info`` in a child process. Each
outcome must be a valid result or one clean :class:`GscodecError`; a failure names the case,
which ``tests.fuzzlib.gsc.make_case(family, seed, seed_index, index)`` or
``tests.fuzzlib.models.make_case(seed, family, index)`` rebuilds. The long run is
``scripts/fuzz.py`` (docs/reliability.md).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from tests.fuzzlib import gsc as fuzz
from tests.fuzzlib import models

FIXTURES = Path(__file__).parent / "fixtures" / "streams"
#: Mutated streams per family (each through decode and info): 1,250 in all.
PER_FAMILY = 250
#: Model cases per format: truncations (spread over every member), byte edits, hostile values.
MODEL_CASES = {"truncate": 60, "bytes": 150, "hostile": 45}
CASE_SECONDS = 10.0


@pytest.fixture(scope="module")
def seeds() -> list[tuple[str, bytes]]:
    return list(fuzz.seed_streams(200, fixtures=FIXTURES).items())


def _check(outcomes: list[tuple[str, str, int, fuzz.Outcome]]) -> Counter:
    kinds = Counter(outcome.kind for *_, outcome in outcomes)
    crashes = [f"{target} of {where} case {index}: {o.detail}" for target, where, index, o in outcomes
               if o.kind not in ("valid", "error")]
    assert not crashes, f"{len(crashes)} crashes, first: {crashes[:5]}"
    # a child process is judged by its CPU time (tests/fuzzlib/cli.py: past the limit it is a hang)
    slow = [(target, where, index, o.seconds) for target, where, index, o in outcomes
            if o.seconds > CASE_SECONDS and target != "cli"]
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


@pytest.fixture(scope="module")
def model_seeds() -> dict[str, models.Seed]:
    return models.make_seeds()


def _model_outcomes(seed: models.Seed, family: str, count: int, *, cli: bool = False):
    cuts = len(models.truncation_cases(seed))
    for n in range(count):
        index = n * cuts // count if family == "truncate" else n
        files, links = models.make_case(seed, family, index)
        outcome = models.run_cli(seed, files, links) if cli else models.run_case(seed, files, links)
        yield "cli" if cli else "read", f"{seed.fmt}/{family}", index, outcome


@pytest.mark.parametrize("fmt", models.FORMATS)
def test_every_model_reader_survives_its_fuzz_sample(model_seeds, fmt):
    seed = model_seeds[fmt]
    assert models.run_case(seed, dict(seed.files), {}).kind == "valid"
    outcomes = [item for family, count in MODEL_CASES.items() for item in _model_outcomes(seed, family, count)]
    kinds = _check(outcomes)
    assert kinds["error"] > len(outcomes) // 2  # the damage does reach the checks


@pytest.mark.parametrize("fmt", models.FORMATS)
def test_hostile_model_files_through_the_command_line_are_one_error_line(model_seeds, fmt):
    """One hostile case of each kind per format through ``gscodec-shac info`` in a child process:
    exit status 0, 2, 3 or 5 with one ``error:`` line, never 70, a signal or a hang."""
    seed = model_seeds[fmt]
    outcomes = list(_model_outcomes(seed, "hostile", len(models.HOSTILE[fmt]), cli=True))
    _check(outcomes)
