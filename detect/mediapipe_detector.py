"""mediapipe 0.10.21 legacy solutions (pose at model_complexity=1, hands) behind the
:class:`detect.base.Detector` interface.

- Single person: ``solutions.pose`` returns at most one person per image, so callers run it on
  crops (the marker wearer's box, the partner's search box) or on an image with the other
  person painted out (:mod:`detect.mask`).
- Weights ship inside the wheel (``mediapipe/modules/*/*.tflite``); nothing is downloaded.
  Only ``model_complexity=1`` is shipped for pose (0 and 2 would download), so it is fixed.
- Handedness: the hand classifier assumes a mirrored (selfie) image, so its label "Left" is
  the person's right hand in our camera images. :func:`hand_side` does the flip.
- Confidence: pose keypoints use the landmark's ``visibility``; hand keypoints all get the
  handedness score (the legacy API exposes no per-landmark confidence).
- Video mode (``MediapipeOptions.video``): a caller that looks at the same person in the same
  view frame after frame (the wearer's crop, the partner's tracked crop) names it with
  ``stream=`` (:mod:`detect.run` runs one view's frames at a time and calls :meth:`reset`
  between views and chunks, so streams name the person, not the view); each stream gets its own ``solutions.pose`` graph in tracking mode
  (``static_image_mode=False``, no landmark smoothing: the crop moves with the person and
  frames may be strided), which skips the person detector while the previous frame's
  landmarks still hold a person. A tracked call that finds nobody is redone in static mode
  (no detection lost), and :meth:`MediapipeDetector.forget` drops a stream whose result the
  caller rejected (the next call detects afresh: tracking never carries a wrong person on).
  After :meth:`reset` every stream detects afresh, as in a new detector (a graph shown a
  blank image drops what it tracked), so results still do not depend on which chunks a
  detector ran before, nor on the number of workers.
  Hand crops that follow one hand (``stream=("hand", person, side)``) likewise get a
  ``solutions.hands`` graph in tracking mode with ``max_num_hands=1`` (with fewer hands
  tracked than its maximum the palm detector runs on every frame): while it holds the hand
  only the landmark model runs (~7 ms against ~14 ms for a static two-hand call). A tracked
  call that finds nothing is final when the stream held no hand (the palm detector ran) and
  redone in static mode when it lost one; the caller redoes a call whose one tracked hand it
  rejects (the other person's, in a handshake) in static mode with ``max_hands``.
- The native code logs to stderr (TFLite, absl); :func:`detect.base.quiet_native_logs`
  silences it around graph construction and every call (and around whole chunks in
  :mod:`detect.run`, since some lines come from graph threads after a call returns).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detect import layout
from detect.base import Detections, Kind, quiet_native_logs
from detect.constants import N_KP
from detect.crops import crop_to_image, crop_window

#: What a stale tracking graph is shown to make it drop its person (see MediapipeDetector.forget).
_BLANK = np.zeros((32, 32, 3), np.uint8)


def hand_side(label: str) -> int:
    """Anatomical side (0 left, 1 right) of a mediapipe handedness label on an unmirrored
    image: the classifier assumes a mirrored selfie, so "Left" means the right hand."""
    if label == "Left":
        return 1
    if label == "Right":
        return 0
    raise ValueError(f"mediapipe handedness label: expected 'Left' or 'Right', got {label!r}")


@dataclass(frozen=True)
class MediapipeOptions:
    """Thresholds of the two mediapipe solutions. Hands always run in static-image mode;
    pose too unless ``video`` (then calls naming a ``stream`` track, see the module doc).

    pose_min_conf : pose detector's minimum person score.
    hand_min_conf : palm detector's minimum score.
    max_hands : hands returned per hand crop (2: in a handshake both people's hands are in the
        crop and the caller picks the one at the expected wrist).
    video : pose calls that name a ``stream`` track the person from the stream's previous
        call (mediapipe's video mode). track_min_conf : its tracking threshold.
    """

    pose_min_conf: float = 0.3
    hand_min_conf: float = 0.3
    max_hands: int = 2
    video: bool = False
    track_min_conf: float = 0.5

    def build(self) -> "MediapipeDetector":
        return MediapipeDetector(self)


def _open(graph) -> None:
    """Have every calculator of a just-built graph opened (call inside
    :func:`detect.base.quiet_native_logs`). ``start_run`` opens them on the graph's own threads
    and returns; a TFLite model opened after the quiet block ends writes "INFO: Created
    TensorFlow Lite XNNPACK delegate for CPU." to stderr (seen on one CI machine). A blank
    image's ``process`` waits until the graph is idle, every model opened; nobody is found, so
    a tracking graph starts with nobody tracked, as a new one does."""
    graph.process(_BLANK)


class MediapipeDetector:
    """One process's mediapipe graphs (not picklable; build one per worker from
    :class:`MediapipeOptions`)."""

    name = "mediapipe"
    needs_pixels = True

    def __init__(self, opts: MediapipeOptions = MediapipeOptions()):
        self.opts = opts
        #: detect() takes stream= and tracks (see detect.base.call_detector): video mode only
        self.streams = bool(opts.video)
        with quiet_native_logs():
            from mediapipe.python.solutions import hands as mp_hands
            from mediapipe.python.solutions import pose as mp_pose

            self._pose = mp_pose.Pose(
                static_image_mode=True, model_complexity=1, enable_segmentation=False,
                min_detection_confidence=opts.pose_min_conf)
            self._hands = mp_hands.Hands(
                static_image_mode=True, max_num_hands=opts.max_hands, model_complexity=1,
                min_detection_confidence=opts.hand_min_conf)
            _open(self._pose)
            _open(self._hands)
        self._tracks: dict = {}
        self._stale: set = set()
        self._had: dict = {}  # stream -> its last call found someone (it is tracking)
        #: tracked pose calls, and those redone in static mode (found nobody); the same for
        #: hand calls (redone when a tracked hand was lost)
        self.tracked_calls = 0
        self.static_retries = 0
        self.tracked_hand_calls = 0
        self.hand_static_retries = 0

    def _tracker(self, stream, kind: Kind = "body"):
        p = self._tracks.get(stream)
        if p is None:
            with quiet_native_logs():
                if kind == "body":
                    from mediapipe.python.solutions import pose as mp_pose

                    p = mp_pose.Pose(static_image_mode=False, model_complexity=1,
                                     smooth_landmarks=False, enable_segmentation=False,
                                     min_detection_confidence=self.opts.pose_min_conf,
                                     min_tracking_confidence=self.opts.track_min_conf)
                else:
                    from mediapipe.python.solutions import hands as mp_hands

                    # one hand: with fewer hands tracked than max_num_hands the palm detector
                    # runs on every frame (the caller falls back to a static two-hand call)
                    p = mp_hands.Hands(static_image_mode=False, max_num_hands=1,
                                       model_complexity=1,
                                       min_detection_confidence=self.opts.hand_min_conf,
                                       min_tracking_confidence=self.opts.track_min_conf)
                _open(p)
            self._tracks[stream] = p
        elif stream in self._stale:
            with quiet_native_logs():
                p.process(_BLANK)  # nobody there: tracking stops, the next call detects
            self._had.pop(stream, None)
        self._stale.discard(stream)
        return p

    def forget(self, stream) -> None:
        """Drop what ``stream`` tracks (its caller rejected the last result): its next call
        runs the person detector again. Restarting a graph costs ~7 pose calls, so the
        stream's graph is instead shown a blank image before its next call (it loses the
        person and detects afresh)."""
        if stream in self._tracks:
            self._stale.add(stream)

    def reset(self) -> None:
        """Forget every stream (:meth:`forget` each): the next call on any detects afresh,
        as a newly built detector's would, but the graphs (and their prepared models) are
        kept."""
        self._stale |= set(self._tracks)

    def close(self) -> None:
        with quiet_native_logs():
            self._pose.close()
            self._hands.close()
            for p in self._tracks.values():
                p.close()
        self._tracks = {}
        self._stale = set()
        self._had = {}

    def detect(self, image: np.ndarray | None, *, kind: Kind, box: np.ndarray | None = None,
               cam: int = 0, frame: int = 0, stream=None) -> Detections:  # noqa: ARG002
        """See :meth:`detect.base.Detector.detect`. image : (H, W, 3) uint8 RGB. stream : any
        hashable naming the person and view followed from call to call (video mode, body
        only); None: static."""
        if image is None:
            raise ValueError("MediapipeDetector.detect: needs the image pixels")
        h, w = image.shape[:2]
        win = (0, 0, w, h) if box is None else crop_window(box, w, h)
        if win is None:
            return Detections.empty()
        x0, y0, x1, y1 = win
        crop = np.ascontiguousarray(image[y0:y1, x0:x1])
        if kind == "body":
            if self.opts.video and stream is not None:
                self.tracked_calls += 1
                out = self._body(crop, win, self._tracker(stream))
                if len(out):
                    return out
                self.static_retries += 1  # the tracker lost the person: detect afresh
            return self._body(crop, win, self._pose)
        if kind == "hands":
            if self.opts.video and stream is not None:
                self.tracked_hand_calls += 1
                out = self._hand_list(crop, win, self._tracker(stream, "hands"))
                had, self._had[stream] = self._had.get(stream, False), len(out) > 0
                if len(out) or not had:
                    return out  # found, or nothing tracked before: the palm detector ran
                self.hand_static_retries += 1  # the tracker lost the hand: detect afresh
            return self._hand_list(crop, win, self._hands)
        raise ValueError(f"MediapipeDetector.detect: kind must be 'body' or 'hands', got {kind!r}")

    def _body(self, crop: np.ndarray, win, graph) -> Detections:
        with quiet_native_logs():
            res = graph.process(crop)
        if res.pose_landmarks is None:
            return Detections.empty()
        lm = res.pose_landmarks.landmark
        xyv = np.array([(p.x, p.y, p.visibility) for p in lm], dtype=np.float64)  # (33, 3)
        kp = np.zeros((1, N_KP, 3), np.float32)
        src, dst = layout.POSE33_SRC, layout.POSE33_DST
        kp[0, dst, :2] = crop_to_image(xyv[src, :2], win)
        kp[0, dst, 2] = np.clip(xyv[src, 2], 0.0, 1.0)
        return Detections(kp)

    def _hand_list(self, crop: np.ndarray, win, graph) -> Detections:
        with quiet_native_logs():
            res = graph.process(crop)
        if not res.multi_hand_landmarks:
            return Detections.empty()
        out = []
        for lms, hd in zip(res.multi_hand_landmarks, res.multi_handedness, strict=True):
            cls = hd.classification[0]
            side = hand_side(cls.label)
            xy = np.array([(p.x, p.y) for p in lms.landmark], dtype=np.float64)  # (21, 2)
            kp = np.zeros((N_KP, 3), np.float32)
            sl = layout.HANDS[side]
            kp[sl, :2] = crop_to_image(xy, win)
            kp[sl, 2] = float(np.clip(cls.score, 0.0, 1.0))
            out.append(kp)
        return Detections(np.stack(out))
