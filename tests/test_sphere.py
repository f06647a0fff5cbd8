"""Light directions from a chrome sphere's highlights (matscan.capture.sphere), on spheres
rendered under known directional lights with the project's renderer."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from matscan.capture.rti import parse_lp, read_lp
from matscan.capture.sphere import directions_from_sphere, find_sphere, highlight_direction
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


def chrome_sphere(
    light: tuple[float, float, float],
    noise: float = 0.0,
    seed: int = 0,
    *,
    size: tuple[int, int] = SIZE,
    centre: tuple[float, float] = CENTRE,
    radius: float = RADIUS,
    background: torch.Tensor | None = None,
    supersample: int = 1,
    matte: bool = False,
) -> torch.Tensor:
    """A mirror-like sphere (F0 0.9, roughness 0.12, no diffuse; ``matte``: a white
    Lambertian one instead) on a grey card (albedo 0.2, or the linear ``background``
    (3, H, W) albedo), seen from straight above, under one directional light: linear
    (3, H, W); ``supersample`` × ``supersample`` samples a pixel, box-filtered, as a
    camera's pixels integrate."""
    h, w = size[0] * supersample, size[1] * supersample
    at = (torch.arange(max(h, w), dtype=torch.float32) + 0.5) / supersample - 0.5  # pixel coordinates of the samples
    rows, cols = at[:h].view(-1, 1).expand(h, w), at[:w].view(1, -1).expand(h, w)
    x, y = (cols - centre[0]) / radius, -(rows - centre[1]) / radius
    inside = x * x + y * y < 1
    z = (1 - x * x - y * y).clamp_min(0).sqrt()
    normal = torch.where(inside, torch.stack([x, y, z]), torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1))
    card = torch.full((3, h, w), 0.2)
    if background is not None:
        card = background.repeat_interleave(supersample, 1).repeat_interleave(supersample, 2)
    diffuse = torch.where(inside, torch.full((3, h, w), 0.8 if matte else 0.0), card)
    specular = torch.where(inside, torch.full((3, h, w), 0.0 if matte else 0.9), torch.full((3, h, w), 0.04))
    roughness = torch.where(inside, torch.full((1, h, w), 0.12), torch.full((1, h, w), 0.8))
    rig = Rig("sphere", 500.0, Camera(direction=(0.0, 0.0, 1.0)), (w, h), (Light(direction=light),))
    pts = torch.zeros(h, w, 3)
    img = render(diffuse, specular, roughness, normal, rig.light_set(), pts)[0]
    if supersample > 1:
        img = torch.nn.functional.avg_pool2d(img[None], supersample)[0]
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
    with pytest.raises(MatscanError, match=r"x\.png: the sphere \(-500, -500, r 10\): its centre lies outside"):
        highlight_direction(dark, (-500.0, -500.0), 10.0, "x.png")


def test_a_sphere_that_does_not_fit_the_photo_is_refused():
    """A radius of 1e9 px (the sphere's mask then covers the photo, every normal is
    nearly straight up) read every light as overhead; such a sphere is refused. One cut
    by the frame by less than a quarter of its radius still gives its lights."""
    light = _direction(40.0, 0.0)
    photo = chrome_sphere(light, centre=(52.0, 88.6), radius=60.0)  # 8 px past the left edge
    assert _angle(highlight_direction(photo, (52.0, 88.6), 60.0, "x.png"), light) < 1.0
    with pytest.raises(MatscanError, match=r"x\.png: the sphere \(101\.3, 88\.6, r 1e\+09\) reaches \d+ px past"):
        highlight_direction(chrome_sphere(light), CENTRE, 1e9, "x.png")
    with pytest.raises(MatscanError, match=r"reaches 40 px past the 200×180 photo's edge"):
        highlight_direction(chrome_sphere(light), CENTRE, 128.6, "x.png")  # 40 px above the top row


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
    # a capture folder: the photos its capture.json lists, not its dark frame
    write_image(folder / "dark.png", torch.zeros(*SIZE, 3).numpy(), bits=8)
    images = [{"light": k, "file": f"img{k:02d}.png"} for k in range(4)]
    (folder / "capture.json").write_text(json.dumps({"format": "matscan-capture/1", "rig": "dome24", "images": images}))
    again = tmp_path / "again.lp"
    assert main(["rig", "from-sphere", str(folder), "--sphere", sphere, "--out", str(again)]) == 0
    assert parse_lp(again.read_text()).files == lp.files


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


