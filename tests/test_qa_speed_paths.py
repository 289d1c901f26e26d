"""The qa metrics' faster paths give the numbers of the plain ones: a posed mesh's AABB tree
kept for the frame's queries measures what ``geometry.nearest_surface`` measures, and the
proxy is decimated once per model object."""
from __future__ import annotations

import dataclasses

import numpy as np

from geometry import nearest_surface
from qa import metrics as QM


def _pair(anny, F: int, inside, z0: float = 1.0):
    """(wearer, partner) fits of F frames: the wearer standing at the origin, the partner
    1.45 m away along x, and 0.65 m away in the frames ``inside`` (the wearer's hand and
    forearm in the partner's chest: the pair's numbers are not all zero there)."""
    from test_qa_metrics import _fit

    wearer = _fit(anny, np.stack([np.zeros(F), np.zeros(F), np.full(F, z0)], 1))
    pt = np.tile([1.45, 0.0, z0], (F, 1))
    pt[list(inside), 0] = 0.65
    return wearer, _fit(anny, pt)


def test_surface_tree_distances_are_nearest_surface_distances(anny):
    from body import forward

    rng = np.random.default_rng(3)
    pose = rng.normal(0, 0.2, (1, anny.num_joints, 3))
    V = forward(anny, np.zeros(1), pose, np.eye(3)[None], np.zeros((1, 3))).vertices[0]
    faces = np.asarray(anny.faces)
    s = QM._Surface(V, np.ascontiguousarray(faces, np.int64))
    for n in (1, 50, 400):  # the same tree answers several queries
        P = V[rng.integers(0, len(V), n)] + rng.normal(0, 0.05, (n, 3))
        np.testing.assert_array_equal(s.distance(P), nearest_surface(P, V, faces).distance)


def test_proxy_is_built_once_per_model(anny):
    """Once per model content: the same model content in a new object (a model file read
    again in another process's way, or a copy) reuses the proxy; a model with another template
    gets its own."""
    import dataclasses

    from fitting.collision import ProxyMesh

    calls = []

    class Counting(ProxyMesh):
        @classmethod
        def from_model(cls, model, n_vertices=2000, rmap=None):
            calls.append(model)
            return ProxyMesh.from_model(model, n_vertices, rmap)

    QM._PER_MODEL.clear()
    a = QM._proxy(anny, Counting)
    assert QM._proxy(anny, Counting) is a and len(calls) == 1
    again = dataclasses.replace(anny, v_template=np.array(anny.v_template))  # same content
    assert again is not anny and QM._proxy(again, Counting) is a and len(calls) == 1
    taller = dataclasses.replace(anny, v_template=np.asarray(anny.v_template) * 1.1)
    b = QM._proxy(taller, Counting)
    assert b is not a and len(calls) == 2 and b.num_vertices == a.num_vertices


def test_surface_tree_over_the_faces_near_the_queries_gives_the_same_distances(anny):
    """With anchors on the mesh (the proxy's points), the tree is built over the faces that
    can hold a nearest point only, and the distances are the whole mesh's: deep inside,
    near the surface, and far points capped at ``cap`` (the others exact); a point whose
    nearest face the subset misses would show up as a larger distance."""
    from body import forward

    rng = np.random.default_rng(5)
    pose = rng.normal(0, 0.2, (1, anny.num_joints, 3))
    V = forward(anny, np.zeros(1), pose, np.eye(3)[None], np.zeros((1, 3))).vertices[0]
    faces = np.ascontiguousarray(anny.faces, np.int64)
    proxy = QM.body_proxy(anny)
    anchors = proxy.points(V)
    for spread, n in ((0.01, 30), (0.05, 200), (0.3, 100)):
        P = V[rng.integers(0, len(V), n)] + rng.normal(0, spread, (n, 3))
        want = nearest_surface(P, V, faces).distance
        got = QM._Surface(V, faces, anchors).distance(P)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        capped = QM._Surface(V, faces, anchors).distance(P, cap=0.02)
        near = want <= 0.02
        np.testing.assert_allclose(capped[near], want[near], rtol=0, atol=1e-12)
        assert (capped[~near] > 0.02 - 1e-12).all()


