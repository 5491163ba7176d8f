"""Atomic outputs: all or nothing, and one clear error for a missing folder."""

import pytest

from gscodec_shac.atomic import atomic_output, write_atomic
from gscodec_shac.errors import PlyFormatError


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_output(target) as handle:
            handle.write(b"half")
            raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.bin"]


def test_a_write_replaces_the_file(tmp_path):
    target = write_atomic(tmp_path / "out.bin", b"new", fsync=True)
    assert target.read_bytes() == b"new"


def test_missing_folder_raises_the_callers_error_or_is_created(tmp_path):
    with pytest.raises(PlyFormatError, match="output directory .* does not exist"):
        write_atomic(tmp_path / "no" / "out.ply", b"x", error=PlyFormatError)
    assert write_atomic(tmp_path / "made" / "out.bin", b"x", make_dirs=True).read_bytes() == b"x"