def _on_dome(k: int, tangential_mm: float, radius: float = 225.0) -> tuple[float, float, float]:
    """dome24's LED ``k`` moved ``tangential_mm`` along its shell (radius 225 mm about the
    field's centre) in a fixed random direction, then set at ``radius`` from the centre."""
    from matscan.rig import builtin_rig

    p = torch.tensor(builtin_rig("dome24").lights[k].position_mm, dtype=torch.float64)
    off = torch.randn(3, generator=torch.Generator().manual_seed(k), dtype=torch.float64)
    off = off - (off @ p) / (p @ p) * p
    q = p + off / off.norm() * tangential_mm
    return tuple((q / q.norm() * radius).tolist())


@pytest.mark.parametrize("k", [0, 9, 13, 22])
def test_near_light_position_from_one_sphere_on_a_dome_of_known_radius(k):
    """A light on a hemispherical dome (5 mm along the shell from the rig file's place),
    one sphere: its highlight's ray meets the shell within 1 mm of the light (measured
    0.02 to 0.64 mm over six LEDs and either sphere). A light 2 mm off the shell is placed
    about 2 mm off: the shell is taken as exact."""
    from matscan.capture.sphere import light_position_from_spheres

    dome = ((0.0, 0.0, 0.0), 225.0)
    light = _on_dome(k, 5.0)
    img = traced_spheres(light, size=960)
    for sphere in SPHERES:
        found, spread = light_position_from_spheres(img, FIELD, CAMERA, [sphere], dome=dome)
        assert math.dist(found, light) < 1.0 and spread == 0.0
        assert math.hypot(*found) == pytest.approx(225.0)
    found, spread = light_position_from_spheres(img, FIELD, CAMERA, SPHERES, dome=dome)
    assert math.dist(found, light) < 1.0 and spread < 0.5
    off = _on_dome(k, 5.0, radius=227.0)
    found, _ = light_position_from_spheres(traced_spheres(off, size=960), FIELD, CAMERA, SPHERES[:1], dome=dome)
    assert 1.5 < math.dist(found, off) < 2.5


def test_a_sphere_outside_the_dome_is_refused():
    from matscan.capture.sphere import light_position_from_spheres

    img = traced_spheres((150.0, 60.0, 120.0))
    with pytest.raises(MatscanError, match="outside the dome"):
        light_position_from_spheres(img, FIELD, CAMERA, SPHERES[:1], dome=((0.0, 0.0, 0.0), 40.0))


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


