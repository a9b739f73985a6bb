"""Headless rendering of a model seen from a camera pose: clean RGB, depth, range, labels.

Five lines from nothing to a rendered frame::

    from uw_sil.sim.render import Renderer
    from uw_sil.sim.scene import facing_pose

    with Renderer() as renderer:                   # shipped intervention panel, 640x480
        frame = renderer.render(facing_pose(1.5))  # .rgb, .depth, .range, .labels

The renderer uses pyrender's OpenGL pipeline in software (Mesa OSMesa/llvmpipe, no GPU, no
display). One OpenGL context is created per :class:`Renderer` and reused for every frame.

Rendering model
---------------
A frame is rasterised without anti-aliasing and without back-face culling (user meshes with
flipped normals still render) in an unlit pass (``RenderFlags.FLAT``) giving the surface albedo
(the model's 8-bit vertex / texture colours divided by 255, no gamma, no lighting; meshes without
colours get :data:`DEFAULT_ALBEDO`) and the depth buffer (24 bit), from which planar depth and
range follow, and exact per-pixel node ids, from which labels and part ids follow:

- **one pass** where it can be exact: under OSMesa (no multisampling), with at most 255 mesh
  nodes and no transparency in the model's colours, every material is made opaque and its
  alpha set to ``node id / 255``, so the pass's alpha channel holds the node id (8 bits hold it
  exactly; water is 0). Its RGB is what the material gave before (opaque blending writes the
  source; the model has no transparency). 640x480: 17-22 ms against 16 + 12 for two passes;
- **two passes** otherwise (EGL multisamples the colour pass, which would mix ids at
  silhouettes): the colour pass, then a segmentation pass (``RenderFlags.SEG``) with the
  node ids as colours and the depth buffer. ``render(T, colour=False)`` is that pass alone.

``rgb`` is ``albedo * shading``. With ``shading="lambert"`` (default) the shading is
``ambient + (1 - ambient) * max(0, cos theta)`` with ``theta`` the angle between the surface
normal and the optical axis: a distant light shining along the camera's viewing
direction, as from lamps mounted next to the camera, **without** distance falloff and
without vignetting, so a surface facing the camera squarely has ``rgb == albedo`` at any
distance. Normals come from the depth buffer (exact on planar faces; one-sided
differences never cross a silhouette or a change of part). ``shading="flat"`` returns
the albedo unchanged. ``rgb`` is therefore in the 8-bit colour space the model's colours
are written in (sRGB-encoded values used as they are): it is the "clear-water radiance"
that the underwater image model attenuates and mixes with the veiling light; pyrender's
own PBR lighting and its 1/2.2 gamma are not used.

Conventions
-----------
Poses are 4x4 ``T_cam_panel`` (model frame expressed in the camera optical frame: x right,
y down, z forward; REP 103). The camera follows OpenCV intrinsics (pixel centres at
integer coordinates; :class:`uw_sil.sim.camera.CameraModel`).

Pitfalls handled here
---------------------
- ``PYOPENGL_PLATFORM`` is set to ``"osmesa"`` (``os.environ.setdefault``) when this
  module first creates a renderer, before OpenGL is imported. Set it yourself to
  ``"egl"`` beforehand to use EGL instead.
- Memory: with OSMesa, PyOpenGL's ``contextdata.getContext()`` returns a fresh ctypes
  pointer object at every call, and pyrender uses that object as a key of its shader
  cache, so every draw call compiles and keeps a new GLSL program (measured without the
  fix: +15 MB per frame for the 21-node panel, 4.5 GB after 300 frames).
  :func:`_patch_context_key`
  makes ``getContext`` return the integer address of the context instead (what it
  already returns under EGL and GLX), once per process.
- pyrender samples pixel centres at ``(u + 0.5, v + 0.5)``; the principal point is passed
  as ``cx + 0.5, cy + 0.5`` so depth matches a ray cast through OpenCV pixel centres.
- Do not ``fork`` a process that holds a renderer: the child hangs. Use the ``spawn``
  start method of :mod:`multiprocessing`, or fork before creating the renderer.
- A renderer is not thread-safe; use one per thread or process. Only :meth:`Renderer.draw` (the OpenGL
  passes) needs that: :meth:`Renderer.develop` of its buffers can run on any thread, side by side.
- Draw order: pyrender keeps mesh nodes in a ``set`` (iteration order = memory addresses of the
  node objects) and draws them in that order where its distance sort ties (every node of the
  shipped panel sits at the origin). Where two surfaces have the same depth (the textured plate
  face on the plate body, at its edges) the first drawn wins, so the clean colour of such pixels
  changed from one :class:`Renderer` to the next, within a process and across processes (up to
  80 grey levels at single pixels; enough to change θ by ~4e-5 and a fit's result). Meshes are
  therefore drawn in the order of the model (:class:`_OrderedScene`): the earlier one wins ties,
  in the colour pass as in the segmentation pass, and a pose renders the same everywhere.
"""
from __future__ import annotations

