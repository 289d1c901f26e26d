"""The contact annotation tool: a local web page where an annotator marks when two people touch
(the contact interval) and where (facet-to-facet correspondences, grouped into 75 regions).

``make annotate RECIPE=... SEQ=<group>/<action>`` (``python -m annotate``) serves it on
127.0.0.1 (``annotate.server``); the page's scripts and three.js come from disk
(``annotate/web``, three.js installed by ``scripts/setup.sh`` with ``npm ci``), nothing is
fetched at run time.

- ``annotate.data``: what the page shows of one sequence (cameras, videos, both people's
  keypoints and fitted meshes, the body model's faces and regions), read from the recipe and
  the engine's artifacts under ``outputs/``;
- ``annotate.proposals``: the proposed interval and facet pairs, from the fitted surfaces
  (within a few mm) or, with keypoints only, the frames where the triangulated keypoints of the
  two people come closest;
- ``annotate.signature``: the file (``interaction_contact_signature.json``, CHI3D layout),
  written atomically after ``fitting.contact_signature.load_contact`` has accepted it;
- ``annotate.agreement``: several annotators' files -> segmentation and signature IoU at
  75 / 37 / 17 / 9 regions (the paper's Table 1);
- ``annotate.browser``: a headless Chromium driven over the DevTools protocol (tests,
  screenshots).
"""
