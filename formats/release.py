"""Files of a release folder beside the CHI3D ones (``shared/FORMATS.md``):

- ``valid/<action>.json``: ``{"valid": (P, F) bools, "reason": (P, F) str, "frames": (F,)
  int}``: which person-frames are ground truth (fitted from evidence, reason ``"fitted"``)
  and why the others are not; ``frames`` are the frame indices (video frames, or capture
  frames on a marker-only sequence) the action's arrays hold, in order. The evaluator reads
  ``valid`` (``evaluate/folders.py``). Optional ``"joints_valid": (P, F, 25) bools``: per
  person, frame and ``joints3d_25`` joint whether that joint is ground truth (false wherever
  the frame is not, and where no marker or view observed the body part: reason
  ``JOINT_NOT_OBSERVED``). A person-frame the fit calls valid but whose QA flags say the fit
  is wrong (stage ``export``'s ``withhold`` reasons) has the reason ``"qa:<reason>"``
  (``QA_REASON_PREFIX`` + the QA threshold name, e.g. ``"qa:reproj_views_body_px"``); a file
  with such reasons lists the QA reasons it withheld for in ``"qa_withhold": [str]``
  (optional key: files without QA reasons, and files written before it, read as before);
- ``text_annotations.json``: ``{action: sentence}``;
- ``MANIFEST.sha256``: one ``<sha256 hex>  <relative path>`` line per file, the format
  ``sha256sum -c`` checks (run in the release folder);
- :func:`cut_video`: a video cut to the exported frames (a CHI3D video has the frames of its
  ``joints3d_25`` file).

Readers raise :class:`formats.errors.InputError` naming the file, the field and the frame.
"""
from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from formats.errors import InputError
from formats.keypoints import load_json

VALID_DIR = "valid"
TEXT_FILE = "text_annotations.json"
MANIFEST_FILE = "MANIFEST.sha256"
#: the reason of a valid person-frame (every other reason marks a frame that is not ground truth)
VALID_REASON = "fitted"
#: why a joint of a valid person-frame is not ground truth (``joints_valid`` false)
JOINT_NOT_OBSERVED = "not_observed"
#: the reason of a person-frame withheld for a QA flag: ``qa:<QA threshold name>``
QA_REASON_PREFIX = "qa:"
_HEX = re.compile(r"^[0-9a-f]{64}$")


def _dump(path: Path, d) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d, allow_nan=False, indent=None))
    return path


# ------------------------------------------------------------------------------ validity mask
def _check_valid(path, valid, reason, frames) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = np.array(valid, dtype=object)
    if v.ndim != 2 or v.shape[0] not in (1, 2):
        raise InputError(path, "valid", f"expected shape (P, F) with P in 1..2, got {v.shape}")
    notbool = np.vectorize(lambda x: not isinstance(x, (bool, np.bool_)), otypes=[bool])(v) \
        if v.size else np.zeros(v.shape, bool)
    if notbool.any():
        raise InputError(path, "valid", "expected booleans", frame=int(np.argwhere(notbool)[0][1]))
    v = v.astype(bool)
    r = np.array(reason, dtype=object)
    if r.shape != v.shape:
        raise InputError(path, "reason", f"shape {r.shape} != valid's {v.shape}")
    notstr = np.vectorize(lambda x: not isinstance(x, str) or not x, otypes=[bool])(r) \
        if r.size else np.zeros(r.shape, bool)
    if notstr.any():
        raise InputError(path, "reason", "expected non-empty strings",
                         frame=int(np.argwhere(notstr)[0][1]))
    r = r.astype(str)
    bad = v != (r == VALID_REASON)
    if bad.any():
        p, f = (int(i) for i in np.argwhere(bad)[0])
        raise InputError(path, "reason", f"person {p}: valid is {bool(v[p, f])} but the reason is "
                         f"{r[p, f]!r} (valid exactly where the reason is {VALID_REASON!r})",
                         frame=f)
    fr = np.array(frames, dtype=object)
    if fr.ndim != 1 or len(fr) != v.shape[1]:
        raise InputError(path, "frames", f"expected ({v.shape[1]},) frame indices, got shape "
                         f"{fr.shape}")
    notint = np.array([isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < 0
                       for x in fr], bool)
    if notint.any():
        raise InputError(path, "frames", "expected non-negative integers",
                         frame=int(np.flatnonzero(notint)[0]))
    fr = fr.astype(np.int64)
    if len(fr) > 1 and np.any(np.diff(fr) <= 0):
        raise InputError(path, "frames", "not increasing",
                         frame=int(np.flatnonzero(np.diff(fr) <= 0)[0]) + 1)
    return v, r, fr


