"""Magic numbers of the QA pictures (``drawing.overlay``, ``drawing.qa_plots``), in one place
(pixels, RGB 0-255, inches).

Kept out of ``drawing.constants`` on purpose: ``drawing.render`` and ``drawing.plots`` import
that module, so every stage hashes it and any edit there recomputes every artifact. Move
these into it when the stages are recomputed anyway.
"""

# ------------------------------------------------------------------------------------ overlays
#: Mesh colour per person in the overlays: marker wearer orange, partner cyan (the colours of
#: ``detect.overlay.PERSON_RGB``, so keypoint and mesh overlays read the same).
PERSON_RGB = ((255, 140, 0), (0, 200, 255))
#: Share of the rendered mesh in the blend over the video image (0: video only, 1: mesh only).
OVERLAY_ALPHA = 0.5
#: Tiled views: label and title text colour, title bar background and height (px), label
#: text scale (cv2 Hershey simplex) and the margin of the labels from the tile's corner (px).
TILE_TEXT_RGB = (255, 255, 255)
TILE_LABEL_SHADOW_RGB = (0, 0, 0)
TILE_TITLE_BG_RGB = (32, 32, 32)
TILE_TITLE_PX = 28
TILE_TEXT_SCALE = 0.55
TILE_TEXT_MARGIN_PX = 8

# ------------------------------------------------------------------------------------ QA plot
#: Figure width and height per panel (inches), resolution.
QA_PLOT_WIDTH_IN = 10.0
QA_PLOT_PANEL_IN = 1.9
QA_PLOT_DPI = 100
#: Flagged spans: shade colour (matplotlib RGB 0-1) and opacity, label colour.
QA_SPAN_RGB = (0.93, 0.33, 0.33)
QA_SPAN_ALPHA = 0.25
QA_SPAN_TEXT_RGB = (0.6, 0.05, 0.05)
#: Threshold lines.
QA_THRESHOLD_RGB = (0.75, 0.1, 0.1)
