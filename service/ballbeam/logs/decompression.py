"""Bounded decompression of MCAP chunks: the one place this project inflates data from a file.

A chunk states its uncompressed size. Compressed data is never trusted to agree: a few KiB of
zstd or lz4 can inflate to gigabytes, and the libraries' own one-shot calls size their output
from the *frame's* header (or not at all) rather than from the chunk. Here a chunk that states
N bytes yields exactly N bytes or an error, and no more than N (+1, to see an excess) is ever
allocated for its output; N itself is bounded by :data:`MAX_CHUNK_BYTES`.
"""

from __future__ import annotations

import importlib
from typing import Any

import zstandard

from ballbeam.errors import DecompressionBombError, LogFormatError

_lz4: Any
try:  # lz4 is optional for us (our writer uses zstd); the mcap library brings it
    _lz4 = importlib.import_module("lz4.frame")
except ImportError:  # pragma: no cover - depends on the environment
    _lz4 = None

# A chunk that decompresses past this is not one of ours (they are about 1 MiB; other writers'
# defaults are a few MiB): a hostile chunk cannot make a reader allocate more.
MAX_CHUNK_BYTES = 64 << 20
# Streaming zstd (a frame that does not state its size) keeps a window: at most this much (the
# largest that zstd's levels up to 19 use).
_MAX_ZSTD_WINDOW_BYTES = 8 << 20


def decompress_chunk(compression: str, data: bytes | memoryview, uncompressed_size: int) -> bytes:
    """The ``uncompressed_size`` bytes that ``data`` holds under ``compression`` ("zstd", "lz4"
    or "" for none). DecompressionBombError if it would inflate past that size or the size is
    beyond :data:`MAX_CHUNK_BYTES`; LogFormatError if it does not decompress to exactly it."""
    if uncompressed_size > MAX_CHUNK_BYTES:
        raise DecompressionBombError(
            f"chunk claims {uncompressed_size} bytes uncompressed (more than the "
            f"{MAX_CHUNK_BYTES >> 20} MiB any log of ours holds in one chunk)"
        )
    try:
        if compression == "zstd":
            out = _zstd(data, uncompressed_size)
        elif compression == "lz4":
            out = _lz4_frame(data, uncompressed_size)
        elif compression == "":
            out = bytes(data)
        else:
            raise LogFormatError(f"unknown chunk compression {compression!r}")
    except (zstandard.ZstdError, ValueError, RuntimeError) as exc:
        if isinstance(exc, LogFormatError):
            raise
        raise LogFormatError(f"{compression} data does not decompress: {exc}") from exc
    if len(out) > uncompressed_size:
        raise DecompressionBombError(
            f"chunk inflates past the {uncompressed_size} bytes it states; refused"
        )
    if len(out) != uncompressed_size:
        raise LogFormatError(
            f"chunk decompresses to {len(out)} bytes, not the {uncompressed_size} stated"
        )
    return out


def _zstd(data: bytes | memoryview, uncompressed_size: int) -> bytes:
    declared = zstandard.frame_content_size(data)
    if declared == uncompressed_size:
        # One shot into a buffer of exactly the stated size: it cannot write past it.
        return bytes(zstandard.ZstdDecompressor().decompress(data))
    if declared > uncompressed_size:
        raise DecompressionBombError(
            f"chunk states {uncompressed_size} bytes but its zstd frame says {declared}; refused"
        )
    if declared != -1:
        raise LogFormatError(
            f"chunk states {uncompressed_size} bytes but its zstd frame says {declared}"
        )
    # A frame without its size: stream it and stop one byte past the stated size. Output and
    # window are both bounded (zstd refuses a frame that wants a larger window).
    decompressor = zstandard.ZstdDecompressor(max_window_size=_MAX_ZSTD_WINDOW_BYTES)
    with decompressor.stream_reader(data, read_across_frames=False) as reader:
        return bytes(reader.read(uncompressed_size + 1))


def _lz4_frame(data: bytes | memoryview, uncompressed_size: int) -> bytes:
    if _lz4 is None:
        raise LogFormatError("chunk is lz4-compressed and the lz4 module is missing")
    declared = _lz4.get_frame_info(data).get("content_size", 0)
    if declared > uncompressed_size:
        raise DecompressionBombError(
            f"chunk states {uncompressed_size} bytes but its lz4 frame says {declared}; refused"
        )
    if declared not in (0, uncompressed_size):  # 0: the frame does not state its size
        raise LogFormatError(
            f"chunk states {uncompressed_size} bytes but its lz4 frame says {declared}"
        )
    # max_length bounds the output (and its buffer): one byte more than stated shows an excess.
    out = _lz4.LZ4FrameDecompressor().decompress(data, max_length=uncompressed_size + 1)
    return bytes(out)