def test_cli_places_the_lights_on_a_dome_from_one_sphere(tmp_path, capsys):
    from matscan.capture.folder import write_capture
    from matscan.rig import builtin_rig, load_rig

    rig = builtin_rig("dome24")
    true = {k: _on_dome(k, 5.0) for k in (0, 11, 22)}
    photos = torch.stack([traced_spheres(true[k], size=960).expand(3, -1, -1) for k in true])
    write_capture(tmp_path / "spheres", photos, rig, light_indices=list(true), encoding="linear", bits=16)
    (x, y, z), r = SPHERES[0]
    args = ["rig", "from-spheres", str(tmp_path / "spheres"), "--sphere", f"{x},{y},{z},{r}"]
    out = tmp_path / "rig.json"
    assert main([*args, "--dome-radius", "225", "--out", str(out)]) == 0
    assert "on the dome" in capsys.readouterr().out
    moved = load_rig(out)
    for k, light in true.items():
        assert math.dist(moved.lights[k].position_mm, light) < 1.0
        assert math.dist(rig.lights[k].position_mm, light) > 4.0
    for bad, message in (
        (["--out", str(tmp_path / "x.json")], "or one with --dome-radius"),
        (["--dome-centre", "0,0,-5", "--out", str(tmp_path / "x.json")], "give the dome's radius"),
        (["--dome-radius", "30", "--out", str(tmp_path / "x.json")], "outside the dome"),
        (["--sphere", f"{x},{y},{z},{r}", "--out", str(tmp_path / "x.json")], "overlap"),  # the same sphere twice
        (["--sphere", f"{x + r},{y},{z},{r}", "--out", str(tmp_path / "x.json")], "overlap (centres"),
        (["--sphere", "0,0,-50,20", "--dome-radius", "225", "--out", str(tmp_path / "x.json")], "below the sample"),
    ):
        assert main([*args, *bad]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


# --- finding the sphere in the photos ------------------------------------------------------

ICON = Path(__file__).parent / "data" / "rti-icon"


def _dome(count: int = 18) -> list[tuple[float, float, float]]:
    return [_direction((15.0, 35.0, 60.0)[k % 3], 360.0 * k / count + 7.0) for k in range(count)]


def test_finds_the_sphere_on_a_textured_card_to_a_tenth_of_a_pixel():
    """Box-filtered spheres on a random card: the outline within 0.1 px, and the light
    directions through it within half a degree of the true ones."""
    card = torch.rand(3, *SIZE, generator=torch.Generator().manual_seed(3)) * 0.5 + 0.1
    lights = _dome()
    photos = torch.stack(
        [chrome_sphere(light, 0.003, k, background=card, supersample=4) for k, light in enumerate(lights)]
    )
    cx, cy, r = find_sphere(photos)
    assert (cx, cy, r) == pytest.approx((*CENTRE, RADIUS), abs=0.1)
    for k, light in enumerate(lights):
        assert _angle(highlight_direction(photos[k], (cx, cy), r), light) < 0.5


def test_a_matte_sphere_is_not_taken_for_a_chrome_one():
    """A white Lambertian sphere beside the chrome one: its shading moves with the light
    but shows no small highlight, so the chrome sphere is the one found; alone, it is
    refused."""
    size, chrome, matte = (160, 320), ((230.4, 80.2), 55.0), ((80.7, 78.9), 60.0)
    photos = []
    for k, light in enumerate(_dome(12)):
        a = chrome_sphere(light, 0.002, k, size=size, centre=chrome[0], radius=chrome[1], supersample=2)
        b = chrome_sphere(light, 0.0, k, size=size, centre=matte[0], radius=matte[1], supersample=2, matte=True)
        left = torch.arange(size[1]) < 160
        photos.append(torch.where(left, b, a))
    photos = torch.stack(photos)
    cx, cy, r = find_sphere(photos)
    assert (cx, cy, r) == pytest.approx((*chrome[0], chrome[1]), abs=0.15)
    with pytest.raises(MatscanError, match="no chrome sphere found"):
        find_sphere(photos[..., :160])


def _icon_with_sphere(centre, radius, every=3):
    """The real rti-icon photos (every ``every``-th) with a box-filtered chrome sphere
    pasted in, lit from each photo's .lp direction: a real, busy scene around it."""
    from matscan.capture.sphere import _read_linear

    lp = read_lp(ICON / "dirs.lp")
    photos, lights = [], []
    for k in range(0, len(lp.files), every):
        photo = _read_linear(ICON / lp.files[k], "srgb")
        size = tuple(photo.shape[-2:])
        ss = 4
        black = torch.zeros(3, *size)  # the rendering is then the sphere's light alone, weighted by its cover
        sphere = chrome_sphere(
            lp.directions[k], size=size, centre=centre, radius=radius, background=black, supersample=ss
        )
        at = (torch.arange(max(size) * ss, dtype=torch.float32) + 0.5) / ss - 0.5
        ys, xs = at[: size[0] * ss, None], at[None, : size[1] * ss]
        inside = (((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) < radius**2).float()
        alpha = torch.nn.functional.avg_pool2d(inside[None, None], ss)[0]
        photos.append(photo * (1 - alpha) + sphere)
        lights.append(lp.directions[k])
    return torch.stack(photos), lights


def test_finds_a_sphere_pasted_into_a_real_capture():
    """The icon's halo is a large round motif; the sphere in the corner is still found,
    within 0.1 px, and the directions it gives are within a degree of the .lp's."""
    photos, lights = _icon_with_sphere((355.4, 48.7), 32.0)
    cx, cy, r = find_sphere(photos)
    assert (cx, cy, r) == pytest.approx((355.4, 48.7, 32.0), abs=0.1)
    worst = max(_angle(highlight_direction(p, (cx, cy), r), light) for p, light in zip(photos, lights, strict=True))
    assert worst < 1.0


def test_a_real_capture_without_a_sphere_is_refused(tmp_path, capsys):
    """rti-icon holds no sphere (its directions came from another session's): the gilded
    halo is round and glossy, but its highlights are broad, so nothing is made up."""
    folder = tmp_path / "icon"
    folder.mkdir()
    for name in read_lp(ICON / "dirs.lp").files[::4]:
        shutil.copy(ICON / name, folder / name)
    code = main(["rig", "from-sphere", str(folder), "--out", str(tmp_path / "dirs.lp")])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "no chrome sphere found" in err and "--sphere CX,CY,R" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "dirs.lp").exists()


def test_cli_finds_the_sphere_when_not_told(tmp_path, capsys):
    folder = tmp_path / "rti"
    folder.mkdir()
    lights = _dome(9)
    for k, light in enumerate(lights):
        img = linear_to_srgb(chrome_sphere(light, 0.002, k, supersample=2))
        write_image(folder / f"img{k:02d}.png", img.permute(1, 2, 0).numpy(), bits=8)
    out = tmp_path / "dirs.lp"
    assert main(["rig", "from-sphere", str(folder), "--out", str(out)]) == 0
    assert "the sphere found at (101.3, 88.6), radius 70.0 px" in capsys.readouterr().out
    for found, true in zip(read_lp(out).directions, lights, strict=True):
        assert _angle(found, true) < 1.0


# --- a sphere seen through a pinhole camera ------------------------------------------------

PINHOLE = (360, 480)  # rows, columns
FOV = 60.0  # across the width
BALL = ((110.0, 80.0, -300.0), 50.0)  # centre (mm; camera at the origin, looking down -z), radius:
# 24° off the optical axis, 77 px in radius


def pinhole_sphere(light, supersample: int = 3) -> torch.Tensor:
    """A mirror-like sphere (GGX, roughness 0.1) on a dark card under a directional light,
    ray traced here from scratch through a pinhole camera of FOV degrees across the
    width, principal point at the image's centre; box-filtered over ``supersample``² rays
    a pixel. Linear (3, H, W), the highlight saturated."""
    h, w = PINHOLE
    f = (w / 2) / math.tan(math.radians(FOV) / 2)
    at = (torch.arange(max(h, w) * supersample, dtype=torch.float64) + 0.5) / supersample - 0.5
    ys, xs = at[: h * supersample].view(-1, 1), at[: w * supersample].view(1, -1)
    d = torch.stack(
        torch.broadcast_tensors(xs - (w - 1) / 2, -(ys - (h - 1) / 2), torch.tensor(-f, dtype=torch.float64))
    )
    d = d / d.norm(dim=0, keepdim=True)
    s, radius = torch.tensor(BALL[0], dtype=torch.float64).view(3, 1, 1), BALL[1]
    b = -(d * s).sum(0)
    disc = b * b - ((s * s).sum() - radius**2)
    n = ((-b - disc.clamp_min(0).sqrt()) * d - s) / radius
    l = torch.tensor(light, dtype=torch.float64).view(3, 1, 1)
    v = -d
    hv = (l + v) / (l + v).norm(dim=0, keepdim=True)
    nh, nv = (n * hv).sum(0).clamp_min(0), (n * v).sum(0).clamp_min(1e-6)
    a2 = 0.1**4
    # radiance: GGX's D F / (4 n·l n·v) times n·l (G taken as 1)
    spec = 0.9 * a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2) / (4 * nv) * 0.05
    img = torch.where(disc > 0, spec + 0.01, torch.full_like(spec, 0.03))
    img = torch.nn.functional.avg_pool2d(img[None, None], supersample)[0, 0]
    return img.clamp(0, 1).float().expand(3, -1, -1)