@dataclasses.dataclass
class NoContact:  # an annotation saying the two never touch: every frame is "outside"
    has_contact: bool = False
    interval: tuple = (0, 0)
    region_pairs: tuple = ()

    def active(self, f):
        return False


def test_geometry_in_worker_processes_gives_the_same_metrics(anny, monkeypatch):
    """The per-frame geometry (self-penetration of each body, interpenetration depth and
    volume, the closest distance outside an annotated contact) computed in two spawned worker
    processes equals the one-process run value for value, and no worker outlives the pass;
    the case has a forearm pushed into the other body in two frames (so the numbers are not
    all zero)."""
    import multiprocessing as mp

    F = 6
    wearer, partner = _pair(anny, F, [2, 3])
    bp = np.array(partner.body_pose)
    bp[4, anny.joint_index("upperarm01.L")] = [0.0, 1.5, 0.0]  # an arm into the own body
    partner = dataclasses.replace(partner, body_pose=bp)

    here = []
    frames_here = QM._geometry_frames

    def spy(*args):  # a worker imports the module afresh: only this process's calls count
        here.append(len(args[1]))
        return frames_here(*args)

    monkeypatch.setattr(QM, "_geometry_frames", spy)
    runs = []
    for w, min_frames in ((1, 48), (2, 1)):
        monkeypatch.setattr(QM, "PARALLEL_MIN_FRAMES", min_frames)
        here.clear()
        runs.append(QM.sequence_metrics(anny, wearer, partner, None, [], NoContact(), None,
                                        25.0, workers=w))
        assert sum(here) == (F if w == 1 else 0)  # with two workers every frame ran in them
    assert mp.active_children() == []
    a, b = runs
    assert list(a.values) == list(b.values)
    for n in a.values:
        np.testing.assert_array_equal(a.values[n], b.values[n], err_msg=n)
    assert (a.values["penetration_mm"][[2, 3]] > 20).all()
    assert (a.values["penetration_mm"][[0, 1, 5]] == 0).all()
    assert np.isfinite(a.values["unexpected_contact_mm"]).all()
    assert a.values["partner.self_penetration_mm"][4] > 50 + a.values["partner.self_penetration_mm"][0]


def test_geometry_stays_in_one_process_below_the_frames_a_worker_is_worth(anny, monkeypatch):
    """Fewer than PARALLEL_MIN_FRAMES frames per worker: no worker is started."""
    from test_qa_metrics import _fit

    import pipeline.procs as procs

    def no_pool(*a, **k):
        raise AssertionError("a worker pool for a few frames")

    monkeypatch.setattr(procs, "process_pool", no_pool)
    F = 4
    fit = _fit(anny, np.stack([np.zeros(F), np.zeros(F), np.ones(F)], 1))
    other = _fit(anny, np.tile([1.45, 0.0, 1.0], (F, 1)))
    m = QM.sequence_metrics(anny, fit, other, None, [], NoContact(), None, 25.0, workers=2)
    assert np.isfinite(m.values["penetration_mm"]).all()


def test_work_beside_runs_in_another_thread_and_its_error_comes_out_here():
    """stages.qa._Beside: the plot and scene run in a thread while the overlays are drawn
    (another thread, the result handed back), in the caller's thread when not parallel; the
    work's own error comes out of result(), raised once."""
    import threading

    import pytest

    from stages.qa import _Beside

    assert _Beside(threading.get_ident, True).result() != threading.get_ident()
    assert _Beside(threading.get_ident, False).result() == threading.get_ident()
    calls = []

    def fails():
        calls.append(threading.get_ident())
        raise KeyError("no such camera")

    side = _Beside(fails, True)
    with pytest.raises(KeyError, match="no such camera"):
        side.result()
    assert len(calls) == 1 and calls[0] != threading.get_ident()
    side.close()  # closing after the result is a no-op


def _two_bodies(anny):
    """Two posed proxies, B shifted so that A's arm region and B's torso overlap."""
    from body import forward

    rng = np.random.default_rng(11)
    pose = rng.normal(0, 0.15, (1, anny.num_joints, 3))
    V = forward(anny, np.zeros(1), pose, np.eye(3)[None], np.zeros((1, 3))).vertices[0]
    proxy = QM.body_proxy(anny)
    PA = proxy.points(V)
    PB = proxy.points(V + np.array([0.25, 0.05, 0.1]))
    return proxy, PA, PB


