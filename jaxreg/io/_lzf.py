"""LZF, the byte-oriented LZ77 codec of liblzf that PCL and Open3D use for PCD files stored
as ``DATA binary_compressed``.

A stream is a sequence of tokens, each opened by a control byte ``c``:

* ``c < 32``: a literal run of ``c + 1`` bytes follows;
* ``c >= 32``: a back-reference of length ``(c >> 5) + 2`` (when ``c >> 5 == 7`` the next
  byte is added to the length) starting ``((c & 31) << 8 | next byte) + 1`` bytes behind the
  end of the output. The source may overlap the bytes being written (a run).

The stream carries no sizes: the caller supplies the decompressed length (PCD stores it in
front of the stream) and :func:`decompress` checks that the stream expands to exactly that.

Why a codec of our own: reading and writing compressed PCD files then needs nothing beyond
numpy (the PyPI bindings of liblzf, ``lzf`` and ``lzf-python``, are not dependencies of
jaxreg). The decoder's Python loop runs once per token and copies each token with one slice;
the encoder finds every position's most recent 3-byte match with one vectorized sort per
64 KiB block, so its Python loop also runs once per emitted token. On PCL's 640x480 RGB-D
frames (4.9 MB decompressed) that is roughly 10-20 MB/s decoding (0.3 s a frame) and 2-3 MB/s
encoding, its output no larger than PCL's: ample for files, not for streaming.
"""

from __future__ import annotations

import bisect

import numpy as np

__all__ = ["compress", "decompress"]

_MAX_LITERAL = 32
_MAX_MATCH = 264  # 2 + 7 + 255
_MAX_DISTANCE = 8192
_MAX_EXPANSION = 88  # a 3-byte long back-reference writes at most 264 bytes
_BLOCK = 1 << 16  # positions whose match candidates are found in one vectorized pass


def decompress(src: bytes, out_len: int) -> bytearray:
    """Decodes the LZF stream ``src`` that must expand to exactly ``out_len`` bytes.

    Raises:
        ValueError: ``out_len`` exceeds what ``len(src)`` bytes can expand to (checked before
            anything is allocated), the stream is truncated, a back-reference points before
            the start of the output, or the output is longer or shorter than ``out_len``.
    """
    n = len(src)
    if out_len > _MAX_EXPANSION * n:
        raise ValueError(
            f"LZF cannot expand {n} bytes to {out_len} bytes (it expands at most {_MAX_EXPANSION}x)"
        )
    out = bytearray(out_len)
    ip = op = 0
    while ip < n:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n:
                raise ValueError(f"LZF stream truncated inside a literal run at byte {ip - 1}")
            if op + length > out_len:
                raise ValueError(f"LZF stream expands beyond the declared {out_len} bytes")
            out[op : op + length] = src[ip : ip + length]
            ip += length
            op += length
            continue
        length = ctrl >> 5
        if length == 7:
            if ip >= n:
                raise ValueError(f"LZF stream truncated inside a back-reference at byte {ip - 1}")
            length += src[ip]
            ip += 1
        if ip >= n:
            raise ValueError(f"LZF stream truncated inside a back-reference at byte {ip - 1}")
        distance = ((ctrl & 31) << 8 | src[ip]) + 1
        ip += 1
        length += 2
        ref = op - distance
        if ref < 0:
            raise ValueError(f"LZF back-reference points {-ref} bytes before the start")
        if op + length > out_len:
            raise ValueError(f"LZF stream expands beyond the declared {out_len} bytes")
        if distance >= length:
            out[op : op + length] = out[ref : ref + length]
        else:  # overlapping copy: the output repeats with period `distance`
            period = out[ref:op]
            out[op : op + length] = (period * (length // distance + 1))[:length]
        op += length
    if op != out_len:
        raise ValueError(f"LZF stream ends after {op} of the declared {out_len} bytes")
    return out


def _literals(out: bytearray, data: bytes, start: int, stop: int) -> None:
    for s in range(start, stop, _MAX_LITERAL):
        e = min(s + _MAX_LITERAL, stop)
        out.append(e - s - 1)
        out += data[s:e]


def _candidates(data: bytes, start: int, stop: int) -> tuple[list[int], list[int]]:
    """The positions ``i`` in ``[start, stop)`` whose next three bytes also start at most
    8192 bytes earlier, and the most recent such earlier position ``p`` of each.

    Found with one stable sort of the 3-byte keys over the window the positions can reach.
    """
    lo = max(start - _MAX_DISTANCE, 0)
    b = np.frombuffer(data, np.uint8, count=stop + 2 - lo, offset=lo).astype(np.int32)
    key = (b[:-2] << 16) | (b[1:-1] << 8) | b[2:]
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    prev = np.full(len(key), -1, np.int64)
    prev[order[1:][same]] = order[:-1][same]
    pos = np.arange(len(key))
    usable = (prev >= 0) & (pos - prev <= _MAX_DISTANCE) & (pos >= start - lo)
    return (pos[usable] + lo).tolist(), (prev[usable] + lo).tolist()


def compress(data: bytes) -> bytes:
    """Greedy LZF compression of ``data``, decodable by liblzf (PCL, Open3D) and `decompress`.

    Each position is matched against the most recent earlier occurrence of its next three
    bytes (`_candidates`, vectorized over blocks of the input), so the Python loop runs
    once per emitted token rather than once per byte.
    """
    n = len(data)
    out = bytearray()
    literal_start = 0
    for block in range(0, max(n - 2, 0), _BLOCK):
        candidates, sources = _candidates(data, block, min(block + _BLOCK, n - 2))
        c = 0
        while True:
            c = bisect.bisect_left(candidates, literal_start, c)
            if c == len(candidates):
                break
            i, p = candidates[c], sources[c]
            limit = min(_MAX_MATCH, n - i)
            if data[p : p + limit] == data[i : i + limit]:
                length = limit
            else:  # three bytes match by construction; a mismatch lies before `limit`
                length = 3
                while data[p + length] == data[i + length]:
                    length += 1
            _literals(out, data, literal_start, i)
            offset = i - p - 1
            if length < 9:
                out += bytes(((length - 2) << 5 | offset >> 8, offset & 255))
            else:
                out += bytes((7 << 5 | offset >> 8, length - 9, offset & 255))
            literal_start = i + length
    _literals(out, data, literal_start, n)
    return bytes(out)
