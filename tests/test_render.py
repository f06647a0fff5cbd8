"""The renderer against an independent scalar implementation of design.md's image formation."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from conftest import random_maps

from matscan.render import render, render_rig, surface_points
from matscan.rig import Light, LightSet, builtin_rig

D64 = torch.float64


def reference_pixel(p, n, rho, f0, r, q, intensity, axis, m, c, R):
    """design.md's image formation and Eq. 1, written out for one pixel in plain Python."""

    def sub(a, b):
        return [a[i] - b[i] for i in range(3)]

    def dot(a, b):
        return sum(a[i] * b[i] for i in range(3))

    def norm(a):
        s = math.sqrt(dot(a, a))
        return [x / s for x in a]

    lv = sub(q, p)
    d = math.sqrt(dot(lv, lv))
    l = norm(lv)
    v = norm(sub(c, p))
    h = norm([l[i] + v[i] for i in range(3)])
    nl, nv, nh, vh = dot(n, l), dot(n, v), dot(n, h), dot(v, h)
    if nl <= 0:
        return [0.0, 0.0, 0.0]
    alpha = max(r * r, 1e-3)
    D = alpha**2 / (math.pi * (nh * nh * (alpha**2 - 1) + 1) ** 2)

    def g1(x):
        return 2 * x / (x + math.sqrt(alpha**2 + (1 - alpha**2) * x * x))

    G = g1(nl) * g1(nv)
    lobe = max(-dot(axis, l), 0.0) ** m
    out = []
    for ch in range(3):
        F = f0[ch] + (1 - f0[ch]) * (1 - vh) ** 5
        fr = rho[ch] / math.pi + (D * G * F / (4 * nl * nv) if nv > 0 else 0.0)
        out.append(math.pi * intensity[ch] * (R / d) ** 2 * lobe * fr * max(nl, 0.0))
    return out


def test_white_lambertian_head_on_is_one():
    for dtype in (torch.float32, D64):
        one = torch.ones(3, 1, 1, dtype=dtype)
        up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).view(3, 1, 1)
        lights = LightSet.points([[0.0, 0.0, 225.0]], [0.0, 0.0, 225.0], 225.0).to(dtype)
        img = render(
            one,
            torch.zeros_like(one),
            torch.full((1, 1, 1), 0.5, dtype=dtype),
            up,
            lights,
            torch.zeros(1, 1, 3, dtype=dtype),
        )
        assert img.shape == (1, 3, 1, 1)
        assert torch.all(img == 1.0)
    # with the dome's m = 1 LED aimed straight down it is 1.0 too (a·(−l) = 1)
    lights = LightSet.from_lights([Light((0.0, 0.0, 225.0))], (0.0, 0.0, 225.0), 225.0)
    torch.testing.assert_close(_white_pixel_at_origin(lights), torch.ones(1, 3, 1, 1))


def _white_pixel_at_origin(lights: LightSet) -> torch.Tensor:
    """A white Lambertian (ρ = 1, F0 = 0) pixel at the origin with an upward normal, rendered."""
    up = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    return render(torch.ones(3, 1, 1), torch.zeros(3, 1, 1), torch.ones(1, 1, 1), up, lights, torch.zeros(1, 1, 3))


def test_matches_scalar_reference():
    rig = builtin_rig("dome24")
    maps = random_maps(size=8, seed=4, dtype=D64)
    img = render_rig(maps.diffuse, maps.specular, maps.roughness, maps.normal, rig)  # (24, 3, 8, 8)
    pts = surface_points(rig.field_mm, (8, 8), dtype=D64)
    for k in (0, 5, 13, 23):
        lt = rig.lights[k]
        for i, j in ((0, 0), (3, 5), (7, 2)):
            ref = reference_pixel(
                pts[i, j].tolist(),
                maps.normal[:, i, j].tolist(),
                maps.diffuse[:, i, j].tolist(),
                maps.specular[:, i, j].tolist(),
                float(maps.roughness[0, i, j]),
                lt.position_mm,
                lt.intensity,
                lt.axis,
                lt.exponent,
                rig.camera.position_mm,
                rig.reference_distance_mm,
            )
            assert img[k, :, i, j].tolist() == pytest.approx(ref, rel=1e-10, abs=1e-12)


