"""Image files read safely: every frame reader (``detect``, ``track``, ``eval``, ``replay``,
the console's folder source, the dataset loader, the calibration sets) goes through here.

Two hostile files broke the readers before (issue 36): a FIFO among the frames blocked the
reader that opened it (forever: nobody writes to it), and a 937 KB PNG declaring 30 000 x
30 000 pixels made OpenCV allocate 2.7 GB per copy. So a file is

1. refused unless it is a regular file, from ``os.stat`` alone, before anything opens it (a
   FIFO, a socket, a device, a folder: ``PATH: not a regular file (a FIFO)``); it is then
   opened non-blocking and checked again on the open descriptor (a file swapped for a FIFO
   between the two cannot block either);
2. sized from its header, read from that descriptor (:func:`header_size`: PNG ``IHDR``, JPEG
   ``SOFn``, BMP, TIFF / BigTIFF, PNM / PAM / PFM, WebP, GIF, Sun raster, Radiance HDR),
   and refused when width x height is above :func:`max_frame_pixels` (``PATH: 30000 x 30000
   px is 900000000 pixels, above the limit of 33554432 (TORCHSEAM_MAX_FRAME_PIXELS)``); a
   format whose size cannot be read before decoding (JPEG 2000, AVIF, OpenEXR, ...) is
   refused too, as a file that cannot be decoded;
3. only then decoded, from the bytes of that same descriptor (``cv2.imdecode``).

Errors are :class:`~torchseam.core.errors.FrameError` naming the file: a command reading one
frame prints it as its one error line (exit 2); the sequence readers mark the frame
``unreadable`` and go on, as for any broken file.

The pixel limit is :data:`MAX_FRAME_PIXELS` (2**25, 33.5 megapixels: 8192 x 4096, six times
a 5-megapixel machine-vision camera; 100 MB as 8-bit BGR, 270 MB as 16-bit RGBA), unless the
environment variable ``TORCHSEAM_MAX_FRAME_PIXELS`` gives another (a whole number >= 1). It
lives here, not in a config file, because it is the reader's own guard: ``detect`` reads no
config at all, the same limit must hold for every command, and a cell with a larger sensor
raises it for all of them in one place.
"""

from __future__ import annotations

import os
import stat
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from torchseam.core.errors import FrameError, TorchseamError

#: Largest image (width x height) any reader decodes, unless ``$TORCHSEAM_MAX_FRAME_PIXELS``
#: says otherwise (see :func:`max_frame_pixels`).
MAX_FRAME_PIXELS = 1 << 25
#: The environment variable that overrides :data:`MAX_FRAME_PIXELS`.
PIXELS_ENV = "TORCHSEAM_MAX_FRAME_PIXELS"
#: Formats whose size :func:`header_size` reads (all that OpenCV decodes and a frame reader
#: takes; the names of the error message).
FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "PNM", "WebP", "GIF", "Sun raster", "Radiance HDR")
#: Most bytes of JPEG segments (EXIF, ICC profiles, thumbnails) before the frame header that
#: gives the size (a TIFF's directory is read wherever its offset points).
MAX_HEADER_SCAN = 16 << 20
#: Bytes per pixel an image file may hold at most (four 32-bit float channels), and metadata
#: on top: a larger file cannot be an image within the pixel limit.
MAX_BYTES_PER_PIXEL, MAX_METADATA_BYTES = 16, 16 << 20

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def max_frame_pixels() -> int:
    """The pixel limit: ``$TORCHSEAM_MAX_FRAME_PIXELS`` when set, else
    :data:`MAX_FRAME_PIXELS`. Raises :class:`TorchseamError` (not a :class:`FrameError`: the
    setting is wrong, not a frame) for a value that is not a whole number >= 1."""
    text = os.environ.get(PIXELS_ENV, "").strip()
    if not text:
        return MAX_FRAME_PIXELS
    try:
        n = int(text.replace("_", ""))
    except ValueError:
        n = 0
    if not 1 <= n <= 1 << 40:
        raise TorchseamError(f"{PIXELS_ENV}={text[:40]!r}: expected a whole number of pixels "
                         f">= 1 (default {MAX_FRAME_PIXELS})")
    return n


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a plain file")


