"""Least-squares fit of an RPC00B model to ground <-> image correspondences.

``fit_rpc`` fits the third-order rational polynomial camera (RPC00B term order) that maps
(lon, lat, alt) to (col, row), given samples of an exact camera over a ground cube. It is how
``satsweep synth`` turns its pushbroom cameras into the RPCs written beside the images, and how
any other physical camera can be turned into an RPC.

Method (the "terrain-independent" RPC fit of Tao and Hu, 2001):

* Normalisation: offsets are the mid-ranges and scales the half-ranges of the samples, so the
  normalised coordinates lie in [-1, 1].
* For each image coordinate ``y`` (normalised col or row), ``y = num(T) / den(T)`` with ``den[0] =
  1`` is linearised as ``num(T) - y * (den(T) - 1) = y``: linear in the 39 unknowns. It is solved
  by least squares (SVD, ``numpy.linalg.lstsq``) with unit-norm columns, then re-solved a few
  times with each equation weighted by ``1 / den`` of the previous solution, which makes the
  minimised quantity the actual image residual ``num/den - y`` rather than ``den`` times it.
* The result is rejected (CameraError) when a denominator comes close to zero at a sample.

The residual is reported as image distances (pixels) between the fitted model and the samples.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from satsweep.errors import CameraError
from satsweep.geometry.rpc import RPCModel

# Number of RPC00B terms (monomials of a cubic in 3 variables) and unknowns per image coordinate.
N_TERMS = 20
N_UNKNOWNS = 2 * N_TERMS - 1  # numerator (20) + denominator without its constant term (19)

# A fit with fewer samples than this many times the unknowns is refused: it would interpolate
# the samples rather than fit the camera.
MIN_SAMPLES_PER_UNKNOWN = 2

# Reweighting rounds after the first linear solution (Tao & Hu's iterative weighting).
DEFAULT_REWEIGHT_ITERATIONS = 2

# Weight of the ridge (Tikhonov) rows pulling each denominator coefficient towards 0, per unit
# of RMS equation weight. A near-affine coordinate (the row of a pushbroom camera) is matched
# equally well by a whole family of (num, den) pairs sharing a factor; the ridge picks the one
# with den close to 1, which behaves well outside the cube. It is small enough not to change
# the residual of a genuinely rational fit measurably (tested to 1e-6 px).
DENOMINATOR_RIDGE = 1e-7

# A fitted denominator smaller than this at a sample means a pole inside the fitted cube.
MIN_DENOMINATOR = 0.1


@dataclasses.dataclass(frozen=True)
class RPCFitResidual:
    """Image-space residual of an RPC against reference samples, in pixels."""

    max_px: float  # largest distance |(col, row)_rpc - (col, row)_ref| over the samples
    rms_px: float  # root mean square of that distance
    max_col_px: float  # largest |col_rpc - col_ref|
    max_row_px: float  # largest |row_rpc - row_ref|
    n_points: int  # number of samples

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def rpc00b_terms(*, lon_n, lat_n, alt_n) -> np.ndarray:
    """The 20 RPC00B monomials of normalised L (lon), P (lat), H (alt), as an (n, 20) array.

    Order: 1, L, P, H, LP, LH, PH, L^2, P^2, H^2, PLH, L^3, LP^2, LH^2, L^2P, P^3, PH^2, L^2H,
    P^2H, H^3 (NITF STDI-0002 RPC00B).
    """
    L, P, H = (np.asarray(x, dtype=np.float64).reshape(-1) for x in (lon_n, lat_n, alt_n))
    return np.stack(
        [np.ones_like(L), L, P, H, L * P, L * H, P * H, L * L, P * P, H * H, P * L * H, L ** 3,
         L * P * P, L * H * H, L * L * P, P ** 3, P * H * H, L * L * H, P * P * H, H ** 3],
        axis=1,
    )


def _offset_scale(name: str, values: np.ndarray) -> tuple[float, float]:
    lo, hi = float(values.min()), float(values.max())
    if not hi > lo:
        raise CameraError(f"RPC fit: all samples have the same {name} ({lo!r}): the cube is degenerate")
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _solve_rational(terms: np.ndarray, y: np.ndarray, iterations: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) with den[0] = 1 minimising the residual of y = num(T) / den(T) (normalised)."""
    a = np.concatenate([terms, -y[:, None] * terms[:, 1:]], axis=1)
    # Ridge rows on the denominator terms: sqrt(n) * DENOMINATOR_RIDGE * den[k] = 0.
    ridge = np.zeros((N_TERMS - 1, a.shape[1]))
    ridge[:, N_TERMS:] = math.sqrt(y.size) * DENOMINATOR_RIDGE * np.eye(N_TERMS - 1)
    weights = np.ones_like(y)
    for _ in range(iterations + 1):
        aw = np.concatenate([a * weights[:, None], ridge])
        rhs = np.concatenate([y * weights, np.zeros(N_TERMS - 1)])
        norms = np.linalg.norm(aw, axis=0)
        norms[norms == 0.0] = 1.0
        sol, *_ = np.linalg.lstsq(aw / norms, rhs, rcond=None)
        sol = sol / norms
        num = sol[:N_TERMS]
        den = np.concatenate([[1.0], sol[N_TERMS:]])
        den_values = terms @ den
        if not np.all(np.isfinite(den_values)) or np.min(np.abs(den_values)) < MIN_DENOMINATOR:
            raise CameraError(f"RPC fit: the {what} denominator vanishes inside the sample cube")
        weights = 1.0 / np.abs(den_values)
    return num, den


