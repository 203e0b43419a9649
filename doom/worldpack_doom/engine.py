"""ViZDoom, headless, as a camera that can be put anywhere: teleport to a map
point, face an angle, render RGB and depth, and report the eye's true pose.

Conventions (docs/doom.md): map axes x east, y north, z up, in map units;
ANGLE in degrees counter-clockwise from +x; the eye is CAMERA_POSITION_Z.
The project's world for Doom is y up in metres (x east, y up, z south, the
voxel world's axes), 32 map units to the metre (Doom's player is 56 units
tall, about 1.75 m)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import vizdoom as vzd

UNITS_PER_METRE = 32.0
# Rendered at 320x240 (4:3): horizontal FoV 90 degrees, pixels 1.2 times as tall
# as wide (fy = 1.2 fx). The 8-bit depth buffer counts DEPTH_UNITS map units a
# level, offset by DEPTH_OFFSET levels, and saturates at DEPTH_SATURATED.
RENDER_WIDTH, RENDER_HEIGHT = 320, 240
RENDER_FX = RENDER_WIDTH / 2 / np.tan(np.radians(45.0))
RENDER_FY = 1.2 * RENDER_FX
DEPTH_UNITS = 7.15
DEPTH_OFFSET = 2.0
DEPTH_SATURATED = 127
# The eye settles this many tics after a teleport.
SETTLE_TICS = 2
EYE_HEIGHT = 41.0

# Map axes (x east, y north, z up) to the project's Doom world (x east, y up, z south).
MAP_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def wad_path(name: str = "freedoom2.wad") -> str:
    return os.path.join(os.path.dirname(vzd.__file__), name)


def camera_to_map(x: float, y: float, z_eye: float, angle_deg: float) -> np.ndarray:
    """4x4 camera-to-map matrix, camera axes OpenCV (x right, y down, z forward)."""
    a = np.radians(angle_deg)
    return np.array([
        [np.sin(a), 0.0, np.cos(a), x],
        [-np.cos(a), 0.0, np.sin(a), y],
        [0.0, -1.0, 0.0, z_eye],
        [0.0, 0.0, 0.0, 1.0],
    ])


def map_to_world(c2m: np.ndarray) -> np.ndarray:
    """A camera-to-map matrix as camera-to-world in the project's Doom world (metres, y up)."""
    out = np.eye(4)
    out[:3, :3] = MAP_TO_WORLD @ c2m[:3, :3]
    out[:3, 3] = MAP_TO_WORLD @ c2m[:3, 3] / UNITS_PER_METRE
    return out


def depth_to_units(levels: np.ndarray) -> np.ndarray:
    """8-bit depth levels to planar z in map units; saturated levels become NaN (unknown)."""
    z = DEPTH_UNITS * (levels.astype(np.float64) + DEPTH_OFFSET)
    return np.where(levels >= DEPTH_SATURATED, np.nan, z)


@dataclass
class View:
    rgb: np.ndarray       # (H, W, 3) uint8 at the render size
    depth: np.ndarray     # (H, W) uint8 levels
    x: float
    y: float
    z_eye: float
    angle: float          # degrees, counter-clockwise from +x

    def c2m(self) -> np.ndarray:
        return camera_to_map(self.x, self.y, self.z_eye, self.angle)


class Engine:
    """One headless Doom game on one map, with no monsters, HUD, weapon or view bob."""

    def __init__(self, map_name: str, wad: str | None = None, seed: int = 0):
        g = vzd.DoomGame()
        g.set_doom_game_path(wad or wad_path())
        g.set_doom_map(map_name)
        g.set_screen_resolution(vzd.ScreenResolution.RES_320X240)
        g.set_screen_format(vzd.ScreenFormat.RGB24)
        g.set_depth_buffer_enabled(True)
        g.set_sectors_info_enabled(True)
        for part in ("hud", "weapon", "crosshair", "decals", "particles", "effects_sprites", "messages",
                     "screen_flashes", "corpses"):
            getattr(g, f"set_render_{part}")(False)
        g.set_window_visible(False)
        g.set_sound_enabled(False)
        V = vzd.GameVariable
        g.set_available_game_variables([V.POSITION_X, V.POSITION_Y, V.POSITION_Z, V.CAMERA_POSITION_Z, V.ANGLE])
        g.set_available_buttons([vzd.Button.TURN_LEFT_RIGHT_DELTA])
        g.add_game_args("-nomonsters +sv_cheats 1 +movebob 0 +freelook 0")
        g.set_episode_timeout(0)
        g.set_seed(seed)
        g.init()
        # Teleports may land on damaging floors: the camera must not die there.
        g.send_game_command("god")
        self.game = g
        self.map_name = map_name

    def close(self) -> None:
        self.game.close()

    def state(self) -> tuple[float, float, float, float, float]:
        s = self.game.get_state()
        if s is None:
            raise RuntimeError(f"{self.map_name}: the episode ended (dead: {self.game.is_player_dead()})")
        x, y, z, cz, a = s.game_variables
        return float(x), float(y), float(z), float(cz), float(a) % 360.0

    def sectors(self):
        return self.game.get_state().sectors

    def view_at(self, x: float, y: float, angle_deg: float) -> View:
        """Teleports to the nearest integer map point (`warp` takes integers),
        turns to `angle_deg` and renders once the eye has settled. The View
        holds the pose the engine reports, not the one asked for."""
        g = self.game
        g.send_game_command(f"warp {int(round(x))} {int(round(y))}")
        # TURN_LEFT_RIGHT_DELTA turns right (clockwise) by its value in degrees. In the first
        # tics after a map loads a turn may not take: turn until the engine reports the angle.
        for _ in range(8):
            *_, a = self.state()
            turn = (a - angle_deg + 180.0) % 360.0 - 180.0
            if abs(turn) < 0.5:
                break
            g.make_action([turn], 1)
        for _ in range(8):
            g.make_action([0.0], 1)
            x1, y1, z, cz, a = self.state()
            if abs(cz - z - EYE_HEIGHT) < 1e-3:
                break
        s = g.get_state()
        return View(rgb=np.ascontiguousarray(s.screen_buffer), depth=np.ascontiguousarray(s.depth_buffer),
                    x=x1, y=y1, z_eye=cz, angle=a)