import ctypes
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import CameraModel
from .normals import plane_terms
from .scene import node_label

__all__ = ["RawRender", "RenderResult", "Renderer", "render", "DEFAULT_ALBEDO"]

SHADINGS = ("lambert", "flat")

#: 8-bit albedo given to meshes that carry no colour or texture (STL files, for example).
DEFAULT_ALBEDO = (150, 150, 150)

# OpenCV optical frame (z forward, y down) -> OpenGL camera frame (z backward, y up).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])

_pyrender_module = None
_ordered_scene_class = None


def _patch_context_key():
    """Make ``OpenGL.contextdata.getContext`` return a stable, hashable integer.

    Under OSMesa, PyOpenGL returns the current context as a ``ctypes`` pointer object, a
    new object at every call that hashes by identity. pyrender keys its shader-program
    and font caches on that value (``pyrender.shader_program.ShaderProgramCache``), so
    the cache never hits and memory grows by one compiled program per draw. Converting
    the pointer to its address (``ctypes.cast(p, c_void_p).value``) gives the same key
    for the same context, as the EGL and GLX platforms already do. Idempotent.
    """
    import OpenGL.contextdata as contextdata

    if getattr(contextdata.getContext, "_uw_sil_patched", False):
        return
    original = contextdata.getContext

    def getContext(context=None):  # noqa: N802 (PyOpenGL's name)
        ctx = original(context)
        if isinstance(ctx, ctypes._Pointer):
            return ctypes.cast(ctx, ctypes.c_void_p).value
        return ctx

    getContext._uw_sil_patched = True
    getContext.__wrapped__ = original
    getContext.__doc__ = original.__doc__
    contextdata.getContext = getContext


def _pyrender():
    """Import pyrender for headless use (OSMesa unless already chosen) and patch it once."""
    global _pyrender_module
    if _pyrender_module is None:
        os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
        import pyrender

        _patch_context_key()
        _pyrender_module = pyrender
    return _pyrender_module


def _OrderedScene():
    """``pyrender.Scene`` subclass whose mesh nodes iterate in the order they were added.

    pyrender sorts ``scene.mesh_nodes`` by the distance of each node's origin to the camera with a
    stable sort, so ties keep the iteration order of the underlying ``set``, which depends on where
    the node objects happen to be in memory (see "Draw order" in the module docstring).
    """
    global _ordered_scene_class
    if _ordered_scene_class is None:
        pyrender = _pyrender()

        class OrderedScene(pyrender.Scene):
            def __init__(self, *args, **kwargs):
                self._draw_index = {}
                super().__init__(*args, **kwargs)

            def add_node(self, node, parent_node=None):
                super().add_node(node, parent_node=parent_node)
                self._draw_index.setdefault(node, len(self._draw_index))

            @property
            def mesh_nodes(self):
                return sorted(self._mesh_nodes, key=self._draw_index.__getitem__)

        _ordered_scene_class = OrderedScene
    return _ordered_scene_class


