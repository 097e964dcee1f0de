"""RPC (rational polynomial coefficients) camera model: projection and localization.

Conventions
-----------
* Image coordinates are ``(col, row)`` = ``(x, y)`` in pixels; pixel ``(0, 0)`` is the *centre* of
  the first (top-left) pixel, so the image covers ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.
  This is the convention of rpcm, S2P and GDAL's RPC TIFF tag; no half-pixel shift is applied.
* Ground coordinates are longitude and latitude in degrees (WGS84) and altitude in metres above
  the WGS84 ellipsoid, always passed by keyword (``lon=``, ``lat=``, ``alt=``) to avoid order traps.
* The four cubic polynomials use the RPC00B term order (NITF STDI-0002) of the monomials of the
  normalised ``P`` = latitude, ``L`` = longitude, ``H`` = altitude::

      1, L, P, H, LP, LH, PH, L^2, P^2, H^2, PLH, L^3, LP^2, LH^2, L^2P, P^3, PH^2, L^2H, P^2H, H^3

  and ``col = col_num(P, L, H) / col_den(P, L, H) * col_scale + col_offset`` (same for ``row``),
  with ``P = (lat - lat_offset) / lat_scale`` and so on.
* Everything is float64. A model is immutable; ``cropped`` returns a new one.

Readers and writers of the file formats are in :mod:`satsweep.geometry.rpc_formats`
(``RPCModel.from_file`` and ``RPCModel.from_image`` detect the format from the content).

Crops: an RPC whose crop offset was folded into the polynomials (LINE_OFF/SAMP_OFF still hold the
full-scene values) needs no special handling, the model is evaluated as stored; ``cropped(x0=,
y0=)`` shifts the offsets for a further crop ``image[y0:, x0:]``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from satsweep.errors import LocalizationError, RPCError

TIFF_TAG_RPC = 50844  # RPCCoefficientTag (GDAL / NITF RPC00B in a TIFF)
N_TERMS = 20  # monomials of a cubic polynomial in 3 variables
N_TAG_VALUES = 92  # 12 scalars + 4 x 20 coefficients

# Points processed at once by projection/localization: bounds the (20, n) monomial matrix to
# ~10 MB and keeps it in cache-friendly blocks.
_CHUNK = 1 << 16

# GDAL key names of the 12 scalars, in tag order, with the attribute names.
_SCALARS: tuple[tuple[str, str], ...] = (
    ("ERR_BIAS", "err_bias"),
    ("ERR_RAND", "err_rand"),
    ("LINE_OFF", "row_offset"),
    ("SAMP_OFF", "col_offset"),
    ("LAT_OFF", "lat_offset"),
    ("LONG_OFF", "lon_offset"),
    ("HEIGHT_OFF", "alt_offset"),
    ("LINE_SCALE", "row_scale"),
    ("SAMP_SCALE", "col_scale"),
    ("LAT_SCALE", "lat_scale"),
    ("LONG_SCALE", "lon_scale"),
    ("HEIGHT_SCALE", "alt_scale"),
)
# GDAL key names of the 4 coefficient vectors, in tag order, with the attribute names.
_POLYS: tuple[tuple[str, str], ...] = (
    ("LINE_NUM_COEFF", "row_num"),
    ("LINE_DEN_COEFF", "row_den"),
    ("SAMP_NUM_COEFF", "col_num"),
    ("SAMP_DEN_COEFF", "col_den"),
)
_OPTIONAL_KEYS = ("ERR_BIAS", "ERR_RAND")  # -1 (unknown) when a file does not give them
_UNKNOWN_ERR = -1.0


# ---------------------------------------------------------------------------------------------
# Polynomial algebra
# ---------------------------------------------------------------------------------------------
def _monomials(lon_n: np.ndarray, lat_n: np.ndarray, alt_n: np.ndarray) -> np.ndarray:
    """The 20 RPC00B monomials of normalised (L, P, H) = (lon, lat, alt), as a (20, n) array."""
    L, P, H = lon_n, lat_n, alt_n
    m = np.empty((N_TERMS, L.size))
    m[0] = 1.0
    m[1] = L
    m[2] = P
    m[3] = H
    np.multiply(L, P, out=m[4])
    np.multiply(L, H, out=m[5])
    np.multiply(P, H, out=m[6])
    np.multiply(L, L, out=m[7])
    np.multiply(P, P, out=m[8])
    np.multiply(H, H, out=m[9])
    np.multiply(m[4], H, out=m[10])  # PLH
    np.multiply(m[7], L, out=m[11])  # L^3
    np.multiply(m[8], L, out=m[12])  # LP^2
    np.multiply(m[9], L, out=m[13])  # LH^2
    np.multiply(m[7], P, out=m[14])  # L^2P
    np.multiply(m[8], P, out=m[15])  # P^3
    np.multiply(m[9], P, out=m[16])  # PH^2
    np.multiply(m[7], H, out=m[17])  # L^2H
    np.multiply(m[8], H, out=m[18])  # P^2H
    np.multiply(m[9], H, out=m[19])  # H^3
    return m


def _derivative_matrices() -> tuple[np.ndarray, np.ndarray]:
    """(D_L, D_P): d(monomial k)/dL = sum_j D_L[k, j] * monomial j (same for P).

    Every derivative of an RPC00B monomial is a multiple of another RPC00B monomial, so the
    derivative of a polynomial with coefficients ``c`` has coefficients ``c @ D``.
    """
    d_l = np.zeros((N_TERMS, N_TERMS))
    d_p = np.zeros((N_TERMS, N_TERMS))
    # (monomial, factor, derivative monomial) with indices of the RPC00B order.
    for k, f, j in ((1, 1, 0), (4, 1, 2), (5, 1, 3), (7, 2, 1), (10, 1, 6), (11, 3, 7),
                    (12, 1, 8), (13, 1, 9), (14, 2, 4), (17, 2, 5)):
        d_l[k, j] = f
    for k, f, j in ((2, 1, 0), (4, 1, 1), (6, 1, 3), (8, 2, 2), (10, 1, 5), (12, 2, 4),
                    (14, 1, 7), (15, 3, 8), (16, 1, 9), (18, 2, 6)):
        d_p[k, j] = f
    return d_l, d_p


_D_LON, _D_LAT = _derivative_matrices()


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _out(a: np.ndarray) -> np.ndarray:
    """0-d arrays become numpy float64 scalars; other arrays are returned as they are."""
    return a[()] if a.ndim == 0 else a


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------
class RPCModel:
    """An RPC00B camera model (immutable, float64). See the module docstring for conventions."""

    __slots__ = ("row_num", "row_den", "col_num", "col_den",
                 "row_offset", "col_offset", "lat_offset", "lon_offset", "alt_offset",
                 "row_scale", "col_scale", "lat_scale", "lon_scale", "alt_scale",
                 "err_bias", "err_rand", "source", "_proj", "_loc")

    def __init__(self, *, row_num: Sequence[float], row_den: Sequence[float],
                 col_num: Sequence[float], col_den: Sequence[float],
                 row_offset: float, col_offset: float, lat_offset: float, lon_offset: float,
                 alt_offset: float, row_scale: float, col_scale: float, lat_scale: float,
                 lon_scale: float, alt_scale: float, err_bias: float = 0.0,
                 err_rand: float = 0.0, source: str | os.PathLike | None = None):
        """Build from the 4 x 20 coefficients (RPC00B order) and the offsets and scales.

        Offsets/scales are in pixels (row/col), degrees (lat/lon) and metres (alt). ``source``
        (a file name, for messages) is kept as a string. Raises RPCError naming ``source`` when a
        coefficient vector does not hold 20 finite numbers, a denominator is all zeros, a value
        is not finite, or a scale is zero.
        """
        src = None if source is None else os.fspath(source)
        set_ = object.__setattr__
        set_(self, "source", src)
        polys = {"row_num": row_num, "row_den": row_den, "col_num": col_num, "col_den": col_den}
        for name, values in polys.items():
            try:
                arr = np.array(values, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise RPCError(src, f"{name} is not a list of numbers ({exc})") from None
            if arr.size != N_TERMS:
                raise RPCError(src, f"{name} has {arr.size} coefficients, expected {N_TERMS}")
            if not np.all(np.isfinite(arr)):
                raise RPCError(src, f"{name} holds non-finite coefficients")
            if name.endswith("_den") and not np.any(arr):
                raise RPCError(src, f"{name} is all zeros: the RPC divides by zero")
            set_(self, name, _readonly(arr))
        scalars = {"row_offset": row_offset, "col_offset": col_offset, "lat_offset": lat_offset,
                   "lon_offset": lon_offset, "alt_offset": alt_offset, "row_scale": row_scale,
                   "col_scale": col_scale, "lat_scale": lat_scale, "lon_scale": lon_scale,
                   "alt_scale": alt_scale, "err_bias": err_bias, "err_rand": err_rand}
        for name, value in scalars.items():
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise RPCError(src, f"{name} = {value!r} is not a number") from None
            if not math.isfinite(v):
                raise RPCError(src, f"{name} = {v} is not finite")
            if name.endswith("_scale") and v == 0.0:
                raise RPCError(src, f"{name} is zero")
            set_(self, name, v)
        # Projection rows: col_num, col_den, row_num, row_den; localization adds d/dL and d/dP.
        proj = np.stack([self.col_num, self.col_den, self.row_num, self.row_den])
        set_(self, "_proj", _readonly(proj))
        set_(self, "_loc", _readonly(np.concatenate([proj, proj @ _D_LON, proj @ _D_LAT])))

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"RPCModel is immutable (cannot set {name})")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"RPCModel is immutable (cannot delete {name})")

    def __eq__(self, other: object) -> bool:
        """Exact equality of every number (the source is not compared)."""
        if not isinstance(other, RPCModel):
            return NotImplemented
        return bool(np.array_equal(self.to_tag_values(), other.to_tag_values()))

    def __hash__(self) -> int:
        return hash(self.to_tag_values().tobytes())

    def __repr__(self) -> str:
        return (f"RPCModel(source={self.source!r}, col_offset={self.col_offset!r}, "
                f"row_offset={self.row_offset!r}, lon_offset={self.lon_offset!r}, "
                f"lat_offset={self.lat_offset!r}, alt_offset={self.alt_offset!r})")

    def __reduce__(self):
        return (_from_dict_pickle, (self.to_dict(),))

    # -- evaluation ----------------------------------------------------------------------------
    def projection(self, *, lon: Any, lat: Any, alt: Any) -> tuple[np.ndarray, np.ndarray]:
        """Ground -> image: (lon, lat in degrees, alt in metres) -> (col, row) in pixels.

        Inputs broadcast together; outputs have the broadcast shape (numpy float64 scalars for
        scalar inputs). Pixel (0, 0) is the centre of the first pixel.
        """
        lon_b, lat_b, alt_b = np.broadcast_arrays(np.asarray(lon, dtype=np.float64),
                                                  np.asarray(lat, dtype=np.float64),
                                                  np.asarray(alt, dtype=np.float64))
        shape = lon_b.shape
        lon_f, lat_f, alt_f = (a.reshape(-1) for a in (lon_b, lat_b, alt_b))
        col = np.empty(lon_f.size)
        row = np.empty(lon_f.size)
        for s in range(0, lon_f.size, _CHUNK):
            e = min(s + _CHUNK, lon_f.size)
            m = _monomials((lon_f[s:e] - self.lon_offset) / self.lon_scale,
                           (lat_f[s:e] - self.lat_offset) / self.lat_scale,
                           (alt_f[s:e] - self.alt_offset) / self.alt_scale)
            v = self._proj @ m
            col[s:e] = v[0] / v[1] * self.col_scale + self.col_offset
            row[s:e] = v[2] / v[3] * self.row_scale + self.row_offset
        return _out(col.reshape(shape)), _out(row.reshape(shape))

    def localization(self, *, col: Any, row: Any, alt: Any, tol_px: float = 1e-6,
                     max_iter: int = 50) -> tuple[np.ndarray, np.ndarray]:
        """Image + altitude -> ground: (col, row in pixels, alt in metres) -> (lon, lat) degrees.

        Inverts ``projection`` at the given altitude by damped Newton iterations with the
        analytic Jacobian, started from the normalised ground origin, until the reprojection of
        every point is within ``tol_px`` pixels of (col, row). Inputs broadcast together.
        Raises LocalizationError for non-finite input, or when some point does not converge
        within ``max_iter`` iterations (singular Jacobian, point far outside the model domain).
        """
        if not (tol_px > 0.0) or int(max_iter) < 1:
            raise ValueError(f"localization needs tol_px > 0 and max_iter >= 1, got "
                             f"tol_px={tol_px!r}, max_iter={max_iter!r}")
        col_b, row_b, alt_b = np.broadcast_arrays(np.asarray(col, dtype=np.float64),
                                                  np.asarray(row, dtype=np.float64),
                                                  np.asarray(alt, dtype=np.float64))
        shape = col_b.shape
        col_f, row_f, alt_f = (a.reshape(-1) for a in (col_b, row_b, alt_b))
        bad = ~(np.isfinite(col_f) & np.isfinite(row_f) & np.isfinite(alt_f))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise LocalizationError(
                f"RPC localization ({self.source or 'RPC model'}): {int(bad.sum())} of "
                f"{col_f.size} input points are not finite (first: col={col_f[i]}, "
                f"row={row_f[i]}, alt={alt_f[i]})")
        lon = np.empty(col_f.size)
        lat = np.empty(col_f.size)
        for s in range(0, col_f.size, _CHUNK):
            e = min(s + _CHUNK, col_f.size)
            lon[s:e], lat[s:e] = self._localize_chunk(col_f[s:e], row_f[s:e], alt_f[s:e],
                                                      float(tol_px), int(max_iter))
        return _out(lon.reshape(shape)), _out(lat.reshape(shape))

    def _residual_and_jacobian(self, x: np.ndarray, y: np.ndarray, h: np.ndarray,
                               col_t: np.ndarray, row_t: np.ndarray):
        """Residuals (pixels) and Jacobian (pixels per normalised unit) at normalised (L, P, H)."""
        v = self._loc @ _monomials(x, y, h)
        cn, cd, rn, rd = v[0], v[1], v[2], v[3]
        cn_l, cd_l, rn_l, rd_l = v[4], v[5], v[6], v[7]
        cn_p, cd_p, rn_p, rd_p = v[8], v[9], v[10], v[11]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            rc = cn / cd * self.col_scale + self.col_offset - col_t
            rr = rn / rd * self.row_scale + self.row_offset - row_t
            kc = self.col_scale / (cd * cd)
            kr = self.row_scale / (rd * rd)
            a = (cn_l * cd - cn * cd_l) * kc  # dcol/dL
            b = (cn_p * cd - cn * cd_p) * kc  # dcol/dP
            c = (rn_l * rd - rn * rd_l) * kr  # drow/dL
            d = (rn_p * rd - rn * rd_p) * kr  # drow/dP
        return rc, rr, a, b, c, d

    def _localize_chunk(self, col_t: np.ndarray, row_t: np.ndarray, alt: np.ndarray,
                        tol_px: float, max_iter: int) -> tuple[np.ndarray, np.ndarray]:
        """Damped Newton on one chunk; returns (lon, lat) in degrees or raises."""
        n = col_t.size
        h = (alt - self.alt_offset) / self.alt_scale
        x = np.zeros(n)  # normalised lon of the current iterate
        y = np.zeros(n)  # normalised lat
        best_x = np.zeros(n)  # last accepted iterate, its residual norm and Newton step
        best_y = np.zeros(n)
        best_norm = np.full(n, np.inf)
        step_x = np.zeros(n)
        step_y = np.zeros(n)
        lam = np.ones(n)  # step length factor: halved on a rejected step, doubled on success
        done = np.zeros(n, dtype=bool)
        singular = np.zeros(n, dtype=bool)
        last_norm = np.full(n, np.inf)
        idx = np.arange(n)
        for _ in range(max_iter + 1):
            if idx.size == 0:
                break
            rc, rr, a, b, c, d = self._residual_and_jacobian(
                x[idx], y[idx], h[idx], col_t[idx], row_t[idx])
            norm = np.hypot(rc, rr)
            last_norm[idx] = norm
            conv = norm <= tol_px
            done[idx[conv]] = True
            # Rejected steps (worse or non-finite residual): retry a shorter step from the last
            # accepted iterate. Accepted: take a new Newton step.
            worse = ~conv & ~(norm < best_norm[idx])
            ok = ~conv & ~worse
            iw = idx[worse]
            lam[iw] *= 0.5
            x[iw] = best_x[iw] + lam[iw] * step_x[iw]
            y[iw] = best_y[iw] + lam[iw] * step_y[iw]
            io = idx[ok]
            a, b, c, d, rc, rr = a[ok], b[ok], c[ok], d[ok], rc[ok], rr[ok]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                det = a * d - b * c
                sx = -(d * rc - b * rr) / det
                sy = -(a * rr - c * rc) / det
            sing = ~(np.isfinite(sx) & np.isfinite(sy))
            singular[io[sing]] = True
            keep = ~sing
            io, sx, sy = io[keep], sx[keep], sy[keep]
            best_x[io] = x[io]
            best_y[io] = y[io]
            best_norm[io] = norm[ok][keep]
            step_x[io] = sx
            step_y[io] = sy
            lam[io] = np.minimum(1.0, 2.0 * lam[io])
            x[io] += lam[io] * sx
            y[io] += lam[io] * sy
            idx = idx[~conv]
            idx = idx[~singular[idx]]
        if not done.all():
            fail = np.flatnonzero(~done)
            i = int(fail[0])
            why = ("singular Jacobian" if singular[i] else
                   f"residual {last_norm[i]:.3g} px > {tol_px:g} px after {max_iter} iterations")
            raise LocalizationError(
                f"RPC localization ({self.source or 'RPC model'}) did not converge for "
                f"{fail.size} of {n} points (first: col={col_t[i]}, row={row_t[i]}, "
                f"alt={alt[i]}: {why})")
        return x * self.lon_scale + self.lon_offset, y * self.lat_scale + self.lat_offset

    def footprint(self, *, width: int, height: int, alt: float) -> tuple[np.ndarray, np.ndarray]:
        """(lon, lat) of the 4 outer image corners at altitude ``alt`` (metres).

        Order: top-left, top-right, bottom-right, bottom-left; the corners are pixel edges,
        (-0.5, -0.5) to (width - 0.5, height - 0.5), since pixel (0, 0) is a pixel centre.
        """
        cols = np.array([-0.5, width - 0.5, width - 0.5, -0.5])
        rows = np.array([-0.5, -0.5, height - 0.5, height - 0.5])
        return self.localization(col=cols, row=rows, alt=alt)

    # -- derived models ------------------------------------------------------------------------
    def cropped(self, *, x0: float, y0: float) -> "RPCModel":
        """The RPC of ``image[y0:, x0:]``: projections are those of this model minus (x0, y0)."""
        src = None if self.source is None else f"{self.source} [crop x0={x0}, y0={y0}]"
        return self._replace(col_offset=self.col_offset - float(x0),
                             row_offset=self.row_offset - float(y0), source=src)

    def corrected(self, shift: Sequence[float]) -> "RPCModel":
        """The RPC of an image whose content of ground point X lies at this model's projection
        of X plus ``shift`` = (col, row) pixels: a pointing correction (the sparse stage's
        ``corrections_px``) folded into the offsets, exactly."""
        dc, dr = (float(v) for v in shift)
        src = (None if self.source is None
               else f"{self.source} [corrected by {dc:+.4f}, {dr:+.4f} px]")
        return self._replace(col_offset=self.col_offset + dc, row_offset=self.row_offset + dr,
                             source=src)

    def _replace(self, **changes: Any) -> "RPCModel":
        kw = self._kwargs()
        kw.update(changes)
        return RPCModel(**kw)

    def _kwargs(self) -> dict[str, Any]:
        kw: dict[str, Any] = {name: getattr(self, name) for _, name in _POLYS}
        kw.update({name: getattr(self, name) for _, name in _SCALARS})
        kw["source"] = self.source
        return kw

    # -- serialisation -------------------------------------------------------------------------
    def to_tag_values(self) -> np.ndarray:
        """The 92 doubles of TIFF tag 50844, in GDAL/RPC00B order (see the module docstring)."""
        return np.concatenate([[getattr(self, name) for _, name in _SCALARS]]
                              + [getattr(self, name) for _, name in _POLYS])

    @classmethod
    def from_tag_values(cls, values: Sequence[float], *,
                        source: str | os.PathLike | None = None) -> "RPCModel":
        """Build from the 92 doubles of TIFF tag 50844; RPCError naming ``source`` otherwise."""
        try:
            v = np.asarray(values, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise RPCError(source, f"RPC tag values are not numbers ({exc})") from None
        if v.size != N_TAG_VALUES:
            raise RPCError(source, f"RPC tag {TIFF_TAG_RPC} holds {v.size} values, "
                                   f"expected {N_TAG_VALUES}")
        fields: dict[str, Any] = {key: float(v[i]) for i, (key, _) in enumerate(_SCALARS)}
        for i, (key, _) in enumerate(_POLYS):
            s = len(_SCALARS) + N_TERMS * i
            fields[key] = v[s:s + N_TERMS]
        from satsweep.geometry.rpc_formats import _model_from_fields  # noqa: PLC0415 (it imports this module)

        return _model_from_fields(source, fields)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (keys = constructor arguments); ``from_dict`` restores it exactly."""
        d: dict[str, Any] = {}
        for key, value in self._kwargs().items():
            d[key] = value.tolist() if isinstance(value, np.ndarray) else value
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "RPCModel":
        """Inverse of ``to_dict``; RPCError for missing or unknown keys."""
        names = {name for _, name in _SCALARS} | {name for _, name in _POLYS} | {"source"}
        src = d.get("source") if isinstance(d, Mapping) else None
        if not isinstance(d, Mapping):
            raise RPCError(None, f"RPC dict expected, got {type(d).__name__}")
        unknown = sorted(set(d) - names)
        if unknown:
            raise RPCError(src, f"unknown RPC dict key(s): {', '.join(map(str, unknown))}")
        required = names - {"source", "err_bias", "err_rand"}
        missing = sorted(required - set(d))
        if missing:
            raise RPCError(src, f"RPC dict lacks key(s): {', '.join(missing)}")
        return cls(**dict(d))

    # -- reading -------------------------------------------------------------------------------
    @classmethod
    def from_file(cls, path: str | os.PathLike) -> "RPCModel":
        """Read an RPC file, detecting the format from its content (see the module docstring).

        A TIFF is read as by ``from_image`` (tag 50844, else a sidecar). Raises RPCError naming
        the file for an unreadable file, an unknown format, a missing key or a non-numeric value.
        """
        from satsweep.geometry.rpc_formats import _TIFF_MAGICS, _parse_rpc_bytes  # noqa: PLC0415

        path = Path(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise RPCError(path, f"cannot read RPC file ({exc.strerror or exc})") from None
        if data[:4] in _TIFF_MAGICS:
            return cls.from_image(path)
        return _parse_rpc_bytes(path, data)

    @classmethod
    def from_image(cls, path: str | os.PathLike) -> "RPCModel":
        """The RPC of a TIFF image: tag 50844, else a sidecar beside it.

        Sidecars, in this order, matched case-insensitively: ``IMG_RPC.TXT``, ``IMG.RPB``,
        ``IMG.XML``, ``IMG_RPC.XML``, ``IMG.tif.aux.xml`` (GDAL PAM), where ``IMG.tif`` is the
        image; then, as GDAL does for Airbus DIMAP deliveries, ``RPC_X.XML`` for an image
        ``IMG_X.tif`` or a tile of it ``IMG_X_RiCj.tif`` (placed in the scene by ``DIM_X.XML``:
        ``rpc_formats.dimap_rpc_by_rule``). XML sidecars that hold no RPC are passed over. Of a
        tiled product's DIM or TIL file (``satsweep.io.products``), the product's RPC.
        Raises ImageFormatError for a missing, non-TIFF or truncated image, RPCError when no RPC
        is found or a sidecar is bad.
        """
        from satsweep.geometry.rpc_formats import (  # noqa: PLC0415
            _NotAnRPC, _read_tiff_rpc_tag, dimap_names, dimap_rpc_by_rule)
        from satsweep.io.products import tiled_product  # noqa: PLC0415

        path = Path(path)
        product = tiled_product(path)
        if product is not None:  # a tiled product's file: the product's RPC, of its scene
            rpc_path = product.rpc_path  # (looked for in the folder on each access)
            if rpc_path is None:
                raise RPCError(path, f"no RPC: the {product.kind}'s RPC file "
                                     f"({product.rpc_names}) is not beside it")
            return cls.from_file(rpc_path)
        values = _read_tiff_rpc_tag(path)
        if values is not None:
            return cls.from_tag_values(values, source=path)
        stem = path.stem.lower()
        wanted = [f"{stem}_rpc.txt", f"{stem}.rpb", f"{stem}.xml", f"{stem}_rpc.xml",
                  f"{path.name.lower()}.aux.xml"]
        try:
            names = {p.name.lower(): p for p in path.parent.iterdir() if p.is_file()}
        except OSError as exc:
            raise RPCError(path, f"cannot list the image folder for RPC sidecars ({exc})") from None
        passed_over = []
        for want in wanted:
            side = names.get(want)
            if side is None:
                continue
            try:
                return cls.from_file(side)
            except _NotAnRPC as exc:
                if not want.endswith(".xml"):
                    raise
                passed_over.append(f"{side.name}: {exc.problem}")
        model = dimap_rpc_by_rule(path, names)
        if model is not None:
            return model
        looked = ", ".join([w.replace(stem, path.stem, 1) for w in wanted]
                           + [n.upper() for n in dimap_names(path, "rpc")])
        extra = f"; passed over {'; '.join(passed_over)}" if passed_over else ""
        raise RPCError(path, f"no RPC found: no TIFF tag {TIFF_TAG_RPC} and no sidecar "
                             f"(looked for {looked}, case-insensitive){extra}")


def _from_dict_pickle(d: dict[str, Any]) -> RPCModel:
    return RPCModel.from_dict(d)
