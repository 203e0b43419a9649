"""A small typed client for the WorldPack REST server (docs/api.md).

Only the standard library, NumPy and Pillow: images go in and come out as
`uint8` arrays of shape (H, W, 3), depth as `uint16` millimetres (H, W).
Refusals for load (429, 503) are retried with backoff, honouring the
server's `Retry-After`; nothing else is retried, and a step is never sent
twice blindly: every step carries the index its frame must get, so a step
re-sent after a lost answer is refused (409) instead of stepping again.
"""

from __future__ import annotations

import base64
import io
import json
import os
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from PIL import Image

Pose = Mapping[str, Any]


class WorldPackError(Exception):
    """An answer other than 2xx: the HTTP status and the field the server named."""

    def __init__(self, status: int, field: str, message: str):
        super().__init__(f"{status} {field}: {message}" if field else f"{status}: {message}")
        self.status, self.field, self.message = status, field, message


# ---- poses, in every form the server takes --------------------------------

def c2w(rotation: Sequence[Sequence[float]] | np.ndarray, position: Sequence[float] | np.ndarray) -> dict:
    """OpenCV camera-to-world: row-major 3×3 rotation and the camera centre."""
    return {"c2w": {"rotation": np.asarray(rotation, float).tolist(), "position": np.asarray(position, float).tolist()}}


def opencv(rvec: Sequence[float], tvec: Sequence[float]) -> dict:
    """OpenCV extrinsics (world-to-camera), as cv2.solvePnP returns them."""
    return {"opencv": {"rvec": np.asarray(rvec, float).ravel().tolist(), "tvec": np.asarray(tvec, float).ravel().tolist()}}


def opengl(matrix: Sequence[Sequence[float]] | np.ndarray) -> dict:
    """OpenGL/Blender camera-to-world 4×4, row-major."""
    return {"opengl": np.asarray(matrix, float).tolist()}


def pose5(x: float, y: float, z: float, pitch: float, yaw: float, convention: str = "minecraft", unit: str = "degrees") -> dict:
    """Position, pitch and yaw in a named convention (minecraft, mineflayer, worldmem) and unit (degrees, radians)."""
    return {"pose5": {"x": x, "y": y, "z": z, "pitch": pitch, "yaw": yaw, "convention": convention, "unit": unit}}


def as_pose(pose: Pose | np.ndarray) -> dict:
    """A pose dict as given, or a 4×4 array taken as OpenCV camera-to-world."""
    if isinstance(pose, np.ndarray):
        if pose.shape != (4, 4):
            raise ValueError(f"pose: a 4×4 camera-to-world array, got shape {pose.shape}")
        return c2w(pose[:3, :3], pose[:3, 3])
    return dict(pose)


