"""Writing rendered frames: MP4 (imageio + imageio-ffmpeg, the ``video`` extra), GIF and PNG (Pillow).

No OpenGL and no MuJoCo here: :mod:`hyqjax.io.render` makes the frames, these functions only write them.
"""
from __future__ import annotations

import os

import numpy as np

__all__ = ["has_ffmpeg", "write_png", "write_video"]


def _even(img: np.ndarray) -> np.ndarray:
    """Crop to even width and height (H.264 with yuv420p needs them)."""
    h, w = img.shape[:2]
    return img[: h - h % 2, : w - w % 2]


def has_ffmpeg() -> bool:
    """Whether MP4 can be written (imageio and imageio-ffmpeg with its ffmpeg binary are installed)."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg

        return bool(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # noqa: BLE001  (not installed, or no binary for this platform)
        return False


def write_video(path: str, images, fps: float) -> int:
    """Write an iterable of frames to ``path`` (``.mp4`` through imageio + imageio-ffmpeg, the ``video`` extra;
    ``.gif`` through Pillow, which matplotlib already needs).

    Returns the number of frames written.
    """
    ext = os.path.splitext(path)[1].lower()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    n = 0
    if ext == ".mp4":
        if not has_ffmpeg():
            raise RuntimeError("writing .mp4 needs imageio-ffmpeg (pip install 'hyqjax[video]'); or write a .gif")
        import imageio.v2 as imageio

        with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", macro_block_size=1,
                                pixelformat="yuv420p", quality=7) as w:
            for img in images:
                w.append_data(_even(img))
                n += 1
    elif ext == ".gif":
        from PIL import Image

        pil = [Image.fromarray(img).convert("P", palette=Image.Palette.ADAPTIVE, colors=128) for img in images]
        n = len(pil)
        if n == 0:
            raise ValueError("no frames to write")
        duration = max(20, int(round(1000.0 / fps / 10.0)) * 10)  # GIF delays are in centiseconds
        pil[0].save(path, save_all=True, append_images=pil[1:], duration=duration, loop=0, optimize=False)
    else:
        raise ValueError(f"unknown video format {ext!r}: use .mp4 or .gif")
    return n


def write_png(path: str, img: np.ndarray) -> None:
    from PIL import Image

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    Image.fromarray(img).save(path)
