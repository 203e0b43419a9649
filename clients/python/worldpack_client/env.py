"""A Gymnasium environment over a WorldPack server: each episode is a
synthetic session, each step one generated frame.

The action is the server's: five keys (0/1) and the camera's yaw and pitch
change in degrees within ±180. The observation is the generated frame with
the camera pose (OpenCV camera-to-world, 4×4). A world model has no reward:
it is 0, and episodes end only by truncation after `max_steps`. `info`
carries the memory plan the step used and, for a synthetic session, the
PSNR/SSIM of the frame against the world's true frame there.

A planner tries futures without living them: `env.imagine(...)` rolls
candidate action sequences out from the present and changes nothing;
`env.fork()` is a second environment at the same present, whose steps are
its own (close it before resetting or closing the one it came from: the
server keeps a session while forks of it live).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .client import Client, Imagined, WorldPackError, pose_matrix

KEYS = ("forward", "back", "left", "right", "jump")
MAX_TURN_DEG = 180.0  # the server's bound on yaw_deg and pitch_deg (docs/api.md)
MAX_COORDINATE = 1e9


def action_space() -> spaces.Dict:
    turn = spaces.Box(-MAX_TURN_DEG, MAX_TURN_DEG, shape=(), dtype=np.float64)
    return spaces.Dict({**{k: spaces.Discrete(2) for k in KEYS}, "yaw_deg": turn, "pitch_deg": turn})


def to_request(action: dict[str, Any]) -> dict[str, Any]:
    """A sample of `action_space()` as the server's JSON action."""
    out: dict[str, Any] = {k: bool(int(action[k])) for k in KEYS if k in action}
    for k in ("yaw_deg", "pitch_deg"):
        if k in action:
            out[k] = float(np.clip(float(action[k]), -MAX_TURN_DEG, MAX_TURN_DEG))
    return out


class WorldPackEnv(gym.Env):
    """`WorldPackEnv(Client(url), max_steps=40)`; `reset(seed=s)` opens synthetic world s.
    `size=(h, w)`: the frames' size (the world is seen and every step answered at it;
    the model still works at its own; a square model makes square frames)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}  # the synthetic world steps at 20 Hz

    def __init__(self, client: Client | None = None, *, max_steps: int = 40, sampler_steps: int | None = None,
                 size: tuple[int, int] = (64, 64), biome: str | None = None, render_mode: str | None = "rgb_array"):
        if max_steps < 1:
            raise ValueError(f"max_steps: at least 1, got {max_steps}")
        self.client = client or Client()
        self.max_steps, self.sampler_steps, self.biome = max_steps, sampler_steps, biome
        self.render_mode = render_mode
        h, w = size
        self.action_space = action_space()
        self.observation_space = spaces.Dict({
            "frame": spaces.Box(0, 255, shape=(h, w, 3), dtype=np.uint8),
            # The server keeps positions within ±1e9 world units.
            "pose": spaces.Box(-MAX_COORDINATE, MAX_COORDINATE, shape=(4, 4), dtype=np.float64),
        })
        self.session: int | None = None
        self.index = 0
        self.steps = 0
        self.frame = np.zeros((h, w, 3), np.uint8)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._close_session()
        world = int(seed) if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        h, w = self.observation_space["frame"].shape[:2]
        self.session = self.client.create_session(synthetic_seed=world, biome=self.biome, size=w)
        self.index, self.steps = 1, 0  # frame 0 is the world's first frame
        self.frame = self.client.frame_image(self.session, 0)
        if self.frame.shape[:2] != (h, w):
            shape = self.frame.shape[:2]
            self._close_session()
            raise ValueError(f"size: asked for {h}x{w} (height x width) frames; the model's aspect gives {shape[0]}x{shape[1]}")
        pose = pose_matrix(self.client.frame(self.session, 0)["pose"])
        return {"frame": self.frame, "pose": pose}, {"session": self.session, "world_seed": world}

    def step(self, action):
        if self.session is None:
            raise RuntimeError("call reset() before step()")
        r = self.client.step(self.session, to_request(action), steps=self.sampler_steps, expected_index=self.index)
        self.index, self.steps, self.frame = r.index + 1, self.steps + 1, r.image
        # Only what a replay with the same seed and actions reproduces (no timings).
        info = {"index": r.index, "plan": r.plan}
        if r.truth is not None:
            info["psnr_db"], info["ssim"] = r.truth["psnr_db"], r.truth["ssim"]
        truncated = self.steps >= self.max_steps
        return {"frame": r.image, "pose": r.pose}, 0.0, False, truncated, info

    def fork(self) -> "WorldPackEnv":
        """An environment at this one's present, on a fork of its session: the same
        frames, pose and step count, then steps of its own. Closing it deletes the fork."""
        if self.session is None:
            raise RuntimeError("call reset() before fork()")
        other = WorldPackEnv(self.client, max_steps=self.max_steps, sampler_steps=self.sampler_steps,
                             size=self.frame.shape[:2], biome=self.biome, render_mode=self.render_mode)
        other.session = self.client.fork(self.session)
        other.index, other.steps, other.frame = self.index, self.steps, self.frame.copy()
        return other

    def imagine(self, actions, **kwargs) -> Imagined:
        """Rolls candidate futures out from the present without stepping: `actions[k]` is
        a sequence of samples of `action_space`; the rest as `Client.imagine` takes it."""
        if self.session is None:
            raise RuntimeError("call reset() before imagine()")
        kwargs.setdefault("steps", self.sampler_steps)
        return self.client.imagine(self.session, [[to_request(a) for a in seq] for seq in actions], **kwargs)

    def render(self):
        return self.frame

    def close(self):
        self._close_session()

    def _close_session(self):
        if self.session is not None:
            try:
                self.client.delete_session(self.session)
            except WorldPackError as e:
                if e.status != 404:  # already gone is fine
                    raise
            self.session = None


def make(url: str = "http://127.0.0.1:8080", token: str | None = None, **kwargs) -> WorldPackEnv:
    """The environment on the server at `url` (with `token` when it has tokens); the
    rest as WorldPackEnv takes it. What `gymnasium.make("WorldPack-v0", url=...)` calls."""
    client = Client(url) if token is None else Client(url, token=token)
    return WorldPackEnv(client, **kwargs)


# Importing this module registers the environment, so either of these works:
#   import worldpack_client.env; gymnasium.make("WorldPack-v0", url="http://127.0.0.1:8080")
#   gymnasium.make("worldpack_client.env:WorldPack-v0", url="http://127.0.0.1:8080")
if "WorldPack-v0" not in gym.registry:
    gym.register(id="WorldPack-v0", entry_point="worldpack_client.env:make", disable_env_checker=True)