def pinhole_outline() -> tuple[tuple[float, float], float]:
    """The circle through the silhouette's points nearest and farthest from the image
    centre, projected here from the sphere's tangent cone (closed form)."""
    h, w = PINHOLE
    f = (w / 2) / math.tan(math.radians(FOV) / 2)
    s = torch.tensor(BALL[0], dtype=torch.float64)
    half = math.asin(BALL[1] / float(s.norm()))
    tilt = math.acos(-float(s[2] / s.norm()))  # the sphere's angle off the optical axis
    radial = s[:2] / s[:2].norm()
    pts = [
        ((w - 1) / 2 + f * math.tan(t) * float(radial[0]), (h - 1) / 2 - f * math.tan(t) * float(radial[1]))
        for t in (tilt - half, tilt + half)
    ]
    return ((pts[0][0] + pts[1][0]) / 2, (pts[0][1] + pts[1][1]) / 2), math.dist(*pts) / 2


@pytest.mark.parametrize("elevation", [20.0, 45.0, 75.0])
@pytest.mark.parametrize("azimuth", [30.0, 200.0])
def test_a_pinhole_view_of_an_off_axis_sphere(elevation, azimuth):
    """The sphere lies 24° off the optical axis: with the angle of view the directions come
    back within 0.3° (measured 0.18° at most); read as orthographic, as RTI software reads
    them, they are 14° to 25° off."""
    light = _direction(elevation, azimuth)
    img = pinhole_sphere(light)
    assert float(img.max()) == 1.0
    centre, radius = pinhole_outline()
    assert _angle(highlight_direction(img, centre, radius, lens=FOV), light) < 0.3
    assert _angle(highlight_direction(img, centre, radius), light) > 10.0


