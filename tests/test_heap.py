"""gscodec_shac.heap: glibc's trim threshold set once at start-up, a no-op without glibc."""

import ctypes
import platform

import pytest

from gscodec_shac import heap


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="needs glibc")
def test_glibc_takes_the_trim_threshold():
    assert heap.trim_freed_memory() is True


def test_without_a_c_library_nothing_happens(monkeypatch):
    def no_library(name):
        raise OSError("no C library")

    monkeypatch.setattr(ctypes, "CDLL", no_library)
    assert heap.trim_freed_memory() is False


def test_a_c_library_without_mallopt_is_left_alone(monkeypatch):
    monkeypatch.setattr(ctypes, "CDLL", lambda name: object())
    assert heap.trim_freed_memory() is False


@pytest.mark.parametrize("argv, trims", [
    (["decode", "in.gsc", "out.ply"], False),
    (["convert", "in.spz", "out.ply"], True),
    (["encode", "in.ply", "out.gsc", "-r", "shac_ladder:rp4"], True),
    (["encode", "in.ply", "out.gsc", "--target-bpg", "50"], False),
    (["encode", "in.ply", "out.gsc", "--target-size", "2MB"], False),
    (["encode", "in.ply", "out.gsc", "--target-psnr", "40"], False),
    (["render", "in.ply", "out", "--cameras", "cameras.json"], False),
])
def test_only_one_pass_commands_return_freed_memory(argv, trims):
    """A trim threshold of 0 makes glibc map large blocks afresh each time: kept for the one-pass
    encodes and conversions (their peak memory), not for decodes (20% of their time, their peak well
    inside the bar) nor runs that render the same cloud many times."""
    from gscodec_shac.cli import build_parser

    assert heap.returns_freed_memory(build_parser().parse_args(argv)) is trims