def pose_matrix(answer: Mapping[str, Any]) -> np.ndarray:
    """The server's pose answer ({"rotation", "position"}) as a 4×4 camera-to-world array."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(answer["rotation"], float)
    m[:3, 3] = np.asarray(answer["position"], float)
    return m


# ---- images ---------------------------------------------------------------

def png_bytes(image: np.ndarray | bytes) -> bytes:
    """An (H, W, 3) uint8 array (or PNG bytes, passed through) as PNG bytes."""
    if isinstance(image, (bytes, bytearray)):
        return bytes(image)
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"image: an (H, W, 3) uint8 array, got {a.dtype} {a.shape}")
    out = io.BytesIO()
    Image.fromarray(a).save(out, format="PNG")
    return out.getvalue()


def depth_png16(depth_mm: np.ndarray) -> bytes:
    """(H, W) depth in millimetres (0 = unknown) as a 16-bit grayscale PNG."""
    d = np.asarray(depth_mm)
    if d.ndim != 2 or d.dtype != np.uint16:
        raise ValueError(f"depth_mm: an (H, W) uint16 array of millimetres, got {d.dtype} {d.shape}")
    out = io.BytesIO()
    Image.fromarray(d).save(out, format="PNG")
    return out.getvalue()


def decode_image(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def decode_depth(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data))).astype(np.uint16)


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


# ---- the client -------------------------------------------------------------

@dataclass
class Step:
    """One generated frame: the step answer, with the image decoded."""

    index: int
    image: np.ndarray
    pose: np.ndarray
    plan: dict
    truth: dict | None
    timings_ms: dict
    raw: dict = field(repr=False)


@dataclass
class Rollout:
    """One imagined candidate: the camera pose of every step (4×4 each), the
    frames asked for by step (an (H, W, 3) uint8 image, or a float32 latent of
    the answer's `latent_shape`), and its last frame's score against the goal
    image when one was given (`psnr_db`, higher is closer; `latent_mse`, lower is closer)."""

    poses: list[np.ndarray]
    frames: dict[int, np.ndarray]
    goal: dict | None
    raw: dict = field(repr=False)


@dataclass
class Imagined:
    """What `Client.imagine` answers: one `Rollout` per candidate, in order."""

    rollouts: list[Rollout]
    model_calls: int
    # Frames the model made: candidates that begin with the same actions share those frames.
    frames_made: int
    timings_ms: dict
    raw: dict = field(repr=False)


@dataclass
class Client:
    """`Client("http://127.0.0.1:8080")`; every method raises `WorldPackError` for a 4xx/5xx answer.
    A server with tokens needs `token=` (or WORLDPACK_TOKEN in the environment): it is sent as
    `Authorization: Bearer <token>` and never printed."""

    base_url: str = "http://127.0.0.1:8080"
    token: str | None = field(default_factory=lambda: os.environ.get("WORLDPACK_TOKEN"), repr=False)
    timeout: float = 120.0
    retries: int = 8
    backoff: float = 0.25
    # Every refusal retried so far: (status, its Retry-After header or None).
    refusals: list[tuple[int, str | None]] = field(default_factory=list)

    def request(self, method: str, path: str, body: Any = None, raw: bool = False) -> Any:
        data = None if body is None else json.dumps(body).encode()
        headers = {"content-type": "application/json"} if body is not None else {}
        if self.token:
            headers["authorization"] = f"Bearer {self.token}"
        for attempt in range(self.retries + 1):
            req = urllib.request.Request(self.base_url.rstrip("/") + path, data=data, headers=headers, method=method)
            try:
                with urllib.request.urlopen(req, timeout=self.timeout) as r:
                    payload = r.read()
                    if raw:
                        return payload
                    return json.loads(payload) if payload else None
            except urllib.error.HTTPError as e:
                payload = e.read()
                if e.code in (429, 503) and attempt < self.retries:
                    wait = e.headers.get("Retry-After")
                    self.refusals.append((e.code, wait))
                    time.sleep(float(wait) if wait and wait.replace(".", "", 1).isdigit() else self.backoff * 2 ** attempt)
                    continue
                try:
                    err = json.loads(payload)["error"]
                    raise WorldPackError(e.code, err.get("field", ""), err.get("message", "")) from None
                except (ValueError, KeyError, TypeError):
                    raise WorldPackError(e.code, "", payload.decode(errors="replace")) from None
        raise AssertionError("unreachable: the last attempt returns or raises")

    def health(self) -> dict:
        return self.request("GET", "/v1/health")

    def create_session(self, *, synthetic_seed: int | None = None, biome: str | None = None, size: int | None = None,
                       frames: Sequence[tuple[np.ndarray | bytes, Pose | np.ndarray]] | None = None,
                       intrinsics: Mapping[str, Any] | None = None, policy: Mapping[str, Any] | None = None) -> int:
        """A synthetic world by seed (its frames `size` pixels wide; default the model's), or
        real frames [(image, pose), ...] with intrinsics, answered at their size; returns the session id."""
        body: dict[str, Any] = {}
        if synthetic_seed is not None:
            body["synthetic"] = {"seed": int(synthetic_seed), **({"biome": biome} if biome else {}),
                                 **({"size": int(size)} if size is not None else {})}
        elif size is not None:
            raise ValueError("size: a synthetic session's; a session of real frames is at its frames' size")
        if frames is not None:
            body["frames"] = [{"image_png": b64(png_bytes(img)), "pose": as_pose(p)} for img, p in frames]
        if intrinsics is not None:
            body["intrinsics"] = dict(intrinsics)
        if policy is not None:
            body["policy"] = dict(policy)
        return self.request("POST", "/v1/sessions", body)["session"]

    def session(self, session: int) -> dict:
        return self.request("GET", f"/v1/sessions/{session}")

    def delete_session(self, session: int) -> None:
        self.request("DELETE", f"/v1/sessions/{session}")

    def observe(self, session: int, image: np.ndarray | bytes, pose: Pose | np.ndarray, *,
                depth_mm: np.ndarray | None = None, action: Mapping[str, Any] | None = None) -> dict:
        body: dict[str, Any] = {"image_png": b64(png_bytes(image)), "pose": as_pose(pose)}
        if depth_mm is not None:
            body["depth_png16"] = b64(depth_png16(depth_mm))
        if action is not None:
            body["action"] = dict(action)
        return self.request("POST", f"/v1/sessions/{session}/observe", body)

    def step(self, session: int, action: Mapping[str, Any], *, pose: Pose | np.ndarray | None = None,
             steps: int | None = None, seed: int | None = None, expected_index: int | None = None,
             observe: bool = False) -> Step:
        """Generates the next frame. The step is sent with the index its frame
        must get (the session's frame count, asked first when not given), so
        a retried refusal can never step twice. With `observe` (synthetic
        sessions), the world's true frame and depth at the new pose are
        recorded instead, as a robot's camera would see its exploration."""
        if expected_index is None:
            expected_index = self.session(session)["frames"]
        body: dict[str, Any] = {"action": dict(action), "expected_index": int(expected_index)}
        if pose is not None:
            body["pose"] = as_pose(pose)
        if steps is not None:
            body["steps"] = int(steps)
        if seed is not None:
            body["seed"] = int(seed)
        if observe:
            body["observe"] = True
        r = self.request("POST", f"/v1/sessions/{session}/step", body)
        return Step(index=r["index"], image=decode_image(base64.b64decode(r["image_png"])), pose=pose_matrix(r["pose"]),
                    plan=r["selection"]["plan"], truth=r.get("truth"), timings_ms=r["timings_ms"], raw=r)

    def fork(self, session: int) -> int:
        """A new session whose memory is `session`'s up to now (shared on the server, not
        copied); returns its id. Its steps are its own. The server refuses to delete a
        session while forks of it live (409, field `session`): delete the forks first."""
        return self.request("POST", f"/v1/sessions/{session}/fork")["session"]

    def imagine(self, session: int, actions: Sequence[Sequence[Mapping[str, Any]]] | None = None, *,
                poses: Sequence[Sequence[Pose | np.ndarray]] | None = None, steps: int | None = None,
                seed: int | None = None, frames: str | int = "last", format: str = "png",
                goal: np.ndarray | bytes | None = None, goal_score: str = "both") -> Imagined:
        """Rolls out candidate futures from the session's present without writing to it:
        `actions[k]` is candidate k's action per step, `poses[k]` (optionally, or instead)
        its pose per step; every candidate has the same number of steps. `frames` is
        "last", "all", "none" or n (every n-th step); `format` "png" (images) or "latent"
        (the model's latents). With `goal` (an image at the model's size) each candidate's
        last frame is scored against it: `goal_score` "both" (PSNR and the latents'
        difference) or "latent" (the latents' only; the last step is then not decoded
        unless its frame is answered, and `psnr_db` is None). Step h of every candidate
        uses noise seed `seed + h` (default: the frame's time), as stepping a fork with
        those seeds would."""
        count = len(actions) if actions is not None else len(poses or [])
        candidates: list[dict[str, Any]] = [{} for _ in range(count)]
        if actions is not None:
            for c, a in zip(candidates, actions):
                c["actions"] = [dict(x) for x in a]
        if poses is not None:
            if len(poses) != count:
                raise ValueError(f"poses: {len(poses)} candidates for {count} action sequences")
            for c, p in zip(candidates, poses):
                c["poses"] = [as_pose(x) for x in p]
        body: dict[str, Any] = {"candidates": candidates, "format": format,
                                "frames": {"every": int(frames)} if isinstance(frames, int) else frames}
        if steps is not None:
            body["steps"] = int(steps)
        if seed is not None:
            body["seed"] = int(seed)
        if goal is not None:
            body["goal_png"] = b64(png_bytes(goal))
            body["goal_score"] = goal_score
        r = self.request("POST", f"/v1/sessions/{session}/imagine", body)
        shape = r.get("latent_shape")

        def frame(f: dict) -> np.ndarray:
            if f.get("image_png") is not None:
                return decode_image(base64.b64decode(f["image_png"]))
            return np.frombuffer(base64.b64decode(f["latent"]), dtype="<f4").reshape(shape)

        rollouts = [Rollout(poses=[pose_matrix(p) for p in c["poses"]], frames={f["step"]: frame(f) for f in c["frames"]},
                            goal=c.get("goal"), raw=c) for c in r["candidates"]]
        return Imagined(rollouts=rollouts, model_calls=r["model_calls"], frames_made=r["frames_made"],
                        timings_ms=r["timings_ms"], raw=r)

    def select(self, session: int, pose: Pose | np.ndarray) -> dict:
        """The plan the session's policy would choose for `pose` (a dry run)."""
        return self.request("POST", f"/v1/sessions/{session}/select", {"pose": as_pose(pose)})

    def frame(self, session: int, index: int) -> dict:
        return self.request("GET", f"/v1/sessions/{session}/frames/{index}")

    def frame_image(self, session: int, index: int) -> np.ndarray:
        return decode_image(self.request("GET", f"/v1/sessions/{session}/frames/{index}/image", raw=True))

    def frame_depth(self, session: int, index: int) -> np.ndarray:
        """Depth in millimetres (0 = unknown), as observed."""
        return decode_depth(self.request("GET", f"/v1/sessions/{session}/frames/{index}/depth", raw=True))

    def frame_truth(self, session: int, index: int) -> np.ndarray:
        """A synthetic session's true frame at frame `index`'s pose."""
        return decode_image(self.request("GET", f"/v1/sessions/{session}/frames/{index}/truth", raw=True))
