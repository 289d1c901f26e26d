"""MCAP logs: JSON streams with jsonschema (mcap) and a Foxglove SceneUpdate channel, read back."""
import json

import jsonschema
import numpy as np
import pytest
from test_calib_camera import random_camera

from formats.errors import InputError
from formats.mcap_log import SequenceLog, frustum_lines, read_log


def camera_frustum(cam, depth):
    """What a caller passes to ``log_scene(frustums=...)``: the camera centre and the points
    ``depth`` m deep on the rays through the 4 image corners (calib knows the lens)."""
    from calib.camera import rays_from_pixels

    w, h = cam.width - 1, cam.height - 1
    d = rays_from_pixels(cam, np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float))
    return cam.T, (d / d[:, 2:3] * depth) @ cam.R + cam.T  # camera frame -> world


def test_write_and_read_back_every_stream(tmp_path):
    rng = np.random.default_rng(0)
    cams = [random_camera(rng, name=f"c{i}") for i in range(2)]
    xyz = rng.normal(size=(5, 4, 3))
    xyz[2, 1] = np.nan
    joints = rng.normal(size=(5, 3, 3))
    joints[3, 2] = np.nan
    kp = rng.uniform(0, 900, (5, 2, 65, 3))
    path = tmp_path / "seq.mcap"
    with SequenceLog(path, fps=50, start_ns=1_000, validate=True) as log:
        for j in range(5):
            log.log_markers(j, ["A", "B", "C", "D"], xyz[j])
            log.log_keypoints(j, "50591643", kp[j])
            log.log_params(j, 0, {"transl": joints[j, 0], "betas": np.arange(3.0)})
            log.log_metrics(j, {"mpjpe_mm": 10.0 + j, "bad": np.nan})
            log.log_scene(j, points={"markers": xyz[j]}, bones={"skeleton": (joints[j], [(0, 1), (1, 2)])},
                          frustums={c.name: camera_frustum(c, 0.3) for c in cams} if j == 0 else None)
    out = read_log(path)
    assert set(out) == {"/markers", "/keypoints/50591643", "/fit/0", "/metrics", "/scene"}
    times = [t for t, _ in out["/markers"]]
    assert times == [1_000 + j * 20_000_000 for j in range(5)]
    m2 = out["/markers"][2][1]
    assert m2["xyz"][1] is None and np.allclose(m2["xyz"][0], xyz[2, 0])
    assert np.allclose(out["/keypoints/50591643"][4][1]["people"][1]["kp"], kp[4, 1])
    assert out["/metrics"][3][1]["values"] == {"mpjpe_mm": 13.0, "bad": None}
    assert np.allclose(out["/fit/0"][1][1]["params"]["transl"], joints[1, 0])

    # every JSON message conforms to the jsonschema stored in the file
    from mcap.reader import make_reader
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        n = 0
        for schema, channel, msg in reader.iter_messages():
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema"
                jsonschema.validate(json.loads(msg.data), json.loads(schema.data))
                n += 1
            else:
                assert (schema.name, schema.encoding, channel.message_encoding) == (
                    "foxglove.SceneUpdate", "protobuf", "protobuf")
        assert n == 20

    scenes = [m for _, m in out["/scene"]]
    ents = {e.id: e for e in scenes[2].entities}
    assert len(ents["markers"].spheres) == 3  # the NaN marker is skipped
    sp = ents["markers"].spheres[0]
    assert np.allclose([sp.pose.position.x, sp.pose.position.y, sp.pose.position.z], xyz[2, 0])
    assert ents["markers"].frame_id == "world"
    assert len(ents["skeleton"].lines[0].points) == 4
    assert len({e.id for e in scenes[3].entities if e.id == "skeleton"}) == 1
    assert len(next(e for e in scenes[3].entities if e.id == "skeleton").lines[0].points) == 2
    cam_ents = [e for e in scenes[0].entities if e.id.startswith("camera/")]
    assert sorted(e.id for e in cam_ents) == ["camera/c0", "camera/c1"]
    pts = np.array([[q.x, q.y, q.z] for q in cam_ents[0].lines[0].points])
    assert np.allclose(pts, frustum_lines(*camera_frustum(cams[int(cam_ents[0].id[-1])], 0.3)))
    assert scenes[1].entities[0].timestamp.nanos == (1_000 + 20_000_000) % 1_000_000_000


def test_frustum_lines_are_the_pyramid_edges():
    from calib import project

    cam = random_camera(np.random.default_rng(1))
    centre, corners = camera_frustum(cam, 0.5)
    seg = frustum_lines(centre, corners)
    assert seg.shape == (16, 3)
    assert np.allclose(seg[0::4], cam.T)  # centre to each corner
    assert np.allclose(seg[1::4], corners)
    assert np.allclose(seg[2::4], corners) and np.allclose(seg[3::4], np.roll(corners, -1, 0))
    assert np.allclose(project(cam, seg[[1, 5, 9, 13]]), [[0, 0], [899, 0], [899, 899], [0, 899]], atol=1e-6)
    with pytest.raises(ValueError, match="'c7'.*corners \\(4, 3\\)"):
        frustum_lines(centre, corners[:3], "c7")
    bad = corners.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="'c7': non-finite"):
        frustum_lines(centre, bad, "c7")


def test_validation_and_bad_files(tmp_path):
    with SequenceLog(tmp_path / "v.mcap", fps=50, validate=True) as log:
        log.add_json_channel("/custom", {"type": "object", "required": ["frame"]})
        log.log_json("/custom", 0, {"frame": 0})
        with pytest.raises(jsonschema.ValidationError):
            log.log_json("/custom", 1, {"nope": 1})
        with pytest.raises(KeyError):
            log.log_json("/unknown", 0, {})
        with pytest.raises(ValueError):
            log.log_json("/custom", 2, {"frame": float("nan")})
    raw = (tmp_path / "v.mcap").read_bytes()
    (tmp_path / "t.mcap").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputError) as e:
        read_log(tmp_path / "t.mcap")
    assert e.value.file == str(tmp_path / "t.mcap")
    with pytest.raises(InputError, match="missing"):
        read_log(tmp_path / "none.mcap")
