"""``load_model``: the registry of body-model loaders (by kind name).

The loaders themselves live with their model (``body.anny.load_anny``,
``body.smplfamily.load_smpl_family``); this module only dispatches, so ``body.model`` (the data
class) imports no loader and no loader imports this registry.
"""
from __future__ import annotations

from pathlib import Path

from body.anny import load_anny
from body.model import BodyModel
from body.smplfamily import load_smpl_family

SMPL_FAMILY_KINDS = ("smpl", "smplh", "smplx")
ANY_SMPL_FAMILY = ("smpl-family", "smplfamily")  # kind read from the file (J = 24/52/55)


def load_model(kind: str = "anny", path: str | Path | None = None, **kwargs) -> BodyModel:
    """Load a body model.

    kind: "anny" (the exported Anny file; path default ``$ANNY_MODEL_PATH`` or
    assets/build/anny_model.npz) or "smpl" / "smplh" / "smplx" / "smpl-family" (a model file in
    the smplx package's schema, .npz or .pkl; path default ``$SMPLX_MODEL_PATH``).
    Raises InputError naming the file and key on a bad file."""
    kind = kind.lower()
    if kind == "anny":
        return load_anny(path)
    if kind in SMPL_FAMILY_KINDS:
        return load_smpl_family(path, kind=kind, **kwargs)
    if kind in ANY_SMPL_FAMILY:
        return load_smpl_family(path, kind=None, **kwargs)
    raise ValueError(f"unknown body model kind {kind!r} (anny, smpl, smplh, smplx, smpl-family)")