@dataclass(eq=False)
class RenderResult:
    """One rendered frame.

    Attributes
    ----------
    rgb : (H, W, 3) float32, or None
        Clean radiance in [0, 1] (albedo times shading, see the module docstring);
        0 where nothing is hit. None for a render of the geometry only (``Renderer.render(T, colour=False)``).
    depth : (H, W) float32
        Planar depth z along the optical axis, metres; ``inf`` where nothing is hit.
    range : (H, W) float32
        Euclidean distance from the optical centre, metres (``depth * camera.ray_norm()``);
        ``inf`` where nothing is hit.
    labels : (H, W) uint8
        0 water / nothing, 1 panel, 2 seafloor, other ids as named in the model
        (:func:`uw_sil.sim.scene.node_label`).
    part_ids : (H, W) uint16
        0 nothing, else ``1 + index`` into :attr:`Renderer.node_names`.
    """

    rgb: np.ndarray
    depth: np.ndarray
    range: np.ndarray
    labels: np.ndarray
    part_ids: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """Boolean mask of pixels where the model is hit."""
        return self.part_ids > 0


@dataclass(frozen=True, eq=False)
class RawRender:
    """One frame's buffers as read from OpenGL (:meth:`Renderer.draw`), with what :meth:`Renderer.develop`
    needs of the camera they were drawn with: ``color`` (H, W, 3) uint8 albedo or None, or (H, W, 4) with the node ids
    in alpha (one pass, ``seg`` None); ``seg`` (H, W, 3) uint8 node colours of the segmentation pass; ``depth``
    (H, W) float32 (0 where nothing is hit), and the camera's per-pixel ray terms."""

    color: object
    seg: object
    depth: np.ndarray
    camera: CameraModel
    ray_norm: np.ndarray
    xt: np.ndarray
    yt: np.ndarray