def test_finds_the_ellipse_of_an_off_axis_sphere_as_its_tangent_cone():
    """Through a pinhole the sphere's outline is an ellipse stretched along the line from
    the image's centre: given the angle of view, the outline comes back within 0.2 px of
    the closed form (measured 0.05 px), where a circle fitted to it misses the long axis
    by 3 px (and the directions read through that circle are up to 5° off)."""
    lights = [_direction(25, 40), _direction(50, 160), _direction(70, 290), _direction(35, 250)]
    photos = torch.stack([pinhole_sphere(light) for light in lights])
    (cx, cy), r = pinhole_outline()
    x, y, radius = find_sphere(photos, lens=FOV)
    assert math.dist((x, y), (cx, cy)) < 0.2 and abs(radius - r) < 0.2
    assert abs(find_sphere(photos)[2] - r) > 2.0  # the circle fit


def test_cli_finds_an_off_axis_sphere_and_reads_it_with_the_angle_of_view(tmp_path, capsys):
    lights = [_direction(25, 40), _direction(50, 160), _direction(70, 290), _direction(35, 250)]
    folder = tmp_path / "rti"
    folder.mkdir()
    for k, light in enumerate(lights):
        write_image(folder / f"img{k:02d}.png", linear_to_srgb(pinhole_sphere(light)).permute(1, 2, 0).numpy(), bits=8)
    out = tmp_path / "dirs.lp"
    assert main(["rig", "from-sphere", str(folder), "--fov", str(FOV), "--out", str(out)]) == 0
    for found, true in zip(parse_lp(out.read_text()).directions, lights, strict=True):
        assert _angle(found, true) < 0.5
    for bad in ("0", "-5", "nan"):
        with pytest.raises(SystemExit):
            main(["rig", "from-sphere", str(folder), "--fov", bad, "--out", str(tmp_path / "x.lp")])
    assert main(["rig", "from-sphere", str(folder), "--fov", "180", "--out", str(tmp_path / "x.lp")]) == 2
    assert "--fov" in capsys.readouterr().err
    assert not (tmp_path / "x.lp").exists()


