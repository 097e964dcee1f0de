"""An exact linear pushbroom satellite camera in a local east/north/up frame.

The synthetic scenes of ``satsweep synth`` are imaged by this camera, and their RPCs are fitted to
it. The model (Gupta and Hartley's linear pushbroom) is:

* The satellite moves along a straight line at constant speed, ``S(row) = center +
  (row - row0) * line_step_m * velocity``, where ``velocity`` is a horizontal unit vector (the
  orbit heading) and ``row`` is the image row: one row is acquired per ``line_step_m`` metres of
  travel. ``center`` is where the satellite is when it images the target point (the scene
  centre), at ``row0``.
* The attitude is constant. The line sensor sees the *view plane* spanned by the boresight ``b``
  (unit vector from the satellite to the target at ``row0``) and the sensor direction ``s``
  (unit, perpendicular to ``b`` and to ``velocity``). The view plane moves with the satellite, so
  a ground point is imaged at the row when it lies in it: ``plane_normal . (X - S(row)) = 0``,
  which is linear in ``row``: the row is closed-form.
* Within the row, the column is a central projection: ``col = col0 + focal_px * (s . D) / (b . D)``
  with ``D = X - S(row)``.

Coordinates: ENU metres (``e``, ``n``, ``u``) of a ``satsweep.geo.ENUFrame``; pixel (0, 0) is the
centre of the first pixel; ``col`` grows along ``s``, ``row`` grows with time. With ``s =
velocity x b`` the images are not mirrored (a descending orbit gives north-up images).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from satsweep.errors import CameraError

# Largest off-nadir angle accepted: beyond it the view is too grazing for a scene-sized camera.
MAX_OFF_NADIR_DEG = 45.0


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _vec3(name: str, value: Any) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise CameraError(f"PushbroomCamera.{name} = {value!r}: need 3 finite numbers")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclasses.dataclass(frozen=True)
class PushbroomCamera:
    """A linear pushbroom camera (see the module docstring). ENU metres, pixels, unit vectors."""

    center: tuple[float, float, float]  # satellite position (ENU m) when row0 is acquired
    velocity: tuple[float, float, float]  # unit horizontal direction of travel
    boresight: tuple[float, float, float]  # unit vector from `center` towards the target
    sensor_dir: tuple[float, float, float]  # unit vector along the sensor line (col grows)
    line_step_m: float  # satellite travel per image row (m); also the along-track GSD
    focal_px: float  # focal length in pixels
    col0: float  # column of the boresight
    row0: float  # row at which the satellite is at `center`
    width: int  # image width in pixels
    height: int  # image height in pixels

    def __post_init__(self) -> None:
        for name in ("center", "velocity", "boresight", "sensor_dir"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        for name in ("line_step_m", "focal_px", "col0", "row0"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise CameraError(f"PushbroomCamera.{name} = {v!r}: must be finite")
            object.__setattr__(self, name, v)
        if not (self.line_step_m > 0.0 and self.focal_px > 0.0):
            raise CameraError("PushbroomCamera: line_step_m and focal_px must be > 0")
        if not (int(self.width) >= 1 and int(self.height) >= 1):
            raise CameraError(f"PushbroomCamera: image size {self.width}x{self.height} is empty")
        b, s, v = (np.array(x) for x in (self.boresight, self.sensor_dir, self.velocity))
        for name, x in (("boresight", b), ("sensor_dir", s), ("velocity", v)):
            if abs(np.linalg.norm(x) - 1.0) > 1e-9:
                raise CameraError(f"PushbroomCamera.{name} = {tuple(x)}: must be a unit vector")
        if abs(b @ s) > 1e-9 or abs(s @ v) > 1e-9:
            raise CameraError("PushbroomCamera: sensor_dir must be perpendicular to boresight and velocity")
        if abs(self._normal @ v) < 1e-6:
            raise CameraError("PushbroomCamera: the view plane contains the direction of travel")

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_angles(
        cls,
        *,
        off_nadir_deg: float,
        azimuth_deg: float,
        orbit_azimuth_deg: float,
        orbit_height_m: float,
        gsd_m: float,
        width: int,
        height: int,
        target: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> "PushbroomCamera":
        """A camera that sees ``target`` (ENU m) at the image centre.

        ``off_nadir_deg``: angle between the vertical and the line of sight at the target (equal
        to the off-nadir angle at the satellite in this flat-orbit model); ``azimuth_deg``: azimuth
        of the satellite seen from the target, clockwise from north; ``orbit_azimuth_deg``:
        heading of the satellite's motion, clockwise from north; ``orbit_height_m``: height of
        the orbit line above the target. ``gsd_m``: ground sample distance at the target on the
        horizontal plane, along-track (``line_step_m``) and across-track (``focal_px`` is set so
        that one column spans ``gsd_m`` there).
        """
        if not 0.0 <= off_nadir_deg <= MAX_OFF_NADIR_DEG:
            raise CameraError(f"off_nadir_deg = {off_nadir_deg!r}: must lie in [0, {MAX_OFF_NADIR_DEG:g}]")
        if not (orbit_height_m > 0.0 and gsd_m > 0.0):
            raise CameraError("orbit_height_m and gsd_m must be > 0")
        th, az, hd = (math.radians(x) for x in (off_nadir_deg, azimuth_deg, orbit_azimuth_deg))
        to_sat = np.array([math.sin(th) * math.sin(az), math.sin(th) * math.cos(az), math.cos(th)])
        slant = orbit_height_m / math.cos(th)
        tgt = np.asarray(target, dtype=np.float64)
        center = tgt + slant * to_sat
        b = -to_sat
        v = np.array([math.sin(hd), math.cos(hd), 0.0])
        s = _unit(np.cross(v, b))
        # d(ground point)/d(tan angle) on the horizontal plane through the target, across-track.
        ground_per_unit = slant * np.linalg.norm(s - (s[2] / b[2]) * b)
        return cls(
            center=tuple(center), velocity=tuple(v), boresight=tuple(b), sensor_dir=tuple(s),
            line_step_m=gsd_m, focal_px=ground_per_unit / gsd_m,
            col0=(width - 1) / 2.0, row0=(height - 1) / 2.0, width=int(width), height=int(height),
        )

    # -- derived quantities ----------------------------------------------------------------
    @property
    def _normal(self) -> np.ndarray:
        """Unit normal of the view plane (spanned by boresight and sensor_dir)."""
        return _unit(np.cross(np.array(self.boresight), np.array(self.sensor_dir)))

    def position(self, *, row) -> np.ndarray:
        """Satellite position (ENU m, shape (..., 3)) when image row ``row`` is acquired."""
        row = np.asarray(row, dtype=np.float64)
        step = (row - self.row0) * self.line_step_m
        return np.asarray(self.center) + step[..., None] * np.asarray(self.velocity)

    # -- projection ------------------------------------------------------------------------
    def project(self, *, e, n, u) -> tuple[np.ndarray, np.ndarray]:
        """ENU point(s) (m) -> (col, row) pixels, exactly (closed form). Inputs broadcast."""
        e, n, u = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (e, n, u)))
        c = self.center
        dx, dy, dz = e - c[0], n - c[1], u - c[2]
        nv = self._normal
        vel = self.velocity
        travel = (nv[0] * dx + nv[1] * dy + nv[2] * dz) / float(nv @ np.asarray(vel))
        row = self.row0 + travel / self.line_step_m
        # D = X - S(row) = (X - center) - travel * velocity
        dx, dy, dz = dx - travel * vel[0], dy - travel * vel[1], dz - travel * vel[2]
        b, s = self.boresight, self.sensor_dir
        along = s[0] * dx + s[1] * dy + s[2] * dz
        depth = b[0] * dx + b[1] * dy + b[2] * dz
        col = self.col0 + self.focal_px * along / depth
        return col, row

    def ray(self, *, col, row) -> tuple[np.ndarray, np.ndarray]:
        """Line of sight of pixel position(s): (origin, unit direction), each of shape (..., 3).

        The origin is the satellite position at ``row``; points ``origin + t * direction``
        (t > 0) project exactly to (col, row).
        """
        col, row = np.broadcast_arrays(np.asarray(col, np.float64), np.asarray(row, np.float64))
        origin = self.position(row=row)
        tan = (col - self.col0) / self.focal_px
        d = np.asarray(self.boresight) + tan[..., None] * np.asarray(self.sensor_dir)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return origin, d

    def ground_point(self, *, col, row, u) -> tuple[np.ndarray, np.ndarray]:
        """(e, n) where the line of sight of (col, row) crosses the horizontal plane ``u``."""
        origin, d = self.ray(col=col, row=row)
        t = (np.asarray(u, np.float64) - origin[..., 2]) / d[..., 2]
        return origin[..., 0] + t * d[..., 0], origin[..., 1] + t * d[..., 1]

    # -- viewing geometry ------------------------------------------------------------------
    def viewing_angles(self, *, target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[float, float]:
        """(off-nadir / incidence angle, satellite azimuth) in degrees of the view of ``target``."""
        col, row = self.project(e=target[0], n=target[1], u=target[2])
        w = self.position(row=row) - np.asarray(target)
        w = w / np.linalg.norm(w)
        incidence = math.degrees(math.acos(min(1.0, max(-1.0, float(w[2])))))
        azimuth = math.degrees(math.atan2(float(w[0]), float(w[1]))) % 360.0
        return incidence, azimuth

    def parallax(self, *, target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
        """Horizontal vector (satellite - target)_h / height of the view of ``target``.

        The base-to-height ratio of two views is the norm of the difference of their parallax
        vectors (the same definition as ``satsweep.viewselect.b_over_h``).
        """
        col, row = self.project(e=target[0], n=target[1], u=target[2])
        w = self.position(row=row) - np.asarray(target)
        return w[:2] / w[2]

    # -- serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict; ``from_dict`` restores the camera exactly (floats are kept as floats)."""
        d = dataclasses.asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "PushbroomCamera":
        """Inverse of ``to_dict``; CameraError for missing or unknown keys."""
        names = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, Mapping) or set(d) != names:
            got = sorted(d) if isinstance(d, Mapping) else type(d).__name__
            raise CameraError(f"pushbroom camera dict: expected keys {sorted(names)}, got {got}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def base_to_height(a: PushbroomCamera, b: PushbroomCamera, *,
                   target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> float:
    """Base-to-height ratio of two views of ``target``: |parallax(a) - parallax(b)|."""
    return float(np.linalg.norm(a.parallax(target=target) - b.parallax(target=target)))
