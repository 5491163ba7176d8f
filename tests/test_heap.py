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
