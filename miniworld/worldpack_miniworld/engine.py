"""MiniWorld, headless, as a camera that can be put anywhere: load an
environment at a world seed, stand at a floor point facing a heading, and
render RGB and metric depth at the project's frame size.

Conventions (docs/miniworld.md): MiniWorld's world is the project's world as
it is, y up in metres. The agent's direction `dir` (radians) faces
(cos dir, 0, -sin dir) and grows to the left; a heading here is that angle in
degrees, so a positive yaw (a turn to the right) lowers it, as Doom's ANGLE.
The camera stands EYE_HEIGHT above the floor point, never pitches, and sees a
VFOV_DEG vertical field of view with square pixels.

RGB comes from a 4x multisampled pass like MiniWorld's own observations
(whose depth buffer is 16-bit); depth from a second, single-sample pass into
a 32-bit float depth buffer, linearised to planar z: each pixel's depth is
the surface at its centre, which is what the pinhole intrinsics describe."""

from __future__ import annotations

import contextlib
import io
import os
from ctypes import POINTER, byref, c_float, c_ubyte

import numpy as np

EYE_HEIGHT = 1.5          # MiniWorld's camera height above the floor (m)
VFOV_DEG = 60.0           # MiniWorld's vertical field of view
Z_NEAR, Z_FAR = 0.04, 100.0   # MiniWorld's projection (render_obs)
RGB_SAMPLES = 4           # multisampling of the colour pass
SIZE = 64
NEAR_M, FAR_M = 0.1, 30.0     # the frustum the memory scores overlap with (intrinsics)
GL_MODES = ("egl", "x11")

_GL_RGBA8 = 0x8058
_GL_DEPTH_COMPONENT24 = 0x81A6
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_MAX_SAMPLES = 0x8D57

_gl_mode: str | None = None


class GLUnavailable(RuntimeError):
    """No OpenGL context could be made: the message says what was tried and what to install."""


def setup_gl(mode: str = "egl") -> None:
    """Chooses how pyglet reaches OpenGL before MiniWorld is imported: `egl`
    renders without any display (Mesa's EGL; llvmpipe on a CPU), `x11` on the
    X display named by DISPLAY (for instance Xvfb's). Once per process."""
    global _gl_mode
    if mode not in GL_MODES:
        raise ValueError(f"gl mode {mode!r}: one of {', '.join(GL_MODES)}")
    if _gl_mode is not None:
        if _gl_mode != mode:
            raise GLUnavailable(f"OpenGL was already set up through {_gl_mode}; a process uses one way ({mode} asked)")
        return
    import pyglet

    if mode == "egl":
        pyglet.options["headless"] = True
    elif not os.environ.get("DISPLAY"):
        raise GLUnavailable("--gl x11 needs an X display in DISPLAY (for instance `xvfb-run -a ...`, Debian's xvfb)")
    pyglet.options["debug_gl"] = False
    _gl_mode = mode


def intrinsics(size: int = SIZE) -> dict:
    """The square camera: fx = fy from the vertical field of view (square
    pixels, so the horizontal one is the same), principal point at the image
    centre in OpenCV's convention (integer pixel coordinates are centres)."""
    f = (size / 2) / np.tan(np.radians(VFOV_DEG) / 2)
    c = (size - 1) / 2
    return {"fx": f, "fy": f, "cx": c, "cy": c, "width": size, "height": size, "near": NEAR_M, "far": FAR_M}


def heading_vector(heading_deg: float) -> np.ndarray:
    """The floor-plane (x, z) direction a heading faces."""
    a = np.radians(heading_deg)
    return np.array([np.cos(a), -np.sin(a)])


def camera_to_world(x: float, z: float, heading_deg: float, eye: float = EYE_HEIGHT) -> np.ndarray:
    """4x4 camera-to-world, camera axes OpenCV (x right, y down, z forward):
    columns right (sin a, 0, cos a), down (0, -1, 0), forward (cos a, 0, -sin a)."""
    a = np.radians(heading_deg)
    s, c = np.sin(a), np.cos(a)
    return np.array([
        [s, 0.0, c, x],
        [0.0, -1.0, 0.0, eye],
        [c, 0.0, -s, z],
        [0.0, 0.0, 0.0, 1.0],
    ])


def linear_depth(window_z: np.ndarray, near: float = Z_NEAR, far: float = Z_FAR) -> np.ndarray:
    """Depth-buffer values in [0, 1] (gluPerspective's projection, glDepthRange 0..1)
    to planar z in metres; cleared pixels (1.0: nothing drawn) are NaN."""
    d = window_z.astype(np.float64)
    ndc = 2.0 * d - 1.0
    with np.errstate(divide="ignore"):
        z = 2.0 * far * near / ((far + near) - ndc * (far - near))
    return np.where(d >= 1.0, np.nan, z)


def depth_millimetres(z_m: np.ndarray) -> np.ndarray:
    """Planar z in metres (NaN unknown) to uint16 millimetres, 0 = unknown or beyond 65.535 m."""
    mm = np.round(np.nan_to_num(z_m, nan=0.0) * 1000.0)
    return np.where((mm > 0) & (mm <= 65535), mm, 0).astype(np.uint16)


