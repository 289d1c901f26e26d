"""The 3D scene MCAP in Foxglove's schemas (formats.foxglove_scene), read back with mcap."""
import json

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from calib.camera import look_at, project
from formats.errors import InputError
from formats.foxglove_scene import (
    VERTEX_QUANTUM_M,
    CameraView,
    MeshTrack,
    decimate_for_scene,
    quaternion_from_matrix,
    scaled_intrinsics,
    write_scene,
)
from formats.mcap_log import read_log

FPS = 30.0
FRAMES = np.array([10, 12, 13, 17])
START = 5_000
W, H = 40, 30
OCTA_FACES = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                       [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def octahedron(rng, F, centre):
    base = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]) * 0.2
    return base[None] + np.asarray(centre) + rng.normal(0, 0.01, (F, 6, 3))


def cameras():
    cams = [look_at("c0", [3.0, 0.5, 1.5], [0, 0, 1.0], f=[50.0, 52.0], c=[19.0, 14.5], width=W,
                    height=H, k=[-0.2, 0.05, 0.01], p=[1e-3, -2e-3], model="opencv"),
            look_at("c1", [-0.5, -3.0, 2.0], [0, 0, 0.8], f=[45.0, 45.0], c=[20.5, 15.0],
                    width=W, height=H, k=[0.1, -0.02, 0.0], p=[0.0, 1e-3], model="opencv")]
    views = [CameraView(name=c.name, R=c.R, centre=c.T, K=c.K, dist=np.r_[c.k[:2], c.p, c.k[2]],
                        width=c.width, height=c.height) for c in cams]
    return cams, views


