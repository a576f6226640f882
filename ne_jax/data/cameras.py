"""Cameras of the procedural scenes: NeRF Synthetic's field of view and near/far, cameras on a sphere
around the origin looking at it (OpenGL convention, camera -z forward, z up as in Blender)."""

from __future__ import annotations

import numpy as np

CAMERA_ANGLE_X = 0.6911112070083618  # the NeRF Synthetic value (about 39.6 degrees)
CAMERA_RADIUS = 4.0
NEAR, FAR = 2.0, 6.0


def look_at(eye: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world ``[4, 4]`` at ``eye`` looking at ``target`` (camera -z forward)."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.cross(forward, (0.0, 1.0, 0.0))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def random_cameras(count: int, rng: np.random.Generator, min_elev=-15.0, max_elev=75.0) -> np.ndarray:
    """``[count, 4, 4]`` cameras on the sphere of radius ``CAMERA_RADIUS``, uniform in area between
    the elevations (degrees)."""
    lo, hi = np.sin(np.deg2rad(min_elev)), np.sin(np.deg2rad(max_elev))
    z = rng.uniform(lo, hi, count)
    az = rng.uniform(0.0, 2 * np.pi, count)
    r = np.sqrt(1 - z**2)
    eyes = CAMERA_RADIUS * np.stack([r * np.cos(az), r * np.sin(az), z], axis=1)
    return np.stack([look_at(e) for e in eyes])


def orbit_cameras(count: int, elevation_deg: float = 25.0) -> np.ndarray:
    """``[count, 4, 4]`` cameras evenly spaced on a circle at ``elevation_deg``."""
    el = np.deg2rad(elevation_deg)
    az = 2 * np.pi * np.arange(count) / count
    eyes = CAMERA_RADIUS * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(count, np.sin(el))], 1)
    return np.stack([look_at(e) for e in eyes])
