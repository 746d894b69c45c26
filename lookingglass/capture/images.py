"""Reading and writing images, masks and environment maps, with clear errors.

In memory, images and environment maps are float32 (H, W, 3) linear RGB; masks are bool (H, W).
8-bit files are sRGB-encoded unless told otherwise; .exr and .hdr are linear. Writes are atomic.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import torch.nn.functional as F
from torch import Tensor

from ..errors import LookingGlassError
from ..fileio import write_atomic

HDR_SUFFIXES = {".exr", ".hdr"}
MIN_ENVMAP_HEIGHT = 8  # pixels: a 16x8 map is the coarsest that still has a sky, a horizon and a ground
MAX_IMAGE_SIDE = 16384  # pixels: larger sizes are typing errors (one 16384x16384 float image is 3 GiB)
LDR_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


def check_image_size(size, what: str = "size") -> tuple[int, int]:
    """`size` (W, H) as two ints, each in 1 .. MAX_IMAGE_SIDE; LookingGlassError naming `what`
    (an option such as "--size") otherwise."""
    try:
        w, h = size
        ok = all(float(s) == int(s) and 1 <= int(s) <= MAX_IMAGE_SIDE for s in (w, h))
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise LookingGlassError(f"{what} must be two whole numbers W H, each from 1 to {MAX_IMAGE_SIDE} pixels, "
                                f"got {' '.join(map(str, size)) if isinstance(size, (tuple, list)) else size}")
    return int(w), int(h)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function inverse, x in [0, 1]."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function, x clipped to [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def _check_exists(path: Path) -> None:
    try:
        if not path.exists():
            raise LookingGlassError("file not found", path)
    except PermissionError:  # a folder on the path that may not be searched
        raise LookingGlassError("cannot read (permission denied on a folder of its path)", path) from None
    if not path.is_file():
        raise LookingGlassError("not a file", path)
    if not os.access(path, os.R_OK):
        raise LookingGlassError("cannot read (permission denied)", path)


_NATIVE_OUTPUT_LOCK = threading.Lock()


@contextlib.contextmanager
def _native_output_held() -> Iterator[None]:
    """Hold what native code prints to the process's stdout and stderr (file descriptors 1 and 2)
    during the block: OpenEXR's C++ library prints its own lines about a corrupt file before
    raising. Held output is passed on when the block succeeds and dropped when it raises (the
    exception then says what was wrong, in one line). Serialized by a lock: the descriptors are the
    process's, shared by every thread."""
    with _NATIVE_OUTPUT_LOCK:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        held = tempfile.TemporaryFile()
        saved = []
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(held.fileno(), fd)
        except OSError:  # no such descriptor (an embedding without stdio): nothing to hold
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            held.close()
            yield
            return
        ok = False
        try:
            yield
            ok = True
        finally:
            _flush_c_stdio()
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            if ok:
                held.seek(0)
                text = held.read()
                if text:
                    os.write(2, text)
            held.close()


