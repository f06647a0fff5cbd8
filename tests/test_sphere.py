"""Light directions from a chrome sphere's highlights (matscan.capture.sphere), on spheres
rendered under known directional lights with the project's renderer."""

from __future__ import annotations

import math

import pytest
import torch

from matscan.capture.rti import parse_lp
from matscan.capture.sphere import directions_from_sphere, highlight_direction
from matscan.cli import main
from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.render import render
from matscan.rig import Camera, Light, Rig

SIZE = (180, 200)
CENTRE = (101.3, 88.6)
RADIUS = 70.0


def _direction(elevation: float, azimuth: float) -> tuple[float, float, float]:
    e, a = math.radians(elevation), math.radians(azimuth)
    return (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))


def chrome_sphere(light: tuple[float, float, float], noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """A mirror-like sphere (F0 0.9, roughness 0.12, no diffuse) on a grey card (albedo 0.2),
    seen from straight above, under one directional light: linear (3, H, W)."""
    h, w = SIZE
    rows = torch.arange(h, dtype=torch.float32).view(-1, 1).expand(h, w)
    cols = torch.arange(w, dtype=torch.float32).view(1, -1).expand(h, w)
    x, y = (cols - CENTRE[0]) / RADIUS, -(rows - CENTRE[1]) / RADIUS
    inside = x * x + y * y < 1
    z = (1 - x * x - y * y).clamp_min(0).sqrt()
    normal = torch.where(inside, torch.stack([x, y, z]), torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1))
    diffuse = torch.where(inside, torch.zeros(3, h, w), torch.full((3, h, w), 0.2))
    specular = torch.where(inside, torch.full((3, h, w), 0.9), torch.full((3, h, w), 0.04))
    roughness = torch.where(inside, torch.full((1, h, w), 0.12), torch.full((1, h, w), 0.8))
    rig = Rig("sphere", 500.0, Camera(direction=(0.0, 0.0, 1.0)), (w, h), (Light(direction=light),))
    pts = torch.zeros(h, w, 3)
    img = render(diffuse, specular, roughness, normal, rig.light_set(), pts)[0]
    if noise:
        img = img + noise * torch.randn(img.shape, generator=torch.Generator().manual_seed(seed))
    return img.clamp(0, 1)


def _angle(a, b) -> float:
    a, b = torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)
    return math.degrees(math.acos(float((a @ b) / (a.norm() * b.norm())).__round__(12)))


@pytest.mark.parametrize("elevation", [15.0, 30.0, 50.0, 70.0, 89.0])
@pytest.mark.parametrize("azimuth", [0.0, 100.0, 230.0])
def test_recovers_directions_within_a_degree(elevation, azimuth):
    light = _direction(elevation, azimuth)
    found = highlight_direction(chrome_sphere(light, noise=0.003), CENTRE, RADIUS)
    assert _angle(found, light) < 1.0


def test_a_sphere_without_a_highlight_is_refused():
    dark = torch.zeros(3, *SIZE)
    with pytest.raises(MatscanError, match="no highlight on the sphere"):
        highlight_direction(dark, CENTRE, RADIUS, "x.png")
    with pytest.raises(MatscanError, match="is not inside the photo"):
        highlight_direction(dark, (-500.0, -500.0), 10.0, "x.png")


def test_cli_writes_an_lp_file_from_sphere_photos(tmp_path, capsys):
    lights = [_direction(20, 10), _direction(45, 135), _direction(65, 260), _direction(35, 300)]
    folder = tmp_path / "rti"
    folder.mkdir()
    for k, light in enumerate(lights):
        img = linear_to_srgb(chrome_sphere(light, noise=0.002, seed=k))
        write_image(folder / f"img{k:02d}.png", img.permute(1, 2, 0).numpy(), bits=8)
    out = tmp_path / "dirs.lp"
    sphere = f"{CENTRE[0]},{CENTRE[1]},{RADIUS}"
    assert main(["rig", "from-sphere", str(folder), "--sphere", sphere, "--out", str(out)]) == 0
    lp = parse_lp(out.read_text())
    assert lp.files == tuple(f"img{k:02d}.png" for k in range(4))
    for found, true in zip(lp.directions, lights, strict=True):
        assert _angle(found, true) < 1.0
    assert directions_from_sphere([folder / "img00.png"], CENTRE, RADIUS)[0] == pytest.approx(
        lp.directions[0], abs=1e-6
    )
    assert main(["rig", "from-sphere", str(folder), "--sphere", "1,2", "--out", str(tmp_path / "x.lp")]) == 2
    assert "--sphere" in capsys.readouterr().err
