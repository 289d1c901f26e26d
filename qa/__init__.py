"""Quality assurance of a sequence's fits (issue #18): per-frame metrics and flags
(``qa.metrics``), the HTML report and the session index (``qa.report``). The ``qa`` stage
(``stages/qa.py``) wires them to the artifacts; overlays and plots are in ``drawing/``, the
Foxglove scene in ``formats/foxglove_scene.py``."""
