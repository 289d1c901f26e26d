"""Video I/O (frame-accurate random access) and mocap->video time resampling; what real
files need: different lengths, a few pixels narrower, rotation metadata, variable frame rate."""
from pathlib import Path

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


# ------------------------------------------------------------------- what real files need (#28)
# sample durations in the mp4v writer's timescale (12800/s, 256 per frame at 50 fps): 50, 25 and
# 100 fps, the same total length (the edit list and track durations stay true)
VFR_DURATIONS = (256, 256, 256, 512, 256, 128, 256, 256, 128, 256)


def _mp4_boxes(data: bytes, lo: int, hi: int):
    import struct

    pos = lo
    while pos + 8 <= hi:
        size, kind = struct.unpack(">I4s", data[pos:pos + 8])
        yield kind.decode(), pos, pos + size
        pos += size


def _mp4_path_to(data: bytes, kinds: tuple) -> list[tuple[int, int]]:
    """(start, end) of the boxes moov > trak > ... > kinds[-1] (first video track)."""
    out, lo, hi = [], 0, len(data)
    for k in kinds:
        lo, hi = next((a, b) for kind, a, b in _mp4_boxes(data, lo, hi) if kind == k)
        out.append((lo, hi))
        lo += 8
    return out


def _mp4_rotate(path, degrees: int):
    """Set the video track's display matrix (tkhd) to a rotation, as phones write portrait."""
    import struct

    data = bytearray(path.read_bytes())
    (lo, _), = _mp4_path_to(bytes(data), ("moov", "trak", "tkhd"))[-1:]
    off = lo + 8 + 4 + (32 if data[lo + 8] == 1 else 20) + 16
    c, s = {90: (0, 1), 180: (-1, 0), 270: (0, -1)}[degrees]
    m = (c << 16, s << 16, 0, (-s) << 16, c << 16, 0, 0, 0, 1 << 30)
    data[off:off + 36] = struct.pack(">9i", *m)
    path.write_bytes(bytes(data))


def _mp4_durations(path, ticks):
    """Rewrite the video track's sample durations (stts) in place: a
    variable frame rate in the container's timestamps (moov is after mdat: no offset moves)."""
    import struct

    data = bytes(path.read_bytes())
    chain = _mp4_path_to(data, ("moov", "trak", "mdia", "minf", "stbl", "stts"))
    st_lo, st_hi = chain[-1]
    payload = struct.pack(">4xI", len(ticks)) + b"".join(struct.pack(">II", 1, t) for t in ticks)
    new = struct.pack(">I4s", 8 + len(payload), b"stts") + payload
    delta = len(new) - (st_hi - st_lo)
    out = bytearray(data[:st_lo] + new + data[st_hi:])
    for lo, _ in chain[:-1]:  # the parents grow
        out[lo:lo + 4] = struct.pack(">I", struct.unpack(">I", out[lo:lo + 4])[0] + delta)
    path.write_bytes(bytes(out))


def test_videos_of_different_lengths_are_cut_to_the_shortest_with_a_warning(tmp_path):
    from stages.common import check_videos, video_length

    paths = [tmp_path / f"c{i}.mp4" for i in range(3)]
    for p, n in zip(paths, (30, 27, 30), strict=True):
        write_mp4(p, (coded_frame(j) for j in range(n)), fps=50)
    assert check_videos(paths, 50.0) == []  # not an error any more
    n, warnings = video_length(paths)
    assert n == 27 and len(warnings) == 2
    for p, w in zip((paths[0], paths[2]), warnings, strict=True):
        assert w.startswith(f"{p}: frames: 30 frames, but {paths[1]} of the same sequence has 27")
        assert "cut to the shortest, 27 frames" in w


