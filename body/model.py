"""BodyModel: the arrays and kinematic tree of a body model (data only), and ``check_arrays``.

No loader here (``body.loaders.load_model`` is the registry) and no math (``body.lbs``): this
module imports no other module of ``body/``, so every loader and ``body.lbs`` can depend on it.

A BodyModel is a frozen dataclass of read-only arrays; the solved variables (betas, poses,
global orientation, translation) never live on it (STYLE.md). The math is in ``body.lbs``.

One formulation covers Anny and the SMPL family (``body.lbs`` for the equations):

- rest mesh ``v_template + shapedirs @ betas`` (V, 3), rest joints (bone heads)
  ``joint_template + joint_shapedirs @ betas`` (J, 3): both exactly linear in betas;
- optional pose correctives ``posedirs`` (SMPL family), optional bind rotations (Anny: the rest
  orientations are the polar factors of ``orient_template + orient_shapedirs @ betas``, the
  reference orientations ``ref_orient``; pose 0 rotates each bone by ``ref_orient @ rest^T``);
- skinning weights as a scipy.sparse CSR (V, J) matrix; ``parents[0] == -1``, parents before
  children.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np
import scipy.sparse as sp

from formats.errors import InputError


@dataclasses.dataclass(frozen=True, eq=False)
class BodyModel:
    """Body model arrays. Axes: V vertices, F faces, J joints, S shape (+ expression) coeffs.

    name: "anny", "smpl", "smplh", "smplx"
    v_template: (V, 3) float64, metres, rest mesh at betas = 0
    faces: (F, 3) int64
    shapedirs: (V, 3, S) float32/64; the first ``num_shape`` columns are body shape, the next
        ``num_expression`` expression (SMPL-X). ``betas`` passed to forward may be shorter (0-padded).
    joint_template: (J, 3) float64, rest joint positions (bone heads) at betas = 0
    joint_shapedirs: (J, 3, S) float64, so rest joints are exactly linear in betas
    parents: (J,) int64, parents[0] = -1, parents[j] < j
    joint_names: J names
    weights: scipy.sparse.csr_matrix (V, J), rows sum to 1
    posedirs: (9 (J-1), 3V) float64 pose correctives (SMPL family, smplx's layout) or None
    orient_template, orient_shapedirs, ref_orient: (J,3,3), (J,3,3,S), (J,3,3) bind-rotation
        data (Anny) or None (SMPL family: bind rotations are I)
    num_shape, num_expression: split of the S columns
    fit_joints: indices of the joints a pose fit solves (the root included, its rotation being
        the global orientation); the others keep pose 0. See ``body.lbs.FitSkeleton``.
    extras: read-only mapping of model-specific arrays (anny's phenotype map and COCO regressor,
        SMPL-X hand PCA, the original J_regressor, ...)
    source: the file it came from
    """

    name: str
    v_template: np.ndarray
    faces: np.ndarray
    shapedirs: np.ndarray
    joint_template: np.ndarray
    joint_shapedirs: np.ndarray
    parents: np.ndarray
    joint_names: tuple[str, ...]
    weights: sp.csr_matrix
    posedirs: np.ndarray | None = None
    orient_template: np.ndarray | None = None
    orient_shapedirs: np.ndarray | None = None
    ref_orient: np.ndarray | None = None
    num_shape: int = 0
    num_expression: int = 0
    fit_joints: tuple[int, ...] = ()
    extras: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    source: str = ""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
        if isinstance(self.weights, sp.spmatrix):
            for a in (self.weights.data, self.weights.indices, self.weights.indptr):
                a.flags.writeable = False
        ex = dict(self.extras)
        for v in ex.values():
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
        object.__setattr__(self, "extras", MappingProxyType(ex))
        if not self.fit_joints:
            object.__setattr__(self, "fit_joints", tuple(range(len(self.joint_names))))
        object.__setattr__(self, "_levels", tuple(kinematic_levels(np.asarray(self.parents))))

    @property
    def levels(self) -> tuple[np.ndarray, ...]:
        """Joints grouped by depth (root excluded), for level-by-level kinematics."""
        return self._levels

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_betas(self) -> int:
        return self.shapedirs.shape[2]

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)


def kinematic_levels(parents: np.ndarray) -> list[np.ndarray]:
    """Joints grouped by depth (root excluded): each level's parents are in earlier levels."""
    depth = np.zeros(len(parents), dtype=int)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [np.flatnonzero(depth == d) for d in range(1, depth.max() + 1)]


def check_arrays(z: Mapping[str, np.ndarray], spec: Mapping[str, str], file: str | Path) -> None:
    """Check that every key of ``spec`` is in ``z`` with the given shape spec (letters must agree
    across keys, digits are exact; "" = scalar). Raises InputError naming the file and key."""
    seen: dict[str, int] = {}
    for key, dims in spec.items():
        if key not in z:
            raise InputError(file, key, "missing array")
        a = np.asarray(z[key])
        d = dims.split()
        if a.ndim != len(d):
            raise InputError(file, key, f"expected shape ({dims}), got {a.shape}")
        for letter, n in zip(d, a.shape, strict=True):
            if letter.isdigit():
                ok = int(letter) == n
            else:
                ok = seen.setdefault(letter, n) == n
            if not ok:
                raise InputError(file, key, f"expected shape ({dims}) with {letter}={seen.get(letter, letter)}, got {a.shape}")
        if a.dtype.kind in "fc" and a.size and not np.all(np.isfinite(a)):
            raise InputError(file, key, "non-finite values")