def _check_joints_valid(path, jv, valid: np.ndarray) -> np.ndarray:
    j = np.array(jv, dtype=object)
    if j.ndim != 3 or j.shape[:2] != valid.shape:
        raise InputError(path, "joints_valid", f"expected shape (P, F, K) with (P, F) = "
                         f"{valid.shape}, got {j.shape}")
    notbool = np.vectorize(lambda x: not isinstance(x, (bool, np.bool_)), otypes=[bool])(j) \
        if j.size else np.zeros(j.shape, bool)
    if notbool.any():
        raise InputError(path, "joints_valid", "expected booleans",
                         frame=int(np.argwhere(notbool)[0][1]))
    j = j.astype(bool)
    bad = j.any(axis=2) & ~valid
    if bad.any():
        p, f = (int(i) for i in np.argwhere(bad)[0])
        raise InputError(path, "joints_valid", f"person {p}: a joint is valid in a frame that "
                         "is not", frame=f)
    return j


def _check_qa_reasons(path, r: np.ndarray, withhold) -> tuple[str, ...] | None:
    """Every ``qa:<reason>`` of ``r`` among ``withhold`` (the file's ``qa_withhold``)."""
    if withhold is not None:
        if not isinstance(withhold, (list, tuple)) or not all(
                isinstance(x, str) and x for x in withhold):
            raise InputError(path, "qa_withhold", f"expected a list of QA reason names, got "
                             f"{withhold!r}")
        withhold = tuple(withhold)
    qa = np.char.startswith(r.astype(str), QA_REASON_PREFIX) if r.size else np.zeros(r.shape, bool)
    for p, f in np.argwhere(qa):
        name = str(r[p, f])[len(QA_REASON_PREFIX):]
        if withhold is None or name not in withhold:
            raise InputError(path, "reason", f"person {int(p)}: {r[p, f]!r} is not a QA reason "
                             f"the file lists in qa_withhold ({withhold})", frame=int(f))
    return withhold


def write_valid(path: str | Path, valid, reason, frames, joints_valid=None,
                qa_withhold=None) -> Path:
    """valid: (P, F) bool; reason: (P, F) str (``"fitted"`` exactly where valid); frames: (F,)
    increasing frame indices; joints_valid: optional (P, F, K) bool, per joint (false wherever
    ``valid`` is); qa_withhold: the QA reasons a flagged frame was withheld for (None: QA was
    not read; every ``qa:<reason>`` of ``reason`` must be among them)."""
    v, r, fr = _check_valid("<memory>", np.asarray(valid).tolist(), np.asarray(reason).tolist(),
                            np.asarray(frames).tolist())
    w = _check_qa_reasons("<memory>", r, None if qa_withhold is None else list(qa_withhold))
    doc = {"valid": v.tolist(), "reason": r.tolist(), "frames": fr.tolist()}
    if joints_valid is not None:
        doc["joints_valid"] = _check_joints_valid(
            "<memory>", np.asarray(joints_valid).tolist(), v).tolist()
    if w is not None:
        doc["qa_withhold"] = list(w)
    return _dump(path, doc)


