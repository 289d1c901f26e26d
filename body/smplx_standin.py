"""The SMPL-X-schema stand-in target: Anny's body on a DIFFERENT mesh, rigged like SMPL-X.

A test-asset builder, not a loader (the licensed SMPL-X files cannot be had here). The
conversion stage needs a target whose mesh is not Anny's: a conversion onto Anny's own vertices
(``body.smplx_from_anny``) would not test the converter. ``standin_path()`` returns
``assets/build/smplx_standin/SMPLX_NEUTRAL.npz``, built on demand (~4 s, plus ~10 s when
``smplx_from_anny``'s file is stale too), a file that ``smplx.SMPLX``, ``smplx.build_layer(...,
model_type='smplx')`` and ``body.load_model("smplx", path)`` read.

The mesh: Anny's reference-posture template at betas 0 (the 4 closed components: body, two
eyes, mouth), Loop-subdivided once (``igl.loop``, 54,848 vertices) and decimated by quadric
edge collapse (``igl.qslim``) to ``TARGET_FACES`` facets (~10.6k vertices: its own count and
triangulation, watertight, consistently oriented, same 4 components so fingers stay separate).
Vertices still within ``MIN_OFFSET_M`` of an Anny vertex are relaxed toward their one-ring
centroid until they are not. More than 9,929 vertices, because ``smplx.SMPLX`` picks its extra
joints (nose, eyes, fingertips, toes) by hard-coded SMPL-X vertex ids up to 9929.

The rig: every stand-in vertex takes the closest point of Anny's surface (face + barycentric
coordinates, the map ``B``); skinning weights of SMPL-X's 55 joints, the 20 shape directions
(10 shape + 10 expression) and the pose correctives are those of ``smplx_from_anny``'s file
interpolated through ``B``. ``J_regressor`` is Anny's regressor carried through the reverse map
``C`` (each Anny vertex on the stand-in surface: ``J ~ Jreg_a C V_s``), then corrected by the
smallest change on its support that puts each joint where ``smplx_from_anny`` puts it, on the
template and along each of the 20 shape directions (so joints follow betas as Anny's do).
Hand PCA arrays (identity, zero mean) and empty landmark arrays as ``smplx_from_anny`` writes
them (DESIGN.md's traps). Extra keys, which the smplx package ignores: ``build_stamp``,
``standin_anny_face``/``standin_anny_bary``/``standin_anny_dist`` (the map ``B``).

``python -m body.smplx_standin [--if-stale] [--out DIR]``; ``scripts/setup.sh`` runs it with
``--if-stale`` after the Anny export. The file's ``build_stamp`` hashes this source,
``smplx_from_anny``'s and the exported Anny model file; a stale file is rebuilt.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from body.anny_paths import REPO, model_path

DEFAULT_OUT_DIR = REPO / "assets" / "build" / "smplx_standin"
FILE_NAME = "SMPLX_NEUTRAL.npz"
TARGET_FACES = 21200  # -> 10,604 vertices (closed, Euler characteristic 8)
MIN_OFFSET_M = 5e-4  # no stand-in vertex within 0.5 mm of an Anny vertex
RELAX_STEP = 0.5
RELAX_ITERS = 8
REGRESSOR_MIN_SUPPORT = 80  # > 4 + 3 * 20 constraints
REGRESSOR_RIDGE = 1e-10

_FILE_HASHES: dict[tuple, str] = {}


def _file_sha256(path: Path) -> str:
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _FILE_HASHES:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 22), b""):
                h.update(chunk)
        _FILE_HASHES[key] = h.hexdigest()
    return _FILE_HASHES[key]


def builder_stamp() -> str:
    """Hash of this builder's source, ``smplx_from_anny``'s (whose rig it transfers) and the
    exported Anny model file."""
    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update((Path(__file__).parent / "smplx_from_anny.py").read_bytes())
    mp = model_path()
    h.update(_file_sha256(mp).encode() if mp.exists() else b"no-anny-model")
    return h.hexdigest()[:16]


def is_stale(path: Path) -> bool:
    if not path.exists():
        return True
    try:
        with np.load(path, allow_pickle=False) as z:
            return str(z["build_stamp"]) != builder_stamp()
    except Exception:
        return True


def standin_path(out_dir: str | Path | None = None) -> Path:
    """``out_dir/SMPLX_NEUTRAL.npz`` (default ``assets/build/smplx_standin/``), built now if
    missing or stale."""
    out_dir = Path(out_dir) if out_dir is not None else DEFAULT_OUT_DIR
    path = out_dir / FILE_NAME
    if is_stale(path):
        build_standin(out_dir)
    return path


# ----------------------------------------------------------------------------- the mesh


def remesh(V: np.ndarray, F: np.ndarray, target_faces: int = TARGET_FACES) -> tuple[np.ndarray, np.ndarray]:
    """Loop-subdivide once, then quadric edge collapse to ``target_faces``; then relax the
    vertices that landed within ``MIN_OFFSET_M`` of a vertex of ``V``. -> (Vs, Fs int64)."""
    import igl
    from scipy.spatial import cKDTree

    V1, F1 = igl.loop(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64), 1)
    U, G, _, _ = igl.qslim(np.asfortranarray(V1), np.asfortranarray(F1.astype(np.int32)), int(target_faces))
    U = np.ascontiguousarray(U, dtype=np.float64)
    G = np.ascontiguousarray(G, dtype=np.int64)
    tree = cKDTree(V)
    # one-ring adjacency (vertex-vertex) as a row-normalised sparse matrix
    e = np.concatenate([G[:, [0, 1]], G[:, [1, 2]], G[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(U),) * 2).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    A = sp.diags(1.0 / np.asarray(A.sum(1)).ravel()) @ A
    for _ in range(RELAX_ITERS):
        d, _ = tree.query(U)
        near = np.flatnonzero(d <= MIN_OFFSET_M)
        if not len(near):
            break
        centroid = A[near] @ U
        U[near] += RELAX_STEP * (centroid - U[near])
    return U, G


def surface_map(P: np.ndarray, V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point of the mesh (V, F) to each point: (face (N,), barycentric (N,3), dist (N,))."""
    import igl

    d2, face, C = igl.point_mesh_squared_distance(np.ascontiguousarray(P, dtype=np.float64),
                                                  np.ascontiguousarray(V, dtype=np.float64),
                                                  np.ascontiguousarray(F, dtype=np.int64))
    tri = V[F[face]]
    bary = _barycentric(C, tri)
    return face, bary, np.sqrt(np.maximum(d2, 0))


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    w = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0, 1)
    return w / w.sum(1, keepdims=True)


