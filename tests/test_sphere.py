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


# --- near lights from two spheres ------------------------------------------------------

FIELD = (120.0, 120.0)
CAMERA = (0.0, 0.0, 225.0)
SPHERES = [((-42.0, -38.0, 12.0), 12.0), ((40.0, 36.0, 10.0), 10.0)]


def traced_spheres(light, size=320, roughness=0.1):
    """Two mirror-like spheres (F0 0.9, GGX) on a dark stage under a point light, ray
    traced here from scratch (not with the project's renderer): camera at CAMERA, images
    rectified to the field (pixel centre -> its point on z = 0 -> the ray from the camera)."""
    n_px = size
    xs = (torch.arange(n_px, dtype=torch.float64) + 0.5) / n_px * FIELD[0] - FIELD[0] / 2
    ys = FIELD[1] / 2 - (torch.arange(n_px, dtype=torch.float64) + 0.5) / n_px * FIELD[1]
    q = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1] + (torch.zeros(n_px, n_px, dtype=torch.float64),), -1)
    q = torch.stack([q[..., 0], q[..., 1], q[..., 2]], -1)
    cam = torch.tensor(CAMERA, dtype=torch.float64)
    img = torch.full((n_px, n_px), 0.02, dtype=torch.float64)
    depth = torch.full((n_px, n_px), math.inf, dtype=torch.float64)
    lpos = torch.tensor(light, dtype=torch.float64)
    alpha = roughness**2
    for centre, radius in SPHERES:
        d = q - cam
        d = d / d.norm(dim=-1, keepdim=True)
        oc = cam - torch.tensor(centre, dtype=torch.float64)
        b = (d * oc).sum(-1)
        disc = b * b - ((oc * oc).sum() - radius * radius)
        t = -b - disc.clamp_min(0).sqrt()
        hit = (disc > 0) & (t < depth)
        p = cam + t[..., None] * d
        n = (p - torch.tensor(centre, dtype=torch.float64)) / radius
        v = -d
        lv = lpos - p
        dist = lv.norm(dim=-1)
        l = lv / dist[..., None]
        h = (l + v) / (l + v).norm(dim=-1, keepdim=True)
        nh, nl, nv = (n * h).sum(-1).clamp_min(0), (n * l).sum(-1).clamp_min(1e-6), (n * v).sum(-1).clamp_min(1e-6)
        dist_term = alpha**2 / (math.pi * (nh * nh * (alpha**2 - 1) + 1) ** 2)
        spec = 0.9 * dist_term / (4 * nl * nv) * nl * math.pi * (225.0 / dist) ** 2
        img = torch.where(hit, spec * 0.05, img)
        depth = torch.where(hit, t, depth)
    return img.clamp(0, 1).float()


@pytest.mark.parametrize("light", [(150.0, 60.0, 120.0), (-100.0, -140.0, 110.0), (20.0, 190.0, 150.0)])
def test_near_light_position_from_two_spheres(light):
    from matscan.capture.sphere import light_position_from_spheres

    # 960 px over the 120 mm field (0.125 mm a pixel; a 12 mm sphere is 96 px across), the
    # spheres at opposite corners: measured 0.5 to 0.8 mm (with the spheres 60 mm apart
    # near the middle, rays to a grazing LED nearly parallel: up to 3 mm, along the ray)
    img = traced_spheres(light, size=960)
    assert float(img.max()) == 1.0  # the highlights saturate, as they do in real photos
    found, spread = light_position_from_spheres(img, FIELD, CAMERA, SPHERES)
    error = math.dist(found, light)
    assert error < 2.0, (found, error)
    assert spread < 1.0


def test_one_sphere_cannot_place_a_light():
    from matscan.capture.sphere import light_position_from_spheres

    with pytest.raises(MatscanError, match="needs two spheres or more"):
        light_position_from_spheres(traced_spheres((150.0, 60.0, 120.0)), FIELD, CAMERA, SPHERES[:1])


def test_cli_moves_the_rig_lights_to_where_the_spheres_place_them(tmp_path):
    """dome24 whose LEDs 0, 11 and 22 sit up to 5 mm off the rig file: two spheres
    photographed under each (ray traced), and `rig from-spheres` puts them back."""
    from matscan.capture.folder import write_capture
    from matscan.rig import builtin_rig, load_rig

    rig = builtin_rig("dome24")
    offsets = {0: (4.0, -3.0, 2.0), 11: (-5.0, 1.0, -2.5), 22: (2.0, 4.5, 3.0)}
    true = {k: tuple(p + o for p, o in zip(rig.lights[k].position_mm, off, strict=True)) for k, off in offsets.items()}
    photos = torch.stack([traced_spheres(true[k], size=960).expand(3, -1, -1) for k in offsets])
    write_capture(tmp_path / "spheres", photos, rig, light_indices=list(offsets), encoding="linear", bits=16)
    args = ["rig", "from-spheres", str(tmp_path / "spheres"), "--out", str(tmp_path / "rig.json")]
    for (x, y, z), r in SPHERES:
        args += ["--sphere", f"{x},{y},{z},{r}"]
    assert main(args) == 0
    moved = load_rig(tmp_path / "rig.json")
    for k in offsets:
        assert math.dist(moved.lights[k].position_mm, true[k]) < 2.0
        assert math.dist(rig.lights[k].position_mm, true[k]) > 4.0  # the rig file was that far off
    assert moved.lights[5] == rig.lights[5]  # not photographed: unchanged
    assert main([*args[:3], "--sphere", "0,0,10,5", "--out", str(tmp_path / "x.json")]) == 2  # one sphere
