"""Declaring how a camera's images kept their colour when they were encoded (``chroma_subsampling``,
``chroma_red_blue_swapped`` in ``episode.json``; docs/episode-format.md).

A JPEG file says it in its header, and the reader takes it from there. PNG files do not: images
that a camera or recorder delivered as JPEG or video (4:2:0 colour) and that were stored again as
PNG look like a renderer's, with every pixel's colour. Reconstruction compares its renders with
such images after the same subsampling only when the episode says so
(:mod:`manisplat.reconstruct.chroma`).
"""

from __future__ import annotations

from pathlib import Path

from manisplat.episode.format import META_FILE, EpisodeFormatError
from manisplat.episode.images import CHROMA_SUBSAMPLING, RGB, StoredChroma, find_image, jpeg_chroma_subsampling
from manisplat.episode.meta import load_meta, save_meta
from manisplat.episode.reader import Episode


def set_chroma_subsampling(episode: str | Path, scheme: str, *, camera: str | None = None,
                           red_blue_swapped: bool = False) -> tuple[StoredChroma | None, StoredChroma]:
    """Record in ``episode``'s ``episode.json`` that ``camera``'s images (default: the one camera)
    kept their colour as ``scheme`` (a key of :data:`~manisplat.episode.images.CHROMA_SUBSAMPLING`)
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
    meta = load_meta(path / META_FILE)
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
    before = Episode.open(path).chroma_subsampling(camera)
    extra = meta.cameras[camera].extra
    extra["chroma_subsampling"] = scheme
    extra["chroma_red_blue_swapped"] = bool(red_blue_swapped)
    save_meta(path / META_FILE, meta)
    return before, StoredChroma(scheme, bool(red_blue_swapped))


__all__ = ["set_chroma_subsampling"]