def bary_matrix(face: np.ndarray, bary: np.ndarray, F: np.ndarray, n_cols: int) -> sp.csr_matrix:
    """(N, n_cols) sparse interpolation matrix of points given as (face, barycentric)."""
    n = len(face)
    return sp.csr_matrix((bary.ravel(), (np.repeat(np.arange(n), 3), F[face].ravel())), shape=(n, n_cols))


# ----------------------------------------------------------------------------- the rig


def _regressor(Jreg_a: np.ndarray, C: sp.csr_matrix, Vs: np.ndarray, Ss: np.ndarray,
               target: np.ndarray, dtarget: np.ndarray) -> np.ndarray:
    """Anny's regressor through the reverse map ``C``, corrected by the smallest change on its
    support (grown to ``REGRESSOR_MIN_SUPPORT`` nearest vertices) so that each row sums to 1,
    gives ``target`` (J,3) on the stand-in template ``Vs`` and moves by ``dtarget`` (J,3,S)
    along each of the stand-in's shape directions ``Ss`` (V,3,S), as Anny's joints do."""
    from scipy.spatial import cKDTree

    R = np.asarray((C.T @ Jreg_a.T).T)  # (J, Vs)
    tree = cKDTree(Vs)
    out = np.zeros_like(R)
    S = Ss.shape[2]
    for j in range(len(R)):
        sup = np.flatnonzero(np.abs(R[j]) > 1e-9)
        if len(sup) < REGRESSOR_MIN_SUPPORT:
            sup = np.union1d(sup, tree.query(target[j], REGRESSOR_MIN_SUPPORT)[1])
        w0 = R[j, sup]
        A = np.vstack([Vs[sup].T, np.ones((1, len(sup)))] + [Ss[sup, :, k].T for k in range(S)])
        b = np.concatenate([target[j], [1.0]] + [dtarget[j, :, k] for k in range(S)])
        out[j, sup] = w0 + A.T @ np.linalg.solve(A @ A.T + REGRESSOR_RIDGE * np.eye(len(A)), b - A @ w0)
    return out


