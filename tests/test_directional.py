"""Directional lights and orthographic cameras (design.md, "Directional lights and
orthographic cameras"), checked against closed forms in every code path that computes
light geometry: the renderer, the flat-surface irradiance and the solver's geometry."""

from __future__ import annotations

import json
import math
import re

import pytest
import torch

from matscan.errors import MatscanError
from matscan.reconstruct.lm import geometry
from matscan.render import flat_irradiance, render, surface_points
from matscan.rig import Camera, Light, Rig, load_rig, rig_from_dict, rig_to_dict, save_rig


def _rig(lights, camera: Camera, field=(120.0, 120.0)) -> Rig:
    return Rig("test", 225.0, camera, field, tuple(lights))


def _direction(elevation_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))


def _flat(size: int, rho: float = 1.0, f0: float = 0.0, r: float = 0.5):
    diffuse = torch.full((3, size, size), rho)
    specular = torch.full((3, size, size), f0)
    roughness = torch.full((1, size, size), r)
    normal = torch.zeros(3, size, size)
    normal[2] = 1
    return diffuse, specular, roughness, normal


@pytest.mark.parametrize("elevation", [15.0, 30.0, 60.0, 90.0])
def test_lambertian_under_a_directional_light_is_sin_elevation_everywhere(elevation):
    # pixel = π·I·(ρ/π)·n·l with n = +z, l the direction: sin(elevation), whatever the pixel
    # (the rendering is linear in ρ; Schlick's F is not 0 off head-on even for F0 = 0, so
    # the diffuse part is the difference of renderings with ρ = 1 and ρ = 0)
    rig = _rig([Light(direction=_direction(elevation, 40.0))], Camera(position_mm=(0.0, 0.0, 225.0)))
    pts = surface_points(rig.field_mm, (16, 16))
    img = render(*_flat(16), rig.light_set(), pts) - render(*_flat(16, rho=0.0), rig.light_set(), pts)
    assert img.shape == (1, 3, 16, 16)
    torch.testing.assert_close(img, torch.full_like(img, math.sin(math.radians(elevation))), atol=1e-6, rtol=0)
    e = flat_irradiance(rig.light_set(), surface_points(rig.field_mm, (16, 16)))
    torch.testing.assert_close(e, torch.full_like(e, math.sin(math.radians(elevation))), atol=1e-6, rtol=0)


def test_a_point_light_varies_over_the_field_where_a_directional_one_does_not():
    point = _rig([Light(position_mm=(0.0, 0.0, 225.0), exponent=0.0)], Camera(position_mm=(0.0, 0.0, 225.0)))
    img = render(*_flat(9), point.light_set(), surface_points(point.field_mm, (9, 9)))[0, 0]
    # centre: head-on at distance R → 1; a corner is farther and oblique
    assert float(img[4, 4]) == pytest.approx(1.0, abs=1e-4)
    assert float(img[0, 0]) < 0.9


@pytest.mark.parametrize("roughness", [0.3, 0.5, 0.8])
def test_specular_head_on_with_an_orthographic_camera(roughness):
    # n = l = v = +z: D = 1/(π α²), G = 1, F = F0, n·l = n·v = 1, so the specular pixel is
    # π · D·G·F / 4 = F0 / (4 α²), the same at every pixel (no position enters)
    f0 = 0.04
    alpha = roughness**2
    rig = _rig([Light(direction=(0.0, 0.0, 1.0))], Camera(direction=(0.0, 0.0, 1.0)))
    img = render(*_flat(8, rho=0.0, f0=f0, r=roughness), rig.light_set(), surface_points(rig.field_mm, (8, 8)))
    expected = f0 / (4 * alpha * alpha)
    torch.testing.assert_close(img, torch.full_like(img, expected), rtol=1e-5, atol=0)
    # a camera 225 mm above sees the corners off the mirror direction: less there
    persp = _rig([Light(direction=(0.0, 0.0, 1.0))], Camera(position_mm=(0.0, 0.0, 225.0)))
    img_p = render(*_flat(8, rho=0.0, f0=f0, r=roughness), persp.light_set(), surface_points(persp.field_mm, (8, 8)))
    assert float(img_p[0, 0, 0, 0]) < 0.99 * expected


def test_solver_geometry_matches_the_closed_form():
    d = _direction(35.0, 120.0)
    rig = _rig([Light(direction=d, intensity=(0.5, 1.0, 2.0))], Camera(direction=(0.0, 0.0, 1.0)))
    pts = surface_points(rig.field_mm, (5, 5)).reshape(-1, 3)
    geo = geometry(rig.light_set(), pts)
    torch.testing.assert_close(geo.l[0], torch.tensor(d).view(3, 1).expand(3, 25), atol=1e-6, rtol=0)
    torch.testing.assert_close(geo.v.expand(1, 3, 25)[0], torch.tensor([0.0, 0, 1]).view(3, 1).expand(3, 25))
    # e = I · (R/d)² · lobe = I: no falloff, no lobe
    torch.testing.assert_close(geo.e[0], torch.tensor([0.5, 1.0, 2.0]).view(3, 1).expand(3, 25), atol=1e-6, rtol=0)


def test_rig_json_round_trip_with_directions(tmp_path):
    data = {
        "name": "rti",
        "reference_distance_mm": 500,
        "camera": {"direction": [0, 0, 1]},
        "field_mm": [100, 80],
        "lights": [
            {"direction": [0.6, 0.0, 0.8], "intensity": [1, 0.9, 0.8]},
            {"position_mm": [0, 100, 400], "exponent": 0},
        ],
    }
    rig = rig_from_dict(data)
    assert rig.camera.orthographic and rig.camera.direction == (0.0, 0.0, 1.0)
    assert rig.lights[0].directional and not rig.lights[1].directional
    assert rig.lights[0].axis == pytest.approx((-0.6, 0.0, -0.8))
    save_rig(rig, tmp_path / "rig.json")
    again = load_rig(tmp_path / "rig.json")
    assert again == rig
    assert json.loads((tmp_path / "rig.json").read_text())["lights"][0]["direction"] == [0.6, 0.0, 0.8]
    assert rig_to_dict(again) == rig_to_dict(rig)
    ls = rig.light_set()
    assert ls.w.tolist() == [0.0, 1.0] and ls.camera_w.tolist() == [0.0, 0.0]


@pytest.mark.parametrize(
    ("light", "message"),
    [
        ({"direction": [0.6, 0, 0.8], "position_mm": [0, 0, 100]}, "either position_mm"),
        ({"intensity": [1, 1, 1]}, "missing field 'position_mm' (a point) or 'direction'"),
        ({"direction": [1, 0, 1]}, "unit vector"),
        ({"direction": [0.6, 0, -0.8]}, "below the sample plane"),
        ({"direction": [0.6, 0]}, "lights[0].direction"),
    ],
)
def test_bad_directions_are_named(light, message):
    data = {
        "name": "rti",
        "reference_distance_mm": 500,
        "camera": {"position_mm": [0, 0, 500]},
        "field_mm": [100, 100],
        "lights": [light],
    }
    with pytest.raises(MatscanError, match=re.escape(message)):
        rig_from_dict(data, "rig.json")
