"""Magic numbers of the drawing package, in one place (metres, pixels, RGB 0-255)."""

# ------------------------------------------------------------------------------------ render
#: Studio look: background, floor quad at z = 0 (colour, half size).
BACKGROUND_RGB = (205, 208, 212)
FLOOR_RGB = (150, 142, 128)
FLOOR_HALF_SIZE_M = 12.0
#: With a room (``Renderer(room=...)``): the colour where no room surface is seen.
ROOM_VOID_RGB = (60, 60, 62)
#: Studio lights for the CPU Lambert shading: (direction the light travels, intensity), ambient.
LIGHTS = (((0.4, -0.6, -1.0), 0.55), ((-0.5, 0.7, -0.6), 0.3))
AMBIENT_LIGHT = 0.45
#: Render margin around the distortion-free region that the output image needs, pixels.
RENDER_MARGIN_PX = 4
#: Near and far clipping planes of the renderer's cameras, metres.
ZNEAR_M, ZFAR_M = 0.2, 20.0
#: The inverse lens map is solved every WARP_GRID_PX pixels and interpolated.
WARP_GRID_PX = 4

# ------------------------------------------------------------------------------------ sheets
#: Contact sheet: marker ring around each point (RGB, radius px, line px), label colour.
SHEET_POINT_RGB = (255, 230, 0)
SHEET_POINT_RADIUS_PX = 7
SHEET_TEXT_RGB = (20, 20, 20)

# ------------------------------------------------------------------------------------ plots
#: Residual plot: figure size (inches) and resolution; the log axis' floor (mm: residuals
#: below it, e.g. exact zeros, are drawn on it); frames marked as the worst.
PLOT_SIZE_IN = (8.0, 3.4)
PLOT_DPI = 100
RESIDUAL_FLOOR_MM = 0.1
WORST_FRAMES = 5
#: The y axis reaches this factor above the highest marked value (room for its label).
PLOT_HEADROOM = 3.0
#: The marked worst frames are at least this far apart (seconds): one per spike.
WORST_SEPARATION_S = 0.2

# ------------------------------------------------------------------------------------ close-ups
#: Close-up cameras (``drawing.sheet.close_up_cameras``): distance from the inspected point
#: (metres), image size (px), azimuths (deg) of the four views, height above the point as a
#: fraction of the distance.
CLOSE_M = 0.7
CLOSE_SIZE_PX = 900
CLOSE_AZIMUTHS_DEG = (20.0, 110.0, 200.0, 290.0)
CLOSE_RISE = 0.5