def image_of(cam_i):
    def f(frame):
        if cam_i == 1 and frame == 13:
            return None  # no image for this frame
        img = np.zeros((H, W, 3), np.uint8)
        img[:, : W // 2] = (200, 30, 30)  # left half red (RGB)
        img[..., 1] = frame
        return img
    return f


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rng = np.random.default_rng(3)
    F = len(FRAMES)
    wearer = octahedron(rng, F, [0, 0, 1.0])
    partner = octahedron(rng, F, [0.6, 0, 1.0])
    partner[2] = np.nan  # no partner fit at the third frame
    markers = wearer[:, :4] + 0.01
    markers[1, 2] = np.nan
    kp = {"wearer": wearer[:, :3], "partner": np.where(np.isfinite(partner[:, :2]), partner[:, :2], np.nan)}
    metrics = {"residual_mm": np.array([1.0, np.nan, 3.0, 4.0]), "depth_mm": np.arange(4.0)}
    flags = np.array([False, True, False, False])
    cams, views = cameras()
    path = tmp_path_factory.mktemp("scene") / "scene.mcap"
    out = write_scene(path, FPS, FRAMES,
                      [MeshTrack("wearer", wearer, OCTA_FACES, (0.9, 0.3, 0.2, 1.0)),
                       MeshTrack("partner", partner, OCTA_FACES, (0.2, 0.5, 0.9, 0.8))],
                      views, markers=markers, marker_names=["A", "B", "C", "D"], points3d=kp,
                      images={"c0": image_of(0), "c1": image_of(1)}, metrics=metrics,
                      flags=flags, image_scale=0.5, jpeg_quality=90, start_ns=START)
    return dict(path=path, out=out, wearer=wearer, partner=partner, markers=markers, cams=cams)


def expected_times():
    return [START + int(round((f - FRAMES[0]) / FPS * 1e9)) for f in FRAMES]


def test_topics_schemas_counts_and_times(scene):
    with open(scene["path"], "rb") as fh:
        summary = make_reader(fh).get_summary()
    schema_of = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    want = {"/bodies": "foxglove.SceneUpdate", "/markers": "foxglove.SceneUpdate",
            "/keypoints3d": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms",
            "/camera/c0/image": "foxglove.CompressedImage", "/camera/c1/image": "foxglove.CompressedImage",
            "/camera/c0/calibration": "foxglove.CameraCalibration",
            "/camera/c1/calibration": "foxglove.CameraCalibration",
            "/metrics": "mocap.SceneMetrics", "/flags": "mocap.SceneFlags"}
    assert schema_of == want
    counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    F = len(FRAMES)
    assert counts == {t: (F - 1 if t == "/camera/c1/image" else F) for t in want}
    assert scene["out"]["topics"] == counts and scene["out"]["frames"] == F
    assert scene["out"]["bytes"] == scene["path"].stat().st_size

    log = read_log(scene["path"])
    times = expected_times()
    assert times[1] - times[0] == int(round(2 / FPS * 1e9))
    for topic, msgs in log.items():
        got = [t for t, _ in msgs]
        assert got == ([t for t, f in zip(times, FRAMES, strict=True) if f != 13] if topic == "/camera/c1/image"
                       else times), topic
    for t, m in log["/bodies"]:
        for e in m.entities:
            assert e.timestamp.seconds * 1_000_000_000 + e.timestamp.nanos == t and e.frame_id == "world"


def test_meshes_round_trip(scene):
    bodies = read_log(scene["path"], topics=["/bodies"])["/bodies"]
    for j, (_t, m) in enumerate(bodies):
        ents = {e.id: e for e in m.entities}
        for name, v in (("wearer", scene["wearer"]), ("partner", scene["partner"])):
            if not np.all(np.isfinite(v[j])):
                assert name not in ents and [d.id for d in m.deletions] == [name]
                continue
            tri = ents[name].triangles[0]
            pts = np.array([[p.x, p.y, p.z] for p in tri.points])
            assert np.allclose(pts, v[j], atol=VERTEX_QUANTUM_M / 2 + 1e-12)
            assert np.array_equal(np.array(tri.indices).reshape(-1, 3), OCTA_FACES)
        assert np.isclose(ents["wearer"].triangles[0].color.r, 0.9)


def test_markers_and_keypoints(scene):
    log = read_log(scene["path"], topics=["/markers", "/keypoints3d"])
    _t, m1 = log["/markers"][1]
    ents = {e.id: e for e in m1.entities}
    xyz = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z]
                    for s in ents["markers"].spheres])
    assert np.allclose(xyz, scene["markers"][1][[0, 1, 3]])  # the gap is skipped
    assert [t.text for t in ents["marker_labels"].texts] == ["A", "B", "D"]
    _t, k2 = log["/keypoints3d"][2]
    ents = {e.id: e for e in k2.entities}
    assert len(ents["wearer"].spheres) == 3 and len(ents["partner"].spheres) == 0


