"""A zip writer that writes what it is told: any member name, method, declared size or CRC.

``zipfile`` refuses to write the lies a hostile file holds; the fuzz cases need them. A
member is ``Member(name, data)`` (stored) plus optional overrides; :func:`build` lays the
members out as local headers and data, a central directory and its end record, the way
every zip writer does (PKWARE APPNOTE 4.3.7, 4.3.12, 4.3.16).
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from dataclasses import dataclass, replace

_LOCAL = struct.Struct("<IHHHHHIIIHH")
_CENTRAL = struct.Struct("<IHHHHHHIIIHHHHHII")
_END = struct.Struct("<IHHHHIIH")


@dataclass(frozen=True)
class Member:
    """One member: ``stored`` holds the bytes as written (already deflated for method 8)."""

    name: str
    stored: bytes
    method: int = 0
    size: int | None = None  # declared uncompressed size (default: the real one)
    crc: int | None = None  # declared CRC (default: the real one)
    raw: bytes | None = None  # the uncompressed bytes (for the real size and CRC)
    flags: int = 0

    def declared(self) -> tuple[int, int]:
        raw = self.raw if self.raw is not None else self.stored
        return (self.size if self.size is not None else len(raw),
                self.crc if self.crc is not None else zlib.crc32(raw))


def deflated(name: str, data: bytes) -> Member:
    """A deflated member (raw deflate, as zip stores it)."""
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return Member(name, packer.compress(data) + packer.flush(), method=8, raw=data)


def members_of(data: bytes) -> list[Member]:
    """The members of a well-formed zip, re-stored (their bytes inflated, written stored)."""
    import io

    with zipfile.ZipFile(io.BytesIO(data)) as bundle:
        return [Member(info.filename, bundle.read(info)) for info in bundle.infolist()]


def build(members: list[Member]) -> bytes:
    """The zip file of ``members`` (no data descriptors, no zip64)."""
    out, central = bytearray(), bytearray()
    for member in members:
        name = member.name.encode("utf-8")
        size, crc = member.declared()
        offset = len(out)
        out += _LOCAL.pack(0x04034B50, 20, member.flags, member.method, 0, 0x21, crc, len(member.stored), size,
                           len(name), 0) + name + member.stored
        central += _CENTRAL.pack(0x02014B50, 20, 20, member.flags, member.method, 0, 0x21, crc, len(member.stored),
                                 size, len(name), 0, 0, 0, 0, 0, offset) + name
    start = len(out)
    out += central
    out += _END.pack(0x06054B50, 0, 0, len(members), len(members), len(central), start, 0)
    return bytes(out)


__all__ = ["Member", "build", "deflated", "members_of", "replace"]
