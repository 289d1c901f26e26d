"""C3D marker files (Vicon exports) through ezc3d.

Reading:

- Labels are ``POINT:LABELS`` followed by ``LABELS2``, ``LABELS3``... (C3D keeps at most 255
  per parameter; ezc3d splits and joins them). Whitespace is stripped.
- ``Subject:Marker`` prefixes are split off; ``subject`` selects one subject's markers.
- Units from ``POINT:UNITS`` (``mm``, ``cm``, ``m``; empty means the C3D default mm) are
  converted to metres.
- Gaps: a negative residual, an all-zero position or a non-finite coordinate -> NaN.
- A marker list decides which points are markers; everything else in the file (model outputs
  such as ``PELO``, ``LFEA``, angles/forces/moments stored as points, props) is ignored. Without
  a list, the points that Vicon lists under ``POINT:ANGLES``, ``FORCES``, ``MOMENTS``,
  ``POWERS``, ``SCALARS`` or ``REACTIONS`` are dropped and the rest are returned.
- Time: sample ``i`` is at ``(first_frame + i) / rate_hz`` seconds, ``first_frame`` 0-based
  (the C3D header's 1-based first frame minus 1; ``TRIAL:ACTUAL_START_FIELD`` when present,
  for captures longer than 65535 frames).
- A truncated file (fewer frames than the header announces), a corrupt file, or a requested
  marker that is absent raise :class:`formats.errors.InputError` naming the file and field.
- Processors: Intel and DEC files are read by ezc3d (which converts DEC floats); SGI/MIPS
  (big-endian) files, which ezc3d 1.7 refuses, by :mod:`formats.c3d_bigendian`.
- ``Markers.unit`` keeps the declared ``POINT:UNITS``; :mod:`formats.plausibility` checks it
  against the body size (the stages call it, not this reader).

Writing (:func:`write_c3d`) produces what Vicon exports: mm, float data, residual -1 on gaps,
``Subject:`` prefixes, extra non-marker points on request.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formats.c3d_bigendian import PROCESSORS, dec_to_ieee, processor_type, read_c3d_dict
from formats.errors import InputError, expect_shape

_UNITS_TO_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "": 1e-3}
_NON_MARKER_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")


@dataclass(frozen=True, eq=False)
class Markers:
    """Marker trajectories of one subject.

    names: (M,) marker labels without the subject prefix
    xyz: (F, M, 3) float64, metres, world (the mocap frame); NaN = gap
    rate_hz: sampling rate, Hz
    first_frame: 0-based index of sample 0 in the capture (sample i is at
        ``(first_frame + i) / rate_hz`` seconds)
    subject: the ``Subject:`` prefix the markers had, or None
    unit: the unit the file declared (``POINT:UNITS``: ``mm``, ``cm`` or ``m``); ``xyz`` is in
        metres whatever it says. :mod:`formats.plausibility` names it when the body size
        suggests the declaration is wrong.
    """

    names: tuple[str, ...]
    xyz: np.ndarray
    rate_hz: float
    first_frame: int = 0
    subject: str | None = None
    unit: str = "mm"

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(self.names))
        xyz = np.asarray(self.xyz, dtype=np.float64)
        expect_shape(xyz, "F M 3", "xyz")
        if xyz.shape[1] != len(self.names):
            raise InputError("<memory>", "xyz", f"{xyz.shape[1]} markers for {len(self.names)} names")
        if not self.rate_hz > 0:
            raise InputError("<memory>", "rate_hz", f"must be positive, got {self.rate_hz}")
        object.__setattr__(self, "xyz", xyz)

    @property
    def times_s(self) -> np.ndarray:
        """(F,) sample times, seconds from the capture start."""
        return (self.first_frame + np.arange(len(self.xyz))) / self.rate_hz

    def select(self, names: Sequence[str]) -> Markers:
        """The markers ``names`` in that order (KeyError naming the first missing one)."""
        idx = [self.names.index(n) if n in self.names else None for n in names]
        missing = [n for n, i in zip(names, idx, strict=True) if i is None]
        if missing:
            raise KeyError(f"markers not present: {missing}")
        return Markers(tuple(names), self.xyz[:, idx], self.rate_hz, self.first_frame, self.subject,
                       self.unit)


def _param(c, group: str, name: str):
    try:
        return c["parameters"][group][name]["value"]
    except KeyError:
        return None


def _labels(c) -> list[str]:
    out: list[str] = []
    i = 1
    while True:
        key = "LABELS" if i == 1 else f"LABELS{i}"
        v = _param(c, "POINT", key)
        if v is None:
            return out
        out.extend(str(s).strip() for s in v)
        i += 1


def _split(label: str) -> tuple[str | None, str]:
    if ":" in label:
        subj, name = label.split(":", 1)
        return subj.strip(), name.strip()
    return None, label


def _check_layout(path: Path) -> int:
    """Check the C3D header and section sizes against the file size before ezc3d parses it
    (ezc3d 1.7 loops forever on a file cut inside its parameter section, and silently returns
    fewer frames for one cut in the data). Returns the frame count the header announces."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(512)
        if len(head) < 512:
            raise InputError(path, "<header>", f"truncated: {size} bytes, a C3D header has 512")
        if head[1] != 0x50:
            raise InputError(path, "<header>", "corrupt or not a C3D file (no 0x50 key byte)")
        param_block = head[0]
        fh.seek(max(param_block - 1, 0) * 512)
        phead = fh.read(4)
    if param_block < 2 or len(phead) < 4:
        raise InputError(path, "<parameters>", f"truncated or corrupt: parameter block {param_block}")
    proc = phead[3]
    if proc not in (84, 85, 86):
        raise InputError(path, "<parameters>", f"corrupt: processor type {proc} (expected 84-86)")
    try:
        return _check_sections(path, head, phead, proc, size)
    except InputError as e:  # name the processor: Intel, DEC or SGI/MIPS
        raise InputError(e.file, e.field, f"{e.msg} ({PROCESSORS[proc]} processor)", e.frame) from None