def test_images_decode_to_scaled_size(scene):
    log = read_log(scene["path"], topics=["/camera/c0/image", "/camera/c0/calibration"])
    _t, im = log["/camera/c0/image"][3]
    assert im.format == "jpeg" and im.frame_id == "camera/c0"
    bgr = cv2.imdecode(np.frombuffer(im.data, np.uint8), cv2.IMREAD_COLOR)
    assert bgr.shape == (H // 2, W // 2, 3)
    assert abs(int(bgr[5, 2, 2]) - 200) < 12 and abs(int(bgr[5, 2, 1]) - 17) < 12  # RGB kept
    assert int(bgr[5, -3, 2]) < 20
    _t, cal = log["/camera/c0/calibration"][0]
    assert (cal.width, cal.height) == (W // 2, H // 2)


def child_from_world(P, t, Rwc):
    """A FrameTransform (child origin t, orientation Rwc in the parent) applied inversely:
    world points -> the child frame, Rwc^T (P - t)."""
    return (P - t) @ Rwc


def test_camera_transform_and_calibration_project_like_the_camera(scene):
    """A world point seen through the decoded /tf transform and calibration (K, D, plumb_bob)
    lands where calib.project puts it, in the scaled image's pixels; the camera centre is the
    origin of camera/<name>."""
    log = read_log(scene["path"], topics=["/tf", "/camera/c0/calibration", "/camera/c1/calibration"])
    _t, tfs = log["/tf"][1]
    tf = {x.child_frame_id: x for x in tfs.transforms}
    assert set(tf) == {"camera/c0", "camera/c1"}
    X = np.random.default_rng(0).uniform([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5], (50, 3))
    for cam in scene["cams"]:
        x = tf[f"camera/{cam.name}"]
        assert x.parent_frame_id == "world"
        t = np.array([x.translation.x, x.translation.y, x.translation.z])
        Rwc = Rotation.from_quat([x.rotation.x, x.rotation.y, x.rotation.z, x.rotation.w]).as_matrix()
        assert np.allclose(child_from_world(cam.T[None], t, Rwc), 0, atol=1e-9)
        Xc = child_from_world(X, t, Rwc)
        assert np.allclose(Xc, (X - cam.T) @ cam.R.T, atol=1e-9)
        assert np.all(Xc[:, 2] > 0)
        cal = log[f"/camera/{cam.name}/calibration"][1][1]
        assert cal.distortion_model == "plumb_bob" and cal.frame_id == f"camera/{cam.name}"
        K = np.array(cal.K).reshape(3, 3)
        P = np.array(cal.P).reshape(3, 4)
        assert np.allclose(P[:, :3], K) and np.allclose(np.array(cal.R).reshape(3, 3), np.eye(3))
        # pinhole: K through the decoded transform == the scaled camera's K with R, centre
        uv = Xc @ K.T
        s = np.array([cal.width / cam.width, cal.height / cam.height])
        pin = project(cam, X, distorted=False)
        assert np.allclose(uv[:, :2] / uv[:, 2:], (pin + 0.5) * s - 0.5, atol=1e-6)
        # with the lens: OpenCV plumb_bob with the decoded D == calib's opencv model
        uvd, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), K, np.array(cal.D))
        assert np.allclose(uvd[:, 0], (project(cam, X) + 0.5) * s - 0.5, atol=1e-6)


def test_metrics_and_flags_json(scene):
    log = read_log(scene["path"], topics=["/metrics", "/flags"])
    rows = [m for _t, m in log["/metrics"]]
    assert rows[1] == {"frame": 12, "residual_mm": None, "depth_mm": 1.0}
    assert [r["residual_mm"] for r in rows] == [1.0, None, 3.0, 4.0]
    assert [m["flagged"] for _t, m in log["/flags"]] == [0, 1, 0, 0]
    with open(scene["path"], "rb") as fh:
        import jsonschema
        for schema, _ch, msg in make_reader(fh).iter_messages(topics=["/metrics", "/flags"]):
            jsonschema.validate(json.loads(msg.data), json.loads(schema.data))
    with open(scene["path"], "rb") as fh:  # every protobuf message decodes with mcap_protobuf
        n = sum(1 for _ in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=["/bodies", "/tf", "/camera/c1/image"]))
    assert n == 3 * len(FRAMES) - 1


def test_bad_input_names_file_field_and_frame(tmp_path):
    rng = np.random.default_rng(1)
    _cams, views = cameras()
    v = octahedron(rng, 4, [0, 0, 1])
    path = tmp_path / "bad.mcap"
    with pytest.raises(InputError, match=r"bad\.mcap: meshes\[w\]\.faces.*out of range"):
        write_scene(path, FPS, FRAMES, [MeshTrack("w", v, OCTA_FACES + 1, (1, 1, 1, 1))], views)
    with pytest.raises(InputError, match=r"meshes\[w\]\.vertices.*F = 4"):
        write_scene(path, FPS, FRAMES, [MeshTrack("w", v[:3], OCTA_FACES, (1, 1, 1, 1))], views)
    with pytest.raises(InputError, match=r"frames \[frame 2\]: not strictly increasing"):
        write_scene(path, FPS, np.array([1, 2, 2, 3]), [], views)
    with pytest.raises(InputError, match=r"images\[c0\] \[frame 12\]: expected \(30, 40, 3\) uint8"):
        write_scene(path, FPS, FRAMES, [], views,
                    images={"c0": lambda f: np.zeros((H, W, 3), np.uint8 if f != 12 else np.float32)})
    with pytest.raises(InputError, match=r"metrics\[x\]"):
        write_scene(path, FPS, FRAMES, [], views, metrics={"x": np.zeros(3)})