class Renderer:
    """Reusable offscreen renderer of one model.

    Parameters
    ----------
    model : None, str, Path, trimesh.Scene or trimesh.Trimesh, optional
        What to render, in the panel frame. None: the shipped intervention panel
        (:func:`uw_sil.sim.scene.load_model`); a path: any file :func:`~uw_sil.sim.scene.load_model`
        reads; or a trimesh object (use :func:`uw_sil.sim.scene.add_seafloor` to add a seafloor).
    camera : CameraModel, optional
        Intrinsics and image size; default ``CameraModel()`` (640x480, 70 deg horizontal FOV).
        Can be changed later through :attr:`camera`.
    shading : {"lambert", "flat"}, optional
        How ``rgb`` is shaded (module docstring).
    ambient : float, optional
        Share of the light that does not depend on orientation, in [0, 1] (lambert only).
    znear, zfar : float, optional
        Clipping distances in metres. Depth resolution scales with ``znear`` (24-bit
        buffer: about 5 um at 2 m with the default 0.05 m).
    labels : dict, optional
        ``{node_name: label_id}`` overriding :func:`uw_sil.sim.scene.node_label`.

    Examples
    --------
    >>> from uw_sil.sim.render import Renderer
    >>> from uw_sil.sim.scene import facing_pose
    >>> with Renderer() as r:                               # doctest: +SKIP
    ...     frame = r.render(facing_pose(1.5, yaw=0.3))
    """

    def __init__(self, model=None, camera: CameraModel | None = None, shading: str = "lambert",
                 ambient: float = 0.3, znear: float = 0.05, zfar: float = 100.0, labels: dict | None = None):
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        if not 0.0 <= float(ambient) <= 1.0:
            raise ValueError(f"ambient must be in [0, 1], got {ambient}")
        if not (0.0 < znear < zfar and np.isfinite(zfar)):
            raise ValueError(f"need 0 < znear < zfar < inf, got znear={znear}, zfar={zfar}")
        camera = CameraModel() if camera is None else camera
        if not isinstance(camera, CameraModel):
            raise TypeError(f"camera must be a CameraModel, got {type(camera).__name__}")
        if labels is not None and not isinstance(labels, dict):
            raise TypeError(f"labels must be a dict {{node_name: id}}, got {type(labels).__name__}")

        self.shading = shading
        self.ambient = float(ambient)
        self.znear, self.zfar = float(znear), float(zfar)
        self._offscreen = None
        pyrender = _pyrender()
        self._flags_color = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.SKIP_CULL_FACES
        self._flags_seg = pyrender.RenderFlags.SEG | pyrender.RenderFlags.SKIP_CULL_FACES

        self._scene = _OrderedScene()(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[0.0, 0.0, 0.0])
        self.node_names: list[str] = []
        self.node_labels: list[int] = []
        self._seg_map = {}
        overrides = dict(labels or {})
        for name, T, geom in _iter_meshes(_as_trimesh_scene(model)):
            node = pyrender.Node(name=name, mesh=pyrender.Mesh.from_trimesh(geom, smooth=False), matrix=T)
            self._scene.add_node(node)
            self.node_names.append(name)
            label = overrides.pop(name) if name in overrides else node_label(name)
            if not (isinstance(label, (int, np.integer)) and 0 <= label <= 255):
                raise ValueError(f"label of node {name!r} must be an integer in 0..255, got {label!r}")
            self.node_labels.append(int(label))
            pid = len(self.node_names)
            if pid > 0xFFFF:
                raise ValueError("models with more than 65535 mesh nodes are not supported")
            self._seg_map[node] = (pid & 0xFF, pid >> 8, 0)
        if overrides:
            raise ValueError(f"labels given for unknown nodes: {sorted(overrides)}; nodes are {self.node_names}")
        if not self.node_names:
            raise ValueError("the model has no triangle meshes to render")
        self._label_lut = np.array([0] + self.node_labels, dtype=np.uint8)
        # one pass (module docstring): the node ids in the colour pass's alpha, under OSMesa only
        self._one_pass = os.environ.get("PYOPENGL_PLATFORM") == "osmesa" and _ids_fit_alpha(self._seg_map)
        if self._one_pass:
            for node, (lo, hi, _) in self._seg_map.items():
                for prim in node.mesh.primitives:
                    prim.material.alphaMode = "OPAQUE"
                    factor = np.array(prim.material.baseColorFactor, dtype=float)
                    factor[3] = (lo | hi << 8) / 255.0
                    prim.material.baseColorFactor = factor
            self._scene.bg_color = np.array([0.0, 0.0, 0.0, 0.0])     # water: id 0

        self._gl_camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=self.znear, zfar=self.zfar)
        self._camera_node = self._scene.add(self._gl_camera, pose=np.eye(4))
        self._camera = None
        self.camera = camera

    # ------------------------------------------------------------------ camera

    @property
    def camera(self) -> CameraModel:
        """The camera model; assign a new :class:`CameraModel` to change intrinsics or size.

        A new size re-creates the OpenGL context (OSMesa buffers have a fixed size), uploads
        the model and compiles the shaders of both passes at once (one throw-away frame of
        each: about 0.2 s with the shipped panel, no memory kept), so that the first
        :meth:`render` after it costs what any other does (a live camera's first poses are not
        skipped while it waits). New intrinsics at the same size cost nothing.
        """
        return self._camera

    @camera.setter
    def camera(self, camera: CameraModel):
        if not isinstance(camera, CameraModel):
            raise TypeError(f"camera must be a CameraModel, got {type(camera).__name__}")
        pyrender = _pyrender()
        size_changed = self._camera is None or self._camera.shape != camera.shape
        self._gl_camera.fx, self._gl_camera.fy = float(camera.fx), float(camera.fy)
        self._gl_camera.cx, self._gl_camera.cy = float(camera.cx) + 0.5, float(camera.cy) + 0.5
        if size_changed:
            if self._offscreen is not None:
                self._offscreen.delete()  # OSMesa buffers have a fixed size: new context
                self._offscreen = None
            self._offscreen = pyrender.OffscreenRenderer(int(camera.width), int(camera.height))
            if self._one_pass:
                _read_rgba_colour(self._offscreen)
            warm = self._offscreen.render(self._scene, flags=self._flags_color)[0]
            if self._one_pass and warm.shape[-1] != 4:
                # the colour was not read through the default framebuffer with its alpha (a platform with
                # framebuffer objects, which multisamples it, or another pyrender): two passes
                self._one_pass = False
            self._offscreen.render(self._scene, flags=self._flags_seg, seg_node_map=self._seg_map)
        self._camera = camera
        rn = camera.ray_norm()
        self._ray_norm = rn.astype(np.float32)
        self._xt = ((np.arange(camera.width) - camera.cx) / camera.fx).astype(np.float32)[None, :]
        self._yt = ((np.arange(camera.height) - camera.cy) / camera.fy).astype(np.float32)[:, None]

    # ------------------------------------------------------------------ rendering

    def render(self, T_cam_panel, colour: bool = True) -> RenderResult:
        """Render the model seen with pose ``T_cam_panel``.

        Parameters
        ----------
        T_cam_panel : (4, 4) array_like
            Rigid transform of the model frame into the camera optical frame.
        colour : bool, optional
            False: the geometry only (depth, range, labels, part ids, from the segmentation pass), ``rgb`` None;
            the colour pass and the shading are skipped (a consumer that needs no image: measured 12.6 against
            38.3 ms for a full 640x480 render of the same poses).

        Returns
        -------
        RenderResult
        """
        return self.develop(self.draw(T_cam_panel, colour))

    def draw(self, T_cam_panel, colour: bool = True) -> RawRender:
        """The OpenGL part of :meth:`render`: the passes and their buffers (one thread at a time per renderer)."""
        if self._offscreen is None:
            raise RuntimeError("renderer is closed")
        T = np.asarray(T_cam_panel, dtype=float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_cam_panel must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1])):
            raise ValueError("T_cam_panel must be a rigid transform (rotation + translation)")
        T_panel_cam = np.eye(4)
        T_panel_cam[:3, :3] = R.T
        T_panel_cam[:3, 3] = -R.T @ T[:3, 3]
        self._scene.set_pose(self._camera_node, T_panel_cam @ _CV_TO_GL)

        if colour and self._one_pass:
            color, depth = self._offscreen.render(self._scene, flags=self._flags_color)
            seg = None
        else:
            color = self._offscreen.render(self._scene, flags=self._flags_color)[0] if colour else None
            seg, depth = self._offscreen.render(self._scene, flags=self._flags_seg, seg_node_map=self._seg_map)
        return RawRender(color, seg, depth, self._camera, self._ray_norm, self._xt, self._yt)

    def develop(self, raw: RawRender) -> RenderResult:
        """The rest of :meth:`render` on the buffers of :meth:`draw`: no OpenGL, so frames drawn one after the other
        can be developed on other threads, side by side."""
        seg, depth, color = raw.seg, raw.depth, raw.color
        alpha = None
        if color is not None and color.shape[-1] == 4:
            alpha, color = color[..., 3], color[..., :3]
        if seg is None:                         # one pass: the node ids are the colour's alpha
            part_ids = alpha.astype(np.uint16)
        else:
            part_ids = seg[..., 0].astype(np.uint16) | (seg[..., 1].astype(np.uint16) << 8)
        hit = part_ids > 0
        depth = np.where(hit, depth, np.float32(np.inf)).astype(np.float32, copy=False)
        rng = depth * raw.ray_norm
        labels = self._label_lut[part_ids]
        if color is None:
            return RenderResult(rgb=None, depth=depth, range=rng, labels=labels, part_ids=part_ids)
        rgb = np.multiply(color, np.float32(1.0 / 255.0), dtype=np.float32)     # one pass: cast and scale
        # water pixels are 0: their shading factor set to 0 (the albedo is finite and >= 0, so the product is the
        # +0.0 an assignment would write), or the pixels zeroed where nothing is shaded
        miss = ~hit
        if self.shading == "lambert":
            shade = self._lambert(depth, part_ids, raw)
            np.copyto(shade, np.float32(0.0), where=miss)
            rgb *= shade[..., None]
        else:
            np.copyto(rgb, np.float32(0.0), where=miss[..., None])
        return RenderResult(rgb=rgb, depth=depth, range=rng, labels=labels, part_ids=part_ids)

    def render_many(self, poses):
        """Render each pose of an iterable in turn; yields :class:`RenderResult`."""
        for T in poses:
            yield self.render(T)

    def _lambert(self, depth, part_ids, raw: RawRender) -> np.ndarray:
        """Shading factor ambient + (1 - ambient) * max(0, cos(normal, optical axis)), the normal of the planar
        face from the depth map (:mod:`uw_sil.sim.normals`; isolated pixels count as facing the camera)."""
        w = np.float32(1.0) / depth             # 0 where nothing is hit (depth inf)
        cam = raw.camera
        mx, my, mz = plane_terms(w, part_ids, cam.fx, cam.fy, raw.xt, raw.yt)
        norm = np.sqrt(mx * mx + my * my + mz * mz)
        cos = np.divide(mz, norm, out=np.ones_like(mz), where=norm > 0)
        np.clip(cos, 0.0, 1.0, out=cos)
        return np.float32(self.ambient) + np.float32(1.0 - self.ambient) * cos

    # ------------------------------------------------------------------ lifetime

    def close(self):
        """Free the OpenGL context and its buffers. Idempotent."""
        if self._offscreen is not None:
            self._offscreen.delete()
            self._offscreen = None

    @property
    def closed(self) -> bool:
        return self._offscreen is None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self):
        cam = self._camera
        size = f"{cam.width}x{cam.height}" if cam is not None else "?"
        state = "closed" if self.closed else "open"
        return f"<Renderer {len(self.node_names)} nodes, {size}, shading={self.shading!r}, {state}>"


