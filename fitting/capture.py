"""A marker capture read, checked and cleaned once: the domain side of stage ``capture``.

:func:`read_capture` reads the marker-wearing subject's markers from a C3D (Vicon ``Subject:``
prefixes, the lab's own labels, units converted to metres) and refuses a capture of
implausible size (a C3D in metres labelled mm is a 1.8 km person: ``InputError`` naming the
file, ``POINT:UNITS`` and the unit the data seem to be in). :func:`prepare_capture` cleans it
(``fitting.marker_clean``: ghosts, spikes, implausible speeds, label swaps of any length) and
returns the typed ``artifacts.Markers`` with what was repaired per marker and sample, and a
JSON report (per marker: observed share, gaps, repairs; the cleaning's runs; warnings).

Gaps are reported, never filled: a sample the file does not hold is not evidence, and the
fits treat it as missing (``docs/ARCHITECTURE.md``, "Capture").
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from artifacts.capture import Markers
from fitting.marker_clean import REPAIR_CODES, CleanOptions, clean_markers

# constants
WARN_REPAIRED_FRACTION = 0.01  # a marker with more of its samples repaired than this is named
WARN_OBSERVED_FRACTION = 0.5   # a marker seen in fewer samples than this is named
WARN_GAP_S = 0.5               # a gap longer than this is named


@dataclass(frozen=True)
class CaptureOptions:
    """The capture stage's options (recipe ``stages.capture``): ``clean`` the cleaner's
    (``fitting.marker_clean.CleanOptions``), ``clean_enabled`` false keeps the capture as
    read (every sample taken as evidence; for a lab that cleaned its data in Nexus)."""

    clean: CleanOptions = field(default_factory=CleanOptions)
    clean_enabled: bool = True


def read_capture(path: str | Path, names, prefix: str | None = None, labels=None):
    """The markers ``names`` of one subject from the C3D at ``path``, metres, NaN gaps,
    checked for a plausible size. ``prefix`` picks the subject's labels (``Derrick:``),
    ``labels`` maps a marker name to the lab's label where they differ. Returns
    ``(formats.c3d.Markers named by names, labels read (M,), unit scale to metres)``."""
    import dataclasses

    from formats.c3d import read_c3d
    from formats.plausibility import check_capture_scale

    labels = dict(labels.as_dict() if hasattr(labels, "as_dict") else (labels or {}))
    wanted = [labels.get(n, n) for n in names]
    m = read_c3d(path, markers=wanted, allow_missing=True, subject=prefix)
    check_capture_scale(m.xyz, path, "POINT:UNITS", m.unit)
    seen = np.all(np.isfinite(m.xyz), axis=-1).any(axis=0)
    read_as = [((f"{prefix}:" if prefix else "") + w) if s else "" for w, s in zip(wanted, seen, strict=True)]
    scale = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}.get(str(getattr(m, "unit", "mm")).lower(), 1e-3)
    out = dataclasses.replace(m, names=tuple(names)) if tuple(m.names) != tuple(names) else m
    return out, read_as, scale


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) of each run of True in a 1-D mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


def prepare_capture(raw, labels_read, unit_scale: float, source: str, opts: CaptureOptions,
                    segments: dict | None = None, log=None) -> tuple[Markers, dict]:
    """Clean a capture read by :func:`read_capture` and make the typed artifact.

    raw : ``formats.c3d.Markers`` (metres); segments : the cleaner's near-rigid groups
    (default: by the marker names). Returns ``(artifacts.Markers, report)``."""
    x0 = np.asarray(raw.xyz, float)
    F, M, _ = x0.shape
    names = tuple(raw.names)
    if opts.clean_enabled:
        cleaned, rep = clean_markers(raw, segments, opts.clean)
        codes, code_names = np.asarray(rep.codes(names), np.int8), tuple(REPAIR_CODES)
        rep_json = rep.to_json()
    else:
        cleaned, rep_json = raw, {"removed_samples": 0, "runs": [], "disabled": True}
        codes, code_names = np.zeros((F, M), np.int8), tuple(REPAIR_CODES)
    art = Markers(names=np.array(names, dtype=str), labels=np.array(labels_read, dtype=str),
                  xyz=np.asarray(cleaned.xyz, float), raw_observed=np.all(np.isfinite(x0), axis=-1),
                  repair=codes, repair_codes=np.array(code_names, dtype=str),
                  rate_hz=float(raw.rate_hz), first_frame=int(raw.first_frame),
                  unit_scale=float(unit_scale), source=str(source))
    art.validate(source)
    per_marker, warnings = {}, []
    obs = art.observed
    for m, n in enumerate(names):
        gaps = [(a, b) for a, b in _runs(~art.raw_observed[:, m]) if 0 < a and b < F - 1]
        longest = max((b - a + 1 for a, b in gaps), default=0)
        fixed = {str(code_names[c]): int(k) for c, k in
                 enumerate(np.bincount(codes[:, m].astype(np.int64), minlength=len(code_names)))
                 if c and k}
        per_marker[n] = {"label": labels_read[m], "observed_fraction": float(obs[:, m].mean()) if F else 0.0,
                         "gaps": len(gaps), "longest_gap_samples": int(longest), "repaired": fixed}
        if not labels_read[m]:
            warnings.append(f"marker {n}: not in the capture (no label "
                            f"{n!r}; the fit goes without it)")
            continue
        if per_marker[n]["observed_fraction"] < WARN_OBSERVED_FRACTION:
            warnings.append(f"marker {n}: observed in {100 * per_marker[n]['observed_fraction']:.0f} % "
                            "of the samples")
        if longest / float(raw.rate_hz) > WARN_GAP_S:
            warnings.append(f"marker {n}: a gap of {longest} samples "
                            f"({longest / float(raw.rate_hz):.2f} s)")
        nrep = sum(fixed.values())
        if F and nrep / F > WARN_REPAIRED_FRACTION:
            warnings.append(f"marker {n}: {nrep} samples repaired by the cleaning ("
                            + ", ".join(f"{k} {v}" for k, v in fixed.items()) + ")")
    repaired_frames = int(art.repaired.any(axis=1).sum())
    report = {"source": str(source), "samples": int(F), "markers": int(M),
              "rate_hz": float(raw.rate_hz), "first_frame": int(raw.first_frame) + 1,
              "unit_scale": float(unit_scale),
              "observed_samples": int(art.raw_observed.sum()),
              "repaired_samples": int(art.repaired.sum()), "repaired_frames": repaired_frames,
              "repaired_by_code": art.repairs_by_code(), "per_marker": per_marker,
              "cleaning": rep_json, "warnings": warnings}
    if log and report["repaired_samples"]:
        log(f"{source}: {report['repaired_samples']} marker samples repaired in "
            f"{repaired_frames} frames (" + ", ".join(f"{k} {v}" for k, v in
                                                      report["repaired_by_code"].items()) + ")")
    return art, report