def test_quaternion_and_scaled_intrinsics():
    for R in Rotation.random(50, random_state=2).as_matrix():
        q = quaternion_from_matrix(R)
        assert np.allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        assert np.allclose(Rotation.from_quat(quaternion_from_matrix(R)).as_matrix(), R)
    K2, w2, h2 = scaled_intrinsics(np.array([[1000.0, 0, 449.5], [0, 1000, 299.5], [0, 0, 1]]),
                                   900, 600, 0.5)
    assert (w2, h2) == (450, 300) and np.allclose(K2[[0, 1], [2, 2]], [224.5, 149.5])
    assert np.allclose(K2[[0, 1], [0, 1]], 500.0)


def test_decimate_anny_within_a_few_mm_and_on_budget():
    import body
    from geometry import nearest_surface

    model = body.load_model("anny")
    V = np.asarray(model.v_template, dtype=np.float64)
    Fc = np.asarray(model.faces)
    ids, faces = decimate_for_scene(V, Fc, target_faces=4000)
    assert ids.ndim == 1 and np.all(np.diff(ids) > 0) and ids.min() >= 0 and ids.max() < len(V)
    assert faces.shape[1] == 3 and faces.min() == 0 and faces.max() == len(ids) - 1
    assert np.all(np.isin(np.arange(len(ids)), faces))  # every kept vertex is used
    assert 0.95 * 4000 <= len(faces) <= 4000
    assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2]))
    import trimesh
    reduced = trimesh.Trimesh(V[ids], faces, process=False)
    assert reduced.is_watertight and reduced.is_winding_consistent and reduced.volume > 0
    d = nearest_surface(V, V[ids], faces).distance  # full mesh -> reduced surface
    assert np.mean(d) < 2e-3 and np.percentile(d, 99) < 5e-3 and d.max() < 10e-3
    # posing is indexing: a posed full mesh gives the posed reduced mesh
    posed = V[None] + np.array([0.1, 0.0, 0.0])
    assert np.allclose(posed[:, ids][0], V[ids] + [0.1, 0, 0])
    # a mesh within the budget comes back whole; bad faces are refused
    ids2, f2 = decimate_for_scene(V[:6] * 0 + np.eye(6, 3), OCTA_FACES, target_faces=100)
    assert np.array_equal(ids2, np.arange(6)) and np.array_equal(f2, OCTA_FACES)
    with pytest.raises(InputError, match="faces"):
        decimate_for_scene(V, Fc + len(V))


def test_images_given_at_the_scaled_size_are_written_as_the_full_ones(tmp_path):
    """An image callable may hand the image already resized to ``image_scale`` (what the QA
    stage's frame feed keeps): the file is byte for byte the one written from the full
    images; another size is an InputError naming it."""
    _cams, views = cameras()
    w2, h2 = scaled_intrinsics(np.eye(3), W, H, 0.5)[1:]
    rng = np.random.default_rng(4)
    full = {f: rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for f in FRAMES}
    small = {f: cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA) for f, img in full.items()}
    a, b = tmp_path / "full.mcap", tmp_path / "small.mcap"
    write_scene(a, FPS, FRAMES, [], views, images={"c0": full.__getitem__}, image_scale=0.5)
    write_scene(b, FPS, FRAMES, [], views, images={"c0": small.__getitem__}, image_scale=0.5)
    assert a.read_bytes() == b.read_bytes()
    with pytest.raises(InputError, match=r"images\[c0\] \[frame 10\]: expected \(30, 40, 3\)"):
        write_scene(tmp_path / "c.mcap", FPS, FRAMES, [], views,
                    images={"c0": lambda f: np.zeros((h2 + 1, w2, 3), np.uint8)}, image_scale=0.5)
