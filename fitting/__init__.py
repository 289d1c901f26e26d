"""Energy terms, the LM solver, the compiled CasADi function cache, priors, and the fits of the
marker-wearing subject (see docs/ARCHITECTURE.md, "Fitting contract").

- ``terms``: ``L_3d``, ``L_2d``, ``L_theta``, ``L_s`` (paper names; residual vectors, no weights)
- ``compiled``: ``build(...) -> ResidualFunction`` (C via gcc, cached by source hash)
- ``lm``: ``solve(...)`` Levenberg-Marquardt with robust groups, quadratic terms, joint limits
- ``robust``: Geman-McClure / Huber
- ``priors``: joint limits + Gaussian pose prior
- ``skinned``, ``marker_graph``: slots on the reduced fit skeleton, the marker/hand graph
- ``marker_fit``: frame-after-frame fit; ``shape``: scan fit and marker placement
- ``mocap``: marker trajectories resampled onto video frames
"""