def test_kept_winding_hierarchy_gives_the_winding_numbers_of_geometry(anny):
    from geometry import winding_number

    proxy, PA, PB = _two_bodies(anny)
    W = QM._Winding(PA, proxy.faces)
    rng = np.random.default_rng(2)
    lo, hi = PA.min(0), PA.max(0)
    for Q in (PB, rng.uniform(lo, hi, (3000, 3)), PA[:5]):  # one hierarchy, several queries
        np.testing.assert_array_equal(W(Q), winding_number(Q, PA, proxy.faces))
    np.testing.assert_array_equal(W.distance(PB), nearest_surface(PB, PA, proxy.faces).distance)


def test_grid_blocks_give_the_cells_of_testing_every_cell(anny):
    """The volume grid's inside test by blocks (one cell for a block the surface does not
    cross) decides every cell as testing each one does, for the whole grid and for a subset
    of wanted cells, at several block sizes; the grid has cells inside, outside and on both
    sides of the surface within single blocks."""
    from geometry import winding_number

    proxy, PA, PB = _two_bodies(anny)
    lo = np.maximum(PA.min(0), PB.min(0))
    hi = np.minimum(PA.max(0), PB.max(0))
    cell = 0.02
    n = np.ceil((hi - lo) / cell).astype(int) + 1
    g = [lo[k] + cell * (np.arange(n[k]) + 0.5) for k in range(3)]
    G = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    wantA = winding_number(G, PA, proxy.faces) > 0.5
    wantB = winding_number(G, PB, proxy.faces) > 0.5
    assert 100 < wantA.sum() < len(G) - 100 and (wantA & wantB).sum() > 50

    class Counting(QM._Winding):
        asked: list = []

        def __call__(self, Q):
            self.asked.append(len(Q))
            return super().__call__(Q)

    WA, WB = Counting(PA, proxy.faces), QM._Winding(PB, proxy.faces)
    old = QM.GRID_BLOCK
    try:
        for b in (1, 3, 5):
            QM.GRID_BLOCK = b
            WA.asked = []
            inA = QM._grid_inside(WA, G, n, np.ones(len(G), bool))
            np.testing.assert_array_equal(inA, wantA)
            if b > 1:  # blocks away from the surface were tested by one cell
                assert sum(WA.asked) < 0.7 * len(G)
            inB = QM._grid_inside(WB, G, n, inA)
            np.testing.assert_array_equal(inB, wantA & wantB)
            assert not QM._grid_inside(WB, G, n, np.zeros(len(G), bool)).any()
    finally:
        QM.GRID_BLOCK = old


def test_self_penetration_is_the_deepest_of_self_collisions(anny):
    """The QA's self-penetration (``fitting.collision.self_penetration``: the region faces
    found once per proxy, no targets made) is ``self_collisions(...).deepest`` number for
    number, with an arm pushed into the own body (a depth > 0) and without, also when given
    the frame's winding-number hierarchy; the cached region faces are those found afresh."""
    from body import forward
    from fitting.collision import SELF_RINGS, _neighbours, self_collisions, self_penetration

    proxy = QM.body_proxy(anny)
    rng = np.random.default_rng(7)
    depths = []
    for k in range(4):
        pose = rng.normal(0, 0.1, (1, anny.num_joints, 3))
        if k >= 2:
            pose[0, anny.joint_index("upperarm01.L")] = [0.0, 1.5, 0.0]  # into the torso
        V = forward(anny, np.zeros(1), pose, np.eye(3)[None], np.zeros((1, 3))).vertices[0]
        P = proxy.points(V)
        want = self_collisions(proxy, P).deepest
        assert self_penetration(proxy, P) == want
        # with the frame's winding-number hierarchy of the posed proxy (qa.metrics._Winding,
        # kept for the pair test): the same number
        assert self_penetration(proxy, P, winding=QM._Winding(P, proxy.faces)) == want
        depths.append(want)
    assert depths[0] == 0.0 and depths[2] > 0.02 and depths[3] > 0.02
    regions = proxy.self_regions(SELF_RINGS)
    assert proxy.self_regions(SELF_RINGS) is regions  # once per proxy
    near = _neighbours(proxy.region_adjacency, SELF_RINGS)
    fr = np.asarray(proxy.face_region)
    for r, (far, rest) in regions.items():
        kept = (fr >= 0) & ~near[r][np.maximum(fr, 0)]
        np.testing.assert_array_equal(far, np.flatnonzero(kept))
        np.testing.assert_array_equal(rest, np.flatnonzero(~kept))
    assert set(regions) == set(np.unique(proxy.vertex_region[proxy.vertex_region >= 0]).tolist())


