"""RPC00B least-squares fit (satsweep.synth.rpcfit), checked against exact cameras and rpcm."""

from __future__ import annotations

import numpy as np
import pytest
import rpcm

from satsweep.errors import CameraError
from satsweep.geometry.geodesy import ENUFrame
from satsweep.geometry.rpc import RPCModel
from satsweep.synth.pushbroom import PushbroomCamera
from satsweep.synth.rpcfit import cube_grid, fit_rpc, rpc00b_terms, rpc_residual

# The issue asks for an RPC that is "the exact camera for all practical purposes": far below
# 0.01 px. A fitted pushbroom camera must reproduce it to this, away from the fit samples.
PUSHBROOM_FIT_TOL_PX = 1e-3
# A genuinely rational RPC00B sampled on a grid is in the model family: its fit must reproduce
# it to float64 rounding amplified by the conditioning of the 39-unknown system.
RATIONAL_FIT_TOL_PX = 1e-6
# Two evaluations of the same polynomial (ours vs rpcm) differ only by summation order.
SAME_POLY_TOL = 1e-12

FRAME = ENUFrame(55.65, -21.23, 2340.0)
HALF_M = 180.0  # half-size of the ground cube (m)
ALT_RANGE = (2330.0, 2410.0)


def _cube():
    lon, lat, _ = FRAME.to_geodetic(e=np.array([-HALF_M, HALF_M]), n=np.array([-HALF_M, HALF_M]), u=np.zeros(2))
    return (float(lon[0]), float(lon[1])), (float(lat[0]), float(lat[1]))


def _camera_samples(cam, lon, lat, alt):
    e, n, u = FRAME.from_geodetic(lon=lon, lat=lat, alt=alt)
    return cam.project(e=e, n=n, u=u)


@pytest.mark.parametrize("off_nadir,azimuth", [(0.0, 0.0), (12.0, 40.0), (25.0, 250.0)])
def test_fit_of_pushbroom_camera_reproduces_it_off_the_samples(off_nadir, azimuth):
    cam = PushbroomCamera.from_angles(off_nadir_deg=off_nadir, azimuth_deg=azimuth, orbit_azimuth_deg=195.0,
                                      orbit_height_m=694e3, gsd_m=0.5, width=700, height=700)
    lon_r, lat_r = _cube()
    lon, lat, alt = cube_grid(lon_range=lon_r, lat_range=lat_r, alt_range=ALT_RANGE, n_lon=15, n_lat=15, n_alt=7)
    col, row = _camera_samples(cam, lon, lat, alt)
    rpc, res = fit_rpc(lon=lon, lat=lat, alt=alt, col=col, row=row)
    assert res.n_points == lon.size
    assert res.max_px < PUSHBROOM_FIT_TOL_PX
    # Random points inside the cube, none of them a fit sample.
    rng = np.random.default_rng(4)
    lo, la, al = rng.uniform(*lon_r, 3000), rng.uniform(*lat_r, 3000), rng.uniform(*ALT_RANGE, 3000)
    col, row = _camera_samples(cam, lo, la, al)
    pc, pr = rpc.projection(lon=lo, lat=la, alt=al)
    assert np.max(np.hypot(pc - col, pr - row)) < PUSHBROOM_FIT_TOL_PX
    # The reported residual is the one measured independently.
    check = rpc_residual(rpc, lon=lo, lat=la, alt=al, col=col, row=row)
    assert check.max_px == pytest.approx(float(np.max(np.hypot(pc - col, pr - row))))


def _random_rational_rpc(rng) -> RPCModel:
    lon_r, lat_r = _cube()
    num = lambda: np.concatenate([rng.uniform(-0.1, 0.1, 1), rng.uniform(-1, 1, 3), rng.uniform(-0.05, 0.05, 16)])
    den = lambda: np.concatenate([[1.0], rng.uniform(-0.05, 0.05, 3), rng.uniform(-0.01, 0.01, 16)])
    return RPCModel(
        row_num=num(), row_den=den(), col_num=num(), col_den=den(),
        row_offset=350.0, col_offset=340.0, lat_offset=sum(lat_r) / 2, lon_offset=sum(lon_r) / 2,
        alt_offset=sum(ALT_RANGE) / 2, row_scale=360.0, col_scale=370.0,
        lat_scale=(lat_r[1] - lat_r[0]) / 2, lon_scale=(lon_r[1] - lon_r[0]) / 2,
        alt_scale=(ALT_RANGE[1] - ALT_RANGE[0]) / 2,
    )


