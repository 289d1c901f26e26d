"""Adapter helpers shared by the stage modules (stage modules never import each other).

What a stage needs of the recipe beyond its declared view (``Stage.reads``) comes through
``ctx.raw``, keyed by content: among them the body-model file, named here once.
"""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ANNY_DEFAULT = REPO / "assets" / "build" / "anny_model.npz"


def body_model_file(recipe) -> Path:
    """The file (or folder) the recipe's body model is loaded from: ``body_model.path``, else
    ``$ANNY_MODEL_PATH`` / ``assets/build/anny_model.npz`` for Anny and ``$SMPLX_MODEL_PATH``
    for the SMPL family. Raw input ``body_model`` of every stage that loads the model, so that
    a rebuilt or replaced model file recomputes what was fitted with it."""
    bm = recipe.body_model
    if bm.path is not None:
        return Path(bm.path)
    if bm.kind == "anny":
        return Path(os.environ.get("ANNY_MODEL_PATH", str(ANNY_DEFAULT)))
    env = os.environ.get("SMPLX_MODEL_PATH")
    if not env:
        from formats.errors import InputError

        raise InputError(getattr(recipe, "source", None) or "recipe", "body_model.path",
                         f"body model {bm.kind!r} needs a path (or $SMPLX_MODEL_PATH)")
    return Path(env)


def ground_of(view):
    """The recipe's floor as the domain functions take it: ``(normal (3,) float, offset)``, the
    plane ``normal . x = offset`` (``view``: a recipe or a stage's recipe view)."""
    import numpy as np

    return np.asarray(view.ground_plane.normal, float), float(view.ground_plane.offset)


def load_body(ctx):
    """The body model of the recipe (kind from the declared view ``body_model.kind``, file from
    the raw input ``body_model``)."""
    from body import load_model

    return load_model(ctx.recipe.body_model.kind, ctx.raw["body_model"])


FPS_TOLERANCE = 1e-4  # relative: 29.97 vs 30000/1001 passes, 30 vs 29.97 (a frame per 1,000) does not


def check_videos(paths: list[Path], fps: float | None) -> list[str]:
    """One message per problem of a sequence's videos (the recipe's camera order): a video that
    can't be read, one whose own rate differs from the recipe's ``fps``. Each message names the
    video and both numbers (:func:`video_errors` as text). Videos of different lengths are not
    a problem: the sequence is cut to the shortest (:func:`video_length` says so)."""
    return [str(e) for e in video_errors(paths, fps)]


def video_errors(paths: list[Path], fps: float | None) -> list:
    """The problems of :func:`check_videos` as ``formats.errors.InputError`` (file = the video,
    field ``fps`` or the reader's), for a stage to raise the first one. ``fps`` None: the
    videos must agree with the first readable one's rate."""
    from formats.errors import InputError
    from formats.video import video_info

    infos, out = {}, []
    for p in paths:
        try:
            infos[Path(p)] = video_info(p)
        except InputError as e:
            out.append(e)
        except OSError as e:
            out.append(InputError(p, "<file>", str(e)))
    if not infos:
        return out
    if fps is None:  # the recipe leaves the rate to the videos: they must agree with each other
        fps = next(iter(infos.values())).fps
    for p, i in infos.items():
        if abs(i.fps - fps) > FPS_TOLERANCE * fps:
            out.append(InputError(p, "fps", f"the video runs at {i.fps:g} fps, the recipe says "
                                  f"{fps:g} (sequences.<id>.fps)"))
    return out


def video_length(paths: list[Path], cams=None) -> tuple[int, list[str]]:
    """The frames a sequence has (the shortest of its videos) and the warnings about its videos:
    each video of another length (both counts, ``formats.video.common_length``), a variable
    frame rate or a rotation (``formats.video.video_warnings``), and, with ``cams`` (the rig's
    ``calib.Camera``s, same order), a decoded size a few pixels off the calibration's (accepted
    and padded at the right / bottom); a size further off raises InputError
    (``formats.video.size_fit``)."""
    from formats.video import common_length, size_fit, video_info, video_warnings

    infos = {Path(p): video_info(p) for p in paths}
    n, warnings = common_length(infos)
    for k, (p, i) in enumerate(infos.items()):
        warnings += video_warnings(p, i)
        if cams is not None:
            dx, dy = size_fit(p, i, cams[k].width, cams[k].height)
            if (dx, dy) != (0, 0):
                warnings.append(f"{p}: size: decoded {i.width}x{i.height}, calibration "
                                f"{cams[k].width}x{cams[k].height}: accepted, pixel coordinates "
                                f"kept (frames padded by {dx}, {dy} px at the right, bottom)")
    return n, warnings


