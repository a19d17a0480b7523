"""Fitting MuJoCo's free camera to points (issue #53 item 7): the view that holds them all, and their projection.

MuJoCo's free camera looks along ``forward = (cos el cos az, cos el sin az, sin el)`` from ``lookat - distance *
forward``, with ``up = (-sin el cos az, -sin el sin az, cos el)`` and the model's vertical field of view
(``vis.global_.fovy``) over the image height; the horizontal one follows from the image's aspect ratio. ``fit_view``
places the look-at point and distance so that every point lies inside the image, with a margin, below a band at the
top (the panel's caption); ``project`` gives the points' normalised image coordinates in such a view (x, y in
-1..1 across the image, y up), which is what the tests check the framing with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import FloatArray

#: The points fill at most this share of the image's half-width and half-height (the rest is margin).
FILL = 0.9
#: No view closer than this (m): MuJoCo's near clipping plane, and a sensible close-up of a small object.
MIN_DISTANCE_M = 0.12


@dataclass(frozen=True)
class View:
    """A free camera's look-at point, distance and direction (degrees)."""

    lookat: FloatArray
    distance: float
    azimuth: float
    elevation: float


def camera_axes(azimuth: float, elevation: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(forward, up, right) unit vectors of MuJoCo's free camera at ``azimuth`` / ``elevation`` (degrees)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    return forward, up, np.cross(forward, up)


def project(points: FloatArray, view: View, fovy_deg: float, aspect: float) -> FloatArray:
    """(N, 2) normalised image coordinates of ``points`` (N, 3) seen from ``view`` in an image of width / height
    ``aspect``: x from -1 (left) to 1 (right), y from -1 (bottom) to 1 (top); a point behind the camera gets inf."""
    forward, up, right = camera_axes(view.azimuth, view.elevation)
    rel = np.asarray(points, dtype=np.float64) - (np.asarray(view.lookat) - view.distance * forward)
    depth = rel @ forward
    ty = np.tan(np.radians(fovy_deg) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(depth > 0, (rel @ right) / (depth * ty * aspect), np.inf)
        y = np.where(depth > 0, (rel @ up) / (depth * ty), np.inf)
    return np.stack([x, y], axis=1)


def fit_view(points: FloatArray, azimuth: float, elevation: float, fovy_deg: float, aspect: float,
             top_band: float = 0.0, fill: float = FILL) -> View:
    """The view from ``azimuth`` / ``elevation`` that holds every finite point of ``points`` (N, 3) within
    ``fill`` of the image, below a band of ``top_band`` (a share of the image height) at the top."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        raise ValueError("no points to frame")
    forward, up, right = camera_axes(azimuth, elevation)
    # The look-at point: the middle of the points' extent across the image and along the view.
    coords = pts @ np.stack([right, up, forward], axis=1)  # (N, 3)
    middle = (coords.min(axis=0) + coords.max(axis=0)) / 2
    lookat = middle @ np.stack([right, up, forward])
    rel = pts - lookat
    x, y, z = rel @ right, rel @ up, rel @ forward
    # Below the band the image spans (1 - top_band) of its height: fit into that, then move the view up by half
    # the band so that the points sit under it.
    ty = np.tan(np.radians(fovy_deg) / 2) * fill * (1.0 - top_band)
    tx = np.tan(np.radians(fovy_deg) / 2) * fill * aspect
    # A point at depth (distance + z) is inside when |x| <= tx (distance + z) and |y| <= ty (distance + z).
    distance = float(max(np.max(np.abs(x) / tx - z), np.max(np.abs(y) / ty - z), MIN_DISTANCE_M))
    shift = top_band * np.tan(np.radians(fovy_deg) / 2) * distance
    return View(lookat + shift * up, distance, float(azimuth), float(elevation))