# --- a lens with an off-centre principal point and radial distortion ------------------------

PRINCIPAL = ((PINHOLE[1] - 1) / 2 - 30.0, (PINHOLE[0] - 1) / 2 + 20.0)  # column, row: 36 px off the centre
K1 = -0.15  # barrel: the sphere's outline (BALL) lies 2.5% nearer the principal point than without
#: OpenCV's five coefficients (k1, k2, p1, p2, k3): k1 alone, and a lens with every term (the
#: tangential ones move the sphere's outline 2.5 px)
LENSES = {"k1": (K1, 0.0, 0.0, 0.0, 0.0), "full": (K1, 0.08, 0.01, -0.008, -0.05)}


def _opencv_camera(principal, dist):
    import numpy as np

    f = (PINHOLE[1] / 2) / math.tan(math.radians(FOV) / 2)
    return np.array([[f, 0, principal[0]], [0, f, principal[1]], [0, 0, 1]]), np.array(dist, dtype=np.float64)


def _pinhole(dist):
    from matscan.capture.sphere import DISTORTION, Pinhole

    return Pinhole(FOV, PRINCIPAL, **dict(zip(DISTORTION, dist, strict=True)))


def lens_sphere(light, principal=PRINCIPAL, dist=LENSES["k1"], supersample: int = 3) -> torch.Tensor:
    """:func:`pinhole_sphere`'s scene through a lens whose rays OpenCV gives: each
    (sub)pixel of the photo undistorted by ``cv2.undistortPointsIter`` (OpenCV's frame: y
    down, z forward; ours: y up, the camera looking down −z)."""
    import cv2
    import numpy as np

    h, w = PINHOLE
    k, dist = _opencv_camera(principal, dist)
    at = (np.arange(max(h, w) * supersample) + 0.5) / supersample - 0.5
    xs, ys = np.meshgrid(at[: w * supersample], at[: h * supersample])
    pts = np.stack([xs.ravel(), ys.ravel()], 1)[:, None, :].astype(np.float64)
    stop = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    und = cv2.undistortPointsIter(pts, k, dist, None, None, stop)
    und = torch.from_numpy(und[:, 0, :]).view(h * supersample, w * supersample, 2)
    d = torch.stack([und[..., 0], -und[..., 1], -torch.ones_like(und[..., 0])])
    d = d / d.norm(dim=0, keepdim=True)
    s, radius = torch.tensor(BALL[0], dtype=torch.float64).view(3, 1, 1), BALL[1]
    b = -(d * s).sum(0)
    disc = b * b - ((s * s).sum() - radius**2)
    n = ((-b - disc.clamp_min(0).sqrt()) * d - s) / radius
    l = torch.tensor(light, dtype=torch.float64).view(3, 1, 1)
    v = -d
    hv = (l + v) / (l + v).norm(dim=0, keepdim=True)
    nh, nv = (n * hv).sum(0).clamp_min(0), (n * v).sum(0).clamp_min(1e-6)
    a2 = 0.1**4
    spec = 0.9 * a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2) / (4 * nv) * 0.05
    img = torch.where(disc > 0, spec + 0.01, torch.full_like(spec, 0.03))
    img = torch.nn.functional.avg_pool2d(img[None, None], supersample)[0, 0]
    return img.clamp(0, 1).float().expand(3, -1, -1)


