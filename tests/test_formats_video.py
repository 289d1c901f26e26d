"""Video I/O (frame-accurate random access) and mocap->video time resampling."""
import numpy as np
import pytest

from formats.c3d import Markers
from formats.errors import InputError
from formats.video import VideoReader, resample_to_video, video_info, write_mp4


def coded_frame(j, h=96, w=128):
    """A frame whose index is written as 8 black/white bars (robust to mp4v compression)."""
    img = np.full((h, w, 3), 60, np.uint8)
    for b in range(8):
        if (j >> b) & 1:
            img[:, b * 16:(b + 1) * 16, 0] = 250
    return img


def decode(img):
    return sum(1 << b for b in range(8) if img[48, b * 16 + 8, 0] > 155)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    path = tmp_path_factory.mktemp("v") / "cam.mp4"
    write_mp4(path, (coded_frame(j) for j in range(120)), fps=50)
    return path


def test_random_access_is_frame_accurate(video):
    info = video_info(video)
    assert (info.n_frames, info.fps, info.width, info.height) == (120, 50.0, 128, 96)
    rng = np.random.default_rng(0)
    with VideoReader(video) as v:
        assert [decode(f) for f in v.frames()] == list(range(120))
        idx = [int(i) for i in rng.integers(0, 120, 80)] + [119, 0, 100, 3, 3, 118]
        assert [decode(v[i]) for i in idx] == idx
        img = v[7]
        assert img.shape == (96, 128, 3) and img.dtype == np.uint8
        assert img[48, 8, 0] > 200 and img[48, 8, 2] < 100  # RGB order: red channel carries bars
        with pytest.raises(InputError) as e:
            v[120]
        assert e.value.frame == 120 and e.value.file == str(video)


def test_bad_videos(tmp_path, video):
    with pytest.raises(InputError, match="missing"):
        VideoReader(tmp_path / "none.mp4")
    (tmp_path / "junk.mp4").write_bytes(b"\x00junk" * 200)
    with pytest.raises(InputError):
        VideoReader(tmp_path / "junk.mp4")
    raw = video.read_bytes()
    (tmp_path / "cut.mp4").write_bytes(raw[: len(raw) // 3])  # moov atom at the end: unreadable
    with pytest.raises(InputError) as e:
        with VideoReader(tmp_path / "cut.mp4") as v:
            for _ in v.frames():
                pass
    assert e.value.file == str(tmp_path / "cut.mp4")
    with pytest.raises(InputError, match="uint8") as e:
        write_mp4(tmp_path / "bad.mp4", [np.zeros((8, 8, 3), np.float32)], 50)
    assert e.value.frame == 0
    with pytest.raises(InputError, match="size") as e:
        write_mp4(tmp_path / "bad.mp4", [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 16, 3), np.uint8)], 50)
    assert e.value.frame == 1


def linear_markers(rate, F, first_frame=0):
    """Two markers moving linearly in time: x = t, y = 2t, z = -t (metres, t in seconds)."""
    t = (first_frame + np.arange(F)) / rate
    xyz = np.stack([t, 2 * t, -t], axis=-1)[:, None, :].repeat(2, axis=1)
    xyz[:, 1] += 1.0
    return Markers(["A", "B"], xyz, rate, first_frame)


@pytest.mark.parametrize("rate", [100.0, 200.0, 240.0])
def test_resample_linear_motion_is_exact(rate):
    m = linear_markers(rate, int(rate * 3), first_frame=int(rate * 0.5))
    out = resample_to_video(m, n_frames=100, fps=50.0, offset_s=-0.613)
    t = np.arange(100) / 50 + 0.613
    assert np.allclose(out[:, 0], np.stack([t, 2 * t, -t], -1), atol=1e-12)
    assert np.allclose(out[:, 1], np.stack([t, 2 * t, -t], -1) + 1, atol=1e-12)
    # peer: numpy's interp on each coordinate
    ref = np.interp(t, m.times_s, m.xyz[:, 0, 0])
    assert np.allclose(out[:, 0, 0], ref, atol=1e-12)


def test_resample_keeps_gaps():
    m = linear_markers(100.0, 300)
    xyz = m.xyz.copy()
    xyz[51, 0] = np.nan  # sample 51 is between video frames 25 (sample 50) and 26 (sample 52)
    xyz[120, 1] = np.nan  # sample 120 is video frame 60 exactly
    g = Markers(m.names, xyz, 100.0)
    out = resample_to_video(g, 140, 50.0, 0.0)
    assert np.isfinite(out[25, 0]).all() and np.isfinite(out[26, 0]).all()  # exact hits survive
    assert np.isnan(out[60, 1]).all() and np.isfinite(out[60, 0]).all()
    assert np.isnan(out).sum() == 3
    out2 = resample_to_video(g, 140, 50.0, -0.005)  # half a sample later: samples 50.5, 120.5 ...
    assert np.isnan(out2[25, 0]).all() and np.isnan(out2[60, 1]).all()  # a gap neighbour
    assert np.isfinite(out2[59, 1]).all() and np.isfinite(out2[26, 0]).all()
    assert np.isnan(out2).sum() == 6


def test_capture_not_covering_the_video_names_file_and_frame():
    m = linear_markers(240.0, 240 * 2)  # 0 .. 1.9958 s
    with pytest.raises(InputError) as e:
        resample_to_video(m, n_frames=120, fps=50.0, offset_s=0.0, source="data/s03/Hug 1.c3d")
    assert e.value.file == "data/s03/Hug 1.c3d" and e.value.frame == 100
    with pytest.raises(InputError) as e:
        resample_to_video(m, n_frames=10, fps=50.0, offset_s=0.05)
    assert e.value.frame == 0


def test_resample_agrees_with_the_fitting_stages_clock():
    """One sync convention for the whole pipeline: formats.video and fitting.mocap (what the
    stages call) give the same positions for the same recipe offset."""
    from fitting import mocap

    m = linear_markers(240.0, 240 * 4, first_frame=30)
    for offset in (-0.35, -0.2013):  # the capture starts at 0.125 s of mocap time
        ref, vis = mocap.resample(m.times_s, m.xyz, mocap.frame_times(60, 50.0, offset))
        out = resample_to_video(m, n_frames=60, fps=50.0, offset_s=offset)
        assert vis.all()
        assert np.allclose(out, ref, atol=1e-12)