def markerset_file(subject_spec) -> dict[str, Path]:
    """Raw input ``markerset`` of a subject whose marker set is a file (``.yaml``/``.yml``/
    ``.json``: ``recipes.schema.markerset_is_file``; ``{}`` for a built-in set, which the view
    gives by name)."""
    from recipes.schema import markerset_is_file

    ms = subject_spec.markerset
    return {"markerset": Path(ms)} if markerset_is_file(ms) else {}


def marker_template(ctx, markerset: str, model):
    """The template placement (``fitting.marker_graph.Placement``) of a subject's marker set on
    ``model``: ``markerset`` is the view's value (a built-in name, or ``"file"`` for a marker-set
    file read from the raw input ``markerset``: ``markerset/2`` YAML/JSON of landmarks or
    ``markerset/1`` JSON, ``body.landmarks.load_markerset``)."""
    from body.landmarks import load_markerset
    from fitting.marker_graph import template_placement

    if markerset == "file":
        return template_placement(model, load_markerset(ctx.raw["markerset"], model))
    return template_placement(model, markerset)


def marker_labels(template, recipe_labels) -> dict[str, str]:
    """The lab's C3D label per marker where it differs from the name: the marker-set file's
    ``label`` fields (``template.labels``), overridden by the recipe's ``marker_labels``."""
    rl = recipe_labels.as_dict() if hasattr(recipe_labels, "as_dict") else (recipe_labels or {})
    return {**(getattr(template, "labels", None) or {}), **dict(rl)}


def sequence_fps(fps: float | None, video: Path) -> float:
    """The video rate of a sequence: the recipe's ``fps``, else the video's own rate."""
    if fps is not None:
        return float(fps)
    from formats.video import video_info

    return float(video_info(video).fps)


def artifact_folder(art) -> Path:
    """An upstream artifact's folder (the engine's artifact, or a folder path in tests)."""
    return Path(getattr(art, "dir", art))


def capture_markers(ctx, names=None):
    """The sequence's cleaned capture from the ``capture`` stage (``artifacts.capture.Markers``);
    ``names``: the marker names the caller's placement expects (an InputError naming the
    artifact when the capture was made for another marker set)."""
    from artifacts.capture import Markers
    from formats.errors import InputError

    art = ctx.inputs["capture"]
    mk = Markers.load(art)
    if names is not None and tuple(names) != mk.marker_names:
        raise InputError(artifact_folder(art) / "markers.npz", "names",
                         f"captured markers {list(mk.marker_names)} differ from the placement's "
                         f"{list(names)} (recompute capture and shape_fit)")
    return mk


def capture_cameras(ctx, names=None) -> list:
    """The sequence's cameras (``calib.Camera``, recipe order or ``names``) from the
    ``capture`` stage's ``artifacts.capture.CameraRig``; ``[]`` on a marker-only sequence."""
    from artifacts.capture import CameraRig

    art = _rig_artifact(ctx)
    if art is None:
        return []
    return CameraRig.load(art).cameras(names)


def _rig_artifact(ctx):
    """The upstream artifact holding the rig: the ``rig`` stage's (the rig refined from the
    person, when the sequence asks for it), else ``capture``'s, or on a markerless sequence
    (no capture stage) the ``keypoints`` stage's, which read the calibration instead."""
    for stage in ("rig", "capture", "keypoints"):
        art = ctx.inputs.get(stage)
        if art is not None and not isinstance(art, dict) and (
                artifact_folder(art) / "rig.npz").exists():
            return art
    return None


def capture_rig(ctx):
    """``([calib.Camera], [calibration file names])`` of the ``capture`` stage's rig, recipe
    order; None on a marker-only sequence."""
    from artifacts.capture import CameraRig

    art = _rig_artifact(ctx)
    if art is None:
        return None
    rig = CameraRig.load(art)
    return rig.cameras(), [str(s) for s in rig.source]


