"""The Gymnasium environment ``satloc/SatLoc-v0``: a car driving over a scene, seeing it in stereo.

Configuration is :class:`EnvConfig` (``SatLocEnv.default_config()`` as a dict); any field can be given as a
keyword to ``gymnasium.make`` and the per-episode ones (see :data:`EPISODE_KEYS`) again in
``reset(options={...})``. Unknown keys raise :class:`satloc.ConfigError`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from satloc.config import from_dict, override, to_dict
from satloc.errors import ConfigError
from satloc.geometry import Pose2, StereoCamera
from satloc.labels import NUM_CLASSES

from .occluders import Appearance, sample_occluders
from .scene import Scene, load_scene
from .vehicle import Autopilot, VehicleParams, step_bicycle


@dataclass
class EnvConfig:
    scene: str = "city"                     # shipped scene name, YAML path or saved scene directory
    resolution: Literal["half", "full"] = "half"   # 620x188 or 1242x375 (KITTI rig)
    route: str | None = None                # route name; default: the scene's database route
    lane_offset_m: float = -1.75            # lateral offset from the route centre line (left positive)
    start_s_m: float = 0.0                  # start position along the route
    random_start: bool = False              # start at a random place on the route (from the episode seed)
    speed_mps: float = 8.0                  # autopilot cruising speed
    dt: float = 0.1                         # seconds per step
    max_steps: int = 1000                   # episode time limit (truncation)
    depth: bool = False                     # add true left-camera depth (metres) to observations
    labels: bool = False                    # add left-camera semantic labels to observations
    odometry_noise: tuple[float, float] = (0.02, 0.003)  # std: fraction of distance, radians per step
    aliasing: float | None = None           # scene knobs (None: the scene file's value)
    occlusion: float | None = None
    appearance: float | None = None
    anisotropy: int = 1                     # >1: anisotropic texture filtering (sharper far ground, ~4x slower on llvmpipe)
    zfar_m: float = 150.0


#: keys that ``reset(options=...)`` may change; the others fix the spaces or the renderer.
EPISODE_KEYS = frozenset({
    "scene", "route", "lane_offset_m", "start_s_m", "random_start", "speed_mps", "max_steps",
    "odometry_noise", "aliasing", "occlusion", "appearance",
})


class SatLocEnv(gym.Env):
    """Drive a stereo-camera car over a textured scene rendered from its satellite tile.

    Observation (Dict): ``left``, ``right`` uint8 RGB images; ``odometry`` float32 (dx, dy, dyaw) of the
    motion since the previous step in the previous vehicle frame, with noise; ``depth`` (float32 metres, 0 =
    nothing) and ``labels`` (uint8 class ids) when enabled.

    Action: Box [speed m/s, yaw rate rad/s], applied through a kinematic bicycle model. ``autopilot_action()``
    returns the route follower's action for scripts.

    ``info``: ``pose`` (x, y, yaw), ``odometry_true``, ``route_s``, ``off_road``, ``route_complete``,
    ``step`` - all fixed-shape numpy values.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, **config: Any):
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.config = from_dict(EnvConfig, config, "SatLocEnv config")
        self.camera = StereoCamera.preset(self.config.resolution)
        self.vehicle = VehicleParams()
        h, w = self.camera.height, self.camera.width
        obs = {
            "left": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "right": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "odometry": spaces.Box(-np.inf, np.inf, (3,), np.float32),
        }
        if self.config.depth:
            obs["depth"] = spaces.Box(0.0, np.inf, (h, w), np.float32)
        if self.config.labels:
            obs["labels"] = spaces.Box(0, NUM_CLASSES - 1, (h, w), np.uint8)
        self.observation_space = spaces.Dict(obs)
        v = self.vehicle
        self.action_space = spaces.Box(np.array([0.0, -v.max_yaw_rate], np.float32),
                                       np.array([v.max_speed_mps, v.max_yaw_rate], np.float32))
        self._episode = self.config
        self._scene: Scene | None = None
        self._scene_key: tuple | None = None
        self._renderer = None
        self.pose = Pose2()
        self._last_obs: dict | None = None

    # --- configuration ----------------------------------------------------------------------------
    @staticmethod
    def default_config() -> dict:
        return to_dict(EnvConfig())

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            raise RuntimeError("call reset() first")
        return self._scene

    def _ensure_scene(self, cfg: EnvConfig) -> None:
        key = (cfg.scene, cfg.aliasing)
        if key == self._scene_key:
            return
        scene = load_scene(cfg.scene, cfg.aliasing)
        from .render import StereoRenderer

        if self._renderer is not None:
            self._renderer.close()
        self._scene, self._scene_key = scene, key
        self._renderer = StereoRenderer(scene.world, self.camera, anisotropy=cfg.anisotropy,
                                        zfar=cfg.zfar_m)

    # --- gym API ----------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        bad = sorted(set(options) - EPISODE_KEYS)
        if bad:
            known = sorted(EPISODE_KEYS)
            raise ConfigError(f"reset options: {bad} cannot change per episode (or are unknown); allowed: {known}")
        cfg = override(self.config, options, "reset options")
        self._episode = cfg
        self._ensure_scene(cfg)
        scene = self.scene
        route_name = cfg.route or scene.spec.database_route
        if route_name not in scene.routes:
            raise ConfigError(f"route: {route_name!r} is not a route of scene {scene.name!r} ({sorted(scene.routes)})")
        self.route = scene.routes[route_name]
        knobs = scene.spec.knobs
        occ = knobs.occlusion if cfg.occlusion is None else cfg.occlusion
        app = knobs.appearance if cfg.appearance is None else cfg.appearance
        for k, val in (("occlusion", occ), ("appearance", app)):
            if not 0.0 <= val <= 1.0:
                raise ConfigError(f"{k}: expected a value in [0, 1], got {val}")
        rng = self.np_random
        s0 = float(rng.uniform(0, self.route.length * 0.9)) if cfg.random_start else cfg.start_s_m
        self.pose = self.route.pose_at(s0, cfg.lane_offset_m)
        self.pilot = Autopilot(self.route, cfg.lane_offset_m, cfg.speed_mps, s0=s0)
        self._renderer.set_occluders(*sample_occluders(self.route, scene.ground_label, occ, cfg.lane_offset_m, rng))
        self.appearance = Appearance(app, rng)
        self.steps = 0
        obs = self._observe(np.zeros(3, np.float32))
        return obs, self._info(np.zeros(3), off_road=False)

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: expected 2 finite values [speed, yaw_rate], got {action!r}")
        cfg = self._episode
        prev = self.pose
        self.pose, _, _ = step_bicycle(prev, a[0], a[1], cfg.dt, self.vehicle)
        self.steps += 1
        self.pilot.s, _ = self.route.project((self.pose.x, self.pose.y), s_hint=self.pilot.s, window=15.0)
        true_odo = prev.between(self.pose).as_array()
        dist = math.hypot(true_odo[0], true_odo[1])
        noise = self.np_random.normal(0.0, 1.0, 3) * np.array(
            [cfg.odometry_noise[0] * dist, cfg.odometry_noise[0] * dist, cfg.odometry_noise[1]])
        obs = self._observe((true_odo + noise).astype(np.float32))
        off_road = not self.scene.is_drivable(self.pose.x, self.pose.y)
        info = self._info(true_odo, off_road)
        terminated = bool(off_road or info["route_complete"])
        truncated = self.steps >= cfg.max_steps
        return obs, 0.0, terminated, truncated, info

    def autopilot_action(self) -> np.ndarray:
        """The route follower's action for the current pose (a scripted driver)."""
        return self.pilot.act(self.pose)

    def _observe(self, odometry: np.ndarray) -> dict:
        cfg = self.config
        out = self._renderer.render(self.pose, depth="left" if cfg.depth else False, labels=cfg.labels)
        obs = {"left": self.appearance(out["left"]), "right": self.appearance(out["right"]), "odometry": odometry}
        if cfg.depth:
            obs["depth"] = out["depth_left"]
        if cfg.labels:
            obs["labels"] = out["labels_left"]
        self._last_obs = obs
        return obs

    def _info(self, true_odo: np.ndarray, off_road: bool) -> dict:
        return {
            "pose": self.pose.as_array(),
            "odometry_true": np.asarray(true_odo, np.float64),
            "route_s": np.float64(self.pilot.s),
            "off_road": np.bool_(off_road),
            "route_complete": np.bool_(self.pilot.done),
            "step": np.int64(self.steps),
        }

    # --- rendering --------------------------------------------------------------------------------
    def render(self):
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return compose_view(self._last_obs["left"], self.scene, self.pose, self.route)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._scene = self._scene_key = None


