"""Headless silhouettes of the body with pyrender (EGL on Mesa, no display).

One :class:`Renderer` holds one OpenGL context and one scene with the body as a
single rigidly skinned mesh: rendering a pose moves the body parts (their
vertices, in one buffer update) and the camera; the scene is never rebuilt. A
silhouette is the rendered depth > 0.

Why one skinned mesh instead of one node per part: pyrender sets four uniforms
and binds a program per node in Python, about 0.13 ms per node; with 18 parts
that was two thirds of the frame time. Transforming 1,500 vertices in numpy and
uploading them with ``glBufferSubData`` costs a few microseconds.
"""

from __future__ import annotations

import os

import numpy as np

from .body import PARTS, bone_lengths, part_meshes, part_transforms
from .camera import Camera
from .joints import N_JOINTS
from .skeleton import FULL_JOINT_NAMES, BodyShape

__all__ = ["Renderer"]


class Renderer:
    """Render binary silhouettes and 2D joints of one body.

    Parameters
    ----------
    shape : BodyShape
        The body to draw. Change it with :meth:`set_shape`.
    image_size : (int, int), optional
        (width, height) of the images; a camera of another size resizes the viewport.

    Notes
    -----
    pyrender must be imported after ``PYOPENGL_PLATFORM`` is set; this class sets
    it to ``egl`` unless the caller chose another platform. Close the renderer
    (or use it as a context manager) to free the OpenGL context.
    """

    def __init__(self, shape: BodyShape, *, image_size: tuple[int, int] = (640, 480)) -> None:
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        import pyrender

        self._pyrender = pyrender
        self._gl = pyrender.OffscreenRenderer(*image_size)
        self._scene = pyrender.Scene(bg_color=[0, 0, 0, 0])
        self._node = None
        self._primitive = None
        self._local: np.ndarray | None = None  # (V, 3) vertices in their part's frame
        self._part_of_vertex: np.ndarray | None = None
        self._camera_node = None
        self._camera_key = None
        self.shape = shape

    def set_shape(self, shape: BodyShape) -> None:
        """Draw another body; its meshes are built at the next render."""
        self.shape = shape
        if self._node is not None:
            self._scene.remove_node(self._node)
        self._node = self._primitive = None

    def _posed_vertices(self, joints: np.ndarray) -> np.ndarray:
        T = part_transforms(joints)[self._part_of_vertex]
        return (np.einsum("vij,vj->vi", T[:, :3, :3], self._local) + T[:, :3, 3]).astype(np.float32)

    def _build(self, joints: np.ndarray) -> None:
        meshes = part_meshes(self.shape, bone_lengths(joints))
        counts = [len(m.vertices) for m in meshes]
        offsets = np.cumsum([0] + counts[:-1])
        self._local = np.concatenate([m.vertices for m in meshes])
        self._part_of_vertex = np.repeat(np.arange(len(meshes)), counts)
        faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
        self._primitive = self._pyrender.Primitive(
            positions=self._posed_vertices(joints), indices=faces, mode=self._pyrender.constants.GLTF.TRIANGLES
        )
        self._node = self._scene.add(self._pyrender.Mesh([self._primitive]))

    def _pose_body(self, joints: np.ndarray) -> None:
        if self._node is None:
            self._build(joints)
            return
        vertices = self._posed_vertices(joints)
        if self._primitive._vaid is None:  # not uploaded yet
            self._primitive.positions = vertices
            return
        from OpenGL import GL

        self._gl._platform.make_current()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, vertices.nbytes, vertices)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def _set_camera(self, camera: Camera) -> None:
        w, h = camera.image_size
        if (self._gl.viewport_width, self._gl.viewport_height) != (w, h):
            self._gl.viewport_width, self._gl.viewport_height = w, h
        key = (camera.orthographic, camera.focal_px, camera.image_size, camera.distance)
        if key != self._camera_key:
            if self._camera_node is not None:
                self._scene.remove_node(self._camera_node)
            cx, cy = camera.principal_point
            near, far = max(0.05, camera.distance - 5.0) * 0.2, camera.distance + 50.0
            if camera.orthographic:
                cam = self._pyrender.OrthographicCamera(
                    xmag=w / 2.0 / camera.focal_px, ymag=h / 2.0 / camera.focal_px, znear=0.01, zfar=far
                )
            else:
                # pyrender puts pixel edges at integers; ours has centres there: +0.5.
                cam = self._pyrender.IntrinsicsCamera(
                    camera.focal_px, camera.focal_px, cx + 0.5, cy + 0.5, znear=near, zfar=far
                )
            self._camera_node = self._scene.add(cam)
            self._camera_key = key
        self._scene.set_pose(self._camera_node, camera.camera_to_world())

    def render(self, joints: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Silhouette and 2D joints of one pose.

        Parameters
        ----------
        joints : ndarray of shape (20, 3)
            Skeleton joints in world coordinates (metres).
        camera : Camera

        Returns
        -------
        silhouette : ndarray of shape (H, W), uint8
            255 where the body is, 0 elsewhere.
        joints2d : ndarray of shape (13, 2)
            The 13 public joints projected into the image (u, v).
        """
        joints = np.asarray(joints, dtype=float)
        if joints.shape != (len(FULL_JOINT_NAMES), 3):
            raise ValueError(f"joints must have shape ({len(FULL_JOINT_NAMES)}, 3), got {joints.shape}")
        self._pose_body(joints)
        self._set_camera(camera)
        depth = self._gl.render(self._scene, flags=self._pyrender.RenderFlags.DEPTH_ONLY)
        silhouette = np.where(depth > 0, np.uint8(255), np.uint8(0))
        return silhouette, camera.project(joints[:N_JOINTS])

    @property
    def n_parts(self) -> int:
        return len(PARTS)

    def close(self) -> None:
        """Free the OpenGL context (and only this renderer's).

        pyrender's own ``delete`` calls ``eglTerminate`` on the display that all
        EGL renderers of the process share, which breaks every other renderer;
        for EGL we destroy just this context.
        """
        if self._gl is None:
            return
        gl, self._gl = self._gl, None
        platform = gl._platform
        display = getattr(platform, "_egl_display", None)
        if display is None:
            gl.delete()
            return
        from OpenGL import EGL

        try:
            platform.make_current()
            gl._renderer.delete()
            EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            EGL.eglDestroyContext(display, platform._egl_context)
        finally:
            # Disarm the platform's __del__ (it would destroy the context again, and call
            # eglTerminate if that did not fail) and OffscreenRenderer's (its delete).
            platform._egl_context = platform._egl_display = None
            gl._renderer = gl._platform = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
