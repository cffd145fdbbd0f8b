"""Blind-spot map: a single LiDAR on a box car's roof against the geometry worked by hand."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.blindspot import (MAX_RASTER_BYTES, azimuth_step_deg, blind_spot_map, default_sector_deg,
                                       footprint_distance, ground_hits, max_blind_extent)
from place3d_kernels.vehicle import VehicleBody

HALF = np.array([2.3, 0.9])              # box car 4.6 m x 1.8 m, roof at 1.6 m
ROOF = 1.6
SENSOR = np.array([0.3, 0.1, 2.0])
EL = np.radians(np.arange(-30.0, 10.5, 1.0) + 0.37)     # no horizontal beam; steps of 1 deg
AZ = np.radians(np.arange(720) * 0.5 + 0.25)             # two rays per 1-deg sector
LIDAR = p3k.LidarModel(EL, AZ, max_range=60.0)


def car() -> VehicleBody:
    return VehicleBody.box(2 * HALF[0], 2 * HALF[1], ROOF)


def analytic_ground_points(ground_z=0.0):
    # per azimuth: distance D from the sensor to the roof's edge; a beam of depression angle a clears the
    # edge when H - D tan(a) > roof height; the steepest such beam lands at H / tan(a) from the sensor
    u = np.stack([np.cos(AZ), np.sin(AZ)], axis=1)
    with np.errstate(divide="ignore"):
        tx = np.where(u[:, 0] > 0, (HALF[0] - SENSOR[0]) / u[:, 0], (-HALF[0] - SENSOR[0]) / u[:, 0])
        ty = np.where(u[:, 1] > 0, (HALF[1] - SENSOR[1]) / u[:, 1], (-HALF[1] - SENSOR[1]) / u[:, 1])
    D = np.minimum(tx, ty)
    dep = -EL[EL < 0]                                                    # depression angles > 0
    clears = SENSOR[2] - D[:, None] * np.tan(dep)[None, :] > ROOF          # (A, C)
    steepest = np.where(clears, dep[None, :], -np.inf).max(axis=1)
    r = (SENSOR[2] - ground_z) / np.tan(steepest)
    return SENSOR[:2] + r[:, None] * u


def test_blind_ring_matches_geometry(backend):
    m = blind_spot_map(car(), LIDAR, np.r_[SENSOR, 0, 0, 0][None],
                       backend=backend)
    pts = analytic_ground_points()
    sec = (np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) % 360).astype(int)
    want_r = np.full(360, np.inf)
    np.minimum.at(want_r, sec, np.hypot(pts[:, 0], pts[:, 1]))
    assert np.all(np.isfinite(want_r))
    np.testing.assert_allclose(m.nearest_radius, want_r, rtol=0, atol=1e-9)
    # the lowest beam alone (no roof) would land at H / tan(30.63 deg) from the sensor; the roof pushes
    # the ring out: the nearest seen point is never nearer than that
    assert np.all(np.hypot(*(pts - SENSOR[:2]).T) >= SENSOR[2] / np.tan(-EL.min()) - 1e-9)
    # the rasterised ring: every cell of the region more than one cell inside the analytic inner radius of
    # its sector is blind, and no cell beyond that radius is
    yc, xc = np.meshgrid(0.5 * (m.y_edges[1:] + m.y_edges[:-1]), 0.5 * (m.x_edges[1:] + m.x_edges[:-1]),
                         indexing="ij")
    r = np.hypot(xc, yc)
    ring = want_r[(np.degrees(np.arctan2(yc, xc)) % 360).astype(int)]
    assert np.all(m.blind[m.region & (r < ring - m.cell)])
    assert not np.any(m.blind[r > ring])
    assert np.any(m.blind[m.region & (r > ring - m.cell)])
    # the area: the blind cells approximate the region between the footprint and the ring
    # (polar quadrature of the blind set: nearer than the sector's ring, outside the footprint, within
    # 10 m of it)
    th = np.radians(np.arange(7200) * 0.05 + 0.025)
    rr = np.arange(0.0025, 13.0, 0.005)           # the region ends 10 m from the footprint, < 12.5 m
    R, T = np.meshgrid(rr, th)
    xy = np.stack([(R * np.cos(T)).ravel(), (R * np.sin(T)).ravel()], axis=1)
    dfp = footprint_distance(xy, car().footprint()).reshape(R.shape)
    inside = (R < want_r[(np.degrees(T) % 360).astype(int)]) & (dfp > 0) & (dfp <= 10.0)
    area = float(np.sum(inside * R) * 0.005 * np.radians(0.05))
    assert m.area_m2 == pytest.approx(area, rel=0.01)
    assert m.max_extent() == pytest.approx(footprint_distance(pts, car().footprint()).max(), abs=0.3)


def test_bumper_height_and_constraint(tmp_path):
    body = car()
    pose = np.r_[SENSOR, 0, 0, 0][None]
    road = blind_spot_map(body, LIDAR, pose, backend="reference")
    bumper = blind_spot_map(body, LIDAR, pose, ground_z=0.5, backend="reference")
    assert bumper.area_m2 < road.area_m2                     # a higher plane is reached nearer the car
    assert max_blind_extent(body, LIDAR, pose, 0.5) == pytest.approx(bumper.max_extent())
    assert max_blind_extent(body, LIDAR, np.array([[0.0, 0.0, 1.0, 0, 0, 0]])) == float("inf")   # inside
    out = bumper.plot(tmp_path / "blind.png")
    assert out.stat().st_size > 10_000
    summary = bumper.summary()
    assert summary["area_m2"] == pytest.approx(bumper.area_m2, abs=1e-3) and len(summary["nearest_from_body_m"]) == 360
    with pytest.raises(ValueError, match="inside"):
        blind_spot_map(body, LIDAR, np.array([[0.0, 0.0, 1.0, 0, 0, 0]]))


def test_cli_writes_json_and_png_or_nothing(tmp_path):
    import argparse
    import json

    from place3d_kernels.blindspot import add_blindspot_parser

    parser = argparse.ArgumentParser()
    add_blindspot_parser(parser.add_subparsers())
    args = parser.parse_args(["blindspot", "pyramid", "--vehicle", "suv", "--ground-z", "0.5", "--backend",
                              "reference", "--output", str(tmp_path / "ok")])
    assert args.func(args) == 0
    data = json.loads((tmp_path / "ok" / "blindspot.json").read_text())
    assert data["vehicle"]["name"] == "suv" and data["area_m2"] > 0
    # place3d_16ch steps 1.44 degrees in azimuth: 2-degree sectors by default
    assert data["sector_deg"] == 2.0 and len(data["nearest_from_body_m"]) == 180
    assert (tmp_path / "ok" / "blindspot.png").stat().st_size > 10_000
    bad = parser.parse_args(["blindspot", "pyramid", "--vehicle", "van", "--output", str(tmp_path / "bad")])
    with pytest.raises(ValueError, match="inside"):                  # the van's roof (2.47 m) swallows the rig
        bad.func(bad)
    with pytest.raises(ValueError, match="unknown vehicle 'bus'"):
        bad.vehicle = "bus"
        bad.func(bad)
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("z", [np.nan, np.inf, -np.inf])
def test_non_finite_ground_height_is_refused(z):
    # --ground-z nan reported 450 m^2 (every comparison with NaN false: nothing seen, all blind)
    pose = np.r_[SENSOR, 0, 0, 0][None]
    for fn in (blind_spot_map, ground_hits):
        with pytest.raises(ValueError, match="ground_z .*finite"):
            fn(car(), LIDAR, pose, z, backend="reference")


def test_sectors_follow_the_azimuth_step():
    lidar16 = p3k.LidarModel.load("place3d_16ch")
    assert azimuth_step_deg(lidar16) == pytest.approx(1.44)
    assert default_sector_deg(lidar16) == 2.0
    assert default_sector_deg(LIDAR) == 1.0                                   # 0.5 degree steps
    # a 120-degree field of view: the gap outside it is not the step
    assert azimuth_step_deg(p3k.LidarModel.load("at128")) == pytest.approx(0.1)
    # a direction table; a list takes the coarsest
    table = np.stack([np.cos(np.radians(np.arange(0, 360, 7.5))), np.sin(np.radians(np.arange(0, 360, 7.5))),
                      -0.2 * np.ones(48)], 1)
    table /= np.linalg.norm(table, axis=1, keepdims=True)
    assert azimuth_step_deg(table) == pytest.approx(7.5) and default_sector_deg(table) == 8.0
    assert default_sector_deg([LIDAR, lidar16]) == 2.0
    pose = np.array([[0.0, 0.0, 2.0, 0, 0, 0]])
    body = VehicleBody.preset("car")
    m = blind_spot_map(body, lidar16, pose, backend="reference")
    assert m.sector_deg == 2.0 and len(m.nearest_radius) == 180
    # 1-degree sectors fell between the 1.44-degree rays: "max extent inf"; 2-degree ones all see ground
    assert np.isfinite(m.max_extent())
    with pytest.raises(ValueError, match=r"sector_deg .*\b1\b.*azimuth step of 1\.44 degrees"):
        blind_spot_map(body, lidar16, pose, sector_deg=1.0, backend="reference")
    assert blind_spot_map(body, lidar16, pose, sector_deg=3.0, backend="reference").sector_deg == 3.0


def test_a_raster_too_large_for_memory_is_refused_with_what_it_needs():
    # --cell 0.0001 raised a MemoryError traceback (406 GiB for one array)
    with pytest.raises(ValueError, match=r"would need about [\d,.]+ GiB .* use a cell of at least") as e:
        blind_spot_map(car(), LIDAR, np.r_[SENSOR, 0, 0, 0][None], cell=1e-4, backend="reference")
    assert "--cell" in str(e.value)
    # the suggested cell fits the limit: memory scales as 1 / cell^2
    need = float(str(e.value).split("about ")[1].split(" GiB")[0].replace(",", ""))
    fits = float(str(e.value).split("at least ")[1].split(" m")[0])
    assert need * (1e-4 / fits) ** 2 <= MAX_RASTER_BYTES / 2**30 < need * (1e-4 / (0.9 * fits)) ** 2
