"""Stage ``silhouettes`` (per sequence): the people's masks per video frame and camera, and the
partner's (the people less the wearer's fitted body), for the partner fit's ``L_sil``
(``fitting/silhouette.py``; issue #27).

Thin adapter around ``detect.silhouette.silhouettes``: reads the videos and the recipe's
clean plates (``sequences.<id>.clean_plates``, per camera; a camera without one uses OpenCV's
MOG2 over the sequence), the cameras (``capture``'s rig) and the wearer's fit (``marker_fit``:
posed with ``body.forward`` and rasterised out of the people mask).

The frames are the wearer's fitted frames (the keypoints' video frames, which the partner fit
fits too: every ``stride``-th one when the keypoints stage strides). Writes

- ``masks.npz``: an ``artifacts.silhouettes.Silhouettes`` (bit-packed masks at
  ``scale``, mask shares of the image, ``usable`` per frame and view);
- ``report.json``: per camera the source, mask areas (share of the image), the frames whose
  mask is implausible (empty, or most of the image) and so not used;
- ``silhouettes.png``: the masks over the middle frame of each view.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detect.silhouette import SilhouetteOptions
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "cameras")


@dataclass(frozen=True)
class Options(SilhouetteOptions):
    """``detect.silhouette.SilhouetteOptions``: scale, threshold, morphology, the wearer's
    dilation, the plausible mask shares."""


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe)}
    for cam in recipe.cameras:
        out[f"video:{cam}"] = Path(seq.videos[cam])
        if cam in seq.clean_plates:
            out[f"clean_plate:{cam}"] = Path(seq.clean_plates[cam])
    return out


def read_plate(path: Path, size: tuple[int, int]) -> list[np.ndarray]:
    """Every frame of a clean-plate video (RGB), checked against the camera's image ``size``
    (width, height): ``formats.errors.InputError`` naming the file when it is missing,
    unreadable or of another size."""
    from formats.errors import InputError
    from formats.video import VideoReader

    with VideoReader(path) as r:
        if (r.info.width, r.info.height) != tuple(size):
            raise InputError(path, "clean_plate", f"the clean plate is {r.info.width}x"
                             f"{r.info.height}, the camera {size[0]}x{size[1]}")
        return list(r.frames())


def run(ctx: StageContext) -> None:
    import cv2

    from artifacts import BodyFit
    from body.lbs import posed_at
    from detect.silhouette import overlay, silhouettes
    from formats.video import VideoReader

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    cams = common.capture_cameras(ctx, list(rv.cameras))
    plates = {c: read_plate(ctx.raw[f"clean_plate:{cam.name}"], (cam.width, cam.height))
              for c, cam in enumerate(cams) if f"clean_plate:{cam.name}" in ctx.raw}
    videos = [ctx.raw[f"video:{c.name}"] for c in cams]
    n, warnings = common.video_length(videos, cams)
    for w in warnings:
        ctx.log(f"{ctx.unit}: {w}")
    frames = np.arange(n)
    wearer_V, faces = None, None
    if "marker_fit" in ctx.inputs:  # the frames fitted (the keypoints' video frames: a stride)
        model = common.load_body(ctx)
        wearer = BodyFit.load(ctx.inputs["marker_fit"])
        frames = np.asarray(wearer.frames, np.int64)
        frames = frames[(frames >= 0) & (frames < n)]
        wearer_V = posed_at(model, wearer, frames, chunk=32)[0]
        faces = np.asarray(model.faces)
    readers = [VideoReader(p, (c.width, c.height)) for p, c in zip(videos, cams, strict=True)]
    try:
        masks, report = silhouettes(lambda c, f: readers[c][f], cams, frames, plates, wearer_V,
                                    faces, o, progress=ctx.progress)
        mid = len(frames) // 2  # an index into frames (a stride of the video)
        img = overlay([r[int(frames[mid])] for r in readers], masks, mid)
    finally:
        for r in readers:
            r.close()
    masks.save(ctx.out)
    report.update({"sequence": ctx.unit, "wearer_rendered_out": wearer_V is not None,
                   "overlay_frame": int(frames[mid])})
    ctx.out.save_json("report", report)
    cv2.imwrite(str(ctx.out.path("silhouettes.png")), img[..., ::-1])
    ctx.log(f"{ctx.unit}: {report['views_usable']}/{report['views']} views usable")


STAGE = Stage(name="silhouettes", func=run, per="sequence", upstream=("capture", "rig", "marker_fit"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="people masks from the clean plates; the partner's with the wearer rendered out")