def lens_outline(principal=PRINCIPAL, dist=LENSES["k1"]) -> tuple[tuple[float, float], float]:
    """The outline as :func:`pinhole_outline` defines it, its two silhouette points
    projected through the lens by ``cv2.projectPoints``."""
    import cv2
    import numpy as np

    k, dist = _opencv_camera(principal, dist)
    s = torch.tensor(BALL[0], dtype=torch.float64)
    half = math.asin(BALL[1] / float(s.norm()))
    tilt = math.acos(-float(s[2] / s.norm()))
    radial = (s[:2] / s[:2].norm()).tolist()
    points = [[math.tan(t) * radial[0], -math.tan(t) * radial[1], 1.0] for t in (tilt - half, tilt + half)]
    px, _ = cv2.projectPoints(np.array(points), np.zeros(3), np.zeros(3), k, dist)
    a, b = px[:, 0, :].tolist()
    return ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2), math.dist(a, b) / 2


@pytest.mark.parametrize("model", sorted(LENSES))
def test_the_lens_model_is_opencvs(model):
    """Pinhole.pixel projects as cv2.projectPoints does, and Pinhole.rays inverts it as
    cv2.undistortPointsIter does."""
    import cv2
    import numpy as np

    lens = _pinhole(LENSES[model])
    k, dist = _opencv_camera(PRINCIPAL, LENSES[model])
    g = torch.Generator().manual_seed(3)
    pts = torch.cat(
        [torch.rand(200, 2, generator=g, dtype=torch.float64) * 1.2 - 0.6, torch.ones(200, 1, dtype=torch.float64)], 1
    )
    ref, _ = cv2.projectPoints(pts.numpy() * [1, -1, 1], np.zeros(3), np.zeros(3), k, dist)  # OpenCV: y down
    ref = torch.from_numpy(ref[:, 0, :])
    ours = torch.tensor([lens.pixel(float(x), float(y), PINHOLE) for x, y, _ in pts], dtype=torch.float64)
    torch.testing.assert_close(ours, ref, atol=1e-6, rtol=0)
    rays = lens.rays(ref[:, 0], ref[:, 1], PINHOLE).T
    truth = torch.cat([pts[:, :2], -pts[:, 2:]], 1)
    torch.testing.assert_close(rays, truth / truth.norm(dim=1, keepdim=True), atol=1e-9, rtol=0)
    stop = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    und = torch.from_numpy(cv2.undistortPointsIter(ref.numpy()[:, None, :], k, dist, None, None, stop)[:, 0, :])
    torch.testing.assert_close(rays[:, :2] / -rays[:, 2:], und * torch.tensor([1.0, -1.0]), atol=1e-9, rtol=0)


def test_a_lens_that_folds_the_image_over_is_refused():
    from matscan.capture.sphere import Pinhole

    with pytest.raises(MatscanError, match="--distortion"):  # strong pincushion-to-barrel folds a wide view over
        Pinhole(150.0, None, -2.0).rays(torch.tensor([0.0]), torch.tensor([0.0]), PINHOLE)
    with pytest.raises(MatscanError, match="--distortion: p2"):
        Pinhole(60.0, None, p2=float("nan"))


@pytest.mark.parametrize("model", sorted(LENSES))
def test_the_outline_and_the_cone_invert_each_other(model):
    """perspective_sphere reads the outline cone_outline gives (the tangential terms move
    the silhouette's two points off the line through the principal point, so the reading
    is iterated there)."""
    from matscan.capture.sphere import cone_outline, outline_cone

    lens = _pinhole(LENSES[model])
    s = torch.tensor(BALL[0], dtype=torch.float64)
    axis, half = s / s.norm(), math.asin(BALL[1] / float(s.norm()))
    centre, radius = lens_outline(dist=LENSES[model])
    torch.testing.assert_close(
        torch.tensor(cone_outline(axis, half, PINHOLE, lens)), torch.tensor([*centre, radius]), atol=1e-6, rtol=0
    )
    found, angle = outline_cone(centre, radius, PINHOLE, lens)
    assert math.degrees(float((found @ axis).clamp(max=1).acos())) < 1e-6
    assert abs(angle - half) < 1e-9


