"""Photos before COLMAP sees them: up-front checks, and the one image reader that matches COLMAP's
frame.

``check_images(image_path, names)`` opens every photo (header, then a cheap decode that finds
truncated or damaged files) and returns the names COLMAP can use and, for the others, why not —
instead of letting COLMAP's reader silently extract SIFT from the grey fill of a truncated JPEG, or
fail on a format it does not read (WebP, JPEG 2000).

``read_image(path)`` gives uint8 RGB pixels in the frame of COLMAP's keypoints. COLMAP (pycolmap
4.2.1, OpenImageIO reader) ignores the EXIF orientation tag: keypoints, camera width/height and the
reconstruction are in the pixel grid as stored in the file, not as a photo viewer shows it. OpenCV's
``imread`` and Pillow's ``ImageOps.exif_transpose`` rotate; anything that pairs pixels with COLMAP
keypoints (the coarse network, match drawings) must read with this function instead.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, ImageFile, UnidentifiedImageError

from . import log
from .conf import merge_conf
from .log import logger

MIN_SIZE = 64  # pixels; smaller photos give (almost) no SIFT keypoints
HUGE_PIXELS = (
    100_000_000  # from here on a warning: decoding takes ~3 bytes/pixel in COLMAP's reader
)
default_conf = {
    "min_size": MIN_SIZE,
    "max_pixels": 600_000_000,  # ~1.8 GB to decode in COLMAP; above that, ask the user to downscale
    "full_decode_pixels": 50_000_000,  # TIFF/BMP up to this size are decoded fully to find damage
}
# Formats COLMAP's reader (OpenImageIO) reads, as Pillow names them. Anything else is tried with
# pycolmap.Bitmap before being refused (WebP and JPEG 2000 are not read by pycolmap 4.2.1).
COLMAP_FORMATS = {"JPEG", "MPO", "PNG", "TIFF", "BMP", "PPM"}
EXIF_ORIENTATION = 0x0112


@contextlib.contextmanager
def _pillow_strict(max_pixels: int):
    """Pillow refusing truncated files and accepting large (but bounded) images, restored
    afterwards."""
    saved = ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS
    ImageFile.LOAD_TRUNCATED_IMAGES = False
    Image.MAX_IMAGE_PIXELS = max_pixels
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            yield
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS = saved


def _colmap_reads(path: Path) -> bool:
    import pycolmap

    return pycolmap.Bitmap.read(str(path), False) is not None


def check_conf(conf: dict | None) -> dict:
    """``conf`` over ``default_conf``; an unknown key is a one-line ValueError."""
    return merge_conf(default_conf, conf, "image check")


def check_image(path: Path, conf: dict | None = None) -> tuple[str | None, dict]:
    """(None, info) for a usable photo, else (reason, info); the reason says what to do about it."""
    conf = check_conf(conf)
    path = Path(path)
    info: dict = {}
    try:
        size = path.stat().st_size
    except OSError as err:
        return f"cannot be read ({err.strerror}); check its permissions", info
    if size == 0:
        return "empty file (0 bytes); copy the photo again", info
    with _pillow_strict(2 * conf["max_pixels"]):
        try:
            with Image.open(path) as im:
                width, height = im.size
                info.update(width=width, height=height, format=im.format, mode=im.mode)
                if im.format != "PNG":  # (PNG: verify() below must come right after open)
                    with contextlib.suppress(Exception):
                        orientation = im.getexif().get(EXIF_ORIENTATION)
                        if orientation and orientation != 1:
                            info["exif_orientation"] = int(orientation)
                if min(width, height) < conf["min_size"]:
                    return (
                        f"too small ({width}x{height} px; at least {conf['min_size']} px "
                        "per side are needed)",
                        info,
                    )
                if width * height > conf["max_pixels"]:
                    return (
                        f"too large ({width * height / 1e6:.0f} MP > "
                        f"{conf['max_pixels'] / 1e6:.0f} MP); downscale it",
                        info,
                    )
                if im.format not in COLMAP_FORMATS and not _colmap_reads(path):
                    return (
                        f"{im.format} files cannot be read by COLMAP; convert it to JPEG or PNG",
                        info,
                    )
                if im.format in ("JPEG", "MPO"):
                    # Decoding at 1/8 scale still reads every entropy-coded byte: finds
                    # truncation/damage.
                    im.draft(
                        im.mode if im.mode in ("RGB", "L") else None,
                        (max(1, width // 8), max(1, height // 8)),
                    )
                    im.load()
                    damage = _libjpeg_damage(path)
                    if damage:
                        return f"damaged image (libjpeg: {damage}); copy or scan it again", info
                elif im.format == "PNG":
                    im.verify()  # chunk CRCs and the end marker, without decoding the pixels
                elif width * height <= conf["full_decode_pixels"]:
                    try:
                        im.load()
                    except OSError as err:
                        if "truncated" in str(err).lower() or not _colmap_reads(path):
                            raise
                        logger.debug(
                            "Pillow cannot decode %s (%s) but COLMAP can; keeping it.", path, err
                        )
        except UnidentifiedImageError:
            return (
                "not an image file (or a format Pillow and COLMAP "
                "do not know); remove it or convert it to JPEG",
                info,
            )
        except Image.DecompressionBombError:
            return (
                f"too large (more than {2 * conf['max_pixels'] / 1e6:.0f} MP); downscale it",
                info,
            )
        except (OSError, SyntaxError, ValueError) as err:
            return f"damaged or truncated image ({err}); copy or scan it again", info
    if width * height >= HUGE_PIXELS:
        info["huge"] = True
    return None, info


def _libjpeg_damage(path: Path) -> str | None:
    """libjpeg's complaint about a JPEG's entropy-coded data, or None.

    Random damage inside a JPEG usually decodes to grey/garbage blocks with only a libjpeg *warning*
    (which Pillow and COLMAP ignore). OpenCV's decoder prints those warnings on file descriptor 2:
    catch them. Junk bytes before the end marker (written by some cameras and scanners) are harmless
    and ignored.
    """
    import os
    import sys
    import tempfile

    import cv2

    data = np.fromfile(str(path), np.uint8)
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 2)
        try:
            cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8 | cv2.IMREAD_IGNORE_ORIENTATION)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        messages = capture.read().decode("utf-8", "replace").splitlines()
    for line in messages:
        low = line.lower()
        if (
            "corrupt jpeg data" in low and "before marker 0xd9" not in low
        ) or "premature end" in low:
            return line.strip()
    return None


def check_images(
    image_path: Path, names: list[str], conf: dict | None = None, progress: bool = True
) -> tuple[list[str], dict[str, str]]:
    """Split ``names`` (relative to ``image_path``) into usable ones and {name: reason} for the
    others."""
    conf = check_conf(conf)  # a typo fails before the first photo is opened
    ok, skipped, huge, rotated = [], {}, [], []
    for name in log.progress(names, "check images", "img", show=progress):
        reason, info = check_image(Path(image_path) / name, conf)
        if reason is None:
            ok.append(name)
            if info.get("huge"):
                huge.append(name)
            if info.get("exif_orientation"):
                rotated.append(name)
        else:
            skipped[name] = reason
            logger.warning("Skipped %s: %s", name, reason)
    if huge:
        logger.warning(
            "%d photo(s) of 100 MP or more (e.g. %s): COLMAP decodes each at "
            "full size (~3 bytes per pixel) before downscaling for SIFT.",
            len(huge),
            huge[0],
        )
    if rotated:
        logger.info(
            "%d photo(s) carry an EXIF rotation (e.g. %s); COLMAP works in "
            "the stored pixel frame, which is fine for reconstruction.",
            len(rotated),
            rotated[0],
        )
    return ok, skipped


def _to_uint8(array: np.ndarray) -> np.ndarray:
    if array.dtype == np.uint8:
        return array
    if len(array) > 256:  # in bands of rows: no float64 copy of a large scan
        out = np.empty(array.shape, np.uint8)
        for row in range(0, len(array), 256):
            out[row : row + 256] = _to_uint8(array[row : row + 256])
        return out
    if array.dtype == np.bool_:
        return array.astype(np.uint8) * 255
    if np.issubdtype(array.dtype, np.floating):
        return np.clip(np.nan_to_num(array) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if array.dtype.itemsize >= 2:  # 16-bit (and 32-bit integer images Pillow stores 16-bit PNGs in)
        return np.clip((array.astype(np.float64) / 257.0) + 0.5, 0, 255).astype(np.uint8)
    return array.astype(np.uint8)


def read_image(path: Path, min_side: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB in COLMAP's frame: the stored pixel grid, EXIF orientation NOT applied.

    Grey, palette, bilevel, alpha (dropped, as COLMAP does), CMYK, 16-bit and float images are
    converted the way COLMAP's reader converts them (within one grey level). Raises ValueError for
    an unreadable file. ``min_side``, for callers that downscale anyway: a JPEG is decoded at 1/2,
    1/4 or 1/8 of its size (libjpeg's DCT scaling) while its longer side stays at least
    ``min_side``; ``decoded_box`` tells which part of that smaller grid the photo covers.
    """
    path = Path(path)
    with _pillow_strict(2 * default_conf["max_pixels"]):
        try:
            with Image.open(path) as im:
                if min_side and im.format in ("JPEG", "MPO"):
                    longer = max(im.size)
                    im.draft(None, tuple(max(1, side * min_side // longer) for side in im.size))
                mode = im.mode
                if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I", "F"):
                    grey = np.asarray(im)
                    if mode == "I" and grey.max(initial=0) <= 255:
                        grey = grey.astype(np.uint8)  # 8-bit data that Pillow widened
                    return np.repeat(_to_uint8(grey)[:, :, None], 3, axis=2)
                rgb = (
                    _rgb_16bit(path, im) if mode == "RGB" and im.format in ("PNG", "TIFF") else None
                )
                if rgb is not None:
                    return rgb
                return np.asarray(im if mode == "RGB" else im.convert("RGB"))  # (no copy of a scan)
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
            raise ValueError(
                f"Cannot read image {path} ({err}); run the reconstruction "
                "once to have it checked, or convert it to JPEG."
            ) from err


def decoded_box(size: tuple[int, int], shape: tuple) -> tuple[float, float, float, float]:
    """The box that a photo of ``size`` (width, height) covers in the grid of ``shape`` (H, W, ...)
    that ``read_image(path, min_side)`` decoded it to, for ``PIL.Image.resize``: a 1/s decode rounds
    up."""
    s = 2 ** round(np.log2(max(size) / max(shape[:2])))
    return 0.0, 0.0, size[0] / s, size[1] / s


def _rgb_16bit(path: Path, im: Image.Image) -> np.ndarray | None:
    """16-bit-per-channel RGB(A) PNG/TIFF: Pillow keeps only 8 bits without rounding; read all 16
    with OpenCV."""
    bits = im.info.get("bits") or getattr(im, "tag_v2", {}).get(258)
    bits = max(bits) if isinstance(bits, tuple) else bits
    if im.format == "PNG":
        # Pillow does not record PNG bit depth in info: read it from the IHDR chunk (byte 24).
        with open(path, "rb") as f:
            head = f.read(26)
        bits = head[24] if len(head) >= 25 else 8
    if bits != 16:
        return None
    import cv2

    data = cv2.imdecode(
        np.fromfile(str(path), np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
    )
    if data is None or data.ndim != 3:
        return None
    return np.ascontiguousarray(_to_uint8(data[:, :, 2::-1]))


def read_thumbnail(path: Path, max_side: int = 640) -> tuple[np.ndarray, float, float]:
    """(uint8 RGB thumbnail, sx, sy) in COLMAP's frame: a COLMAP coordinate x maps to x * sx in the
    thumbnail. JPEGs are decoded at reduced size (no full-size decode of a 100 MP scan)."""
    path = Path(path)
    with _pillow_strict(2 * default_conf["max_pixels"]), Image.open(path) as im:
        width, height = im.size
        scale = min(1.0, max_side / max(width, height))
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        if im.mode in ("1", "L", "P", "RGB", "RGBA", "LA", "CMYK", "YCbCr") and not (
            im.mode == "RGB" and im.format in ("PNG", "TIFF")
        ):
            if im.format in ("JPEG", "MPO"):
                im.draft("RGB" if im.mode != "L" else "L", size)
            thumb = np.asarray(
                im.convert("RGB").resize(size, Image.Resampling.BILINEAR, reducing_gap=2.0)
            )
            return thumb, size[0] / width, size[1] / height
    import cv2

    full = read_image(path)
    thumb = cv2.resize(full, size, interpolation=cv2.INTER_AREA)
    return thumb, size[0] / width, size[1] / height


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) in COLMAP's frame (EXIF orientation not applied), from the header only."""
    with _pillow_strict(2 * default_conf["max_pixels"]), Image.open(path) as im:
        return im.size


def file_digest(path: Path) -> str:
    """SHA-256 of a file (the tests prove photos are never written)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def folder_digests(folder: Path) -> dict[str, tuple[str, int]]:
    """{relative path: (sha256, mtime_ns)} of every file below ``folder``."""
    folder = Path(folder)
    return {
        p.relative_to(folder).as_posix(): (file_digest(p), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


__all__ = [
    "check_conf",
    "check_image",
    "check_images",
    "read_image",
    "decoded_box",
    "read_thumbnail",
    "image_size",
    "folder_digests",
    "MIN_SIZE",
    "HUGE_PIXELS",
]