def _check_sections(path: Path, head: bytes, phead: bytes, proc: int, size: int) -> int:
    """The parameter records and the data size of :func:`_check_layout`."""
    import struct

    param_block = head[0]
    endian = ">" if proc == 86 else "<"  # 84 Intel, 85 DEC (little-endian integers), 86 MIPS
    param_end = (param_block - 1 + phead[2]) * 512
    if size < param_end:
        raise InputError(path, "<parameters>", f"truncated: {size} bytes, parameters end at {param_end}")
    with open(path, "rb") as fh:
        fh.seek((param_block - 1) * 512)
        _check_parameter_records(path, fh.read(param_end - (param_block - 1) * 512), endian)
    n_pts, n_analog, first, last = struct.unpack(endian + "HHHH", head[2:10])
    if proc == 85:  # DEC (VAX) float: only its sign matters here
        scale = float(dec_to_ieee(head[12:16])[0])
    else:
        scale = struct.unpack(endian + "f", head[12:16])[0]
    data_start = struct.unpack(endian + "H", head[16:18])[0]
    frames = last - first + 1
    frame_bytes = (4 * n_pts + n_analog) * (4 if scale < 0 else 2)
    data_off = max(data_start - 1, 0) * 512
    if frame_bytes and frames > 0 and size < data_off + frames * frame_bytes:
        have = max(size - data_off, 0) // frame_bytes
        raise InputError(path, "<data>", f"truncated: {have} of {frames} frames present", frame=have)
    return frames


def _check_parameter_records(path: Path, sec: bytes, endian: str) -> None:
    """Walk the parameter records (name, id, next-offset, type, dims, data, description) and
    check that each lies inside the section and the chain moves forward; raise InputError on
    the first that does not (ezc3d can loop on such records)."""
    import struct

    pos, n = 4, len(sec)
    while True:
        if pos + 2 > n:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} past the end")
        name_len = abs(struct.unpack("b", sec[pos:pos + 1])[0])
        gid = struct.unpack("b", sec[pos + 1:pos + 2])[0]
        if name_len == 0:
            return
        p = pos + 2 + name_len
        if p + 2 > n:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} past the end")
        nxt = struct.unpack(endian + "h", sec[p:p + 2])[0]
        end = p + 2
        if gid > 0:  # a parameter: type, dims, data
            if end + 2 > n:
                raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} past the end")
            typ, ndim = struct.unpack("bB", sec[end:end + 2])
            if typ not in (-1, 1, 2, 4):
                raise InputError(path, "<parameters>", f"corrupt: type {typ} at byte {pos}")
            dims = sec[end + 2:end + 2 + ndim]
            end += 2 + ndim + abs(typ) * int(np.prod(list(dims), dtype=np.int64))
        end += 1 + (sec[end] if end < n else 0)  # description
        if end > n:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} overruns the section")
        if nxt == 0 or p + nxt + 2 > n:
            # 0 ends the chain; a link leaving the section follows the last record (the SGI
            # files of the C3D sample suite store that last link byte-swapped)
            return
        if p + nxt < end:
            raise InputError(path, "<parameters>", f"corrupt: record at byte {pos} links backwards")
        pos = p + nxt