def render(T_cam_panel, model=None, camera: CameraModel | None = None, **kw) -> RenderResult:
    """Render one frame with a temporary :class:`Renderer` (convenient, slow for many frames)."""
    with Renderer(model, camera, **kw) as r:
        return r.render(T_cam_panel)


# ---------------------------------------------------------------------- helpers


def _as_trimesh_scene(model):
    import trimesh

    from .scene import load_model

    if model is None or isinstance(model, (str, Path)):
        return load_model(model)
    if isinstance(model, trimesh.Scene):
        return model
    if isinstance(model, trimesh.Trimesh):
        return trimesh.Scene(model)
    raise TypeError(f"model must be None, a path, a trimesh.Scene or a trimesh.Trimesh, got {type(model).__name__}")


def _ids_fit_alpha(seg_map) -> bool:
    """Whether the colour pass's alpha can carry the node ids exactly: at most 255 nodes, every material a
    metallic-roughness one (its base colour's alpha is the shader's) and nothing transparent (base colour alpha,
    texture alpha, vertex colour alpha all 1, so the alpha written is the factor's alone)."""
    pyrender = _pyrender()
    if len(seg_map) > 255:
        return False
    for node in seg_map:
        for prim in node.mesh.primitives:
            mat = prim.material
            if not isinstance(mat, pyrender.MetallicRoughnessMaterial) or mat.baseColorFactor[3] < 1.0:
                return False
            if mat.baseColorTexture is not None and mat.baseColorTexture.is_transparent(1.0):
                return False
            if prim.color_0 is not None and np.any(prim.color_0[:, 3] != 1.0):
                return False
    return True


def _read_rgba_colour(offscreen):
    """Make ``offscreen`` (OSMesa: it reads the default framebuffer) return RGBA from its colour reads (pyrender
    reads RGB there whatever the flags; the one-pass render needs the alpha channel)."""
    from OpenGL import GL

    renderer = offscreen._renderer

    def read_color_buf():
        w, h = renderer.viewport_width, renderer.viewport_height
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, 0)
        GL.glReadBuffer(GL.GL_FRONT)
        buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
        return np.flip(np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 4), axis=0)

    renderer.read_color_buf = read_color_buf


def _iter_meshes(scene):
    """(node name, 4x4 world transform, Trimesh) for every triangle mesh node of ``scene``."""
    import trimesh

    skipped = []
    for name in scene.graph.nodes_geometry:
        T, geom_name = scene.graph[name]
        geom = scene.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            skipped.append(name)
            continue
        if not geom.visual.defined:  # e.g. STL: give it a documented albedo
            geom = geom.copy()
            geom.visual.vertex_colors = np.array([*DEFAULT_ALBEDO, 255], dtype=np.uint8)
        yield str(name), np.asarray(T, dtype=float), geom
    if skipped:
        warnings.warn(f"not rendering nodes without triangles: {skipped}", stacklevel=3)
