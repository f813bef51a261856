"""Headless pictures: `bh8 render` (PNG of the hand), and `write_animation` (GIF and MP4) that
`record_episode` and `bh8 eval` use (issue 5, deliverable 6)."""
from __future__ import annotations

import sys

import imageio.v2 as imageio
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bh8_gym.cli import main
from bh8_gym.rendering import gif_durations, steps_per_frame, write_animation


def _frames(count: int, height: int = 48, width: int = 64) -> list[np.ndarray]:
    """Frames that differ from each other: a bright bar moving across a dark picture."""
    frames = []
    for k in range(count):
        frame = np.full((height, width, 3), 30, dtype=np.uint8)
        frame[:, 4 * k: 4 * k + 8] = (250, 200, 40)
        frames.append(frame)
    return frames


def test_bh8_render_writes_a_png_of_the_hand_closed_on_an_object(tmp_path, capsys):
    path = tmp_path / "closed.png"
    code = main(["render", "--closed", "--object", "cylinder:d0.06x0.10", "--width", "160", "--height", "120",
                 "-o", str(path)])
    assert code == 0, capsys.readouterr()
    picture = imageio.imread(path)
    assert picture.shape[:2] == (120, 160)
    assert picture[..., :3].std() > 10  # a hand and a cylinder, not a blank frame


@pytest.mark.parametrize("arguments, message", [
    (["--spread", "200"], "--spread must be 0..180"),
    (["--object", "teapot:3"], "teapot"),
    (["--width", "0"], "--width and --height must be 16..4096"),
    (["--object", "{tmp}/bad.urdf"], "is not well-formed XML"),
])
def test_bh8_render_refuses_bad_arguments_with_exit_code_2(tmp_path, capsys, arguments, message):
    """Errors on stderr, one line, no traceback, nothing written."""
    (tmp_path / "bad.urdf").write_text("not xml")
    path = tmp_path / "never.png"
    assert main(["render", "-o", str(path), *[a.format(tmp=tmp_path) for a in arguments]]) == 2
    assert message in capsys.readouterr().err
    assert not path.exists()
    assert main(["render", "-o", str(tmp_path)]) == 2  # a directory, not a .png
    assert "--output must be a .png file" in capsys.readouterr().err


def test_gif_keeps_every_frame_at_the_frame_rate(tmp_path):
    frames = _frames(10)
    path = write_animation(frames, tmp_path / "clip.gif", fps=25.0)
    reader = imageio.get_reader(path)
    read = [frame[..., :3] for frame in reader]
    assert len(read) == 10
    assert reader.get_meta_data(0)["duration"] == pytest.approx(40.0, abs=1.0)  # ms per frame
    assert np.abs(read[3].astype(int) - frames[3]).mean() < 8  # GIF's palette, nothing worse


@given(count=st.integers(1, 400), fps=st.floats(0.5, 200.0))
def test_gif_durations_keep_the_clip_length_in_whole_centiseconds(count, fps):
    """A GIF frame lasts whole centiseconds: 38.6 fps (25.9 ms) must not play as 50 fps (20 ms), nor
    51.5 fps (19.4 ms, `bh8 eval`'s old GIF) with some 10 ms frames, which browsers show at 100 ms."""
    durations = gif_durations(count, fps)
    # every frame at least 20 ms: browsers play 10 ms frames at 100 ms
    assert len(durations) == count and all(d >= 20 and d % 10 == 0 for d in durations)
    if 1000.0 / fps >= 20.0:  # frames players can show: the clip ends within 5 ms of its length
        assert abs(sum(durations) - count * 1000.0 / fps) <= 5.0 + 1e-6


def test_steps_per_frame_makes_frames_of_at_least_20_ms():
    """The grasp env's 6.47 ms steps: every 4th (25.9 ms); reach's 4.65 ms: every 5th; 9600 baud's 32 ms: each."""
    assert [steps_per_frame(s) for s in (0.00646875, 0.00465, 0.02, 0.03225)] == [4, 5, 1, 1]


def test_mp4_keeps_every_frame_at_the_frame_rate(tmp_path):
    frames = _frames(12)
    path = write_animation(frames, tmp_path / "clip.mp4", fps=25.0)
    reader = imageio.get_reader(path, format="FFMPEG")
    assert reader.get_meta_data()["fps"] == pytest.approx(25.0)
    read = list(reader.iter_data())  # its len() is unknown (inf) for a stream
    assert len(read) == 12 and read[0].shape == (48, 64, 3)
    assert np.abs(read[5].astype(int) - frames[5]).mean() < 12  # lossy, but the same picture


@pytest.mark.parametrize("frames, path, fps, message", [
    ([], "clip.gif", 20.0, "at least one frame"),
    (None, "clip.gif", 0.0, "fps must be positive"),
    (None, "clip.gif", float("nan"), "fps must be positive"),
    (None, "clip.avi", 20.0, "'.*clip.avi'"),
])
def test_write_animation_refuses_bad_arguments(tmp_path, frames, path, fps, message):
    with pytest.raises(ValueError, match=message):
        write_animation(_frames(3) if frames is None else frames, tmp_path / path, fps=fps)
    assert not (tmp_path / path).exists()


def test_mp4_without_imageio_ffmpeg_says_which_extra_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if not installed
    with pytest.raises(RuntimeError, match=r"bh8-gym\[video\]"):
        write_animation(_frames(2), tmp_path / "clip.mp4")