def _announced_frames(c, header_frames: int) -> int:
    """Frames announced: Vicon's ``TRIAL:ACTUAL_START_FIELD``/``ACTUAL_END_FIELD`` (long
    captures overflow the uint16 header) or the header's count."""
    start, end = _param(c, "TRIAL", "ACTUAL_START_FIELD"), _param(c, "TRIAL", "ACTUAL_END_FIELD")
    if start is not None and end is not None and len(start) >= 2 and len(end) >= 2:
        return (int(end[0]) + 65536 * int(end[1])) - (int(start[0]) + 65536 * int(start[1])) + 1
    return header_frames


def read_c3d(path: str | Path, markers: Sequence[str] | None = None, subject: str | None = None,
             allow_missing: bool = False) -> Markers:
    """Read marker trajectories from a C3D file.

    path: the .c3d file. markers: marker names (without prefix) to return, in this order; None
    returns every point that is not a listed model output. subject: keep only labels with this
    ``Subject:`` prefix (unprefixed labels always qualify); needed when two subjects share names.
    allow_missing: a requested marker absent from the file becomes all-NaN instead of an error.
    Returns :class:`Markers` (``xyz: (F, M, 3)`` metres, NaN gaps).
    """
    import ezc3d

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "missing")
    header_frames = _check_layout(path)
    proc = processor_type(path)
    try:
        # ezc3d 1.7 refuses SGI/MIPS (big-endian) files: parse those ourselves.
        c = read_c3d_dict(path) if proc == 86 else ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError) as e:
        if isinstance(e, InputError):
            raise
        raise InputError(path, "<c3d>", f"corrupt or not a C3D file ({PROCESSORS.get(proc, proc)} "
                         f"processor): {e}") from None

    labels = _labels(c)
    pts = c["data"]["points"]  # (4, N, F) in file units, NaN where ezc3d saw residual < 0
    n_pts, n_frames = pts.shape[1], pts.shape[2]
    if len(labels) < n_pts:
        raise InputError(path, "POINT:LABELS", f"{len(labels)} labels for {n_pts} points")
    labels = labels[:n_pts]
    hdr = c["header"]["points"]
    expected = _announced_frames(c, header_frames)
    if n_pts and n_frames < expected:
        raise InputError(path, "<data>", f"truncated: {n_frames} of {expected} frames present",
                         frame=n_frames)
    rate = _param(c, "POINT", "RATE")
    rate = float(rate[0]) if rate is not None and len(rate) else float(hdr["frame_rate"])
    if not np.isfinite(rate) or rate <= 0:
        raise InputError(path, "POINT:RATE", f"must be positive, got {rate}")
    units = _param(c, "POINT", "UNITS")
    unit = str(units[0]).strip().lower() if units is not None and len(units) else ""
    if unit not in _UNITS_TO_M:
        raise InputError(path, "POINT:UNITS", f"unknown unit {unit!r} (expected mm, cm or m)")
    first = int(hdr["first_frame"])
    start = _param(c, "TRIAL", "ACTUAL_START_FIELD")
    if start is not None and len(start) >= 2:
        first = int(start[0]) + 65536 * int(start[1]) - 1

    split = [_split(lb) for lb in labels]
    # Candidate points: right subject (or no prefix).
    cand = [i for i, (s, _) in enumerate(split) if subject is None or s in (subject, None)]
    if markers is None:
        skip = set()
        for g in _NON_MARKER_GROUPS:
            v = _param(c, "POINT", g)
            if v is not None:
                skip.update(_split(str(s).strip())[1] for s in v)
        cand = [i for i in cand if split[i][1] not in skip and split[i][1]]
        wanted = [split[i][1] for i in cand]
    else:
        wanted = list(markers)
    by_name: dict[str, int] = {}
    for i in cand:
        name = split[i][1]
        if name in by_name and name in wanted:
            raise InputError(path, "POINT:LABELS", f"marker {name!r} appears twice "
                             f"({labels[by_name[name]]!r}, {labels[i]!r}); pass subject=")
        by_name.setdefault(name, i)
    if len(set(wanted)) != len(wanted):
        raise InputError(path, "markers", "requested marker names repeat")

    residuals = c["data"]["meta_points"].get("residuals") if "meta_points" in c["data"] else None
    scale = _UNITS_TO_M[unit]
    xyz = np.full((n_frames, len(wanted), 3), np.nan)
    subjects = set()
    for j, name in enumerate(wanted):
        i = by_name.get(name)
        if i is None:
            if allow_missing:
                continue
            raise InputError(path, "POINT:LABELS", f"marker {name!r} not in the file"
                             + (f" for subject {subject!r}" if subject else ""))
        subjects.add(split[i][0])
        x = pts[:3, i, :].T.astype(np.float64) * scale
        gap = ~np.all(np.isfinite(x), axis=1) | np.all(x == 0, axis=1)
        if residuals is not None:
            gap |= residuals[0, i, :] < 0
        x[gap] = np.nan
        xyz[:, j] = x
    subjects.discard(None)
    subj = subject if subject is not None else (subjects.pop() if len(subjects) == 1 else None)
    return Markers(tuple(wanted), xyz, rate, first, subj, unit or "mm")