def test_surface_points_convention():
    pts = surface_points((120.0, 60.0), (3, 4))
    # x = (j + 0.5)/W·width − width/2 ; y = height/2 − (i + 0.5)/H·height
    assert pts[0, 0].tolist() == pytest.approx([-45.0, 20.0, 0.0])
    assert pts[2, 3].tolist() == pytest.approx([45.0, -20.0, 0.0])
    crop = surface_points((120.0, 60.0), (2, 2), offset=(1, 2), full_size=(3, 4))
    torch.testing.assert_close(crop, pts[1:3, 2:4])


def _flat_white(size=16, tilt=None):
    normal = torch.zeros(3, size, size)
    normal[2] = 1
    if tilt is not None:
        normal = torch.tensor(tilt, dtype=torch.float32).view(3, 1, 1).expand(3, size, size)
        normal = normal / normal.norm(dim=0, keepdim=True)
    return (torch.full((3, size, size), 0.8), torch.zeros(3, size, size), torch.full((1, size, size), 0.6), normal)


def test_normal_convention_x():
    rig = builtin_rig("dome24")
    flat = render_rig(*_flat_white(), rig)
    tilted = render_rig(*_flat_white(tilt=(0.3, 0.0, 1.0)), rig)
    # light 8 at azimuth 0° (+x), light 12 at 180° (−x)
    assert tilted[8].mean() > flat[8].mean() * 1.1
    assert tilted[12].mean() < flat[12].mean() * 0.9


def test_normal_convention_y_and_top_rows():
    rig = builtin_rig("dome24")
    flat = render_rig(*_flat_white(), rig)
    tilted = render_rig(*_flat_white(tilt=(0.0, 0.3, 1.0)), rig)
    # light 10 at azimuth 90° (+y), light 14 at 270° (−y)
    assert tilted[10].mean() > flat[10].mean() * 1.1
    assert tilted[14].mean() < flat[14].mean() * 0.9
    # +y is the top of the image: under a +y light the top rows are nearer the light and brighter
    assert flat[10, :, :2].mean() > flat[10, :, -2:].mean() * 1.1
    assert flat[14, :, :2].mean() < flat[14, :, -2:].mean() * 0.9
    # and +x is the right: under a +x light the last columns are brighter
    assert flat[8, :, :, -2:].mean() > flat[8, :, :, :2].mean() * 1.1


def test_gradcheck():
    maps = random_maps(size=3, seed=5, dtype=D64)
    lights = builtin_rig("dome24").light_set([0, 9, 20]).to(D64)
    pts = surface_points((120.0, 120.0), (3, 3), dtype=D64)
    pos = lights.position.clone().requires_grad_()

    def f(d, s, r, n, q):
        ls = LightSet(q, lights.intensity, lights.axis, lights.exponent, lights.camera, lights.reference_distance_mm)
        return render(d, s, r, n, ls, pts)

    inputs = tuple(t.clone().requires_grad_() for t in (maps.diffuse, maps.specular, maps.roughness, maps.normal))
    assert torch.autograd.gradcheck(f, (*inputs, pos))


def test_chunking_and_batching_agree():
    maps = random_maps(size=20, seed=6)
    rig = builtin_rig("dome24")
    pts = surface_points(rig.field_mm, (20, 20))
    args = (maps.diffuse, maps.specular, maps.roughness, maps.normal)
    whole = render(*args, rig.light_set(), pts, chunk=1 << 30)
    chunked = render(*args, rig.light_set(), pts, chunk=1000)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=0)
    # batch of 2 with different lights per element equals two separate renders
    a, b = rig.light_set([0, 1]), rig.light_set([5, 17])
    batched_lights = LightSet(
        *(
            torch.stack([x, y])
            for x, y in zip(
                (a.position, a.intensity, a.axis, a.exponent, a.camera),
                (b.position, b.intensity, b.axis, b.exponent, b.camera),
                strict=True,
            )
        ),
        225.0,
    )
    out = render(*(t[None].expand(2, *t.shape) for t in args), batched_lights, pts)
    assert out.shape == (2, 2, 3, 20, 20)
    torch.testing.assert_close(out[0], whole[[0, 1]])
    torch.testing.assert_close(out[1], whole[[5, 17]])


def test_flash_colocated_light():
    # flash beside the lens, straight above at distance R, m = 0: a white Lambertian centre pixel is 1.0
    lights = LightSet.from_lights([Light((0.0, 0.0, 300.0), exponent=0.0)], [(0.0, 0.0, 300.0)], 300.0)
    torch.testing.assert_close(_white_pixel_at_origin(lights), torch.ones(1, 3, 1, 1))