def test_a_video_a_few_pixels_narrower_is_accepted_padded_and_reported(tmp_path):
    from types import SimpleNamespace

    from formats.video import SIZE_TOL_PX, size_fit
    from stages.common import video_length

    p = tmp_path / "narrow.mp4"
    write_mp4(p, (coded_frame(j, w=128) for j in range(5)), fps=50)
    cam = SimpleNamespace(width=130, height=96)  # the calibration: 2 px wider
    n, warnings = video_length([p], [cam])
    assert n == 5 and len(warnings) == 1
    assert warnings[0].startswith(f"{p}: size: decoded 128x96, calibration 130x96: accepted")
    with VideoReader(p, size=(130, 96)) as v:
        for j in (0, 3, 1):
            img = v[j]
            assert img.shape == (96, 130, 3) and decode(img) == j  # same pixel coordinates
            assert not img[:, 128:].any()  # padded at the right, black
    with VideoReader(p, size=(126, 96)) as v:  # a calibration narrower: cropped
        assert v[2].shape == (96, 126, 3) and decode(v[2]) == 2
    info = video_info(p)
    too_far = 128 + SIZE_TOL_PX + 1
    with pytest.raises(InputError, match=rf"narrow.mp4: size: decoded frames are 128x96 .*"
                                         rf"calibration says {too_far}x96"):
        size_fit(p, info, too_far, 96)
    with pytest.raises(InputError, match="width and height are swapped"):
        video_length([p], [SimpleNamespace(width=96, height=128)])


def test_rotation_metadata_is_applied_and_a_swapped_calibration_is_named(tmp_path):
    from formats.video import size_fit

    p = tmp_path / "phone.mp4"
    write_mp4(p, (coded_frame(j) for j in range(4)), fps=30)
    _mp4_rotate(p, 90)
    info = video_info(p)
    assert info.rotation in (90, 270)
    with VideoReader(p) as v:
        img = v[2]
    assert (info.width, info.height) == (96, 128) and img.shape == (128, 96, 3)  # upright
    assert decode(np.ascontiguousarray(np.rot90(img, 1 if info.rotation == 90 else -1))) == 2
    with pytest.raises(InputError, match=r"phone.mp4: size: decoded frames are 96x128 "
                                         r"\(container rotation (90|270) deg.*swapped"):
        size_fit(p, info, 128, 96)  # a calibration of the unrotated sensor
    assert size_fit(p, info, 96, 128) == (0, 0)


def test_a_variable_frame_rate_is_flagged_from_the_container(tmp_path):
    from formats.video import video_warnings

    p = tmp_path / "vfr.mp4"
    write_mp4(p, (coded_frame(j) for j in range(len(VFR_DURATIONS))), fps=50)
    assert not video_info(p).variable_rate and video_warnings(p, video_info(p)) == []
    _mp4_durations(p, VFR_DURATIONS)
    info = video_info(p)
    assert info.variable_rate
    assert info.fps_min == pytest.approx(25.0) and info.fps_max == pytest.approx(100.0)
    (w,) = video_warnings(p, info)
    assert w.startswith(f"{p}: fps: variable frame rate: the container's frame durations give "
                        "25.000..100.000 fps")
    with VideoReader(p) as v:  # still decodes frame-accurately
        assert [decode(v[j]) for j in (0, 5, 9)] == [0, 5, 9]


@pytest.mark.skipif(not Path("/work/shared/real/video/pose2sim_demo/videos").is_dir(),
                    reason="no ../shared/real pose2sim demo")
def test_pose2sim_videos_meet_their_qualisys_calibration():
    """The real files: portrait 1088x1920 calibration, two videos encoded 1080 wide (accepted,
    reported), 100 frames at a constant 60 fps each."""
    from calib.io import read_camera
    from stages.common import video_length

    root = Path("/work/shared/real/video/pose2sim_demo")
    videos = [root / "videos" / f"cam0{i}.mp4" for i in range(1, 5)]
    cams = [read_camera(root / "calibration" / "Calib.qca.txt", f"cam0{i}") for i in range(1, 5)]
    n, warnings = video_length(videos, cams)
    assert n == 100
    assert [w.split(": ")[0] for w in warnings] == [str(videos[0]), str(videos[1])]
    assert all("decoded 1080x1920, calibration 1088x1920: accepted" in w for w in warnings)
    for v in videos:
        info = video_info(v)
        assert info.fps == 60.0 and not info.variable_rate and info.rotation == 0