class _Target:
    """A framebuffer with a colour and a depth renderbuffer; MiniWorld's
    render_obs draws into it through bind() and then calls resolve()."""

    def __init__(self, width: int, height: int, samples: int, depth_format: int):
        from pyglet import gl

        self.width, self.height = width, height
        self.fbo = gl.GLuint(0)
        gl.glGenFramebuffers(1, byref(self.fbo))
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        for fmt, attachment in ((_GL_RGBA8, gl.GL_COLOR_ATTACHMENT0), (depth_format, gl.GL_DEPTH_ATTACHMENT)):
            rb = gl.GLuint(0)
            gl.glGenRenderbuffers(1, byref(rb))
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
            if samples > 1:
                gl.glRenderbufferStorageMultisample(gl.GL_RENDERBUFFER, samples, fmt, width, height)
            else:
                gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, width, height)
            gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER, rb)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise GLUnavailable(f"framebuffer ({samples} samples, depth format {depth_format:#x}) incomplete: {status:#x}")

    def bind(self) -> None:
        from pyglet import gl

        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        gl.glViewport(0, 0, self.width, self.height)


class _ColourTarget(_Target):
    def __init__(self, width: int, height: int, samples: int):
        super().__init__(width, height, samples, _GL_DEPTH_COMPONENT24)
        self.resolved = _Target(width, height, 1, _GL_DEPTH_COMPONENT24)

    def bind(self) -> None:
        from pyglet import gl

        gl.glEnable(gl.GL_MULTISAMPLE)
        super().bind()

    def resolve(self) -> np.ndarray:
        from pyglet import gl

        w, h = self.width, self.height
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, self.fbo)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, self.resolved.fbo)
        gl.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, gl.GL_COLOR_BUFFER_BIT, gl.GL_NEAREST)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.resolved.fbo)
        out = np.zeros((h, w, 3), np.uint8)
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
        gl.glReadPixels(0, 0, w, h, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, out.ctypes.data_as(POINTER(c_ubyte)))
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return np.ascontiguousarray(out[::-1])   # OpenGL's rows start at the bottom


class _DepthTarget(_Target):
    def __init__(self, width: int, height: int):
        super().__init__(width, height, 1, _GL_DEPTH_COMPONENT32F)

    def bind(self) -> None:
        from pyglet import gl

        gl.glDisable(gl.GL_MULTISAMPLE)
        super().bind()

    def resolve(self) -> np.ndarray:
        from pyglet import gl

        w, h = self.width, self.height
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        out = np.zeros((h, w), np.float32)
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
        gl.glReadPixels(0, 0, w, h, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT, out.ctypes.data_as(POINTER(c_float)))
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return np.ascontiguousarray(out[::-1])


class Engine:
    """MiniWorld environments, one instance per id made on first use and
    reset to each world seed asked for. The world last loaded is the one
    rendered (MiniWorld compiles each reset's rooms into the same display list)."""

    def __init__(self, gl: str = "egl", size: int = SIZE):
        setup_gl(gl)
        self.gl, self.size = gl, size
        self.envs: dict = {}
        self.targets: dict = {}
        self.env = None
        self.env_id: str | None = None
        self.world_seed: int | None = None

    def _make(self, env_id: str):
        try:
            import gymnasium as gym
            import miniworld  # noqa: F401  (registers the MiniWorld-* ids)
        except Exception as e:  # pyglet reaches for OpenGL when MiniWorld is imported
            raise GLUnavailable(self._why(e)) from e
        try:
            # MiniWorld prints its multisampling fallbacks; the tool keeps stdout for its progress.
            with contextlib.redirect_stdout(io.StringIO()):
                env = gym.make(env_id, obs_width=self.size, obs_height=self.size, window_width=self.size,
                               window_height=self.size, domain_rand=True).unwrapped
        except gym.error.Error:
            raise
        except Exception as e:
            raise GLUnavailable(self._why(e)) from e
        from pyglet import gl

        env.shadow_window.switch_to()
        most = gl.GLint(0)
        gl.glGetIntegerv(_GL_MAX_SAMPLES, byref(most))
        self.targets[env_id] = (_ColourTarget(self.size, self.size, max(1, min(RGB_SAMPLES, most.value))),
                                _DepthTarget(self.size, self.size))
        return env

    def _why(self, e: Exception) -> str:
        if self.gl == "egl":
            return (f"MiniWorld could not get an OpenGL context through EGL ({type(e).__name__}: {e}). It needs Mesa's "
                    "EGL and drivers (Debian: apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri libglu1-mesa), "
                    "or an X display with --gl x11 (xvfb-run -a, Debian's xvfb)")
        return (f"MiniWorld could not get an OpenGL context on DISPLAY={os.environ.get('DISPLAY')} "
                f"({type(e).__name__}: {e}); start one with xvfb-run -a (Debian's xvfb) or use --gl egl")

    def load(self, env_id: str, world_seed: int):
        """Resets `env_id` to `world_seed` (its layout, objects, textures and
        light) and pins the camera (height, no pitch, field of view)."""
        if env_id not in self.envs:
            self.envs[env_id] = self._make(env_id)
        env = self.envs[env_id]
        with contextlib.redirect_stdout(io.StringIO()):
            env.reset(seed=int(world_seed))
        agent = env.agent
        agent.cam_height, agent.cam_fwd_disp, agent.cam_pitch, agent.cam_fov_y = EYE_HEIGHT, 0.0, 0.0, VFOV_DEG
        self.env, self.env_id, self.world_seed = env, env_id, int(world_seed)
        return env

    def view(self, x: float, z: float, heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(rgb uint8 (size, size, 3), depth uint16 millimetres (size, size)) from
        the floor point (x, z) facing `heading_deg`, in the world last loaded."""
        if self.env is None:
            raise RuntimeError("load an environment first")
        env = self.env
        env.agent.pos = np.array([x, 0.0, z], dtype=float)
        env.agent.dir = float(np.radians(heading_deg))
        colour, depth = self.targets[self.env_id]
        rgb = env.render_obs(colour)
        window_z = env.render_obs(depth)
        return rgb, depth_millimetres(linear_depth(window_z))

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
            env.shadow_window.close()
        self.envs.clear()
        self.env = None
