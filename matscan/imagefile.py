"""Reading and writing image files: PNG (8/16-bit), JPEG, TIFF, EXR, and RAW.

Arrays here are NumPy, (H, W, C) with C in {1, 3, 4}, RGB order (OpenCV's BGR
is converted at this boundary and nowhere else). Integer files keep their code
values (``ImageData.stored``, uint8 or uint16) and give them as float32 scaled to
[0, 1] on request (``ImageData.pixels``; no transfer function applied: the caller
knows whether a file is sRGB or linear); EXR and float TIFF are float32 as
stored. Writers take a temporary name and rename it when the file is complete.

Libraries: OpenCV for PNG/JPEG (exact 16-bit PNG), tifffile for TIFF, the
OpenEXR package for EXR (exact float32), rawpy for RAW (the ``raw`` extra).
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from matscan.atomic import atomic_file
from matscan.errors import MatscanError, input_error

cv2.setNumThreads(1)

#: File endings matscan reads as images, and which reader handles them.
PNG_LIKE = {".png", ".jpg", ".jpeg"}
TIFF = {".tif", ".tiff"}
EXR = {".exr"}
RAW = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw"}
READABLE = PNG_LIKE | TIFF | EXR | RAW


@dataclass(frozen=True)
class ImageData:
    """Pixels of an image file and how they were stored.

    ``stored`` is (H, W, C) as the file holds it: uint8 or uint16 code values, or
    float32. ``pixels`` is the same as float32, integer codes scaled to [0, 1]
    (made on first use: a 16-bit photo's codes take half the memory of its floats).
    ``kind`` is ``"int"`` (code values, transfer function unknown), ``"float"`` (EXR
    or float TIFF, linear), or ``"raw"`` (a camera RAW developed linearly, 16-bit
    codes). ``bits`` is the stored bit depth (8, 16, 32).
    """

    stored: np.ndarray
    kind: str
    bits: int

    @cached_property
    def pixels(self) -> np.ndarray:
        if self.stored.dtype == np.float32:
            return self.stored
        return self.stored.astype(np.float32) / np.float32((1 << self.bits) - 1)


def _suffix(path: Path) -> str:
    return path.suffix.lower()


class _Undecodable(Exception):
    """A decoder returned nothing (OpenCV's imdecode gives None for a corrupt file)."""


_STDERR_LOCK = threading.Lock()
#: OpenCV's log prefix (``[ WARN:0@0.025] global grfmt_png.cpp:793 readHeader ``).
_CV_PREFIX = re.compile(r"^\[\s*\w+:[^\]]*\]\s*(global\s+)?(\S+:\d+\s+)?(\w+\s+)?")


@contextmanager
def _library_output(lines: list[str]) -> Iterator[None]:
    """Send what C libraries (libpng, OpenCV's log, OpenEXR) print to the process's
    stderr while a file is decoded into ``lines`` instead, so a bad file gives one
    line of ours and nothing else. One decoder at a time holds file descriptor 2."""
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no usable stderr: nothing to quiet
            yield
            return
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield
            finally:
                try:
                    sys.stderr.flush()
                except (OSError, ValueError):
                    pass
                os.dup2(saved, 2)
                os.close(saved)
                sink.seek(0)
                lines.extend(sink.read(4096).decode("utf-8", "replace").splitlines())


def _one_line(text: str, limit: int = 200) -> str:
    """``text`` on one line (whitespace runs, newlines included, become one space), shortened."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _library_message(lines: list[str]) -> str:
    """The most telling line a library printed (an error line if there is one)."""
    lines = [line for line in lines if line.strip()]
    errors = [line for line in lines if "error" in line.lower()]
    return _CV_PREFIX.sub("", (errors or lines or [""])[0]).strip()


def _decode_any(path: Path, suffix: str) -> ImageData:
    if suffix in EXR:
        return _read_exr(path)
    if suffix in TIFF:
        return _read_tiff(path)
    if suffix in RAW:
        return _read_raw(path)
    return _read_cv2(path)


def read_image(path: str | Path) -> ImageData:
    """Read an image file; every error is one line naming the file and the problem.

    What the decoding libraries print on the way (libpng, OpenCV, OpenEXR) does not
    reach the terminal; the most telling line of it joins our message.
    """
    path = Path(path)
    suffix = _suffix(path)
    if suffix not in READABLE:
        raise input_error(
            path, f"unsupported image type {suffix or '(none)'!r} (expected one of {', '.join(sorted(READABLE))})"
        )
    if not path.is_file():
        raise input_error(path, "is a folder, not an image file" if path.is_dir() else "no such file")
    printed: list[str] = []
    try:
        with _library_output(printed):
            img = _decode_any(path, suffix)
    except MatscanError as exc:
        raise MatscanError(_one_line(str(exc), 400)) from None
    except Exception as exc:  # decoders raise many types for a corrupt file
        detail = "corrupt or not an image" if isinstance(exc, _Undecodable) else f"{type(exc).__name__}: {exc}"
        said = _library_message(printed)
        if said and said not in detail:
            detail = f"{detail}: {said}"
        raise input_error(path, f"cannot read as {suffix[1:].upper()} ({_one_line(detail)})") from None
    if img.stored.ndim != 3 or 0 in img.stored.shape:
        raise input_error(path, f"holds no pixels (an array of shape {img.stored.shape})")
    return img


def _stored(arr: np.ndarray, path: Path) -> tuple[np.ndarray, str, int]:
    """(stored values, kind, bits): integer codes kept as they are, floats as float32."""
    if arr.dtype == np.uint8:
        return arr, "int", 8
    if arr.dtype == np.uint16:
        return arr, "int", 16
    if arr.dtype in (np.float32, np.float64, np.float16):
        return arr.astype(np.float32), "float", 32
    raise input_error(path, f"unsupported pixel type {arr.dtype}")


def _channels_last(arr: np.ndarray) -> np.ndarray:
    return arr[:, :, None] if arr.ndim == 2 else arr


def _read_cv2(path: Path) -> ImageData:
    data = np.fromfile(str(path), dtype=np.uint8)
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise _Undecodable()
    arr = _channels_last(arr)
    if arr.shape[2] == 3:
        arr = arr[:, :, ::-1]
    elif arr.shape[2] == 4:
        arr = arr[:, :, [2, 1, 0, 3]]
    stored, kind, bits = _stored(np.ascontiguousarray(arr), path)
    return ImageData(stored, kind, bits)


def _read_tiff(path: Path) -> ImageData:
    import tifffile

    with tifffile.TiffFile(str(path)) as tif:
        series = tif.series[0]  # the full-resolution image; later series are previews
        axes, arr = series.axes, np.asarray(series.asarray())
    single = [i for i, a in enumerate(axes) if arr.shape[i] == 1 and a not in "YX"]  # a one-page "stack"
    if single:
        arr = arr.squeeze(axis=tuple(single))
        axes = "".join(a for i, a in enumerate(axes) if i not in single)
    # Samples are stored either interleaved (YXS) or one plane per channel (SYX, the
    # "planar" layout); any other axis (pages, Z, time) makes the file a stack.
    if axes in ("YX", "YXS", "YXC"):
        arr = _channels_last(arr)
    elif axes in ("SYX", "CYX"):
        arr = np.moveaxis(arr, 0, -1)
    else:
        raise input_error(
            path, f"holds a stack of images (axes {axes}, shape {tuple(arr.shape)}); expected one 2-D image"
        )
    stored, kind, bits = _stored(arr, path)
    return ImageData(stored, kind, bits)


def _read_exr(path: Path) -> ImageData:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    if "RGB" in channels:
        arr = channels["RGB"]
    elif "RGBA" in channels:
        arr = channels["RGBA"]
    elif all(c in channels for c in "RGB"):
        arr = np.stack([channels[c] for c in "RGB"], axis=-1)
    elif "Y" in channels:
        arr = channels["Y"]
    elif len(channels) == 1:
        arr = next(iter(channels.values()))
    else:
        raise input_error(path, f"no RGB or Y channels (found {', '.join(channels)})")
    return ImageData(_channels_last(arr).astype(np.float32), "float", 32)


def _read_raw(path: Path) -> ImageData:
    try:
        import rawpy
    except ImportError:
        raise input_error(path, "reading RAW files needs the 'raw' extra: pip install 'matscan[raw]'") from None
    with rawpy.imread(str(path)) as raw:
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True, user_flip=0)
    return ImageData(np.ascontiguousarray(rgb, dtype=np.uint16), "raw", 16)


#: Rec. 709 / sRGB primaries and D65 white (x, y each): red, green, blue, white.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
PNG_COLOURSPACES = ("srgb", "linear")


def write_image(
    path: str | Path,
    pixels: np.ndarray,
    bits: int = 8,
    header: dict | None = None,
    colourspace: str | None = None,
    atomic: bool = True,
) -> None:
    """Write (H, W, C) pixels; C in {1, 3, 4}; RGB order.

    PNG/JPEG/TIFF with ``bits`` 8 or 16 take values in [0, 1] (clipped, rounded);
    TIFF and EXR with ``bits`` 32 store float32 exactly (EXR always does).
    ``header`` adds attributes to an EXR file (strings, or numbers and tuples such as
    ``chromaticities``). ``colourspace`` marks a PNG: ``"srgb"`` (sRGB, gAMA 1/2.2 and
    cHRM chunks: the values are sRGB-encoded) or ``"linear"`` (gAMA 1.0 and cHRM: data
    or linear values), so viewers and engines need not guess. ``atomic=False`` writes
    ``path`` directly (a temporary that a caller's own atomic write renames).
    """
    if colourspace is not None and colourspace not in PNG_COLOURSPACES:
        raise MatscanError(f"{path}: colour space {colourspace!r} is not one of {', '.join(PNG_COLOURSPACES)}")
    path = Path(path)
    suffix = _suffix(path)
    arr = _channels_last(np.asarray(pixels))
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4):
        raise MatscanError(f"{path}: cannot write an image of shape {arr.shape}")
    if suffix not in EXR | TIFF | PNG_LIKE:
        raise MatscanError(f"{path}: cannot write {suffix or 'files without an ending'} (use .png, .tif or .exr)")
    if suffix in PNG_LIKE and (bits not in (8, 16) or (bits == 16 and suffix != ".png")):
        raise MatscanError(f"{path}: {suffix[1:].upper()} cannot hold {bits}-bit values")
    with atomic_file(path) if atomic else nullcontext(path) as tmp:
        if suffix in EXR:
            _write_exr(tmp, arr.astype(np.float32), header or {})
        elif suffix in TIFF:
            import tifffile

            data = arr.astype(np.float32) if bits == 32 else _quantise(arr, bits)
            tifffile.imwrite(
                str(tmp),
                data[:, :, 0] if data.shape[2] == 1 else data,
                photometric=("minisblack" if data.shape[2] == 1 else "rgb"),
            )
        else:
            tmp.write_bytes(encode_image(arr, bits, suffix, colourspace, str(path)))


def encode_image(
    pixels: np.ndarray, bits: int = 8, suffix: str = ".png", colourspace: str | None = None, where: str = "image"
) -> bytes:
    """The bytes of a PNG (8 or 16-bit) or JPEG file of (H, W, C) values in [0, 1]
    (clipped, rounded; RGB order), as :func:`write_image` writes them."""
    data = _quantise(_channels_last(np.asarray(pixels)), bits)
    if data.shape[2] == 3:
        data = data[:, :, ::-1]
    elif data.shape[2] == 4:
        data = data[:, :, [2, 1, 0, 3]]
    ok, buf = cv2.imencode(suffix, np.ascontiguousarray(data))
    if not ok:
        raise MatscanError(f"{where}: the encoder refused the image")
    encoded = buf.tobytes()
    if colourspace is not None and suffix == ".png":
        encoded = _png_colour_chunks(encoded, colourspace)
    return encoded


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_colour_chunks(png: bytes, colourspace: str) -> bytes:
    """``png`` with colour-space chunks after its IHDR (PNG 1.2 §4.2.2: sRGB, gAMA, cHRM;
    gAMA and cHRM beside sRGB as the specification recommends for older readers)."""
    import struct

    ihdr_end = 8 + 4 + 4 + 13 + 4  # signature, then IHDR: length, type, 13 bytes, CRC
    if png[12:16] != b"IHDR":
        raise MatscanError("PNG encoder output does not start with IHDR")
    chrm = struct.pack(">8I", *(round(v * 100000) for v in (*REC709_CHROMATICITIES[6:], *REC709_CHROMATICITIES[:6])))
    if colourspace == "srgb":
        chunks = _png_chunk(b"sRGB", b"\0") + _png_chunk(b"gAMA", struct.pack(">I", 45455))
    else:
        chunks = _png_chunk(b"gAMA", struct.pack(">I", 100000))
    chunks += _png_chunk(b"cHRM", chrm)
    return png[:ihdr_end] + chunks + png[ihdr_end:]


def _quantise(arr: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.rint(np.clip(arr.astype(np.float64), 0.0, 1.0) * top).astype(dtype)


def _write_exr(path: Path, arr: np.ndarray, header: dict) -> None:
    import OpenEXR

    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update({str(k): v if isinstance(v, (int, float, tuple)) else str(v) for k, v in header.items()})
    c = arr.shape[2]
    if c == 1:
        channels = {"Y": np.ascontiguousarray(arr[:, :, 0])}
    elif c == 3:
        channels = {"RGB": np.ascontiguousarray(arr)}
    else:
        channels = {"RGBA": np.ascontiguousarray(arr)}
    with OpenEXR.File(hdr, channels) as f:
        f.write(str(path))
