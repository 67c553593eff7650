"""Declaring how a camera's images kept their colour when they were encoded (``chroma_subsampling``,
``chroma_red_blue_swapped`` in ``episode.json``; docs/episode-format.md).

A JPEG file says it in its header, and the reader takes it from there. PNG files do not: images
that a camera or recorder delivered as JPEG or video (4:2:0 colour) and that were stored again as
PNG look like a renderer's, with every pixel's colour. Reconstruction compares its renders with
such images after the same subsampling only when the episode says so
(:mod:`manisplat.reconstruct.chroma`). A video file says it in its pixel format (:func:`video_chroma`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import av

from manisplat.episode.format import CHROMA_SUBSAMPLING, META_FILE, EpisodeFormatError
from manisplat.episode.images import RGB, StoredChroma, chroma_keys, find_image, jpeg_chroma_subsampling
from manisplat.episode.meta import save_meta
from manisplat.episode.reader import Episode

log = logging.getLogger(__name__)

def video_chroma(path: str | Path) -> StoredChroma | None:
    """How the video ``path`` kept its colour: the scheme of its first video stream's pixel format
    (``yuv420p``: 4:2:0; RGB formats: 4:4:4; the decoder converts to RGB, so red and blue are not
    swapped). None for a grey video, and (logged) for a stream whose header names no pixel format
    or one whose colour planes are not a scheme of
    :data:`~manisplat.episode.format.CHROMA_SUBSAMPLING`."""
    with av.open(str(path)) as container:
        pixel_format = container.streams.video[0].codec_context.format
    if pixel_format is None:
        log.warning("%s: no pixel format in the stream's header; how it kept its colour is not known", path)
        return None
    probe = av.VideoFormat(pixel_format.name, 64, 48)
    if probe.is_rgb:
        return StoredChroma("4:4:4")
    colour = [c for c in probe.components if not c.is_luma and not c.is_alpha]
    if not colour:  # grey
        return None
    block = (64 // colour[0].width, 48 // colour[0].height)
    scheme = next((name for name, b in CHROMA_SUBSAMPLING.items() if b == block), None)
    if scheme is None:
        log.warning("%s: pixel format %s keeps one colour sample per %dx%d pixels, not a scheme the reconstruction "
                    "models; how it kept its colour is taken as not known", path, pixel_format.name, *block)
        return None
    return StoredChroma(scheme)


def set_chroma_subsampling(episode: str | Path, scheme: str, *, camera: str | None = None,
                           red_blue_swapped: bool = False) -> tuple[StoredChroma | None, StoredChroma]:
    """Record in ``episode``'s ``episode.json`` that ``camera``'s images (default: the one camera)
    kept their colour as ``scheme`` (a key of :data:`~manisplat.episode.format.CHROMA_SUBSAMPLING`)
    when they were encoded, the encoder having taken red for blue when ``red_blue_swapped``.
    ``episode.json`` is rewritten atomically; nothing else changes.

    Returns ``(before, after)``: what the episode said before (its ``episode.json``, else its JPEG
    files' header; None: nothing), and now.

    Raises:
        ValueError: ``scheme`` is not a known scheme, or the camera's images are JPEG files whose
            header says otherwise (the files are the truth).
        EpisodeFormatError: no such camera, or none named in an episode with several.
    """
    if scheme not in CHROMA_SUBSAMPLING:
        raise ValueError(f"chroma subsampling {scheme!r} is not one of {', '.join(CHROMA_SUBSAMPLING)}")
    path = Path(episode)
    opened = Episode.open(path)
    meta = opened.meta
    if camera is None:
        if len(meta.cameras) != 1:
            raise EpisodeFormatError(f"{path} has cameras {', '.join(meta.cameras)}: name one (--camera NAME)")
        camera = next(iter(meta.cameras))
    if camera not in meta.cameras:
        raise EpisodeFormatError(f"{path} has no camera {camera!r}; cameras: {', '.join(meta.cameras)}")
    first = find_image(path / meta.layout.camera(camera).folder(RGB.folder), 0)
    if first is not None and first.suffix == ".jpg":
        header = jpeg_chroma_subsampling(first.read_bytes())
        if header != scheme:
            raise ValueError(f"{path}: camera {camera}'s images are JPEG files whose header says "
                             f"{header or 'grey'}, not {scheme}")
    before = opened.chroma_subsampling(camera)
    after = StoredChroma(scheme, bool(red_blue_swapped))
    meta.cameras[camera].extra.update(chroma_keys(after))
    save_meta(path / META_FILE, meta)
    return before, after


__all__ = ["set_chroma_subsampling", "video_chroma"]
