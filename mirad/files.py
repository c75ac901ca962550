"""Output files: atomic writes that honour the umask, image bytes, sRGB and display colours.

A leaf module (it imports nothing else of mirad but ``errors``), so every output module can
use it without importing each other.

Every file mirad writes goes through :func:`atomic_write`: the bytes go to a temporary
``.NAME.XXXX.part`` beside the target and are renamed over it only when complete, so an
interrupted run (Ctrl-C, SIGTERM, a full disk) never leaves a half-written file or a stray
``.part``. A new file gets the mode ``0o666`` minus the process umask (as ``open`` would give
it); an overwritten file keeps its mode. :data:`WRITTEN` lists the files written by this
process, so an interrupted command can say what it had written.
"""

from __future__ import annotations

import errno
import io
import os
import signal
import tempfile
import threading
from pathlib import Path

import numpy as np

from .errors import OutputError

__all__ = ["atomic_write", "check_output", "WRITTEN", "exr_bytes", "read_exr", "png_bytes", "srgb_encode",
           "srgb8", "display_colors", "Terminated", "raise_on_sigterm"]

#: Paths written by :func:`atomic_write` in this process, in order.
WRITTEN: list = []


class Terminated(BaseException):
    """Raised in place of the default SIGTERM action (see :func:`raise_on_sigterm`), so pending
    writes clean up their temporary files before the process exits."""


def raise_on_sigterm():
    """Make SIGTERM raise :class:`Terminated` in the main thread (the CLI installs this while a
    command runs). Returns the handler it replaced, for ``signal.signal`` to put back, or None where
    it installed nothing (called outside the main thread, which may not set handlers)."""
    def handler(signum, frame):
        raise Terminated(signum)

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, handler)


def _umask() -> int:
    """The process umask (read without changing it where /proc allows)."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_output(path, suffixes: tuple = ()) -> Path:
    """Check that ``path`` can be written (suffix, folder exists and is writable, not a folder);
    raise OutputError naming it and the fix. Call it before any long work."""
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise OutputError(f"output '{path}' must end in one of {', '.join(suffixes)}")
    folder = path.parent if str(path.parent) else Path(".")
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"cannot write '{path}': '{folder}' is a file, not a folder; choose another output path")
    if path.is_dir():
        example = f"{str(path).rstrip('/')}/out{suffixes[0] if suffixes else ''}"
        raise OutputError(f"cannot write '{path}': it is a folder; give a file name such as {example}")
    if not folder.is_dir():
        raise OutputError(f"cannot write '{path}': folder '{folder}' does not exist; create it first")
    if not os.access(folder, os.W_OK):
        raise OutputError(f"cannot write '{path}': folder '{folder}' is not writable; choose another output path")
    return path


def atomic_write(path, writer) -> Path:
    """Call ``writer(binary handle)`` on a temporary file beside ``path``, then rename it into place.

    The temporary file is removed on any failure or interruption (KeyboardInterrupt,
    :class:`Terminated`). The result has the mode of the file it replaces, or 0o666 minus the
    umask. A full disk or another OS error raises OutputError naming ``path``.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    check_output(path)
    try:
        mode = os.stat(path).st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=folder)
        with os.fdopen(fd, "wb") as handle:
            writer(handle)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        reason = "the disk is full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        raise OutputError(f"cannot write '{path}': {reason}; free space or choose another output path") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
    WRITTEN.append(path)
    return path


# ------------------------------------------------------------------------------------------
# Colours
# ------------------------------------------------------------------------------------------

def srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve of linear values in [0, 1] (same shape, float)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0), 1 / 2.4) - 0.055)


def srgb8(image: np.ndarray, *, exposure: float = 0.0) -> np.ndarray:
    """Tonemap linear radiance (..., 3) to 8-bit sRGB: scale by 2^exposure, clip to [0, 1], sRGB curve."""
    x = np.clip(np.nan_to_num(np.asarray(image, np.float64) * 2.0 ** exposure), 0.0, 1.0)
    return np.round(srgb_encode(x) * 255).astype(np.uint8)


def display_colors(radiosity: np.ndarray, *, exclude=None) -> np.ndarray:
    """(N, 4) uint8 sRGB RGBA colours of radiance B/pi for radiosity (N, C) W/m^2.

    The exposure maps the 99th percentile of the brightest channel to white, taken over the
    rows not in ``exclude`` ((N,) bool, e.g. emitters, so a light in view does not darken the
    rest); excluded rows are clipped like the others.
    """
    radiance = np.asarray(radiosity, dtype=np.float64) / np.pi
    if radiance.shape[1] == 1:
        radiance = np.repeat(radiance, 3, axis=1)
    peak = radiance.max(axis=1)
    if exclude is not None and (~np.asarray(exclude, bool)).any():
        peak = peak[~np.asarray(exclude, bool)]
    scale = np.percentile(peak, 99) if len(peak) else 1.0
    rgb = srgb8(radiance / (scale if scale > 0 else 1.0))
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)


# ------------------------------------------------------------------------------------------
# Image bytes
# ------------------------------------------------------------------------------------------

def exr_bytes(channels: dict) -> bytes:
    """An OpenEXR file (float32 channels, ZIP compression) as bytes; channels: name -> (H, W)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(values, dtype=np.float32) for name, values in channels.items()}
    with tempfile.TemporaryDirectory() as tmp:
        name = os.path.join(tmp, "image.exr")
        with OpenEXR.File(header, data) as exr:
            exr.write(name)
        with open(name, "rb") as handle:
            return handle.read()


def read_exr(path) -> dict:
    """Channels of an OpenEXR file: name -> (H, W) float32."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        return {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}


def png_bytes(rgb8: np.ndarray) -> bytes:
    """An 8-bit RGB PNG (H, W, 3 uint8) as bytes."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8, dtype=np.uint8), "RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def read_csv_text(path: Path, what: str, columns: str, error) -> str:
    """The text of the CSV file ``path`` (a byte-order mark dropped), or ``error`` (an exception
    class) naming ``what`` the file is ("band table", "points file") and the ``columns`` its
    header should hold, where the file is missing, binary or not UTF-8."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} '{path}' does not exist; give a CSV file with a header {columns}")
    raw = path.read_bytes()
    try:
        if b"\0" in raw:
            raise UnicodeDecodeError("utf-8", raw, 0, 1, "NUL byte")
        return raw.decode("utf-8-sig")          # a byte-order mark (Excel's "CSV UTF-8") is dropped
    except UnicodeDecodeError:
        raise error(f"{what} '{path}' is not a text CSV (binary or not UTF-8); save it as UTF-8 text with a "
                    f"header {columns}") from None
