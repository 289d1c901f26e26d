"""shape_fit: scan loading errors, the scan fit on a synthetic Anny scan (noise, holes, unknown
heading), and marker placement refinement recovering slid markers."""
from __future__ import annotations

import numpy as np
import pytest

from formats.errors import InputError
from formats.scan import read_scan as load_scan


def _write_ply(path, pts, normals=None):
    n = len(pts)
    cols = "x y z" + (" nx ny nz" if normals is not None else "")
    head = ["ply", "format ascii 1.0", f"element vertex {n}"]
    head += [f"property float {c}" for c in cols.split()]
    head += ["end_header"]
    data = pts if normals is None else np.hstack([pts, normals])
    path.write_text("\n".join(head) + "\n" + "\n".join(" ".join(f"{v:.6f}" for v in r)
                                                      for r in data) + ("\n" if n else ""))
    return path


def test_missing_or_empty_scan_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply: scan: file not found"):
        load_scan(tmp_path / "nope.ply")
    empty = _write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    with pytest.raises(InputError, match=r"empty\.ply: scan: .*(no points|unreadable)"):
        load_scan(empty)
    few = _write_ply(tmp_path / "few.ply", np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(InputError, match="only 10 points"):
        load_scan(few)
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage")
    with pytest.raises(InputError, match=r"junk\.ply: scan"):
        load_scan(tmp_path / "junk.ply")


def test_scan_points_and_normals_read_back(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3))
    nrm = rng.normal(size=(500, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    p, n = load_scan(_write_ply(tmp_path / "s.ply", pts, nrm))
    np.testing.assert_allclose(p, pts, atol=1e-5)
    np.testing.assert_allclose(n, nrm, atol=1e-5)
    p2, n2 = load_scan(_write_ply(tmp_path / "s2.ply", pts))
    assert n2 is None and len(p2) == 500


def test_scan_fit_goes_on_while_its_cost_falls():
    """The scan fit's last phase runs past its scheduled iterations while the mean cost of the
    last three iterations is more than 5 % below the three before (per-iteration sampling noise
    at the plateau does not count), never past max_iters."""
    from fitting.shape import _still_falling

    assert _still_falling([5.0, 4.0, 3.0], 0.05)  # too few to judge: go on
    plateau = [4.5e-6, 4.4e-6, 4.6e-6, 4.4e-6, 4.6e-6, 4.5e-6]
    assert not _still_falling(plateau, 0.05)
    falling = [1.035e-5, 1.053e-5, 1.020e-5, 9.67e-6, 9.40e-6, 8.75e-6]  # measured, head 63 mm off
    assert _still_falling(falling, 0.05)
    assert not _still_falling(falling, 0.2)


@pytest.mark.slow
def test_scan_fit_recovers_shape(anny):
    """A scan of a known body (2 mm noise, armpit holes, no soles, random heading and place):
    the fitted neutral-pose mesh is within a few mm of the truth."""
    from body.lbs import rest_state
    from fitting import shape, skinned
    from studio.scan import sample_scan

    m = anny
    rng = np.random.default_rng(4)
    bt = np.zeros(m.num_betas)
    bt[:40] = rng.normal(0, 1, 40)
    skel = skinned.fit_skeleton(m, shape.body_joints(m))
    x = np.zeros(skel.n)
    x[6:] = rng.normal(0, 0.02, skel.n - 6)
    x[:3] = [0, 0, rng.uniform(-np.pi, np.pi)]
    x[3:6] = [0.4, -0.2, 0.0]
    v = shape._posed_vertices(m, skel, bt, x)
    v[:, 2] -= v[:, 2].min()
    joints = rest_state(m, bt).joints[0]
    armpits = joints[[m.joint_index("upperarm01.L"), m.joint_index("upperarm01.R")]]
    pts, nrm = sample_scan(v, np.asarray(m.faces), np.zeros((0, 3)), rng)
    del armpits
    fit = shape.fit_scan(m, pts, nrm, rng, shape.ScanFitOptions(num_betas=60, iters=30,
                                                               n_points=2500, n_vertices=1500))
    rt, rf = rest_state(m, bt).vertices[0], rest_state(m, fit.betas).vertices[0]
    v2v = np.linalg.norm((rt - rt.mean(0)) - (rf - rf.mean(0)), axis=1) * 1000
    posed = np.linalg.norm(shape._posed_vertices(m, skel, fit.betas, fit.x) - v, axis=1) * 1000
    assert np.median(fit.scan_to_model_mm) < 2.0  # 2 mm noise: median |n| ~ 1.35 mm
    assert posed.mean() < 3.0, posed.mean()  # same vertices, in the scan's pose and frame
    # neutral pose: measured 4.8 mm; 6.1 when model vertices over the missing soles paired
    # with the sole rim's scan points (ScanFitOptions.min_normal_dot)
    assert v2v.mean() < 5.8, v2v.mean()


@pytest.mark.slow
def test_shape_fit_stage_with_scan_and_captures(tmp_path, anny):
    """The stage adapter: a scan and one Vicon-like capture -> shape.npz and a mm report;
    a recipe pointing at a missing scan fails naming the file."""
    import json
    from types import SimpleNamespace

    from test_marker_fit_stage import FakeWriter, _session, view

    import stages.shape_fit as stage
    from artifacts import ShapeFit
    from body.lbs import rest_state
    from stages.shape_fit import Options, run
    from studio.scan import sample_scan

    rng = np.random.default_rng(8)
    s = _session(tmp_path, anny, rng, F=30, swap=False)
    betas = s.shape.betas
    v = rest_state(anny, betas).vertices[0]
    pts, nrm = sample_scan(v - [0, 0, v[:, 2].min()], np.asarray(anny.faces), np.zeros((0, 3)),
                           rng)
    scan = _write_ply(tmp_path / "s1.ply", pts, nrm)
    out = FakeWriter(tmp_path / "shape_out")
    raw = {"body_model": s.raw["body_model"], "scan": scan}  # the capture: stage capture's
    ctx = SimpleNamespace(stage="shape_fit", unit="s1", recipe=view(stage, s.values),
                          params=Options(num_betas=30, scan_iters=10, frames=5, rounds=2),
                          inputs={"capture": {"g/take": s.capture_dir}}, raw=raw, out=out,
                          progress=lambda it, **k: it, log=lambda s: None)
    run(ctx)
    rep = json.loads((out.dir / "report.json").read_text())
    sh = ShapeFit.load(out.dir)
    assert rep["shape_source"] == "scan" and rep["scan_to_model_mm"]["median"] < 6.0
    assert rep["marker_sequences"] == ["g/take"]
    assert len(rep["placement_frames"]) == 5
    assert rep["placement_residual_mm"]["median"] < 5.0
    assert sh.betas.shape == (30,) and sh.marker_face.shape == (39,)
    assert str(sh.shape_source) == "scan" and str(sh.placement_source) == "refined"
    ctx.raw = {**raw, "scan": tmp_path / "missing.ply"}
    with pytest.raises(InputError, match=r"missing\.ply: scan: file not found"):
        run(ctx)


def test_shape_fit_options_name_the_bad_field():
    from stages.shape_fit import Options

    with pytest.raises(ValueError, match=r"frames: must be >= 1, got 0"):
        Options(frames=0)
    with pytest.raises(ValueError, match=r"slide_sd_mm: must be > 0, got -1"):
        Options(slide_sd_mm=-1)
    with pytest.raises(ValueError, match=r"compile: must be one of auto, compiled, interpreted"):
        Options(compile="fast")


def test_vertex_jacobian_vs_finite_differences(anny):
    """The scan fit's Jacobian: betas (analytic, through rest vertices, joints, offsets and the
    bind rotations) and pose (forward differences) against central differences of forward."""
    from body.lbs import rest_state
    from fitting import shape, skinned

    m = anny
    rng = np.random.default_rng(0)
    skel = skinned.fit_skeleton(m, shape.body_joints(m))
    S = 12
    b = rng.normal(0, 1, S)
    x = np.zeros(skel.n)
    x[:3] = [0.1, 0.2, 1.0]
    x[3:6] = [0.3, 0.1, 0.2]
    x[6:] = rng.normal(0, 0.2, skel.n - 6)
    rest = rest_state(m, b)
    vids = rng.choice(m.num_vertices, 150, replace=False)
    Jv = shape.vertex_jacobian(m, rest, skel, x, vids, S, shape.bind_jacobian(m, b, S))
    z = np.concatenate([b, x])

    def f(zz):
        return shape._posed_vertices(m, skel, zz[:S], zz[S:])[vids]

    fd = np.zeros_like(Jv)
    for k in range(len(z)):
        e = np.zeros_like(z)
        e[k] = 1e-6
        fd[:, :, k] = (f(z + e) - f(z - e)) / 2e-6
    np.testing.assert_allclose(Jv[:, :, :S], fd[:, :, :S], atol=1e-8)
    np.testing.assert_allclose(Jv[:, :, S:], fd[:, :, S:], atol=1e-5)
    # without the bind-rotation part the beta columns are measurably wrong (Anny)
    J0 = shape.vertex_jacobian(m, rest, skel, x, vids, S)
    assert np.abs(J0[:, :, :S] - fd[:, :, :S]).max() > 1e-3
    # the scan fit's rows (weighted sums of vertices) projected term by term: B @ Jv
    n_rows = 40
    rows = rng.integers(0, n_rows, 3 * n_rows)
    pick = rng.integers(0, len(vids), 3 * n_rows)
    vecs = rng.normal(0, 1, (3 * n_rows, 3))
    Jr = shape.residual_jacobian(m, rest, skel, x, rows, vids[pick], vecs, n_rows, S,
                                 shape.bind_jacobian(m, b, S))
    want = np.zeros((n_rows, Jv.shape[2]))
    np.add.at(want, rows, np.einsum("ma,maz->mz", vecs, Jv[pick]))
    np.testing.assert_allclose(Jr[:, :S], want[:, :S], atol=1e-10)
    np.testing.assert_allclose(Jr[:, S:], want[:, S:], atol=1e-8)


def test_bind_jacobian_closed_form_matches_central_differences(anny):
    """The polar factor's closed-form derivative against central differences of
    ``bind_rotations`` on every beta of Anny, at a shape far from the mean."""
    from body.lbs import bind_rotations, pad_betas
    from fitting import shape

    m = anny
    S = m.num_betas
    b = pad_betas(m, np.random.default_rng(1).normal(0, 1.0, S))
    dA = shape.bind_jacobian(m, b[0], S)
    assert dA.shape == (m.num_joints, 3, 3, S)
    eps = 1e-6
    E = np.eye(S) * eps
    fd = np.moveaxis((bind_rotations(m, b + E) - bind_rotations(m, b - E)) / (2 * eps), 0, -1)
    assert np.abs(fd).max() > 1e-2  # the bind rotations do move with the shape
    np.testing.assert_allclose(dA, fd, atol=1e-7)