def test_bad_shapes_are_reported():
    maps = random_maps(size=4)
    with pytest.raises(ValueError, match=r"roughness must be \(1, H, W\)"):
        render(
            maps.diffuse,
            maps.specular,
            maps.diffuse,
            maps.normal,
            builtin_rig("dome24").light_set(),
            surface_points((1, 1), (4, 4)),
        )


def test_compiled_kernel_agrees_with_eager():
    # the fused kernel (or its eager fallback where no compiler exists) gives the same numbers
    maps = random_maps(size=40, seed=7)
    rig = builtin_rig("dome24")
    pts = surface_points(rig.field_mm, (40, 40))
    args = (maps.diffuse, maps.specular, maps.roughness, maps.normal, rig.light_set(), pts)
    eager = render(*args, compile=False, chunk=24 * 300)
    fused = render(*args, compile=True, chunk=24 * 300)  # several chunks, the last one padded
    torch.testing.assert_close(fused, eager, rtol=1e-5, atol=1e-6)


def test_flat_irradiance_closed_form():
    from matscan.render import flat_irradiance

    # isotropic light at (0, 0, R): E(x) = (R/d)² · cos θ = R³ / (R² + x²)^(3/2)
    R = 225.0
    lights = LightSet.points([[0.0, 0.0, R]], [0.0, 0.0, R], R)
    pts = torch.tensor([[[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, -80.0, 0.0]]])
    e = flat_irradiance(lights, pts)[0, 0, 0]
    expected = torch.tensor([R**3 / (R**2 + x**2) ** 1.5 for x in (0.0, 50.0, 80.0)])
    torch.testing.assert_close(e, expected)
    # and it is what the renderer gives a white Lambertian surface
    ones = torch.ones(3, 1, 3)
    up = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 1, 3)
    img = render(ones, torch.zeros(3, 1, 3), torch.ones(1, 1, 3), up, lights, pts)
    torch.testing.assert_close(img[0, 0, 0], expected)


def test_flat_albedo_drops_highlights_and_keeps_the_lambertian_value():
    from matscan.render import flat_albedo

    irr = torch.rand(3, 3, 4, 4) + 0.5
    rho = torch.full((3, 4, 4), 0.3)
    photos = rho * irr
    photos[1] += 0.5  # two of three photos carry a highlight (the dome24 "3" subset on a gloss)
    photos[2] += 0.2
    torch.testing.assert_close(flat_albedo(photos, irr), rho)
    # 24 photos, 7 of them highlighted and 1 shadowed: sorted index 7 is still a clean reading
    irr = torch.rand(24, 3, 2, 2) + 0.5
    photos = 0.3 * irr
    photos[:7] *= 3.0
    photos[7] *= 0.2
    torch.testing.assert_close(flat_albedo(photos, irr), torch.full((3, 2, 2), 0.3))
    # one photo: its own ratio, clipped to [0, 1]
    torch.testing.assert_close(flat_albedo(torch.full((1, 3, 1, 1), 2.0), torch.ones(1, 3, 1, 1)), torch.ones(3, 1, 1))


def _special_maps(size: int, dtype: torch.dtype = D64):
    """random_maps with an alpha and an emissive map."""
    from matscan.mapset import MapSet

    g = torch.Generator().manual_seed(11)
    base = random_maps(size=size, seed=5, dtype=dtype)
    alpha = torch.rand(1, size, size, generator=g, dtype=dtype)
    emissive = 0.2 * torch.rand(3, size, size, generator=g, dtype=dtype)
    return MapSet(**base.present(), alpha=alpha, emissive=emissive)