def test_geometry_in_a_given_pool_gives_the_same_metrics(anny):
    """``sequence_metrics(pool=...)``: the per-frame geometry goes to the pool (here a thread
    pool) in chunks, submitted before the other metrics, with the values of the run without
    it."""
    import concurrent.futures as cf

    F = 4
    wearer, partner = _pair(anny, F, [1])
    a = QM.sequence_metrics(anny, wearer, partner, None, [], NoContact(), None, 25.0)
    submitted = []

    class Pool(cf.ThreadPoolExecutor):
        def submit(self, fn, *args, **kw):
            submitted.append(fn)
            return super().submit(fn, *args, **kw)

    with Pool(1) as pool:
        b = QM.sequence_metrics(anny, wearer, partner, None, [], NoContact(), None, 25.0,
                                pool=pool)
    assert submitted == [QM._geometry_frames] * F  # one chunk per frame (F < SHARE_CHUNKS)
    assert list(a.values) == list(b.values)
    for n in a.values:
        np.testing.assert_array_equal(a.values[n], b.values[n], err_msg=n)
    assert a.values["penetration_mm"][1] > 20


def test_region_map_is_built_once_per_model(anny):
    from body import load_model
    from body.regions import region_map

    QM._PER_MODEL.clear()
    r = QM.qa_region_map(anny)
    assert QM.qa_region_map(load_model("anny")) is r
    np.testing.assert_array_equal(r.face_region, region_map(anny).face_region)


def test_geometry_shared_by_a_pool_and_this_process_gives_the_same_metrics(anny, monkeypatch):
    """qa.metrics._SharedGeometry: the chunks the pool has not started when this process has
    its other metrics are computed here, from the last one on; the pool keeps what it started.
    Planted order: the pool's one thread is held until this process has taken the last chunk,
    then this process waits until the pool has started its first; every frame's numbers equal
    those of the run in one process, and each chunk ran once."""
    import concurrent.futures as cf
    import threading

    F = 6
    wearer, partner = _pair(anny, F, [1, 4])
    a = QM.sequence_metrics(anny, wearer, partner, None, [], NoContact(), None, 25.0)

    main = threading.get_ident()
    ran: list[tuple[int, bool]] = []  # (first frame row, ran in this thread)
    go, started = threading.Event(), threading.Event()
    frames_here = QM._geometry_frames

    def spy(static, rows, verts, frames):
        here = threading.get_ident() == main
        if not here:
            started.set()
        ran.append((int(rows[0]), here))
        out = frames_here(static, rows, verts, frames)
        if here and not go.is_set():  # the last chunk done here: let the pool start its first
            go.set()
            assert started.wait(30)
        return out

    monkeypatch.setattr(QM, "_geometry_frames", spy)
    monkeypatch.setattr(QM, "SHARE_CHUNKS", 3)
    with cf.ThreadPoolExecutor(1) as pool:
        pool.submit(go.wait, 30)  # the pool is busy until this process has started sharing
        b = QM.sequence_metrics(anny, wearer, partner, None, [], NoContact(), None, 25.0,
                                pool=pool)
    assert sorted(r for r, _ in ran) == [0, 2, 4]  # three chunks of two frames, each run once
    assert (4, True) in ran and (0, False) in ran
    assert list(a.values) == list(b.values)
    for n in a.values:
        np.testing.assert_array_equal(a.values[n], b.values[n], err_msg=n)
    assert (a.values["penetration_mm"][[1, 4]] > 20).all()