def marker_timeline(seq, raw: dict, markers, keypoints=None):
    """The frames a marker stage fits and how capture samples map onto them, from the
    sequence's view (``fps``, ``mocap``, ``has_video``) and raw inputs (``video``).

    With video: the keypoints' frames (the keypoints stage may run with a stride), else every
    video frame, on the video clock. Marker-only: every sample of the capture at its own rate
    (or ``mocap.rate_hz``), frame ``f`` = the capture's 0-based frame number
    ``first_frame + i`` of sample ``i`` (C3D frame number ``f + 1``).
    Returns ``(frames (F,), fitting.mocap.VideoClock, what the frames are)``."""
    import numpy as np

    from fitting.mocap import VideoClock

    if seq.has_video:
        from formats.video import video_info

        fps = sequence_fps(seq.fps, raw.get("video"))
        if keypoints is not None:
            frames = np.asarray(keypoints.frames, dtype=np.int64)
        else:
            frames = np.arange(video_info(raw["video"]).n_frames)
        return frames, VideoClock(fps, seq.mocap.sync_offset_s, seq.mocap.rate_hz), "video frames"
    rate = float(seq.mocap.rate_hz or markers.rate_hz)
    frames = markers.first_frame + np.arange(len(markers.xyz), dtype=np.int64)
    return (frames, VideoClock(rate, 0.0, seq.mocap.rate_hz),
            "capture frames (0-based: the C3D frame number - 1)")


# ------------------------------------------------------------------ upstream reports, figures
# The stages without a typed report (shape_fit, keypoints, marker_fit, partner_fit) are shown
# as they are: their ``report.json`` in the QA page and a pick in export's figures, their PNGs
# copied beside the QA report. Every such read goes through these two helpers.


def stage_report(art) -> dict | None:
    """An upstream stage's ``report.json`` as written (None: the stage wrote none)."""
    try:
        rep = art.json("report")
    except FileNotFoundError:
        return None
    return rep if isinstance(rep, dict) else None


def stage_figures(art) -> list[Path]:
    """The PNG pictures an upstream stage drew at the top of its folder, sorted by name."""
    return sorted(Path(art.dir).glob("*.png"))



# ------------------------------------------------------------------ the fitted people
def fitted_people(ctx) -> list[tuple[object, str]]:
    """``[(artifact, stage)]`` of the sequence's fitted people, person 0 first: the marker
    wearer's ``marker_fit`` and the partner's ``partner_fit``; on a markerless sequence (no
    marker_fit) both from ``partner_fit``: person 0 in its ``person0/`` folder (given as that
    folder's path: ``BodyFit.load`` and :func:`artifact_folder` take one), person 1 (when there
    is one) at its top."""
    mf, pf = ctx.inputs.get("marker_fit"), ctx.inputs.get("partner_fit")
    if mf is not None:
        return [(mf, "marker_fit")] + ([(pf, "partner_fit")] if pf is not None else [])
    if pf is None:
        return []
    folder = artifact_folder(pf)
    out: list[tuple[object, str]] = [(folder / "person0", "partner_fit")]
    if (folder / "fit.npz").is_file():
        out.append((pf, "partner_fit"))
    return out


def calibration_inputs(recipe, seq) -> dict[str, Path]:
    """The raw inputs ``calibration:<camera>`` of a sequence (and ``calibration_pair:<camera>``,
    the other file of an EasyMocap intri/extri pair, which is read too): what ``capture`` and a
    markerless ``keypoints`` read of the calibration."""
    out: dict[str, Path] = {}
    for cam in recipe.cameras:
        if cam in seq.calibration:
            p = Path(seq.calibration[cam])
            out[f"calibration:{cam}"] = p
            if seq.calibration_format == "easymocap" or (
                    p.suffix.lower() in (".yml", ".yaml") and p.stem in ("intri", "extri")):
                from calib.io import easymocap_pair

                intri, extri = easymocap_pair(p)
                out[f"calibration_pair:{cam}"] = extri if p == intri else intri
    return out
