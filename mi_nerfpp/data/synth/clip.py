"""A synthetic video: rendered frames encoded as a phone's clip would be, H.264 in an MP4
(PyAV, the decoder ``optimize.py clip.mp4`` reads videos with), for the tests and benchmarks of
video in (:mod:`mi_nerfpp.data.video`)."""
from __future__ import annotations

# Frames per second of a clip, and its constant rate factor: 8 is nearly lossless, so that the
# tests see the frames as rendered (motion blur included), not the codec's artefacts.
CLIP_FPS = 24
CLIP_CRF = 8


def encode_clip(path, frames, fps=CLIP_FPS, crf=CLIP_CRF) -> None:
    """``frames`` (each H x W x 3 uint8, sRGB) as an H.264 MP4 video at ``path``."""
    import av  # deferred: PyAV decodes the videos given to optimize; only clips import it here
    h, w = frames[0].shape[:2]
    with av.open(str(path), 'w') as container:
        stream = container.add_stream('libx264', rate=fps, options={'crf': str(crf)})
        stream.width, stream.height, stream.pix_fmt = w, h, 'yuv420p'
        for image in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format='rgb24')):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