def _flush_c_stdio() -> None:
    """fflush(NULL): C stdio buffers (std::cout shares them) go out to the descriptors now."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None).fflush(None)


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    try:
        with _native_output_held(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "RGB" in channels:
                rgb = channels["RGB"].pixels
            elif all(c in channels for c in "RGB"):
                rgb = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
            elif "RGBA" in channels:
                rgb = channels["RGBA"].pixels[..., :3]
            elif len(channels) == 1:
                (only,) = channels.values()
                rgb = np.repeat(np.asarray(only.pixels)[..., None], 3, axis=-1)
            else:
                raise LookingGlassError(f"EXR has no RGB channels (found {sorted(channels)})", path)
    except LookingGlassError:
        raise
    except Exception as exc:  # OpenEXR raises plain exceptions on corrupt files
        raise LookingGlassError(f"cannot read EXR image: corrupt or truncated file ({exc})", path) from None
    return np.ascontiguousarray(rgb, dtype=np.float32)


def read_raw(path: str | os.PathLike) -> tuple[np.ndarray, bool]:
    """Read any supported image as float32 (H, W, C) with C in {1, 3, 4}, RGB(A) order.

    Returns (pixels, is_hdr): 8/16-bit images are scaled to [0, 1] but not linearized.
    """
    path = Path(path)
    _check_exists(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        return _read_exr(path), True
    if suffix not in HDR_SUFFIXES | LDR_SUFFIXES:
        raise LookingGlassError(f"unsupported image type '{suffix}' (use PNG, JPG, EXR or HDR)", path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | (cv2.IMREAD_ANYDEPTH if suffix == ".hdr" else 0))
    if img is None:
        raise LookingGlassError("cannot read image (corrupt or not an image)", path)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] >= 3:  # OpenCV is BGR(A)
        img = np.concatenate([img[..., 2::-1], img[..., 3:]], axis=-1)
    if img.dtype == np.uint8:
        out = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        out = img.astype(np.float32) / 65535.0
    else:
        out = img.astype(np.float32)
    return np.ascontiguousarray(out), suffix in HDR_SUFFIXES


def read_image(path: str | os.PathLike, encoding: str = "srgb") -> np.ndarray:
    """A photo or rendering as linear float32 (H, W, 3).

    encoding applies to 8/16-bit files: "srgb" (linearized) or "linear". EXR/HDR are linear.
    """
    if encoding not in ("srgb", "linear"):
        raise LookingGlassError(f"unknown image encoding '{encoding}' (use 'srgb' or 'linear')")
    img, is_hdr = read_raw(path)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    img = img[..., :3]
    if not np.isfinite(img).all():
        raise LookingGlassError("image contains NaN or infinite values", path)
    if is_hdr and (img < 0).any():
        count = int((img < 0).any(axis=-1).sum())
        raise LookingGlassError(f"image has negative radiance values ({count} pixel{'s' if count > 1 else ''}, "
                                f"down to {float(img.min()):.3g}); "
                                "clip them to 0", path)
    if not is_hdr and encoding == "srgb":
        img = srgb_to_linear(img)
    return np.ascontiguousarray(img, dtype=np.float32)


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """An object mask as bool (H, W): object where > 127 of 255.

    A single-channel or grey image is read directly; an image with an alpha channel that is not
    fully opaque uses the alpha channel (masks saved as PNG alpha); otherwise the first channel.
    """
    img, _ = read_raw(path)
    if img.shape[-1] in (2, 4) and img[..., -1].min() < 1.0:
        m = img[..., -1]
    else:
        m = img[..., 0]
    return m > (127.5 / 255.0)


def read_envmap(path: str | os.PathLike, scale: float = 1.0) -> np.ndarray:
    """An equirectangular environment map as linear float32 (H, W, 3) times `scale`.

    8-bit maps are linearized from sRGB. Rejects NaN/inf, negative values, an all-black map, a
    width that is not twice the height and a height below MIN_ENVMAP_HEIGHT.
    """
    path = Path(path)
    env = read_image(path, encoding="srgb")
    h, w = env.shape[:2]
    if w != 2 * h:
        raise LookingGlassError(f"environment map must be equirectangular with width = 2 x height, got {w}x{h}", path)
    if h < MIN_ENVMAP_HEIGHT:
        raise LookingGlassError(f"environment map is {w}x{h}: too small to light anything (at least "
                                f"{2 * MIN_ENVMAP_HEIGHT}x{MIN_ENVMAP_HEIGHT}; the networks use 256x128)", path)
    if (env < 0).any():
        raise LookingGlassError("environment map has negative radiance values", path)
    if not env.max() > 0:
        raise LookingGlassError("environment map is black (all zero): it lights nothing", path)
    if not np.isfinite(scale) or scale <= 0:
        raise LookingGlassError(f"environment map scale must be a positive number, got {scale}", path)
    return env * np.float32(scale)


def write_image(path: str | os.PathLike, image: np.ndarray, encoding: str = "srgb") -> Path:
    """Write linear float (H, W, 3) atomically: .exr/.hdr as linear float, .png/.jpg as 8-bit
    (sRGB-encoded when encoding == "srgb", else the clipped linear values)."""
    path = Path(path)
    suffix = path.suffix.lower()
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if suffix == ".exr":
        import OpenEXR

        def writer(tmp: Path) -> None:
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            with OpenEXR.File(header, {"RGB": np.ascontiguousarray(img[..., :3])}) as f:
                f.write(str(tmp))

        return write_atomic(path, writer)
    if suffix == ".hdr":
        bgr = np.ascontiguousarray(img[..., 2::-1])
        return write_atomic(path, lambda tmp: _cv_write(tmp, bgr))
    if suffix in (".png", ".jpg", ".jpeg"):
        enc = linear_to_srgb(img) if encoding == "srgb" else np.clip(img, 0, 1)
        u8 = np.round(enc * 255).astype(np.uint8)
        bgr = np.ascontiguousarray(u8[..., 2::-1]) if u8.shape[-1] >= 3 else u8
        return write_atomic(path, lambda tmp: _cv_write(tmp, bgr))
    raise LookingGlassError(f"unsupported output image type '{suffix}'", path)


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> Path:
    """Write a bool (H, W) mask as an 8-bit PNG (0 / 255), atomically."""
    u8 = np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8)
    return write_atomic(path, lambda tmp: _cv_write(tmp, u8))


def _cv_write(path: Path, pixels: np.ndarray) -> None:
    if not cv2.imwrite(str(path), pixels):
        raise LookingGlassError("cannot write image", path)


def exposure_factor(images: Tensor, target_mean: float = 0.5) -> float:
    """Factor that brings the mean of `images` (any shape, linear) to `target_mean`."""
    mean = float(images.double().mean())
    if not np.isfinite(mean) or mean <= 0:
        raise ValueError("images are black (mean radiance 0): nothing to normalize")
    return target_mean / mean


def resize_images(images: Tensor, width: int, height: int) -> Tensor:
    """(V, H, W, C) float -> (V, height, width, C), area-averaged when shrinking."""
    if images.shape[1:3] == (height, width):
        return images
    x = images.permute(0, 3, 1, 2)
    shrink = height <= images.shape[1] and width <= images.shape[2]
    x = F.interpolate(x, size=(height, width), mode="area") if shrink else \
        F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
    return x.permute(0, 2, 3, 1).contiguous()


def resize_masks(masks: Tensor, width: int, height: int) -> Tensor:
    """(V, H, W) bool -> (V, height, width) bool by area coverage >= 1/2."""
    return resize_images(masks.unsqueeze(-1).float(), width, height)[..., 0] >= 0.5