def _as_samples(**arrays: Any) -> dict[str, np.ndarray]:
    out = {}
    shape = None
    for name, value in arrays.items():
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        if shape is None:
            shape = arr.shape
        elif arr.shape != shape:
            raise CameraError(f"RPC fit: {name} has {arr.size} samples, others have {shape[0]}")
        if not np.all(np.isfinite(arr)):
            raise CameraError(f"RPC fit: {name} holds non-finite values")
        out[name] = arr
    return out


def fit_rpc(
    *,
    lon,
    lat,
    alt,
    col,
    row,
    iterations: int = DEFAULT_REWEIGHT_ITERATIONS,
    source: str | None = None,
) -> tuple[RPCModel, RPCFitResidual]:
    """Fit an RPC00B model to samples (lon, lat in degrees, alt in metres above the ellipsoid)
    -> (col, row) in pixels ((0, 0) = centre of the first pixel).

    The samples should fill the ground cube where the model will be used (e.g. a regular grid of
    lon x lat x alt); offsets and scales are the mid-ranges and half-ranges of the samples.
    Returns the model (``err_bias = err_rand = 0``) and its residual over the samples. Raises
    CameraError for mismatched or non-finite samples, too few of them, a degenerate cube, or a
    fit whose denominator vanishes.
    """
    s = _as_samples(lon=lon, lat=lat, alt=alt, col=col, row=row)
    n = s["lon"].size
    if n < MIN_SAMPLES_PER_UNKNOWN * N_UNKNOWNS:
        raise CameraError(
            f"RPC fit: {n} samples, need at least {MIN_SAMPLES_PER_UNKNOWN * N_UNKNOWNS} "
            f"({MIN_SAMPLES_PER_UNKNOWN} per unknown)"
        )
    if not (isinstance(iterations, int) and iterations >= 0):
        raise CameraError(f"RPC fit: iterations = {iterations!r}: must be an integer >= 0")
    norm = {k: _offset_scale(k, s[k]) for k in ("lon", "lat", "alt", "col", "row")}
    terms = rpc00b_terms(
        lon_n=(s["lon"] - norm["lon"][0]) / norm["lon"][1],
        lat_n=(s["lat"] - norm["lat"][0]) / norm["lat"][1],
        alt_n=(s["alt"] - norm["alt"][0]) / norm["alt"][1],
    )
    col_num, col_den = _solve_rational(terms, (s["col"] - norm["col"][0]) / norm["col"][1], iterations, "col")
    row_num, row_den = _solve_rational(terms, (s["row"] - norm["row"][0]) / norm["row"][1], iterations, "row")
    rpc = RPCModel(
        row_num=row_num, row_den=row_den, col_num=col_num, col_den=col_den,
        row_offset=norm["row"][0], col_offset=norm["col"][0],
        lat_offset=norm["lat"][0], lon_offset=norm["lon"][0], alt_offset=norm["alt"][0],
        row_scale=norm["row"][1], col_scale=norm["col"][1],
        lat_scale=norm["lat"][1], lon_scale=norm["lon"][1], alt_scale=norm["alt"][1],
        err_bias=0.0, err_rand=0.0, source=source,
    )
    return rpc, rpc_residual(rpc, lon=s["lon"], lat=s["lat"], alt=s["alt"], col=s["col"], row=s["row"])


def rpc_residual(rpc: RPCModel, *, lon, lat, alt, col, row) -> RPCFitResidual:
    """Image distance (pixels) between ``rpc.projection`` of the ground samples and (col, row)."""
    s = _as_samples(lon=lon, lat=lat, alt=alt, col=col, row=row)
    pc, pr = rpc.projection(lon=s["lon"], lat=s["lat"], alt=s["alt"])
    dc, dr = np.asarray(pc) - s["col"], np.asarray(pr) - s["row"]
    dist = np.hypot(dc, dr)
    return RPCFitResidual(
        max_px=float(dist.max()), rms_px=float(math.sqrt(np.mean(dist ** 2))),
        max_col_px=float(np.abs(dc).max()), max_row_px=float(np.abs(dr).max()), n_points=int(dist.size),
    )


def cube_grid(*, lon_range: tuple[float, float], lat_range: tuple[float, float],
              alt_range: tuple[float, float], n_lon: int = 21, n_lat: int = 21,
              n_alt: int = 9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flattened (lon, lat, alt) of a regular grid over a ground cube, edges included."""
    lo = np.linspace(lon_range[0], lon_range[1], n_lon)
    la = np.linspace(lat_range[0], lat_range[1], n_lat)
    al = np.linspace(alt_range[0], alt_range[1], n_alt)
    g = np.meshgrid(lo, la, al, indexing="ij")
    return g[0].ravel(), g[1].ravel(), g[2].ravel()