def _rpcm_model(rpc: RPCModel) -> rpcm.RPCModel:
    d = {key: " ".join(repr(float(v)) for v in np.atleast_1d(val)) for key, val in {
        "LINE_OFF": rpc.row_offset, "SAMP_OFF": rpc.col_offset, "LAT_OFF": rpc.lat_offset,
        "LONG_OFF": rpc.lon_offset, "HEIGHT_OFF": rpc.alt_offset, "LINE_SCALE": rpc.row_scale,
        "SAMP_SCALE": rpc.col_scale, "LAT_SCALE": rpc.lat_scale, "LONG_SCALE": rpc.lon_scale,
        "HEIGHT_SCALE": rpc.alt_scale, "LINE_NUM_COEFF": rpc.row_num, "LINE_DEN_COEFF": rpc.row_den,
        "SAMP_NUM_COEFF": rpc.col_num, "SAMP_DEN_COEFF": rpc.col_den}.items()}
    return rpcm.RPCModel(d)


def test_fit_recovers_a_rational_rpc_checked_with_rpcm():
    rng = np.random.default_rng(11)
    truth = _random_rational_rpc(rng)
    lon_r, lat_r = _cube()
    lon, lat, alt = cube_grid(lon_range=lon_r, lat_range=lat_r, alt_range=ALT_RANGE, n_lon=13, n_lat=13, n_alt=7)
    col, row = truth.projection(lon=lon, lat=lat, alt=alt)
    rpc, res = fit_rpc(lon=lon, lat=lat, alt=alt, col=col, row=row)
    assert res.max_px < RATIONAL_FIT_TOL_PX
    # The fitted model, evaluated by rpcm (an independent RPC00B implementation), at new points.
    lo, la, al = rng.uniform(*lon_r, 2000), rng.uniform(*lat_r, 2000), rng.uniform(*ALT_RANGE, 2000)
    ref_col, ref_row = _rpcm_model(truth).projection(lo, la, al)
    fit_col, fit_row = _rpcm_model(rpc).projection(lo, la, al)
    assert np.max(np.hypot(fit_col - ref_col, fit_row - ref_row)) < RATIONAL_FIT_TOL_PX


def test_normalisation_is_mid_range_and_half_range_of_the_samples():
    rng = np.random.default_rng(3)
    truth = _random_rational_rpc(rng)
    lon_r, lat_r = _cube()
    lon = rng.uniform(*lon_r, 400)
    lat = rng.uniform(*lat_r, 400)
    alt = rng.uniform(*ALT_RANGE, 400)
    col, row = truth.projection(lon=lon, lat=lat, alt=alt)
    rpc, _ = fit_rpc(lon=lon, lat=lat, alt=alt, col=col, row=row)
    for name, values in (("lon", lon), ("lat", lat), ("alt", alt), ("col", col), ("row", row)):
        assert getattr(rpc, f"{name}_offset") == pytest.approx((values.max() + values.min()) / 2, rel=1e-15)
        assert getattr(rpc, f"{name}_scale") == pytest.approx((values.max() - values.min()) / 2, rel=1e-15)
    assert rpc.row_den[0] == 1.0 and rpc.col_den[0] == 1.0


def test_terms_follow_rpc00b_order_as_rpcm_evaluates_it():
    rng = np.random.default_rng(5)
    L, P, H = rng.uniform(-1, 1, (3, 50))
    terms = rpc00b_terms(lon_n=L, lat_n=P, alt_n=H)
    assert terms.shape == (50, 20)
    for k in range(20):
        unit = np.zeros(20)
        unit[k] = 1.0
        # rpcm's apply_poly takes (x, y, z) = (lat, lon, alt), normalised.
        np.testing.assert_allclose(terms[:, k], rpcm.rpc_model.apply_poly(unit, P, L, H), rtol=0, atol=SAME_POLY_TOL)


def test_bad_samples_are_refused():
    lon_r, lat_r = _cube()
    lon, lat, alt = cube_grid(lon_range=lon_r, lat_range=lat_r, alt_range=ALT_RANGE, n_lon=5, n_lat=5, n_alt=4)
    col = np.linspace(0, 100, lon.size)
    row = np.linspace(0, 50, lon.size)
    with pytest.raises(CameraError, match="samples, need at least"):
        fit_rpc(lon=lon[:30], lat=lat[:30], alt=alt[:30], col=col[:30], row=row[:30])
    with pytest.raises(CameraError, match="row has"):
        fit_rpc(lon=lon, lat=lat, alt=alt, col=col, row=row[:-1])
    bad = col.copy()
    bad[3] = np.nan
    with pytest.raises(CameraError, match="col holds non-finite"):
        fit_rpc(lon=lon, lat=lat, alt=alt, col=bad, row=row)
    with pytest.raises(CameraError, match="same alt"):
        fit_rpc(lon=lon, lat=lat, alt=np.full(lon.size, 2340.0), col=col, row=row)
