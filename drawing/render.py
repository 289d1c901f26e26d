"""Offscreen rendering of people (triangle meshes) in calibrated views (pyrender, EGL).

One renderer at a time per process: closing a :class:`Renderer` terminates the process's EGL
display (pyrender's teardown), which breaks any other renderer still open. Headless machines
need ``PYOPENGL_PLATFORM=egl`` (set by default when the renderer is created, before pyrender
is imported).

pyrender draws an ideal pinhole image; the lens distortion of each ``calib.Camera`` is applied
afterwards by resampling (``cv2.remap``) a slightly larger pinhole canvas with the exact
inverse map: output pixel ``uv`` (distorted) shows what the pinhole camera sees at
``calib.camera.undistort_pixels(cam, uv)``. So a world point projected with
``calib.camera.project(cam, X)`` lands on the pixel where it is drawn.

Scene: a plain background, a floor quad at ``z = 0`` and one mesh per person with per-vertex
colours (clothing), Lambert-shaded on the CPU under fixed studio lights and drawn unlit
(``RenderFlags.FLAT``: Mesa's software rasteriser is 2-3x faster without pyrender's PBR
shader). :meth:`Renderer.render_ids` draws the same scene as person ids (-1 for floor and
background) for tests and masks. Colours, lights and the floor are ``drawing.constants``.

With ``room`` (a list of :class:`SceneMesh`: textured or per-vertex coloured static meshes,
e.g. ``studio.lab``'s lab room) the floor quad and the plain background are replaced by the
room. The room is static: it is drawn once per camera (colour and depth on the pinhole canvas,
:meth:`Renderer.render_room` gives it through the lens: the clean plate), and each frame draws
only the people, composited over the room where they are nearer than it (exact occlusion by
furniture), so a furnished room costs no more per frame than the floor quad.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from calib.camera import Camera, undistort_pixels
from drawing import constants as C
from geometry import vertex_normals


@dataclass(frozen=True)
class PersonMesh:
    """One person to draw. vertices: (V, 3) world metres; faces: (T, 3) int; colors: (V, 3)
    uint8 RGB."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray


@dataclass(frozen=True)
class SceneMesh:
    """One static mesh of a room. vertices: (V, 3) world metres; faces: (T, 3) int; colors:
    (V, 3) uint8 RGB (multiplies the texture when both are given; None: white); uv: (V, 2)
    texture coordinates and texture: (H, W, 3) uint8 RGB image, or both None; shade: Lambert
    shading under the studio lights (constants.LIGHTS) baked into the vertex colours."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    shade: bool = True


def shading(normals: np.ndarray) -> np.ndarray:
    """(V,) Lambert shading factor of unit normals (V, 3) under the studio's fixed lights
    (constants.LIGHTS: world directions the light travels, intensities) plus ambient light."""
    s = np.full(len(normals), C.AMBIENT_LIGHT)
    for d, k in C.LIGHTS:
        d = np.asarray(d, float) / np.linalg.norm(d)
        s += k * np.clip(-(normals @ d), 0, None)
    return s


@dataclass(frozen=True)
class _Warp:
    """Per camera: where the pinhole canvas sits and the remap tables into the output image."""

    offset: np.ndarray  # (2,) canvas pixel = undistorted pixel + offset
    map_x: np.ndarray  # (H, W) float32 canvas x of each output pixel
    map_y: np.ndarray


def _warps(cams: list[Camera]) -> tuple[list[_Warp], tuple[int, int]]:
    from scipy.ndimage import map_coordinates

    warps, lo, hi = [], [], []
    step = C.WARP_GRID_PX
    for cam in cams:
        # the inverse lens map is smooth: solve it on a coarse grid, interpolate (cubic)
        pad = 3 * step  # keep the spline's boundary effects outside the image
        gu = np.arange(-pad, cam.width + pad, step, dtype=float)
        gv = np.arange(-pad, cam.height + pad, step, dtype=float)
        u, v = np.meshgrid(gu, gv)
        und = undistort_pixels(cam, np.stack([u, v], -1))
        if not np.all(np.isfinite(und)):
            raise ValueError(f"camera {cam.name}: distortion not invertible over the image")
        py, px = (np.mgrid[0:cam.height, 0:cam.width] + pad) / step
        und = np.stack([map_coordinates(und[..., k], [py, px], order=3, mode="nearest")
                        for k in range(2)], -1)
        mn, mx = und.reshape(-1, 2).min(0), und.reshape(-1, 2).max(0)
        off = C.RENDER_MARGIN_PX - np.floor(mn)
        warps.append(_Warp(off, (und[..., 0] + off[0]).astype(np.float32),
                           (und[..., 1] + off[1]).astype(np.float32)))
        lo.append(mn)
        hi.append(mx + off)
    size = np.ceil(np.max(hi, axis=0)).astype(int) + C.RENDER_MARGIN_PX
    return warps, (int(size[0]), int(size[1]))


def _gl_pose(cam: Camera) -> np.ndarray:
    """(4, 4) world_from_camera in OpenGL axes (x right, y up, z backwards)."""
    M = np.eye(4)
    M[:3, :3] = cam.R.T @ np.diag([1.0, -1.0, -1.0])
    M[:3, 3] = cam.T
    return M


class Renderer:
    """Offscreen renderer for a fixed camera rig. Use as a context manager (it owns a GL
    context). Not thread-safe, and one at a time per process: closing one terminates the EGL
    display (pyrender's teardown), which breaks any other renderer still open."""

    def __init__(self, cams: list[Camera], room: list[SceneMesh] | None = None):
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        import pyrender

        self._pr = pyrender
        self.cams = list(cams)
        self._warps, (cw, ch) = _warps(self.cams)
        self._renderer = pyrender.OffscreenRenderer(cw, ch)
        self.room = room
        bg = np.array((C.ROOM_VOID_RGB if room else C.BACKGROUND_RGB) + (255,)) / 255.0
        self.scene = pyrender.Scene(bg_color=bg)
        self._cam_nodes = self._add_cameras(self.scene)
        self._floor = None
        self._room_scene, self._room_nodes, self._plates = None, [], {}
        if room is None:
            s = C.FLOOR_HALF_SIZE_M
            fv = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], float)
            ff = np.array([[0, 1, 2], [0, 2, 3]])
            self._floor = self.scene.add(self._mesh(fv, ff, np.tile(C.FLOOR_RGB, (4, 1)), shade=False))
        else:
            self._room_scene = pyrender.Scene(bg_color=bg)
            self._room_nodes = self._add_cameras(self._room_scene)
            # one mesh of a primitive per room part: pyrender draws a mesh's primitives in list
            # order but its nodes in a set's order (``_sorted_mesh_nodes``: equal distance keys
            # for identity poses), which changes from process to process; where two parts
            # tie in depth the first drawn wins the pixel, so one node keeps the bytes fixed
            self._room_scene.add(self._pr.Mesh([
                self._primitive(m.vertices, m.faces, m.colors, m.shade, m.uv, m.texture)
                for m in room]))
        self._people: list = []

    def _add_cameras(self, scene) -> list:
        nodes = []
        for cam, w in zip(self.cams, self._warps, strict=True):
            # +0.5: OpenGL pixel i spans [i, i + 1] (centre i + 0.5); calib's pixel centres
            # are integers
            pc = self._pr.IntrinsicsCamera(cam.f[0], cam.f[1], cam.c[0] + w.offset[0] + 0.5,
                                           cam.c[1] + w.offset[1] + 0.5, znear=C.ZNEAR_M,
                                           zfar=C.ZFAR_M)
            nodes.append(scene.add(pc, pose=_gl_pose(cam)))
        return nodes

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def _mesh(self, vertices, faces, colors, shade=True, uv=None, texture=None):
        return self._pr.Mesh([self._primitive(vertices, faces, colors, shade, uv, texture)])

    def _primitive(self, vertices, faces, colors, shade=True, uv=None, texture=None):
        pr = self._pr
        if colors is None:
            col = np.ones((len(vertices), 3), np.float32)
        else:
            col = np.asarray(colors, np.float32) / 255.0
        if shade:
            col = np.clip(col * shading(vertex_normals(np.asarray(vertices, float), faces))[:, None], 0, 1)
        col = np.concatenate([col, np.ones((len(vertices), 1), np.float32)], 1)
        mat = pr.MetallicRoughnessMaterial(metallicFactor=0.0)
        kw = {}
        if texture is not None:
            mat = pr.MetallicRoughnessMaterial(
                metallicFactor=0.0, doubleSided=True, baseColorTexture=pr.Texture(source=np.ascontiguousarray(texture),
                                                                source_channels="RGB"))
            kw["texcoord_0"] = np.asarray(uv, np.float32)
        return pr.Primitive(positions=np.asarray(vertices, np.float32), color_0=col,
                            indices=np.asarray(faces, np.uint32), material=mat, **kw)

    def _set_people(self, people: list[PersonMesh]) -> None:
        for n in self._people:
            self.scene.remove_node(n)
        # each person's node at its own centroid: pyrender sorts the nodes by the distance of
        # their poses to the camera and draws equal keys in a set's order (process-dependent),
        # so distinct poses keep the draw order, and a depth tie's winner, fixed
        self._people = []
        for p in people:
            v = np.asarray(p.vertices, float)
            pose = np.eye(4)
            pose[:3, 3] = v.mean(axis=0)
            self._people.append(self.scene.add(self._mesh(v - pose[:3, 3], p.faces, p.colors),
                                               pose=pose))

    def _each_view(self, flags, warp_interp, seg_node_map=None, views=None):
        import cv2

        out = []
        kw = {} if seg_node_map is None else {"seg_node_map": seg_node_map}
        views = range(len(self.cams)) if views is None else views
        for c in views:
            node, w = self._cam_nodes[c], self._warps[c]
            self.scene.main_camera_node = node
            img = self._renderer.render(self.scene, flags=flags, **kw)
            if self.room is not None:  # people over the room where they are nearer
                col, depth = img
                plate, plate_depth = self._plate(c)
                near = ((depth > 0) & ((plate_depth <= 0) | (depth < plate_depth))).view(np.uint8)
                img = np.zeros_like(col) if seg_node_map is not None else plate.copy()
                cv2.copyTo(col, near, img)
            else:
                img = img[0] if isinstance(img, tuple) else img
            out.append(cv2.remap(np.ascontiguousarray(img), w.map_x, w.map_y, warp_interp,
                                 borderMode=cv2.BORDER_REPLICATE))
        return out

    def _plate(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """The room seen by camera ``c`` on its pinhole canvas: colour (h, w, 3) uint8, depth
        (h, w) metres (0: nothing). Drawn once per camera."""
        if c not in self._plates:
            self._room_scene.main_camera_node = self._room_nodes[c]
            col, depth = self._renderer.render(self._room_scene, flags=self._pr.RenderFlags.FLAT)
            self._plates[c] = (np.ascontiguousarray(col), depth)
        return self._plates[c]

    def render_room(self, views: list[int] | None = None) -> list[np.ndarray]:
        """The room without anybody, one RGB (H, W, 3) uint8 per camera (or per index in
        ``views``): the clean plate. Without a room: the plain background and floor."""
        if self.room is None:
            return self.render([], views)
        import cv2

        views = range(len(self.cams)) if views is None else views
        return [cv2.remap(self._plate(c)[0], self._warps[c].map_x, self._warps[c].map_y,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for c in views]

    def render(self, people: list[PersonMesh], views: list[int] | None = None) -> list[np.ndarray]:
        """One RGB frame per camera (or per camera index in ``views``): list of (H, W, 3) uint8."""
        import cv2

        self._set_people(people)
        return self._each_view(self._pr.RenderFlags.FLAT, cv2.INTER_LINEAR, views=views)

    def render_ids(self, people: list[PersonMesh], views: list[int] | None = None) -> list[np.ndarray]:
        """Person id per pixel, one (H, W) int8 per camera (or per index in ``views``): i for
        ``people[i]``, -1 elsewhere (with a room: where the room hides the person too)."""
        import cv2

        self._set_people(people)
        seg = {} if self._floor is None else {self._floor: (0, 0, 0)}
        seg.update({n: (i + 1, 0, 0) for i, n in enumerate(self._people)})
        imgs = self._each_view(self._pr.RenderFlags.SEG, cv2.INTER_NEAREST, seg, views)
        return [v[..., 0].astype(np.int8) - 1 for v in imgs]