def test_render_maps_adds_emission_and_multiplies_alpha():
    # reference: the plain-Python pixel above, then design.md's (scale·reflection + emissive)·alpha
    from matscan.render import render_maps

    rig = builtin_rig("dome24")
    maps = _special_maps(8)
    scale = 1.3
    img = render_maps(maps, rig.light_set([2, 17], D64), rig.field_mm, scale)
    assert img.shape == (2, 3, 8, 8) and img.dtype == D64
    pts = surface_points(rig.field_mm, (8, 8), dtype=D64)
    for slot, k in enumerate((2, 17)):
        lt = rig.lights[k]
        for i, j in ((0, 0), (3, 5), (7, 2)):
            reflected = reference_pixel(
                pts[i, j].tolist(),
                maps.normal[:, i, j].tolist(),
                maps.diffuse[:, i, j].tolist(),
                maps.specular[:, i, j].tolist(),
                float(maps.roughness[0, i, j]),
                lt.position_mm,
                lt.intensity,
                lt.axis,
                lt.exponent,
                rig.camera.position_mm,
                rig.reference_distance_mm,
            )
            a = float(maps.alpha[0, i, j])
            ref = [(scale * reflected[c] + float(maps.emissive[c, i, j])) * a for c in range(3)]
            assert img[slot, :, i, j].tolist() == pytest.approx(ref, rel=1e-10, abs=1e-12)
    # without alpha and emissive it is the renderer's image
    plain = random_maps(size=8, seed=5)
    lights = rig.light_set([2, 17])
    expected = render(
        plain.diffuse, plain.specular, plain.roughness, plain.normal, lights, surface_points(rig.field_mm, (8, 8))
    )
    assert torch.equal(render_maps(plain, lights, rig.field_mm), expected)


def test_render_maps_rows_are_a_band_of_the_whole():
    from matscan.errors import MatscanError
    from matscan.render import render_maps

    rig = builtin_rig("dome24")
    maps = _special_maps(12, torch.float32)
    lights = rig.light_set([0, 9])
    whole = render_maps(maps, lights, rig.field_mm, 0.8)
    band = render_maps(maps, lights, rig.field_mm, 0.8, rows=(3, 8))
    assert band.shape == (2, 3, 5, 12)
    torch.testing.assert_close(band, whole[..., 3:8, :], rtol=0, atol=0)
    for rows in ((5, 5), (-1, 4), (0, 13)):
        with pytest.raises(MatscanError, match="are not a band of the 12 rows"):
            render_maps(maps, lights, rig.field_mm, rows=rows)


def test_render_maps_gradcheck():
    from matscan.mapset import MapSet
    from matscan.render import render_maps

    rig = builtin_rig("dome24")
    base = _special_maps(2)
    lights = rig.light_set([4, 20]).to(D64)
    inputs = tuple(t.clone().requires_grad_() for t in (base.diffuse, base.roughness, base.alpha, base.emissive))

    def f(diffuse, roughness, alpha, emissive):
        maps = MapSet(diffuse, base.specular, roughness, base.normal, alpha=alpha, emissive=emissive)
        return render_maps(maps, lights, rig.field_mm, 0.9)

    assert torch.autograd.gradcheck(f, inputs)


@pytest.mark.parametrize("m", [0.01, 0.05, 0.2, 1.0])
def test_an_led_lights_nothing_behind_it(m):
    """design.md's lobe is max(a·(−l), 0)^m: 0 where the LED points away from the point.
    It was clamped to (1e-30)^m there, which is 0.5 of the light at m = 0.01, and the
    solver's own geometry did the same."""
    from matscan.reconstruct.lm import geometry
    from matscan.rig import Camera, Light, Rig

    # an LED at (100, 0, 50) aimed at (200, 0, 0): the origin lies behind it (a·(−l) = −0.6)
    led = Light(position_mm=(100.0, 0.0, 50.0), aim_mm=(200.0, 0.0, 0.0), exponent=m)
    rig = Rig("behind", 225.0, Camera(position_mm=(0.0, 0.0, 225.0)), (1e-3, 1e-3), (led,))
    lights = rig.light_set(dtype=torch.float64)

    def one(*v):
        return torch.tensor(v, dtype=torch.float64).view(-1, 1, 1)

    point = torch.zeros(1, 1, 3, dtype=torch.float64)

    def white(light_set):  # a white Lambertian, normal up, at the origin
        return render(one(1.0, 1.0, 1.0), one(0.0, 0.0, 0.0), one(0.5), one(0.0, 0.0, 1.0), light_set, point)

    assert float(white(lights).abs().max()) == 0.0
    assert float(geometry(lights, point.view(1, 3)).e.abs().max()) == 0.0
    # an isotropic emitter (m = 0) lights every way: the same LED lights the origin
    iso = Rig("iso", 225.0, rig.camera, rig.field_mm, (replace(led, exponent=0.0),))
    assert float(white(iso.light_set(dtype=torch.float64)).min()) > 0
