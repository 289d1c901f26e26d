"""``load_model``: the registry of body-model loaders (by kind name).

The loaders themselves live with their model (``body.anny.load_anny``,
``body.smplfamily.load_smpl_family``); this module only dispatches, so ``body.model`` (the data
class) imports no loader and no loader imports this registry.
"""
from __future__ import annotations

from pathlib import Path

from body.anny import load_anny
from body.anny_paths import model_path
from body.model import BodyModel
from body.smplfamily import load_smpl_family, resolve_path

SMPL_FAMILY_KINDS = ("smpl", "smplh", "smplx")
ANY_SMPL_FAMILY = ("smpl-family", "smplfamily")  # kind read from the file (J = 24/52/55)
CACHE_SIZE = 2  # models kept per process (a session has one, a conversion two)

_CACHE: dict = {}  # (kind, file, its size, mtime and inode, kwargs) -> BodyModel


def load_model(kind: str = "anny", path: str | Path | None = None, **kwargs) -> BodyModel:
    """Load a body model.

    kind: "anny" (the exported Anny file; path default ``$ANNY_MODEL_PATH`` or
    assets/build/anny_model.npz) or "smpl" / "smplh" / "smplx" / "smpl-family" (a model file in
    the smplx package's schema, .npz or .pkl; path default ``$SMPLX_MODEL_PATH``).
    Raises InputError naming the file and key on a bad file.

    A model is read once per process and file version: a second call with the same kind and
    the same file (same size, modification time and inode) returns the same object (a
    ``BodyModel`` is frozen and its arrays read-only, so sharing it is safe). The engine's
    stages each load the model (0.4 s for Anny's 147 MB): in one process they now pay it once.
    """
    kind = kind.lower()
    if kind == "anny":
        load, args = load_anny, {}
        file = Path(path) if path is not None else model_path()
    elif kind in SMPL_FAMILY_KINDS or kind in ANY_SMPL_FAMILY:
        load = load_smpl_family
        args = {"kind": kind if kind in SMPL_FAMILY_KINDS else None, **kwargs}
        file = resolve_path(path)  # the loader's own: raises as it would
    else:
        raise ValueError(f"unknown body model kind {kind!r} (anny, smpl, smplh, smplx, smpl-family)")
    key = _cache_key(kind, file, args)
    if key is not None and key in _CACHE:
        return _CACHE[key]
    model = load(file, **args)
    if key is not None and key == _cache_key(kind, file, args):  # not rewritten meanwhile
        while len(_CACHE) >= CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = model
    return model


def _cache_key(kind: str, file: Path, args: dict) -> tuple | None:
    """What identifies a loaded model: its kind, its file (resolved) and that file's version,
    and the loader's arguments; None when there is no file to look at (the loader raises)."""
    try:
        st = file.resolve().stat()
    except OSError:
        return None
    if not file.is_file():
        return None
    return (kind, str(file.resolve()), st.st_size, st.st_mtime_ns, st.st_ino,
            tuple(sorted((k, repr(v)) for k, v in args.items())))
