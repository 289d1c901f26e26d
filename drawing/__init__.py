"""Pictures: the offscreen renderer (``drawing.render``: :class:`Renderer`, :class:`PersonMesh`),
contact sheets and close-ups (``drawing.sheet``) and fit-quality plots (``drawing.plots``:
:func:`residual_plot`). May import body, calib, formats, geometry; pyrender, matplotlib and
cv2 are imported where used, so importing ``drawing`` is cheap."""
