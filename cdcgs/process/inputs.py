"""What ``cdcgs process`` starts from: a folder of photos or a video, turned into upright images.

Photos are read with PIL, turned upright by their EXIF orientation and written as they are
otherwise (JPEG stays JPEG). From a video, ``count`` frames are kept: the video is cut into
``count`` windows of equal length and the sharpest frame of each (the variance of its Laplacian)
is written as PNG. Every reading error names the file and what is wrong with it.
"""

from __future__ import annotations

import os

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from ..errors import InputError

__all__ = ["IMAGE_EXTENSIONS", "VIDEO_EXTENSIONS", "copy_photos", "list_photos", "sharpness", "video_frames"]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
EXIF_ORIENTATION = 0x0112


def list_photos(folder: str) -> list[str]:
    """The image files directly in ``folder``, sorted by name."""
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith(IMAGE_EXTENSIONS) and not n.startswith("."))
    if not names:
        raise InputError(folder, f"holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    return [os.path.join(folder, n) for n in names]


def copy_photos(paths: list[str], out_dir: str, progress: bool = True) -> list[str]:
    """Write each photo upright into ``out_dir``; returns the names. A JPEG or PNG without a
    rotation in its EXIF is copied byte for byte (its EXIF focal length stays for COLMAP); a
    rotated one is turned upright and written again (JPEG at quality 95, EXIF kept); other formats
    become PNG."""
    from tqdm import tqdm

    os.makedirs(out_dir, exist_ok=True)
    names = []
    for path in tqdm(paths, desc="images", unit="img", disable=not progress, leave=False):
        name = os.path.basename(path)
        try:
            with Image.open(path) as image:
                image.load()
                kind = "JPEG" if image.format == "MPO" else image.format  # MPO: phones' multi-picture JPEGs
                orientation = image.getexif().get(EXIF_ORIENTATION, 1)
                if kind in ("JPEG", "PNG") and orientation == 1:
                    with open(path, "rb") as src, open(os.path.join(out_dir, name), "wb") as dst:
                        dst.write(src.read())
                else:
                    upright = ImageOps.exif_transpose(image)
                    if upright.mode not in ("RGB", "L"):
                        upright = upright.convert("RGB")
                    if kind == "JPEG":
                        upright.save(os.path.join(out_dir, name), quality=95, exif=upright.getexif())
                    else:
                        name = os.path.splitext(name)[0] + ".png"
                        upright.save(os.path.join(out_dir, name))
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
            raise InputError(path, f"cannot be read as an image ({err})") from None
        names.append(name)
    if len(set(names)) != len(names):
        raise InputError(os.path.dirname(paths[0]), "two images would get the same name after conversion to PNG")
    return names


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (higher: sharper)."""
    grey = rgb.astype(np.float32).mean(axis=-1)
    step = max(1, min(grey.shape) // 360)  # about 360 px on the short side is enough to judge blur
    grey = grey[::step, ::step]
    lap = grey[1:-1, 1:-1] * 4 - grey[:-2, 1:-1] - grey[2:, 1:-1] - grey[1:-1, :-2] - grey[1:-1, 2:]
    return float(lap.var())


def video_frames(path: str, out_dir: str, count: int, progress: bool = True) -> list[str]:
    """Decode ``path``, keep the sharpest frame of each of ``count`` equal windows, write them as
    ``frame_00000.png`` ... into ``out_dir``; returns the names."""
    import imageio_ffmpeg
    from tqdm import tqdm

    try:
        total, _ = imageio_ffmpeg.count_frames_and_secs(path)
        reader = imageio_ffmpeg.read_frames(path)
        meta = next(reader)
    except (RuntimeError, OSError, StopIteration, ValueError) as err:
        raise InputError(
            path, f"cannot be decoded as a video ({str(err).strip().splitlines()[-1] if str(err) else err})"
        ) from None
    if total <= 0:
        raise InputError(path, "the video has no frames")
    width, height = meta["size"]
    count = min(count, total)
    edges = np.linspace(0, total, count + 1)
    os.makedirs(out_dir, exist_ok=True)
    names: list[str] = []
    best: tuple[int, float, np.ndarray] | None = None  # (window, sharpness, frame) of the window being read

    def keep(window: int, frame: np.ndarray) -> None:
        names.append(f"frame_{window:05d}.png")
        Image.fromarray(frame).save(os.path.join(out_dir, names[-1]))

    index = 0
    try:
        for raw in tqdm(reader, total=total, desc="frames", unit="frame", disable=not progress, leave=False):
            frame = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3)
            window = min(int(np.searchsorted(edges, index, side="right")) - 1, count - 1)
            if best is not None and window != best[0]:
                keep(best[0], best[2])  # one frame in memory at a time, not one per window
                best = None
            score = sharpness(frame)
            if best is None or score > best[1]:
                best = (window, score, frame.copy())
            index += 1
    except (RuntimeError, OSError) as err:
        raise InputError(path, f"decoding stopped at frame {index} ({err})") from None
    finally:
        reader.close()
    if best is not None:
        keep(best[0], best[2])
    if not names:
        raise InputError(path, "no frame could be decoded")
    return names