def write_c3d(path: str | Path, markers: Markers, subject: str | None = None,
              extra_points: Mapping[str, np.ndarray] | None = None, angles: Sequence[str] = (),
              analogs: Mapping[str, np.ndarray] | None = None,
              analog_units: Mapping[str, str] | None = None,
              parameters: Mapping[str, Mapping[str, object]] | None = None) -> Path:
    """Write ``markers`` as a Vicon-style C3D (mm, float, residual -1 on NaN gaps).

    subject: label prefix (``"<subject>:<marker>"``), defaults to ``markers.subject``.
    extra_points: non-marker points ``{label: (F, 3) metres}`` (model outputs, props) written
    after the markers with the same prefix (labels starting with ``*``, Vicon's unlabelled
    trajectories, get none); labels also listed in ``angles`` are declared under
    ``POINT:ANGLES`` like Vicon's joint angles (values written as given, not scaled).
    analogs: analog channels ``{label: (F * n,)}`` sampled at ``n`` (an integer >= 1, the same
    for all) times the point rate (force plates, EMG), written unscaled (``SCALE`` 1,
    ``GEN_SCALE`` 1, ``OFFSET`` 0) with ``analog_units`` ``{label: unit}`` (default "V").
    parameters: extra parameter groups ``{group: {name: value}}`` (e.g. ``FORCE_PLATFORM``);
    a value is a list of ints, floats or strings, or a float array of any shape.
    """
    import ezc3d

    path = Path(path)
    subject = subject if subject is not None else markers.subject
    prefix = f"{subject}:" if subject else ""
    F = len(markers.xyz)
    names = [prefix + n for n in markers.names]
    data = [markers.xyz * 1000.0]
    for label, arr in (extra_points or {}).items():
        a = np.asarray(arr, dtype=np.float64)
        expect_shape(a, f"{F} 3", f"extra_points[{label}]")
        names.append(label if label.startswith("*") else prefix + label)
        data.append((a if label in angles else a * 1000.0)[:, None, :])
    xyz = np.concatenate(data, axis=1) if data else np.zeros((F, 0, 3))
    gap = ~np.all(np.isfinite(xyz), axis=2)  # (F, N)
    pts = np.ones((4, xyz.shape[1], F))
    pts[:3] = np.where(gap[..., None], 0.0, xyz).transpose(2, 1, 0)
    res = np.where(gap, -1.0, 0.0).T[None]  # (1, N, F)

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(markers.rate_hz)]
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(names)
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = tuple("" for _ in names)
    if angles:
        c.add_parameter("POINT", "ANGLES", [prefix + a for a in angles])
    first = int(markers.first_frame)
    c["header"]["points"]["first_frame"] = min(first, 65534 - F) if first + F >= 65535 else first
    if first + F >= 65535:  # the header holds uint16 frame numbers: Vicon's TRIAL fields
        start, end = first + 1, first + F
        c.add_parameter("TRIAL", "ACTUAL_START_FIELD", [start % 65536, start // 65536])
        c.add_parameter("TRIAL", "ACTUAL_END_FIELD", [end % 65536, end // 65536])
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res}
    if analogs:
        labels = list(analogs)
        chans = [np.asarray(analogs[k], dtype=np.float64).reshape(-1) for k in labels]
        n = len(chans[0]) // F if F else 0
        for k, a in zip(labels, chans, strict=True):
            if n < 1 or len(a) != n * F:
                raise InputError(path, f"analogs[{k}]", f"{len(a)} samples: expected {n or 1} x {F} "
                                 "(an integer multiple of the point frames, the same for every channel)")
        c["parameters"]["ANALOG"]["RATE"]["value"] = [float(markers.rate_hz) * n]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = tuple(labels)
        c["parameters"]["ANALOG"]["DESCRIPTIONS"]["value"] = tuple("" for _ in labels)
        c["parameters"]["ANALOG"]["UNITS"]["value"] = tuple((analog_units or {}).get(k, "V") for k in labels)
        c["data"]["analogs"] = np.stack(chans)[None]  # (1, channels, F * n)
    for group, params in (parameters or {}).items():
        for name, value in params.items():
            if isinstance(value, np.ndarray):
                value = value.astype(np.float64)
            c.add_parameter(group, name, value)
    path.parent.mkdir(parents=True, exist_ok=True)
    c.write(str(path))
    return path