def regular_file(path: str | os.PathLike[str]) -> os.stat_result:
    """``os.stat`` of ``path`` (a link is followed) when it is a regular file; else
    :class:`FrameError`: ``PATH: no such file`` or ``PATH: not a regular file (a FIFO)``.
    Nothing is opened."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FrameError(f"{p}: no such file") from None
    except OSError as e:  # a broken link's loop, a name too long, no permission on the way
        raise FrameError(f"{p}: cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise FrameError(f"{p}: not a regular file ({_kind(st.st_mode)})")
    return st


class _Reader:
    """Bounded reads at offsets of an open file, for the header parsers: 64 KB blocks read
    once (``os.pread``) and kept, so a parser stepping byte by byte makes few system calls."""

    BLOCK = 1 << 16

    def __init__(self, read_at: Callable[[int, int], bytes], size: int) -> None:
        self._read_at = read_at
        self._blocks: dict[int, bytes] = {}
        self.size = size

    def _block(self, k: int) -> bytes:
        b = self._blocks.get(k)
        if b is None:
            if len(self._blocks) >= 64:   # a TIFF jumping about: keep the memory bounded
                self._blocks.clear()
            b = self._blocks[k] = self._read_at(k * self.BLOCK, self.BLOCK)
        return b

    def at(self, offset: int, n: int) -> bytes:
        """``n`` bytes at ``offset``; :class:`_Truncated` when the file ends first."""
        if offset < 0 or n < 0 or offset + n > self.size:
            raise _Truncated
        out = b""
        while len(out) < n:
            k, o = divmod(offset + len(out), self.BLOCK)
            piece = self._block(k)[o:o + n - len(out)]
            if not piece:
                raise _Truncated
            out += piece
        return out


class _Truncated(Exception):
    """The header ends (or points) beyond the file."""


class _Bad(Exception):
    """The header is malformed (the message says how)."""


def _png(r: _Reader) -> tuple[int, int]:
    b = r.at(0, 24)
    if b[12:16] != b"IHDR":
        raise _Bad("PNG without IHDR first")
    return struct.unpack(">II", b[16:24])


#: JPEG frame headers (SOF0..SOF15 but DHT C4, JPG C8, DAC CC).
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg(r: _Reader) -> tuple[int, int]:
    pos = 2
    for _ in range(100_000):
        if pos > MAX_HEADER_SCAN:
            raise _Bad(f"JPEG without a frame header in its first {MAX_HEADER_SCAN >> 20} MB")
        if r.at(pos, 1) != b"\xff":
            raise _Bad("JPEG segment without a marker")
        fill = pos
        while r.at(pos, 1) == b"\xff":   # fill bytes
            pos += 1
            if pos - fill > 64:
                raise _Bad("JPEG with a run of fill bytes")
        m = r.at(pos, 1)[0]
        pos += 1
        if m == 0x01 or 0xD0 <= m <= 0xD8:   # TEM, RSTn, SOI: no length
            continue
        if m in (0xD9, 0xDA):
            raise _Bad("JPEG without a frame header before its image data")
        (length,) = struct.unpack(">H", r.at(pos, 2))
        if length < 2:
            raise _Bad("JPEG segment of length < 2")
        if m in _SOF:
            if length < 8:
                raise _Bad("JPEG frame header too short")
            h, w = struct.unpack(">HH", r.at(pos + 3, 4))
            if h == 0:
                raise _Bad("JPEG whose height is given after the image data (DNL)")
            return w, h
        pos += length
    raise _Bad("JPEG with too many segments before its frame header")


def _bmp(r: _Reader) -> tuple[int, int]:
    (dib,) = struct.unpack("<I", r.at(14, 4))
    if dib == 12:   # BITMAPCOREHEADER
        w, h = struct.unpack("<HH", r.at(18, 4))
        return w, h
    if dib < 16:
        raise _Bad(f"BMP header of {dib} bytes")
    w, h = struct.unpack("<ii", r.at(18, 8))
    return w, abs(h)   # a negative height: rows top-down


def _tiff(r: _Reader) -> tuple[int, int]:
    e = "<" if r.at(0, 2) == b"II" else ">"
    (version,) = struct.unpack(e + "H", r.at(2, 2))
    big = version == 43
    if big:
        off_size, zero = struct.unpack(e + "HH", r.at(4, 4))
        if off_size != 8 or zero != 0:
            raise _Bad("BigTIFF with a bad header")
        (ifd,) = struct.unpack(e + "Q", r.at(8, 8))
        (n,) = struct.unpack(e + "Q", r.at(ifd, 8))
        first, entry = ifd + 8, 20
    else:
        (ifd,) = struct.unpack(e + "I", r.at(4, 4))
        (n,) = struct.unpack(e + "H", r.at(ifd, 2))
        first, entry = ifd + 2, 12
    if n > 4096:
        raise _Bad(f"TIFF directory of {n} entries")
    size: dict[int, int] = {}
    for k in range(n):
        b = r.at(first + k * entry, entry)
        tag, typ = struct.unpack(e + "HH", b[:4])
        if tag not in (256, 257):
            continue
        value = b[12:] if big else b[8:]
        fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)
        if fmt is None:
            raise _Bad(f"TIFF image {'width' if tag == 256 else 'length'} of type {typ}")
        (size[tag],) = struct.unpack_from(e + fmt, value)
    if 256 not in size or 257 not in size:
        raise _Bad("TIFF without ImageWidth and ImageLength")
    return size[256], size[257]


def _tokens(r: _Reader, start: int, count: int) -> list[bytes]:
    """Up to ``count`` whitespace-separated tokens from ``start`` in the first 4 KB (``#``
    comments to the end of the line skipped), as PNM headers write them."""
    head = r.at(0, min(r.size, 4096))
    out: list[bytes] = []
    tok = b""
    i = start
    while i < len(head) and len(out) < count:
        c = head[i:i + 1]
        if c == b"#" and not tok:
            while i < len(head) and head[i:i + 1] not in (b"\n", b"\r"):
                i += 1
        elif c.isspace():
            if tok:
                out.append(tok)
                tok = b""
        else:
            tok += c
        i += 1
    return out


def _number(tok: bytes, what: str) -> int:
    if not tok.isdigit() or len(tok) > 12:
        raise _Bad(f"{what} {tok[:20]!r} is not a whole number")
    return int(tok)


def _pnm(r: _Reader) -> tuple[int, int]:
    if r.at(1, 1) == b"7":   # PAM: WIDTH / HEIGHT lines up to ENDHDR
        tokens = _tokens(r, 2, 64)
        size: dict[bytes, int] = {}
        for k, t in enumerate(tokens[:-1]):
            if t in (b"WIDTH", b"HEIGHT"):
                size[t] = _number(tokens[k + 1], t.decode())
            if t == b"ENDHDR":
                break
        if len(size) != 2:
            raise _Bad("PAM header without WIDTH and HEIGHT")
        return size[b"WIDTH"], size[b"HEIGHT"]
    wh = _tokens(r, 2, 2)
    if len(wh) < 2:
        raise _Bad("PNM header without width and height in its first 4 KB")
    return _number(wh[0], "PNM width"), _number(wh[1], "PNM height")


def _webp(r: _Reader) -> tuple[int, int]:
    chunk = r.at(12, 4)
    if chunk == b"VP8 ":
        b = r.at(20, 10)
        if b[3:6] != b"\x9d\x01\x2a":
            raise _Bad("WebP VP8 without its start code")
        w, h = struct.unpack("<HH", b[6:10])
        return w & 0x3FFF, h & 0x3FFF
    if chunk == b"VP8L":
        b = r.at(20, 5)
        if b[0] != 0x2F:
            raise _Bad("WebP VP8L without its signature")
        (bits,) = struct.unpack("<I", b[1:5])
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":
        b = r.at(24, 6)
        return (int.from_bytes(b[:3], "little") + 1, int.from_bytes(b[3:], "little") + 1)
    raise _Bad(f"WebP with a first chunk {chunk!r}")


def _gif(r: _Reader) -> tuple[int, int]:
    w, h = struct.unpack("<HH", r.at(6, 4))
    return w, h


def _sun(r: _Reader) -> tuple[int, int]:
    w, h = struct.unpack(">II", r.at(4, 8))
    return w, h


def _hdr(r: _Reader) -> tuple[int, int]:
    head = r.at(0, min(r.size, 65536))
    end = head.find(b"\n\n")
    if end < 0:
        raise _Bad("Radiance HDR header without its end in the first 64 KB")
    line = head[end + 2:head.find(b"\n", end + 2)].split()
    if len(line) != 4 or {line[0][1:], line[2][1:]} != {b"X", b"Y"} \
            or not all(s[:1] in (b"+", b"-") for s in (line[0], line[2])):
        raise _Bad("Radiance HDR without a resolution line")
    n1, n2 = _number(line[1], "HDR size"), _number(line[3], "HDR size")
    return (n2, n1) if line[0][1:] == b"Y" else (n1, n2)


#: (leading bytes, format name, parser); the first that matches.
_SIGNATURES: tuple[tuple[Callable[[bytes], bool], str, Callable[[_Reader], tuple[int, int]]],
                   ...] = (
    (lambda b: b.startswith(b"\x89PNG\r\n\x1a\n"), "PNG", _png),
    (lambda b: b.startswith(b"\xff\xd8\xff"), "JPEG", _jpeg),
    (lambda b: b.startswith(b"BM"), "BMP", _bmp),
    (lambda b: b[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"), "TIFF", _tiff),
    (lambda b: b[:1] == b"P" and b[1:2] in b"1234567" and b[2:3].isspace(), "PNM", _pnm),
    (lambda b: b[:2] in (b"PF", b"Pf") and b[2:3].isspace(), "PFM", _pnm),
    (lambda b: b[:4] == b"RIFF" and b[8:12] == b"WEBP", "WebP", _webp),
    (lambda b: b[:6] in (b"GIF87a", b"GIF89a"), "GIF", _gif),
    (lambda b: b[:4] == b"\x59\xa6\x6a\x95", "Sun raster", _sun),
    (lambda b: b.startswith((b"#?RADIANCE", b"#?RGBE")), "Radiance HDR", _hdr),
)


def header_size(read_at: Callable[[int, int], bytes], file_size: int) -> tuple[str, int, int]:
    """``(format, width, height)`` from an image file's header, decoding nothing.

    Args:
        read_at: ``read_at(offset, n)`` -> up to ``n`` bytes of the file at ``offset``.
        file_size: the file's size in bytes.

    Raises:
        ValueError: a message saying why (not a format of :data:`FORMATS`, a header cut short
            or malformed, a zero side).
    """
    if file_size <= 0:
        raise ValueError("empty file")
    r = _Reader(read_at, file_size)
    try:
        lead = r.at(0, min(file_size, 16))
    except _Truncated:
        raise ValueError("file cut short") from None
    hit = next(((name, parse) for match, name, parse in _SIGNATURES if match(lead)), None)
    if hit is None:
        raise ValueError(f"not a {', '.join(FORMATS[:-1])} or {FORMATS[-1]} file")
    name, parse = hit
    try:
        w, h = parse(r)
    except _Truncated:
        raise ValueError(f"{name} header cut short") from None
    except (_Bad, struct.error) as e:
        raise ValueError(str(e) or f"malformed {name} header") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"{name} header gives {w} x {h} px")
    return name, int(w), int(h)


def _open_regular(path: Path) -> tuple[int, os.stat_result]:
    """A descriptor of ``path`` opened for reading, checked regular before (``stat``) and
    after (``fstat``): a FIFO opened non-blocking does not wait for a writer."""
    regular_file(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) \
        | getattr(os, "O_BINARY", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as e:
        raise FrameError(f"{path}: cannot be read ({e.strerror or e})") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise FrameError(f"{path}: not a regular file ({_kind(st.st_mode)})")
    return fd, st


def _pread(fd: int) -> Callable[[int, int], bytes]:
    if hasattr(os, "pread"):
        return lambda off, n: os.pread(fd, n, off)

    def read_at(off: int, n: int) -> bytes:  # pragma: no cover - Windows
        os.lseek(fd, off, os.SEEK_SET)
        return os.read(fd, n)
    return read_at


def _checked_size(path: Path, fd: int, st: os.stat_result, limit: int) -> tuple[int, int]:
    try:
        name, w, h = header_size(_pread(fd), st.st_size)
    except ValueError as e:
        raise FrameError(f"{path}: cannot be decoded as an image ({e})") from None
    except OSError as e:
        raise FrameError(f"{path}: cannot be read ({e.strerror or e})") from None
    if w * h > limit:
        raise FrameError(f"{path}: {name} of {w} x {h} px is {w * h} pixels, above the limit "
                         f"of {limit} ({PIXELS_ENV}); not decoded")
    if st.st_size > limit * MAX_BYTES_PER_PIXEL + MAX_METADATA_BYTES:
        raise FrameError(f"{path}: {st.st_size} bytes is larger than an image of at most "
                         f"{limit} pixels can be ({PIXELS_ENV}); not read")
    return w, h


def image_size(path: str | os.PathLike[str], limit: int | None = None) -> tuple[int, int]:
    """(width, height) of the image file ``path`` from its header alone, checked against the
    pixel limit (``limit``, default :func:`max_frame_pixels`).

    Raises:
        FrameError: naming the file: not a regular file (refused before opening), not an
            image format whose size can be read, a malformed header, above the limit.
    """
    p = Path(path)
    limit = max_frame_pixels() if limit is None else limit
    fd, st = _open_regular(p)
    try:
        return _checked_size(p, fd, st, limit)
    finally:
        os.close(fd)


def read_image(path: str | os.PathLike[str], flags: int | None = None,
               limit: int | None = None) -> np.ndarray:
    """Decode the image file ``path`` (``cv2.imdecode`` with ``flags``, default
    ``cv2.IMREAD_UNCHANGED``) after the checks of :func:`image_size`, from the bytes of the
    descriptor those checks were made on.

    Raises:
        FrameError: as :func:`image_size`, or ``PATH: cannot be decoded as an image`` when
            OpenCV cannot decode it.
    """
    import cv2

    p = Path(path)
    limit = max_frame_pixels() if limit is None else limit
    fd, st = _open_regular(p)
    try:
        _checked_size(p, fd, st, limit)
        chunks, left = [], st.st_size
        while left > 0:
            b = os.read(fd, min(left, 1 << 24))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
    except OSError as e:
        raise FrameError(f"{p}: cannot be read ({e.strerror or e})") from None
    finally:
        os.close(fd)
    data = np.frombuffer(b"".join(chunks), np.uint8)
    del chunks
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED if flags is None else flags)
    if img is None:
        raise FrameError(f"{p}: cannot be decoded as an image")
    if img.shape[0] * img.shape[1] > limit:  # the decoder disagreed with the header
        raise FrameError(f"{p}: decoded to {img.shape[1]} x {img.shape[0]} px, above the "
                         f"limit of {limit} pixels ({PIXELS_ENV})")
    return img


__all__ = ["FORMATS", "MAX_FRAME_PIXELS", "PIXELS_ENV", "header_size", "image_size",
           "max_frame_pixels", "read_image", "regular_file"]
