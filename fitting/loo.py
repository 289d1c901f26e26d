"""Leave-one-out marker error: the honest accuracy figure of a marker fit on real data.

A fit's own residuals flatter it (each marker pulled the body towards itself). Here each
marker ``m`` in turn is hidden (its observations set to NaN), the sequence is refitted by the
same path as the stage (:func:`fitting.marker_fit.fit_markers`), and ``m`` is predicted from
the fitted body through the subject's placement (posed surface point + offset along the posed
face normal, ``fitting.skinned.SkinnedPoints``, the same marker definition as
``body.markers.marker_positions``). The distance to the observed ``m`` is what a marker the
fit never saw is off by: placement error + pose error + soft tissue.

The refits run with the marker fit's own options (``opts``: the recipe's
``stages.marker_fit`` section), so leave-one-out scores the fit the stage made.

``stride`` fits every k-th video frame only, each warm-started from the previous fitted frame
(``fit_sequence``'s warm start across a k-frame step). Measured on a synthetic 39-marker
capture of 1,000 video frames at 50 Hz (bench/fitting_synth.py, compiled graph, a shared
2-core machine): all 39 refits at stride 4 took 50 CPU-s (~5 ms per marker-frame), so stride
1 would be ~200 CPU-s, over the ~3 CPU-minute budget; ``DEFAULT_STRIDE`` = 2 is ~100 CPU-s
and scores 500 frames per marker.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from artifacts import ShapeFit
from body.lbs import rest_state
from body.rotations import rotmat_to_rotvec
from fitting import mocap, skinned
from fitting.marker_fit import MarkerFitOptions, fit_markers
from fitting.marker_graph import Placement, marker_coeffs, placement_of
from formats.c3d import Markers
from formats.errors import InputError

DEFAULT_STRIDE = 2
DEFAULT_FIT_OPTIONS = MarkerFitOptions()


def _stats_mm(d_m: np.ndarray) -> dict:
    d = np.asarray(d_m, float) * 1000
    if d.size == 0:
        return {"median_mm": None, "p90_mm": None, "frames": 0}
    return {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)),
            "frames": int(d.size)}


def predicted_markers(model, fit, pl: Placement, fitted_joints) -> np.ndarray:
    """(F, M) positions of the placement's markers on a :class:`artifacts.BodyFit`'s body
    (fitted joints by name, as ``fit_markers``' report lists them), metres, world."""
    skel = skinned.fit_skeleton(model, [model.joint_index(n) for n in fitted_joints])
    rest = rest_state(model, np.asarray(fit.betas, float))
    u, _ = skinned.reduced_offsets(model, rest, skel)
    H = marker_coeffs(model, rest, skel, pl)
    F = len(fit.frames)
    X = np.concatenate([rotmat_to_rotvec(np.asarray(fit.global_orient)),
                        np.asarray(fit.transl), np.asarray(fit.body_pose)[:, skel.joints[1:]]
                        .reshape(F, -1)], axis=1)
    return np.stack([H.positions(skel, u, x) for x in X])


class _Refits:
    """The leave-one-out refits of one sequence with what does not depend on the held marker
    built once: the subject's rest state, the skeleton, the placement's coefficients, the
    compiled graph, the prior and the frame solver, exactly as ``fit_markers`` builds them for
    a markers-only fit (no keypoints). Each refit then is ``fit_markers``' own path with the
    marker hidden: ``fit_sequence`` from the first frame with ``MIN_MARKERS`` visible (searched
    from the initial pose), every later frame warm-started from the previous one; frames before
    it and frames with fewer markers are not valid. Same numbers as calling ``fit_markers``
    per marker (tested), without its ~0.1 s of set-up and report per refit."""

    def __init__(self, model, shape: ShapeFit, template: Placement, obs, vis, opts, source):
        from fitting import compiled, priors
        from fitting.marker_fit import FrameSolver
        from fitting.marker_graph import GraphSpec, MarkerGraph, body_joints, placement_support

        pl = placement_of(shape)
        if template.names != pl.names:
            diff = sorted(set(template.names) ^ set(pl.names)) or "order"
            raise InputError(source, "markers", f"the shape_fit placement and the marker set "
                             f"differ ({diff})")
        rest = rest_state(model, np.asarray(shape.betas, float))
        self.skel = skinned.fit_skeleton(model, body_joints(model))
        self.u, _ = skinned.reduced_offsets(model, rest, self.skel)
        self.Hm = marker_coeffs(model, rest, self.skel, pl)
        spec = GraphSpec(self.skel.topology, placement_support(model, self.skel, template, self.Hm),
                         (), 0, "h36m")
        graph = MarkerGraph(spec, compiled.CompileOptions(mode=opts.compile))
        self.solver = FrameSolver(graph, self.skel, self.u, self.Hm,
                                  priors.default_prior(self.skel.names[1:]), opts)
        self.obs, self.vis, self.source = obs, np.asarray(vis, bool), source

    def held_out(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Refit without marker ``k``: its predicted position (F, 3) and the frames where the
        refit is valid."""
        from fitting.marker_fit import MIN_MARKERS, fit_sequence

        vis = self.vis.copy()
        vis[:, k] = False
        n_vis = vis.sum(1)
        if not np.any(n_vis >= MIN_MARKERS):
            raise InputError(self.source, "markers",
                             f"no video frame has {MIN_MARKERS} or more markers")
        first = int(np.argmax(n_vis >= MIN_MARKERS))
        obs = self.obs.copy()
        obs[:, k] = 0.0  # as video_observations gives a marker never seen
        fit = fit_sequence(self.solver, obs[first:], vis[first:].astype(float))
        X = np.concatenate([np.repeat(fit.x[:1], first, axis=0), fit.x])
        pred = np.stack([self.Hm.positions(self.skel, self.u, x)[k] for x in X])
        valid = n_vis >= MIN_MARKERS
        valid[:first] = False
        return pred, valid


def leave_one_out(model, shape: ShapeFit, template: Placement, markers: Markers,
                  clock: mocap.VideoClock, frames, held=None,
                  opts: MarkerFitOptions = DEFAULT_FIT_OPTIONS, stride: int = DEFAULT_STRIDE,
                  progress=None, source: str = "markers", reference: bool = False) -> dict:
    """Leave-one-out error of each held-out marker.

    model, shape, template, markers, clock, frames : as :func:`fit_markers` (``frames`` the
    video frames to score); opts : the :class:`MarkerFitOptions` every refit runs with: pass
    the ones the recipe gives ``stages.marker_fit`` (weights, robust scale, iterations,
    compile mode), so the figure scores the fit the stage made (no keypoints are passed:
    ``use_hands`` has no effect here); ``opts.max_frames`` applies after the stride; held : marker
    names to hold out (default every marker of the shape's placement); stride : fit every
    k-th frame (>= 1); progress : optional iterable wrapper over the held markers; source :
    the capture's file, named in input errors; reference : refit by calling
    ``fit_markers`` once per held marker (slower; the graph is still built once), the path
    the default (:class:`_Refits`, the same numbers) is tested against.

    Returns ``{"per_marker": {name: {"median_mm", "p90_mm", "frames"}}, "median_mm",
    "p90_mm"`` (over every held-out marker-frame), ``"cpu_s"`` (process CPU seconds),
    ``"fps_per_cpu_s"`` (the sequence's frames, ``frames`` before the stride, per CPU second),
    ``"stride"``, ``"fitted_frames"``, ``"frames"`` (F',) the frames fitted and ``"error_mm"``
    (F', len(held)) each held marker's prediction error, NaN where not scored}. Only frames
    where the fit is valid and the held marker observed are scored.
    """
    if int(stride) < 1:
        raise ValueError(f"stride: must be >= 1, got {stride}")
    pl = placement_of(shape)
    held = list(pl.names if held is None else held)
    unknown = [n for n in held if n not in pl.names]
    if unknown:
        raise InputError(source, "held", f"markers not in the placement: {unknown}")
    try:
        markers = markers.select(pl.names)
    except KeyError as e:
        raise InputError(source, "markers", str(e)) from None
    n_sequence = len(frames)
    frames = np.asarray(frames, dtype=np.int64)[::int(stride)]
    if opts.max_frames:
        frames = frames[:opts.max_frames]
    obs, vis = mocap.video_observations(markers, frames, clock)
    c0 = time.process_time()
    per, pooled = {}, []
    err = np.full((len(frames), len(held)), np.nan)
    it = held if progress is None else progress(held, total=len(held), desc="leave-one-out")
    refit = None if reference else _Refits(model, shape, template, obs, vis, opts, source)
    graphs: dict = {}  # one graph for every refit: hiding a marker does not change its spec
    for name in it:
        k = pl.names.index(name)
        if refit is not None:
            pred, valid = refit.held_out(k)
        else:
            xyz = markers.xyz.copy()
            xyz[:, k] = np.nan
            hidden = Markers(markers.names, xyz, markers.rate_hz, markers.first_frame,
                             markers.subject)
            fit, rep = fit_markers(model, shape, template, hidden, clock, frames, opts=opts,
                                   source=source, graphs=graphs)
            one = Placement((name,), pl.face[[k]], pl.bary[[k]], pl.offset[[k]])
            pred = predicted_markers(model, fit, one, rep["fitted_joints"])[:, 0]
            valid = np.asarray(fit.valid, bool)
        ok = vis[:, k] & valid
        d = np.linalg.norm(pred[ok] - obs[ok, k], axis=1)
        err[ok, held.index(name)] = d * 1000
        per[name] = _stats_mm(d)
        pooled.append(d)
    allm = np.concatenate(pooled) if pooled else np.zeros(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        overall = _stats_mm(allm)
    cpu = float(time.process_time() - c0)
    return {"per_marker": per, "median_mm": overall["median_mm"], "p90_mm": overall["p90_mm"],
            "cpu_s": cpu, "fps_per_cpu_s": n_sequence / max(cpu, 1e-9), "stride": int(stride),
            "fitted_frames": int(len(frames)), "frames": frames, "error_mm": err}
