"""A video replaces the earlier one only once it is complete (issue 63, item 5): the frames are
encoded into a temporary file beside the output and moved onto it on success (the temporaries
a killed writer left are removed). An encoder that
fails midway, is interrupted or writes nothing leaves the earlier video byte-identical, no
temporary file, and one line naming the file and what to do; it is never announced as
written."""
import importlib.util

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.commands.cli import describe, main
from mi_nerfpp.output.video import VideoWriteError, write_video

FRAMES = [np.full((18, 24, 3), 40 * i, np.uint8) for i in range(4)]
HAS_FFMPEG = importlib.util.find_spec('imageio_ffmpeg') is not None


def _earlier(path):
    """An earlier video at ``path``: its bytes."""
    write_video(str(path), FRAMES[:2], fps=5)
    return path.read_bytes()


def _leftovers(folder, keep):
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def _gif_encoder_failing_midway(monkeypatch, error=RuntimeError('GIF encoder crashed')):
    """Pillow's GIF writer (what imageio writes a GIF with) writes part of the file, then
    raises ``error``."""
    def save(im, fp, filename):
        fp.write(b'GIF89a' + b'\0' * 100)
        raise error
    Image.init()
    monkeypatch.setitem(Image.SAVE, 'GIF', save)
    monkeypatch.setitem(Image.SAVE_ALL, 'GIF', save)     # (an animation is saved by this one)


def test_a_gif_that_fails_midway_keeps_the_earlier_one(tmp_path, monkeypatch):
    out = tmp_path / 'v.gif'
    before = _earlier(out)
    _gif_encoder_failing_midway(monkeypatch)
    with pytest.raises(VideoWriteError) as e:
        write_video(str(out), FRAMES, fps=5)
    line = describe(e.value, None)
    assert '\n' not in line and line.startswith(f'{out}: cannot write the video (the encoder '
                                                f'failed: GIF encoder crashed)')
    assert 'earlier file' in line and 'a bug' not in line
    assert out.read_bytes() == before
    assert _leftovers(tmp_path, {'v.gif'}) == []


def test_a_video_interrupted_while_encoding_keeps_the_earlier_one(tmp_path, monkeypatch):
    out = tmp_path / 'v.gif'
    before = _earlier(out)
    _gif_encoder_failing_midway(monkeypatch, KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        write_video(str(out), FRAMES, fps=5)
    assert out.read_bytes() == before
    assert _leftovers(tmp_path, {'v.gif'}) == []


def test_a_complete_video_replaces_the_earlier_one(tmp_path):
    for name in ['v.gif'] + (['v.mp4'] if HAS_FFMPEG else []):
        out = tmp_path / name
        before = _earlier(out)
        stem, ext = name.split('.')
        (tmp_path / f'.{stem}.0123abcd.tmp.{ext}').write_bytes(b'left by a killed writer')
        write_video(str(out), FRAMES, fps=5)
        assert out.read_bytes() != before
        assert _leftovers(tmp_path, {'v.gif', 'v.mp4'}) == []
        if name.endswith('.gif'):
            assert iio.imread(out).shape[0] == len(FRAMES)


@pytest.mark.skipif(not HAS_FFMPEG, reason='writing MP4 needs imageio-ffmpeg')
@pytest.mark.parametrize('failure', ['raises at frame 2', 'writes nothing', 'writes garbage'])
def test_an_mp4_the_encoder_failed_to_write_is_refused(tmp_path, monkeypatch, failure):
    import imageio_ffmpeg

    def write_frames(path, *args, **kwargs):
        """imageio-ffmpeg's writer (a generator that takes frames), failing as asked."""
        if failure == 'writes garbage':
            with open(path, 'wb') as f:
                f.write(b'\0' * 64)
        frame = yield
        count = 0
        while frame is not None:
            count += 1
            if failure == 'raises at frame 2' and count == 2:
                with open(path, 'wb') as f:
                    f.write(b'\0\0\0\x18ftypisom' + b'\0' * 20)     # a partial MP4
                raise OSError('[Errno 32] Broken pipe\n\nFFMPEG COMMAND:\nffmpeg -y ...')
            frame = yield
    monkeypatch.setattr(imageio_ffmpeg, 'write_frames', write_frames)
    out = tmp_path / 'v.mp4'
    before = b'an earlier video'
    out.write_bytes(before)
    with pytest.raises(VideoWriteError) as e:
        write_video(str(out), FRAMES, fps=5)
    line = describe(e.value, None)
    assert '\n' not in line and line.startswith(f'{out}: cannot write the video ('), line
    assert {'raises at frame 2': 'the encoder failed', 'writes nothing': 'wrote nothing, 0 bytes',
            'writes garbage': 'not an MP4'}[failure] in line, line
    assert out.read_bytes() == before
    assert _leftovers(tmp_path, {'v.mp4'}) == []


def test_the_video_command_does_not_announce_a_video_it_failed_to_write(tiny_run, tmp_path,
                                                                        monkeypatch, capsys):
    out = tmp_path / 'orbit.gif'
    args = ['video', tiny_run, '-o', str(out), '--frames', '3', '--res', '24x18']
    assert main(args) == 0
    before = out.read_bytes()
    capsys.readouterr()
    _gif_encoder_failing_midway(monkeypatch)
    assert main(args) == 1
    captured = capsys.readouterr()
    assert 'wrote' not in captured.out
    lines = [line for line in captured.err.splitlines() if line.startswith('error')]
    assert len(lines) == 1 and str(out) in lines[0] and 'cannot write the video' in lines[0]
    assert 'Traceback' not in captured.err and 'a bug' not in captured.err
    assert out.read_bytes() == before
    assert _leftovers(tmp_path, {'orbit.gif', 'orbit_frames'}) == []
