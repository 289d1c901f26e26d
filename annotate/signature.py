"""The annotation file: ``interaction_contact_signature.json`` in the CHI3D layout.

One file per group (subject folder), keyed by action (``formats.chi3d``); saving one action
keeps the file's other actions. An action's entry: ``fr_id``, ``start_fr``, ``end_fr``,
``smplx_signature`` and ``ghum_signature`` (``region_id`` / ``face_id`` pairs, person 0 = the
marker wearer first), ``anny_signature`` (our model's facets, their 75 region ids and
``region_names``), and ``annotation``: who saved it, when, and for which mesh (``model``,
``num_vertices``, ``num_faces``; a file made for another mesh is refused on reading). Where the
``convert`` stage has registered the SMPL-X target to our model, ``smplx_signature`` carries
the facets of that target nearest to the annotated ones (its ``src_face_tgt_face``) and their
regions in our 75-region map of the target (not CHI3D's official region ids); else it is empty.

:func:`save` writes into a temporary file beside the target, checks it with the reader the
partner fit uses (``fitting.contact_signature.load_contact``, for our model's family, and for
SMPL-X with the target when there is one), and only then renames it over the file: a refused
annotation leaves the file as it was. :func:`load` reads an action back for the page.
"""
from __future__ import annotations

import datetime
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from formats.errors import InputError


def _pairs(a) -> list[list[int]]:
    return np.asarray(a, np.int64).reshape(-1, 2).tolist()


def entry(model, rmap, family: str, fr_id: int, interval: tuple[int, int], facet_pairs,
          annotator: str = "", conversion=None) -> dict:
    """One action's entry of the file from the annotated facet pairs (K, 2) of ``model``."""
    fp = np.asarray(facet_pairs, np.int64).reshape(-1, 2)
    T = len(model.faces)
    if len(fp) and (fp.min() < 0 or fp.max() >= T):
        bad = fp[(fp < 0).any(1) | (fp >= T).any(1)][0].tolist()
        raise InputError("annotation", "face_id", f"facet pair {bad} outside the model's {T} faces")
    regions = rmap.region_of(fp) if len(fp) else np.zeros((0, 2), np.int64)
    e: dict = {"fr_id": int(fr_id), "start_fr": int(interval[0]), "end_fr": int(interval[1])}
    empty = {"region_id": [], "face_id": []}
    e["smplx_signature"], e["ghum_signature"] = dict(empty), dict(empty)
    sig = {"region_id": _pairs(regions), "face_id": _pairs(fp)}
    if family == "anny":
        sig["region_names"] = [[rmap.names[a], rmap.names[b]] for a, b in regions]
        e["anny_signature"] = sig
    else:
        e[f"{family}_signature"] = sig
    if conversion is not None and family == "anny" and len(fp):
        corr, target, trmap = conversion
        tf = np.asarray(corr.src_face_tgt_face, np.int64)[fp]
        e["smplx_signature"] = {"region_id": _pairs(trmap.region_of(tf)), "face_id": _pairs(tf)}
    e["annotation"] = {"tool": "annotate", "annotator": annotator, "model": model.name,
                       "num_vertices": int(model.num_vertices), "num_faces": T,
                       "smplx_from": None if conversion is None or family != "anny" else {
                           "model": conversion[1].name, "num_faces": int(len(conversion[1].faces))},
                       "saved": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    return e


def _check_meta(path: Path, action: str, e: dict, model, fr: int | None) -> None:
    meta = e.get("annotation")
    if not isinstance(meta, dict):
        return
    want = {"model": model.name, "num_vertices": int(model.num_vertices), "num_faces": len(model.faces)}
    for k, v in want.items():
        if k in meta and meta[k] != v:
            raise InputError(path, f"{action}.annotation.{k}", f"the file was annotated on "
                             f"{k} {meta[k]!r}, this model has {v!r} (a stale file: annotate "
                             "again or use the model it was made for)", fr)


def validate(path: Path, action: str, model, n_frames: int, family: str, rmap,
             target=None):
    """The reader the partner fit uses, on ``path``'s ``action`` (plus the model check of the
    ``annotation`` block, and the SMPL-X signature against ``target`` when given)."""
    from fitting.contact_signature import load_contact

    raw = json.loads(Path(path).read_text())
    e = raw.get(action) if isinstance(raw, dict) else None
    ann = load_contact(path, action, model, n_frames, family=family, rmap=rmap)
    if isinstance(e, dict):
        _check_meta(Path(path), action, e, model, ann.frame)
    if target is not None:
        tmodel, trmap = target
        sig = e.get("smplx_signature") if isinstance(e, dict) else None
        if sig and (sig.get("face_id") or sig.get("region_id")):
            load_contact(path, action, tmodel, n_frames, family="smplx", rmap=trmap)
    return ann


def save(path: str | Path, action: str, e: dict, model, n_frames: int, family: str, rmap,
         target=None) -> Path:
    """Write ``e`` as ``action`` of the file ``path`` (other actions kept), atomically, after
    :func:`validate` accepted the new file. Raises InputError (the file untouched) otherwise."""
    path = Path(path)
    d: dict = {}
    if path.exists():
        try:
            d = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as ex:
            raise InputError(path, "<file>", f"the existing file is not JSON ({ex}); move it "
                             "away to save here") from None
        if not isinstance(d, dict):
            raise InputError(path, "<file>", "the existing file is not a JSON object")
    d[action] = e
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # as a plain open() would have made it (mkstemp: 0600)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(d, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        try:
            validate(Path(tmp), action, model, n_frames, family, rmap, target)
        except InputError as ex:  # name the file being saved, not the temporary one
            raise InputError(path, ex.field, ex.msg, ex.frame) from None
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def load(path: str | Path, action: str, model, n_frames: int, family: str, rmap) -> dict | None:
    """The saved annotation of ``action`` for the page: {"fr_id", "interval", "pairs",
    "annotator"}; None when the file or the action does not exist. Raises InputError (file,
    field, frame) when it is there but bad or made for another mesh."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as ex:
        raise InputError(path, "<file>", f"not JSON: {ex}") from None
    if not isinstance(raw, dict) or action not in raw:
        return None
    ann = validate(path, action, model, n_frames, family, rmap)
    meta = raw[action].get("annotation") if isinstance(raw[action], dict) else None
    return {"fr_id": ann.frame, "interval": list(ann.interval),
            "pairs": ann.facet_pairs.tolist(),
            "annotator": (meta or {}).get("annotator", "") if isinstance(meta, dict) else ""}