PANEL_PX = 360
PANEL_M = 80.0


def birdseye(scene: Scene, pose: Pose2, route=None, size_px: int = PANEL_PX, size_m: float = PANEL_M) -> np.ndarray:
    """North-up crop of the satellite tile around ``pose`` with the route and the vehicle drawn on it."""
    sm = scene.satmap
    img = sm.crop((pose.x, pose.y), size_m, out_px=size_px).copy()
    scale = size_px / size_m

    def to_px(xy):
        d = np.asarray(xy, np.float64) - (pose.x, pose.y)
        return np.stack([size_px / 2 + d[..., 0] * scale, size_px / 2 - d[..., 1] * scale], -1)

    if route is not None:
        pts = to_px(route.points)
        cv2.polylines(img, [np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)], False, (80, 200, 255), 1,
                      cv2.LINE_AA, shift=4)
    tri = pose.transform(np.array([[2.6, 0.0], [-1.6, 1.3], [-1.6, -1.3]]))
    cv2.fillPoly(img, [np.round(to_px(tri) * 16).astype(np.int32).reshape(-1, 1, 2)], (255, 40, 40), cv2.LINE_AA,
                 shift=4)
    return img


def compose_view(camera_img: np.ndarray, scene: Scene, pose: Pose2, route=None) -> np.ndarray:
    """Camera view (scaled to the panel height) beside the bird's-eye panel."""
    h, w = camera_img.shape[:2]
    cam = cv2.resize(camera_img, (int(round(w * PANEL_PX / h)), PANEL_PX), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(np.hstack([cam, birdseye(scene, pose, route)]))
