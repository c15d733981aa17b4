"""Whether the autopilot can drive a route: the recorder's off-road check, run before any work.

:func:`autopilot_drive` moves the vehicle exactly as the environment does when the recorder steps it with
the autopilot's action (:meth:`satloc_env.envs.drive.SatLocEnv.step`: the action clipped to the action space, one
bicycle-model step of ``dt``, the autopilot's progress updated, the pose checked against the scene's
drivable area), without rendering anything: a 1 km route takes about a tenth of a second. The poses are
the ones a recording would have (the vehicle's motion has no noise), so a route it drives to the end is
recorded without leaving the road, and the first off-road pose it finds is where the recorder would stop.

:func:`check_route` raises :class:`satloc.ConfigError` naming the route, the lane offset and that first
point (map metres, lon/lat on a scene over georeferenced imagery, and how far along the route it lies).
``satloc scene``, :func:`satloc_env.envs.record.record_passes` (``satloc record``, ``satloc demo``, the
experiments) and the experiments' multi-scene commands call it before they start.
"""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from satloc.errors import ConfigError
from satloc.geometry import Pose2

from .vehicle import DEFAULT_DT, Autopilot, VehicleParams, action_bounds, drift_at, step_bicycle

__all__ = ["autopilot_drive", "check_route", "first_off_road", "off_road_message"]


def autopilot_drive(scene, route: str, lane_offset_m: float, speed_mps: float = 8.0, dt: float = DEFAULT_DT,
                    vehicle: VehicleParams = VehicleParams(), start_s_m: float = 0.0, wander=None
                    ) -> Iterator[tuple[Pose2, float, bool]]:
    """(pose, route_s, off_road) after each step of the autopilot driving ``route`` of ``scene`` at
    ``lane_offset_m`` from ``start_s_m`` until it completes the route or leaves the road (the last item),
    as the environment steps it. ``wander``: a drift profile (:func:`satloc_env.envs.vehicle.wander_profile`)
    the drive follows, as the environment's with that seed. Stops after ``20 x`` the steps the route should
    take (a vehicle that never gets there)."""
    r = scene.routes[route]
    pose = r.pose_at(start_s_m, lane_offset_m + drift_at(r, lane_offset_m, wander, start_s_m))
    pilot = Autopilot(r, lane_offset_m, speed_mps, s0=start_s_m, wander=wander)
    low, high = (b.astype(np.float64) for b in action_bounds(vehicle))
    limit = 1000 + 20 * int(r.length / max(speed_mps * dt, 1e-3))
    for _ in range(limit):
        a = np.clip(np.asarray(pilot.act(pose)).astype(np.float64), low, high)
        pose, _, _ = step_bicycle(pose, a[0], a[1], dt, vehicle)
        pilot.follow(pose)
        off = not scene.is_drivable(pose.x, pose.y)
        yield pose, float(pilot.s), off
        if off or pilot.done:
            return


def first_off_road(scene, route: str, lane_offset_m: float, speed_mps: float = 8.0, dt: float = DEFAULT_DT,
                   wander=None) -> tuple[Pose2, float] | None:
    """The first pose (and its route arc length) where the autopilot leaves the road on ``route`` (drifting
    as ``wander`` says, if given), None if it drives the route to its end on the road."""
    for pose, s, off in autopilot_drive(scene, route, lane_offset_m, speed_mps, dt, wander=wander):
        if off:
            return pose, s
    return None


def off_road_message(scene, route: str, lane_offset_m: float, pose, s: float) -> str:
    """``routes.<route>: the autopilot leaves the road at ...``: where (map metres, lon/lat where the scene
    has a geo frame), how far along the route and at which lane offset."""
    x, y = float(pose[0]), float(pose[1])
    where = f"({x:.1f}, {y:.1f}) m"
    frame = getattr(scene.satmap, "frame", None)
    if frame is not None:
        lon, lat = frame.to_lonlat(np.array([x, y]))
        where += f" (lon {lon:.6f}, lat {lat:.6f})"
    length = scene.routes[route].length
    if getattr(scene, "tour", None) is not None:   # derived from the road graph: the user drew no route to move
        advice = ("the route was derived from the road graph, and a turn there is sharper than the car can "
                  "follow (roads meeting at an acute angle, a turn-round loop with little room): leave that "
                  "junction out of the area (generator.region) or give routes of your own")
    else:
        advice = "move the route onto the road there, give another lane offset, or widen the road"
    return (f"routes.{route}: the autopilot leaves the road at {where}, {s:.0f} m of {length:.0f} m along the "
            f"route, driving at lane offset {lane_offset_m:g} m; {advice}")


def check_route(scene, route: str, lane_offset_m: float, speed_mps: float = 8.0, dt: float = DEFAULT_DT,
                where: str | None = None, wander=None) -> None:
    """ConfigError (see :func:`off_road_message`, prefixed by ``where`` or the scene's name) when the
    autopilot leaves the road on ``route`` at ``lane_offset_m`` (drifting as ``wander`` says, if given)."""
    if route not in scene.routes:
        raise ConfigError(f"{where or f'scene {scene.name!r}'}: route: {route!r} is not a route of scene "
                          f"{scene.name!r} ({sorted(scene.routes)})")
    hit = first_off_road(scene, route, lane_offset_m, speed_mps, dt, wander=wander)
    if hit is not None:
        pose, s = hit
        raise ConfigError(f"{where or f'scene {scene.name!r}'}: "
                          f"{off_road_message(scene, route, lane_offset_m, pose.as_array(), s)}")