def read_valid(path: str | Path) -> dict[str, np.ndarray]:
    """``valid/<action>.json`` -> ``{"valid": (P, F) bool, "reason": (P, F) str,
    "frames": (F,) int64}``, and ``"joints_valid": (P, F, K) bool`` / ``"qa_withhold":
    tuple[str]`` when the file has them."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict):
        raise InputError(path, "<json>", f"expected an object, got {type(d).__name__}")
    for k in ("valid", "reason", "frames"):
        if k not in d:
            raise InputError(path, k, "missing")
    v, r, fr = _check_valid(path, d["valid"], d["reason"], d["frames"])
    out = {"valid": v, "reason": r, "frames": fr}
    if "joints_valid" in d:
        out["joints_valid"] = _check_joints_valid(path, d["joints_valid"], v)
    w = _check_qa_reasons(path, r, d.get("qa_withhold"))
    if w is not None:
        out["qa_withhold"] = w
    return out


def withheld_counts(reason: np.ndarray) -> dict[str, int]:
    """Person-frames of each ``qa:<reason>`` (withheld for a QA flag), all persons."""
    r = np.asarray(reason, str).ravel()
    r = r[np.char.startswith(r, QA_REASON_PREFIX)] if r.size else r
    return {str(k): int(n) for k, n in zip(*np.unique(r, return_counts=True), strict=True)}


def reason_counts(reason: np.ndarray) -> list[dict[str, int]]:
    """Per person, the person-frames of each reason other than ``"fitted"``."""
    r = np.asarray(reason, str)
    return [{str(k): int(n) for k, n in zip(*np.unique(row[row != VALID_REASON],
                                                        return_counts=True), strict=True)}
            for row in r]


# ------------------------------------------------------------------------------------- text
def write_text_annotations(path: str | Path, texts: Mapping[str, str]) -> Path:
    """``{action: sentence}`` (non-empty strings)."""
    for a, t in texts.items():
        if not isinstance(t, str) or not t.strip():
            raise InputError("<memory>", a, "expected a non-empty sentence")
    return _dump(path, dict(texts))


def read_text_annotations(path: str | Path) -> dict[str, str]:
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict):
        raise InputError(path, "<json>", f"expected an object, got {type(d).__name__}")
    for a, t in d.items():
        if not isinstance(t, str) or not t.strip():
            raise InputError(path, a, f"expected a non-empty sentence, got {t!r}")
    return d


# ---------------------------------------------------------------------------------- manifest
def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while b := f.read(chunk):
            h.update(b)
    return h.hexdigest()


def write_manifest(root: str | Path, files: Iterable[str | Path] | None = None) -> Path:
    """``<root>/MANIFEST.sha256`` over ``files`` (paths relative to root, or absolute inside
    it; default every file under root but the manifest), sorted, ``sha256sum -c`` format."""
    root = Path(root).resolve()
    if files is None:
        files = [p for p in root.rglob("*") if p.is_file() and p.name != MANIFEST_FILE]
    rels = sorted({(Path(f) if Path(f).is_absolute() else root / f).relative_to(root).as_posix()
                   for f in files})
    for r in rels:
        if "\n" in r or "\\" in r:
            raise InputError(root / r, "<name>", "a file name with a newline or backslash "
                             "cannot be listed in a sha256sum manifest")
    lines = [f"{sha256_file(root / r)}  {r}\n" for r in rels]
    out = root / MANIFEST_FILE
    out.write_text("".join(lines))
    return out


def read_manifest(path: str | Path) -> dict[str, str]:
    """``MANIFEST.sha256`` -> ``{relative path: sha256 hex}``."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(path, "<file>", f"cannot read: {e.strerror or e}") from None
    out = {}
    for i, line in enumerate(text.splitlines(), 1):
        h, sep, name = line.partition("  ")
        if not sep or not _HEX.match(h) or not name:
            raise InputError(path, f"line {i}", f"expected '<sha256 hex>  <path>', got {line!r}")
        if name in out:
            raise InputError(path, f"line {i}", f"{name!r} listed twice")
        out[name] = h
    return out


def verify_manifest(root: str | Path) -> list[str]:
    """Problems of ``<root>/MANIFEST.sha256`` against the folder, one line each naming the file
    (``[]``: every listed file is there with its hash and every file is listed)."""
    root = Path(root).resolve()
    listed = read_manifest(root / MANIFEST_FILE)
    problems = []
    for name, h in listed.items():
        p = root / name
        if not p.is_file():
            problems.append(f"{p}: listed in {MANIFEST_FILE} but missing")
        elif sha256_file(p) != h:
            problems.append(f"{p}: sha256 differs from {MANIFEST_FILE}")
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and p.name != MANIFEST_FILE and rel not in listed:
            problems.append(f"{p}: not listed in {MANIFEST_FILE}")
    return problems


# ------------------------------------------------------------------------------------- video
def cut_video(src: str | Path, dst: str | Path, frames, fps: float) -> Path:
    """Write the ``frames`` (indices, in order) of video ``src`` to ``dst`` (mp4v, ``fps``)."""
    from formats.video import VideoReader, write_mp4

    frames = [int(f) for f in frames]
    if not frames:
        raise InputError(src, "frames", "no frames to cut")
    with VideoReader(src) as v:
        if frames[-1] >= len(v) or frames[0] < 0:
            bad = next(f for f in frames if not 0 <= f < len(v))
            raise InputError(src, "frames", f"the video has {len(v)} frames (0..{len(v) - 1})",
                             frame=bad)
        return write_mp4(dst, v.frames(frames), fps)