@pytest.mark.parametrize("model", sorted(LENSES))
@pytest.mark.parametrize("elevation", [20.0, 45.0, 75.0])
@pytest.mark.parametrize("azimuth", [30.0, 200.0])
def test_a_sphere_through_a_distorting_lens_off_its_principal_point(elevation, azimuth, model):
    """With the principal point 36 px off the centre and barrel distortion (k1 alone, or
    OpenCV's five terms), the directions come back within 0.5° when the lens is described
    (measured 0.42° at most with k1, at 20° elevation, where the highlight lies in the
    outline's compressed rim; 0.09° from 45° up; 0.26° at most with the five terms, which
    read with their k1 alone are up to 0.50° off); read with the angle of view alone they
    are 6.7° to 8° off."""
    light = _direction(elevation, azimuth)
    img = lens_sphere(light, dist=LENSES[model])
    centre, radius = lens_outline(dist=LENSES[model])
    assert _angle(highlight_direction(img, centre, radius, lens=_pinhole(LENSES[model])), light) < 0.5
    assert _angle(highlight_direction(img, centre, radius, lens=FOV), light) > 5.0


@pytest.mark.parametrize("model", sorted(LENSES))
def test_finds_the_outline_through_the_lens(model):
    lights = [_direction(25, 40), _direction(50, 160), _direction(70, 290), _direction(35, 250)]
    photos = torch.stack([lens_sphere(light, dist=LENSES[model]) for light in lights])
    (cx, cy), r = lens_outline(dist=LENSES[model])
    x, y, radius = find_sphere(photos, lens=_pinhole(LENSES[model]))
    assert math.dist((x, y), (cx, cy)) < 0.2 and abs(radius - r) < 0.2


@pytest.mark.parametrize("model", sorted(LENSES))
def test_cli_reads_the_sphere_through_a_described_lens(tmp_path, capsys, model):
    dist = LENSES[model]
    lights = [_direction(25, 40), _direction(50, 160), _direction(70, 290), _direction(35, 250)]
    folder = tmp_path / "rti"
    folder.mkdir()
    for k, light in enumerate(lights):
        img = linear_to_srgb(lens_sphere(light, dist=dist)).permute(1, 2, 0).numpy()
        write_image(folder / f"img{k:02d}.png", img, bits=8)
    out = tmp_path / "dirs.lp"
    lens = ["--fov", str(FOV), "--principal-point", f"{PRINCIPAL[0]},{PRINCIPAL[1]}"]
    lens += ["--k1", str(K1)] if model == "k1" else ["--distortion", ",".join(map(str, dist))]
    assert main(["rig", "from-sphere", str(folder), *lens, "--out", str(out)]) == 0
    for found, true in zip(parse_lp(out.read_text()).directions, lights, strict=True):
        assert _angle(found, true) < 0.5
    capsys.readouterr()
    for bad, message in (
        (["--k1", "-0.1"], "give its angle of view with --fov"),
        (["--distortion", "-0.1,0,0,0"], "give its angle of view with --fov"),
        (["--fov", "60", "--principal-point", "3,nan"], "--principal-point"),
        (["--fov", "60", "--distortion", "-0.1,0,0"], "not 4 or 5 comma-separated numbers"),
        (["--fov", "60", "--distortion", "-0.1,0,0,x"], "--distortion"),
        (["--fov", "60", "--k1", "-0.1", "--distortion", "-0.1,0,0,0"], "give k1 in one of them"),
    ):
        assert main(["rig", "from-sphere", str(folder), *bad, "--out", str(tmp_path / "x.lp")]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.lp").exists()