def build_standin(out_dir: str | Path | None = None, verbose: bool = False) -> Path:
    """Write ``out_dir/SMPLX_NEUTRAL.npz`` (smplx schema, float32, compressed). See module doc."""
    from body.smplx_from_anny import smplx_from_anny_path

    t0 = time.time()
    out_dir = Path(out_dir) if out_dir is not None else DEFAULT_OUT_DIR
    stamp = builder_stamp()
    src = smplx_from_anny_path()
    with np.load(src, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    Va = a["v_template"].astype(np.float64)
    Fa = a["f"].astype(np.int64)
    # Anny's own template at betas 0 (the float32 copy is within 1e-7 of it): its joints
    Ja = a["J_regressor"].astype(np.float64)
    joints = Ja @ Va

    Vs, Fs = remesh(Va, Fa)
    face, bary, dist = surface_map(Vs, Va, Fa)
    B = bary_matrix(face, bary, Fa, len(Va))  # stand-in vertex <- Anny surface
    rface, rbary, _ = surface_map(Va, Vs, Fs)
    C = bary_matrix(rface, rbary, Fs, len(Vs))  # Anny vertex <- stand-in surface

    def interp(x):
        x = np.asarray(x, dtype=np.float64)
        return (B @ x.reshape(len(Va), -1)).reshape((len(Vs),) + x.shape[1:])

    W = interp(a["weights"])
    W = np.where(W < 1e-8, 0.0, W)
    W /= W.sum(1, keepdims=True)
    Sa = a["shapedirs"].astype(np.float64)
    Ss = interp(Sa)
    z = {
        "v_template": Vs, "f": Fs, "weights": W,
        "J_regressor": _regressor(Ja, C, Vs, Ss, joints, np.einsum("jv,vdk->jdk", Ja, Sa)),
        "kintree_table": a["kintree_table"],
        "shapedirs": Ss, "posedirs": interp(a["posedirs"]),
        "hands_componentsl": a["hands_componentsl"], "hands_componentsr": a["hands_componentsr"],
        "hands_meanl": a["hands_meanl"], "hands_meanr": a["hands_meanr"],
        "lmk_faces_idx": a["lmk_faces_idx"], "lmk_bary_coords": a["lmk_bary_coords"],
        # provenance: each stand-in vertex on the Anny template surface (for tests / reports)
        "standin_anny_face": face.astype(np.int64), "standin_anny_bary": bary,
        "standin_anny_dist": dist,
    }
    z32 = {k: (v.astype(np.float32) if isinstance(v, np.ndarray) and v.dtype == np.float64 else v)
           for k, v in z.items()}
    z32["build_stamp"] = np.array(stamp)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / FILE_NAME
    tmp = out_dir / f".{FILE_NAME}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **z32)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    if verbose:
        print(f"[smplx_standin] {len(Vs)} vertices, {len(Fs)} faces -> {path} "
              f"({time.time() - t0:.1f} s)", flush=True)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m body.smplx_standin", description=__doc__.split("\n")[0])
    ap.add_argument("--if-stale", action="store_true", help="do nothing when the file is current")
    ap.add_argument("--out", default=None, help=f"output folder (default {DEFAULT_OUT_DIR})")
    args = ap.parse_args(argv)
    out_dir = Path(args.out) if args.out else DEFAULT_OUT_DIR
    if args.if_stale and not is_stale(out_dir / FILE_NAME):
        return 0
    build_standin(out_dir, verbose=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
