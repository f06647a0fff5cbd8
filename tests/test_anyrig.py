"""The any-rig network (matscan.anyrig): its inputs against closed forms, pooling over any
number and order of photos, the random rigs it trains on, and that it learns."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from matscan.anyrig import (
    AnyRigConfig,
    AnyRigNet,
    TrainAnyRig,
    _batch,
    loss,
    photo_input,
    pool,
    ps_estimate,
    random_lights,
)
from matscan.render import surface_points
from matscan.rig import Camera, Light, Rig


def test_photo_input_closed_form():
    # a white Lambertian card under a directional light at 30° elevation, seen from an
    # orthographic camera: photo = sin 30° = irradiance, so the ratio is 1 everywhere
    d = (math.cos(math.radians(30)), 0.0, math.sin(math.radians(30)))
    rig = Rig("t", 500.0, Camera(direction=(0.0, 0.0, 1.0)), (40.0, 40.0), (Light(direction=d),))
    pts = surface_points(rig.field_mm, (8, 8))
    x = photo_input(torch.full((3, 8, 8), 0.5), rig.light_set(), pts)
    assert x.shape == (10, 8, 8)
    torch.testing.assert_close(x[:3], torch.ones(3, 8, 8), atol=1e-5, rtol=0)  # log1p(100·1)/log1p(100)
    torch.testing.assert_close(x[3:6], torch.tensor(d).view(3, 1, 1).expand(3, 8, 8).float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(x[6:9], torch.tensor([0.0, 0, 1]).view(3, 1, 1).expand(3, 8, 8), atol=1e-6, rtol=0)
    torch.testing.assert_close(x[9], torch.zeros(8, 8), atol=1e-6, rtol=0)  # no falloff
    # a point light at twice the reference distance straight above the centre: falloff (1/2)², log/4
    near = Rig("t", 100.0, Camera(position_mm=(0.0, 0.0, 300.0)), (40.0, 40.0), (Light(position_mm=(0, 0, 200.0)),))
    x = photo_input(torch.zeros(3, 9, 9), near.light_set(), surface_points(near.field_mm, (9, 9)))
    assert float(x[9, 4, 4]) == pytest.approx(math.log(0.25) / 4, abs=1e-5)


def _lambertian_photos(normal, albedo, rig):
    """Photos of a plane of one normal and albedo (RGB) under each of a rig's directional
    lights, seen orthographically: ρ (n · l) times the light's intensity, no shadows."""
    n = torch.tensor(normal) / torch.tensor(normal).norm()
    photos = []
    for light in rig.lights:
        l = torch.tensor(light.direction) / torch.tensor(light.direction).norm()
        photos.append((torch.tensor(albedo) * float(n @ l)).view(3, 1, 1).expand(3, 6, 6))
    return n, photos


def test_photometric_stereo_skip_recovers_a_lambertian_plane():
    # six directional lights at 20°-70° elevation around a plane tilted 25°: ρ n·l is
    # linear in b = ρ n, so the ridge solve gives n and ρ up to the ridge's small pull
    dirs = []
    for k in range(6):
        el, az = math.radians(20 + 10 * k), math.radians(60 * k)
        dirs.append((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
    rig = Rig("t", 500.0, Camera(direction=(0.0, 0.0, 1.0)), (40.0, 40.0), tuple(Light(direction=d) for d in dirs))
    tilt = math.radians(25)
    n, photos = _lambertian_photos((math.sin(tilt) * 0.6, math.sin(tilt) * 0.8, math.cos(tilt)), (0.6, 0.4, 0.2), rig)
    pts = surface_points(rig.field_mm, (6, 6))
    xs = [photo_input(p, rig.light_set([k]), pts) for k, p in enumerate(photos)]
    slope, albedo, code = ps_estimate(lambda: ((x[None], None) for x in xs))
    got = torch.cat([slope[0], torch.ones(1, 6, 6)])
    got = got / got.norm(dim=0, keepdim=True)
    angle = math.degrees(math.acos(min(1.0, float((got[:, 2, 3] * n).sum()))))
    assert angle < 0.5
    torch.testing.assert_close(albedo[0, :, 2, 3], torch.tensor([0.6, 0.4, 0.2]), atol=0.01, rtol=0)
    assert code.shape == (1, 7, 6, 6) and torch.isfinite(code).all()
    # one photo cannot fix a normal: the ridge keeps it near flat, and the conditioning
    # channel says so
    slope1, _, code1 = ps_estimate(lambda: iter([(xs[0][None], None)]))
    assert float(code1[0, 5].max()) < 0.05 < float(code[0, 5].min())
    assert float(slope1.abs().max()) < float(slope.abs().max())


@pytest.mark.parametrize("ps_skip", [False, True])
def test_pooling_takes_any_number_and_order_of_photos(ps_skip):
    torch.manual_seed(0)
    net = AnyRigNet(AnyRigConfig(ps_skip=ps_skip)).eval()
    x = torch.randn(1, 5, 10, 16, 16)
    with torch.no_grad():
        a = net(x, torch.ones(1, 5))
        b = net(x[:, [3, 0, 4, 1, 2]], torch.ones(1, 5))
        c = net(torch.cat([x, torch.randn(1, 2, 10, 16, 16)], 1), torch.tensor([[1.0, 1, 1, 1, 1, 0, 0]]))
        one = net(x[:, :1], torch.ones(1, 1))
    tol = 1e-4 if ps_skip else 1e-5  # the skip's solve sums photos in another order
    streamed_tol = tol
    for key in a:
        torch.testing.assert_close(a[key], b[key], atol=tol, rtol=0)  # order does not matter
        torch.testing.assert_close(a[key], c[key], atol=tol, rtol=0)  # absent photos do not count
    streamed = net.predict(iter(x[0]))
    for key in a:
        torch.testing.assert_close(streamed[key], a[key][0], atol=streamed_tol, rtol=0)
    assert one["normal"].shape == (1, 3, 16, 16)
    torch.testing.assert_close(one["normal"].norm(dim=1), torch.ones(1, 16, 16), atol=1e-5, rtol=0)
    f = torch.tensor([[[[[1.0]]], [[[5.0]]]]])  # (B=1, K=2, C=1, 1, 1)
    assert pool(f, torch.tensor([[1.0, 0.0]])).flatten().tolist() == [1.0, 1.0]


def test_random_rigs_are_valid():
    g = torch.Generator().manual_seed(3)
    kinds = set()
    for _ in range(40):
        lights, _ = random_lights(g, 5)
        d = lights.position / lights.position.norm(dim=-1, keepdim=True)
        assert bool((d[:, 2] > math.sin(math.radians(9))).all())  # above 10° (flashes: far above)
        assert torch.isfinite(lights.intensity).all() and bool((lights.intensity > 0).all())
        kinds.add(("point" if bool((lights.w == 1).all()) else "dir", float(lights.camera_w[0])))
    assert {("dir", 0.0), ("dir", 1.0), ("point", 1.0)} <= kinds


def test_it_learns_a_batch():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    batch = _batch(g, TrainAnyRig(size=16, batch=2, max_photos=4))
    net = AnyRigNet()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    present = torch.ones(batch["x"].shape[:2])
    with torch.no_grad():
        first = float(loss(net(batch["x"], present), batch))
    for _ in range(40):
        value = loss(net(batch["x"], present), batch)
        opt.zero_grad()
        value.backward()
        opt.step()
    with torch.no_grad():
        assert float(loss(net(batch["x"], present), batch)) < 0.6 * first


def test_without_a_library_a_sample_is_the_procedural_material_of_its_first_draw():
    from matscan.anyrig import sample
    from matscan.materials.procedural import random_material

    got = sample(torch.Generator().manual_seed(5), 16, 2, prior="v4")
    seed = int(torch.randint(0, 2**31 - 1, (), generator=torch.Generator().manual_seed(5)))
    want = random_material(16, seed, prior="v4")[1]
    for k in ("diffuse", "specular", "roughness", "normal"):
        torch.testing.assert_close(got[k], getattr(want, k), rtol=0, atol=0)


def test_library_samples_are_crops_of_the_library_maps():
    from matscan.anyrig import sample
    from matscan.mapset import MapSet

    # every pixel of the 24² set has its own diffuse value, so a crop's place is unique
    ramp = torch.arange(24 * 24, dtype=torch.float32).view(1, 24, 24) / (24 * 24)
    normal = torch.nn.functional.normalize(torch.stack([ramp[0] - 0.5, 0.5 - ramp[0], torch.ones(24, 24)]), dim=0)
    lib = MapSet(
        diffuse=torch.cat([ramp, 1 - ramp, ramp.flip(-1)]),
        specular=torch.full((3, 24, 24), 0.04),
        roughness=0.2 + 0.5 * ramp,
        normal=normal,
    )
    g = torch.Generator().manual_seed(2)
    places = set()
    for _ in range(6):
        s = sample(g, 8, 3, library=[lib], library_prob=1.0)
        found = [
            (r, c)
            for r in range(24 - 8 + 1)
            for c in range(24 - 8 + 1)
            if torch.equal(s["diffuse"], lib.diffuse[:, r : r + 8, c : c + 8])
        ]
        assert len(found) == 1
        r, c = found[0]
        assert torch.equal(s["normal"], lib.normal[:, r : r + 8, c : c + 8])
        assert torch.equal(s["roughness"], lib.roughness[:, r : r + 8, c : c + 8])
        assert s["x"].shape == (3, 10, 8, 8) and torch.isfinite(s["x"]).all()
        places.add(found[0])
    assert len(places) > 1  # the crop moves
    metal = sample(torch.Generator().manual_seed(2), 8, 1, library=[lib], library_prob=1.0, library_metal_prob=1.0)
    assert float(metal["specular"].amax()) > 0.3  # metal patches: F0 far above the set's 0.04


def test_train_anyrig_mixes_a_library_and_names_a_bad_folder(tmp_path, capsys):
    from matscan.cli import main
    from matscan.mapset import write_mapset
    from matscan.materials.procedural import random_material

    write_mapset(tmp_path / "lib", random_material(32, 1)[1])
    small = ["--size", "16", "--batch", "2", "--max-photos", "2", "--max-steps", "2"]
    out = tmp_path / "run"
    assert main(["train-anyrig", "--out", str(out), "--library", str(tmp_path / "lib"), "--lr", "1e-4", *small]) == 0
    import json

    cfg = json.loads((out / "config.json").read_text())["train"]
    assert cfg["library"] == [str(tmp_path / "lib")] and cfg["lr"] == 1e-4
    capsys.readouterr()
    code = main(["train-anyrig", "--out", str(tmp_path / "bad"), "--library", str(tmp_path / "nowhere"), *small])
    err = capsys.readouterr().err.strip()
    assert code != 0 and str(tmp_path / "nowhere") in err and len(err.splitlines()) == 1
    assert not (tmp_path / "bad").exists()  # checked before the run folder is made
    with pytest.raises(SystemExit):
        main(["train-anyrig", "--out", str(tmp_path / "bad"), "--library-prob", "1.5", *small])


# --- inference over a whole capture, and reconstruct's --anyrig -------------------------


def _rti_capture(tmp_path, size=(44, 58), count=9):
    """A simulated capture of a 9-light directional dome (no dome24 network reads it)."""
    from matscan.capture.folder import write_capture
    from matscan.capture.rti import LightFile, rig_from_lp
    from matscan.capture.virtual import CameraModel, simulate_images
    from matscan.materials.procedural import generate

    dirs = []
    for k in range(count):
        e, a = math.radians((20.0, 45.0, 70.0)[k % 3]), 2 * math.pi * k / count
        dirs.append((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))
    rig = rig_from_lp(LightFile(tuple(f"{k:02d}.png" for k in range(count)), tuple(dirs)), (58.0, 44.0))
    maps = generate("leather", max(size), 4).crop(0, 0, *size)
    photos = simulate_images(maps, rig.light_set(), rig.field_mm, CameraModel(read_noise=0.002), seed=1)
    write_capture(tmp_path / "rti", photos, rig, light_indices=list(range(count)))
    return tmp_path / "rti"


def _weights(tmp_path, ps_skip=False):
    from safetensors.torch import save_file

    torch.manual_seed(5)
    path = tmp_path / "anyrig.safetensors"
    save_file(AnyRigNet(AnyRigConfig(ps_skip=ps_skip)).state_dict(), path)
    return path


def test_a_run_keeps_its_network_and_load_knows_it(tmp_path):
    from matscan.anyrig import load, train
    from matscan.errors import MatscanError

    cfg = TrainAnyRig(size=16, batch=1, max_photos=3)
    assert train(tmp_path / "run", cfg, max_steps=2, net_cfg=AnyRigConfig(ps_skip=True))["steps"] == 2
    assert load(tmp_path / "run" / "checkpoint.safetensors").cfg == AnyRigConfig(ps_skip=True)
    assert train(tmp_path / "run", cfg, max_steps=3)["steps"] == 3  # resumes with the checkpoint's network
    with pytest.raises(MatscanError, match="use a new run folder"):
        train(tmp_path / "run", cfg, max_steps=4, net_cfg=AnyRigConfig(ps_skip=False))
    assert load(_weights(tmp_path)).cfg == AnyRigConfig(ps_skip=False)
    from matscan.cli import main

    small = ["--size", "16", "--batch", "1", "--max-photos", "3"]
    assert main(["train-anyrig", "--out", str(tmp_path / "plain"), "--max-steps", "1", "--no-ps-skip", *small]) == 0
    assert main(["train-anyrig", "--out", str(tmp_path / "plain"), "--max-steps", "2", *small]) == 0  # keeps it
    assert load(tmp_path / "plain" / "checkpoint.safetensors").cfg == AnyRigConfig(ps_skip=False)
    assert main(["train-anyrig", "--out", str(tmp_path / "plain"), "--max-steps", "3", "--ps-skip", *small]) != 0


@pytest.mark.parametrize("ps_skip", [False, True])
def test_tiles_give_the_whole_image_maps(tmp_path, ps_skip):
    """One tile over the whole capture is the network's forward pass on the stacked
    inputs; overlapping tiles blend to nearly the same maps."""
    import torch.nn.functional as F

    from matscan.anyrig import load, predict_capture
    from matscan.capture import load_capture

    cap = load_capture(_rti_capture(tmp_path))
    net = load(_weights(tmp_path, ps_skip))
    h, w = cap.size
    points = surface_points(cap.field_mm, (h, w))
    x = torch.stack([photo_input(cap.linear([i])[0], cap.lights.select([i]), points) for i in range(9)])
    x = F.pad(x, (0, (-w) % 4, 0, (-h) % 4), mode="replicate")
    with torch.no_grad():
        direct = net(x[None], torch.ones(1, 9))
    whole = predict_capture(net, cap, tile=512)
    tiled = predict_capture(net, cap, tile=24, overlap=12)
    for key in whole:
        torch.testing.assert_close(whole[key], direct[key][0, :, :h, :w], atol=1e-5, rtol=0)
        assert float((tiled[key] - whole[key]).abs().mean()) < 0.01
    torch.testing.assert_close(tiled["normal"].norm(dim=0), torch.ones(h, w), atol=1e-5, rtol=0)


def test_reconstruct_starts_from_the_anyrig_network_where_the_dome24_networks_do_not_apply(tmp_path):
    import json

    from matscan.reconstruct import ReconstructConfig
    from matscan.reconstruct.job import reconstruct

    capture, weights = _rti_capture(tmp_path), _weights(tmp_path)
    rec = reconstruct(capture, tmp_path / "a", ReconstructConfig(anyrig=str(weights)))
    assert rec["start"] == "any-rig network" and rec["refined"]
    assert not any("light slots" in w for w in rec["warnings"])  # asked for: its use, not a warning
    assert json.loads((tmp_path / "a" / "matscan.json").read_text())["model"]["anyrig_file"].endswith(
        "anyrig.safetensors"
    )
    plain = reconstruct(capture, tmp_path / "b", ReconstructConfig())
    assert plain["start"] == "flat" and plain["model"]["anyrig_file"] is None
    assert any("starting refinement from flat maps" in w for w in plain["warnings"])


def test_bad_anyrig_weights_are_one_line_errors(tmp_path, capsys):
    from safetensors.torch import save_file

    from matscan.cli import main

    capture = _rti_capture(tmp_path)
    text = tmp_path / "notes.safetensors"
    text.write_text("not weights")
    foreign = tmp_path / "foreign.safetensors"
    save_file({"encoder.weight": torch.zeros(2, 2)}, foreign)
    for path, message in (
        (tmp_path / "missing.safetensors", "no such weights file"),
        (text, "is not a readable safetensors file"),
        (foreign, "is not an any-rig network's weights"),
    ):
        code = main(["reconstruct", str(capture), "--out", str(tmp_path / "out"), "--anyrig", str(path)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and len(err.splitlines()) == 1
        assert not (tmp_path / "out" / "matscan.json").exists()


def test_bad_anyrig_weights_are_named_where_the_dome24_networks_read_the_capture(tmp_path, capsys):
    """On dome24 the shipped networks read the capture and the any-rig network is not
    used, but a damaged ``--anyrig`` file is still an error: it was passed over in
    silence, and failed later on the first capture of another rig."""
    from matscan.cli import main

    text = tmp_path / "notes.safetensors"
    text.write_text("not weights")
    code = main(["reconstruct", "@sample", "--out", str(tmp_path / "out"), "--anyrig", str(text), "--refine", "off"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "notes.safetensors: is not a readable safetensors file" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_the_moving_average_is_the_mean_of_the_weights_it_has_seen(tmp_path):
    """With ``ema`` the checkpoint keeps w̄ ← d·w̄ + (1 − d)·w after every step; from a
    run's own weights: after one step at decay d it is d·w0 + (1 − d)·w1 exactly, and load
    gives it, not the raw weights. Resuming carries it on."""
    from safetensors.torch import load_file

    from matscan.anyrig import load, train
    from matscan.cli import main

    cfg = TrainAnyRig(size=16, batch=1, max_photos=3)
    run = tmp_path / "run"
    train(run, cfg, max_steps=1)
    w0 = load_file(run / "checkpoint.safetensors")
    assert not any(k.startswith("ema.") for k in w0)  # none unless asked for
    d = 0.75
    train(run, TrainAnyRig(size=16, batch=1, max_photos=3, ema=d), max_steps=2)
    w1 = load_file(run / "checkpoint.safetensors")
    names = [k for k in w1 if not k.startswith("ema.") and k != "step"]
    assert int(w1["step"]) == 2 and names
    moved = 0
    for k in names:
        torch.testing.assert_close(w1["ema." + k], d * w0[k] + (1 - d) * w1[k], rtol=0, atol=1e-6)
        moved += int(not torch.equal(w0[k], w1[k]))
    assert moved > 0
    net = load(run / "checkpoint.safetensors")
    for k, v in net.state_dict().items():
        torch.testing.assert_close(v, w1["ema." + k], rtol=0, atol=0)
    for k, v in load(run / "checkpoint.safetensors", averaged=False).state_dict().items():
        torch.testing.assert_close(v, w1[k], rtol=0, atol=0)
    train(run, TrainAnyRig(size=16, batch=1, max_photos=3, ema=d), max_steps=3)
    w2 = load_file(run / "checkpoint.safetensors")
    for k in names:
        torch.testing.assert_close(w2["ema." + k], d * w1["ema." + k] + (1 - d) * w2[k], rtol=0, atol=1e-6)
    small = ["--size", "16", "--batch", "1", "--max-photos", "3"]
    assert main(["train-anyrig", "--out", str(run), "--max-steps", "4", *small]) == 2  # would drop the average
    assert int(load_file(run / "checkpoint.safetensors")["step"]) == 3
    assert main(["train-anyrig", "--out", str(tmp_path / "bad"), "--max-steps", "1", "--ema", "1", *small]) == 2
    assert not (tmp_path / "bad").exists()


def test_a_run_exports_its_averaged_weights_in_float16(tmp_path):
    """weights.safetensors holds the checkpoint's moving average (what ``load`` uses) cast
    to float16, without the raw weights or the step, which goes in the metadata; it loads
    as the same network to float16's precision. A file that is not a network is a one-line
    error and writes nothing."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    from matscan.anyrig import export, load, train
    from matscan.errors import MatscanError

    run = tmp_path / "run"
    result = train(run, TrainAnyRig(size=16, batch=1, max_photos=3, ema=0.5), max_steps=2)
    assert result["weights"] == str(run / "weights.safetensors")
    ckpt, shipped = load_file(run / "checkpoint.safetensors"), load_file(run / "weights.safetensors")
    assert set(shipped) == {k[len("ema.") :] for k in ckpt if k.startswith("ema.")}
    for k, v in shipped.items():
        assert v.dtype == torch.float16
        assert torch.equal(v, ckpt["ema." + k].to(torch.float16))
    with safe_open(run / "weights.safetensors", "pt") as f:
        assert f.metadata()["step"] == "2" and f.metadata()["format"] == "matscan-anyrig/1"
    x = torch.rand(1, 3, 10, 16, 16)
    present = torch.ones(1, 3)
    with torch.no_grad():
        a = load(run / "checkpoint.safetensors")(x, present)
        b = load(run / "weights.safetensors")(x, present)
    for name in a:
        torch.testing.assert_close(b[name], a[name], rtol=0, atol=2e-2)
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a network")
    with pytest.raises(MatscanError, match="bad.safetensors") as err:
        export(bad, tmp_path / "out.safetensors")
    assert "\n" not in str(err.value) and not (tmp_path / "out.safetensors").exists()


def test_the_rendering_term_adds_the_log_l1_of_relighting_under_novel_lights(tmp_path, capsys):
    """``render_weight`` adds w · Σ_k mean |log(0.01 + rendering of the prediction) −
    log(0.01 + rendering of the truth)| over the novel lights k, each sample at its own
    surface points; true maps cost nothing, and a roughness off by 0.2 costs its map term
    plus that, recomputed here from :func:`matscan.render.render` per sample."""
    from matscan.anyrig import _batch, loss, render_lights
    from matscan.cli import main
    from matscan.render import render
    from matscan.rig import LightSet

    g = torch.Generator().manual_seed(3)
    batch = _batch(g, TrainAnyRig(size=16, batch=2, max_photos=3))
    assert batch["points"].shape == (2, 16, 16, 3)
    truth = {k: batch[k] for k in ("diffuse", "specular", "roughness", "normal")}
    lights = render_lights(torch.Generator().manual_seed(1), 2, 4)
    assert float(loss(truth, batch, 0.5, lights)) == pytest.approx(0.0, abs=1e-6)
    pred = {**truth, "roughness": (truth["roughness"] + 0.2).clamp(0, 1)}
    relight = []
    for b in range(2):
        one = LightSet.points(lights.position[b][None], lights.camera[b][None], lights.reference_distance_mm)
        a = render(*(pred[k][b : b + 1] for k in truth), one, batch["points"][b : b + 1])
        t = render(*(truth[k][b : b + 1] for k in truth), one, batch["points"][b : b + 1])
        relight.append((torch.log(0.01 + a) - torch.log(0.01 + t)).abs().mean(dim=(0, 2, 3, 4)))
    expected = float(torch.stack(relight).mean(0).sum())
    assert expected > 0.01
    plain = float(loss(pred, batch))
    assert plain == pytest.approx(float((pred["roughness"] - truth["roughness"]).abs().mean()), rel=1e-5)
    assert float(loss(pred, batch, 0.5, lights)) == pytest.approx(plain + 0.5 * expected, rel=1e-4)
    with pytest.raises(ValueError):
        loss(pred, batch, 0.5)
    small = ["--size", "16", "--batch", "1", "--max-photos", "3", "--max-steps", "2"]
    assert main(["train-anyrig", "--out", str(tmp_path / "r"), "--render-weight", "0.0417", *small]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["train-anyrig", "--out", str(tmp_path / "bad"), "--render-weight", "-1", *small])
    assert "--render-weight" in capsys.readouterr().err


def test_miscalibrated_lights_are_off_by_the_drawn_angle_and_brightness():
    """Each light's place turns by |N(0, σ)| (the half-normal's mean is σ √(2/π)) at its own
    distance, its intensity scales by 1 + N(0, s); none is moved with σ = s = 0."""
    from matscan.anyrig import miscalibrated

    g = torch.Generator().manual_seed(4)
    lights, _ = random_lights(g, 4000)
    same = miscalibrated(lights, torch.Generator().manual_seed(1), 0.0, 0.0)
    torch.testing.assert_close(same.position, lights.position)
    torch.testing.assert_close(same.intensity, lights.intensity)
    off = miscalibrated(lights, torch.Generator().manual_seed(1), 3.0, 0.1)
    a, b = lights.position.double(), off.position.double()
    torch.testing.assert_close(b.norm(dim=-1), a.norm(dim=-1), rtol=1e-5, atol=0)
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))
    angle = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
    assert abs(float(angle.mean()) - 3.0 * math.sqrt(2 / math.pi)) < 0.1
    ratio = off.intensity[:, 0] / lights.intensity[:, 0]
    assert abs(float(ratio.mean()) - 1) < 0.01 and abs(float(ratio.std()) - 0.1) < 0.01
    torch.testing.assert_close(off.axis.double(), -b / b.norm(dim=-1, keepdim=True), atol=1e-6, rtol=0)


def test_train_anyrig_trains_on_miscalibrated_captures_and_refuses_wild_ones(tmp_path, capsys):
    import json

    from matscan.cli import main

    small = ["--size", "16", "--batch", "2", "--max-photos", "2", "--max-steps", "2"]
    out = tmp_path / "run"
    assert main(["train-anyrig", "--out", str(out), "--miscalibration", "3,0.1", *small]) == 0
    cfg = json.loads((out / "config.json").read_text())["train"]
    assert (cfg["miscal_degrees"], cfg["miscal_intensity"]) == (3.0, 0.1)
    capsys.readouterr()
    for bad in ("90,0.1", "3", "3,nan"):
        assert main(["train-anyrig", "--out", str(tmp_path / "bad"), "--miscalibration", bad, *small]) == 2
        err = capsys.readouterr().err.strip()
        assert "--miscalibration" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "bad").exists()


def test_miscalibration_can_spare_single_photos():
    """``miscal_min_photos`` 2: a one-photo sample is photographed under the very light it
    names (the same draws as with no miscalibration), a two-photo sample is not."""
    from matscan.anyrig import TrainAnyRig, _batch

    off = {"miscal_degrees": 3.0, "miscal_intensity": 0.1, "miscal_min_photos": 2}
    for k, spared in ((1, True), (2, False)):
        plain = TrainAnyRig(size=16, batch=1, min_photos=k, max_photos=k)
        a = _batch(torch.Generator().manual_seed(3), replace(plain, **off))
        b = _batch(torch.Generator().manual_seed(3), plain)
        assert torch.equal(a["x"], b["x"]) is spared


def test_one_photo_starts_from_flat_maps_even_with_an_anyrig_network(tmp_path):
    from matscan.anyrig import load
    from matscan.capture import load_capture
    from matscan.reconstruct import ReconstructConfig, reconstruct_capture

    cap = load_capture(_rti_capture(tmp_path))
    net = load(_weights(tmp_path))
    one = reconstruct_capture(cap.select([4]), ReconstructConfig(), None, anyrig=net)
    assert one.start == "flat" and any("one photo: starting from flat maps" in w for w in one.warnings)
    two = reconstruct_capture(cap.select([2, 4]), ReconstructConfig(), None, anyrig=net)
    assert two.start == "any-rig network"


def _plane(size, albedo: float, tilt_degrees: float):
    """A uniform plane of grey albedo, specular 0.04 and roughness 0.6, its normal tilted
    toward +x."""
    from matscan.mapset import MapSet

    h, w = size
    t = math.radians(tilt_degrees)
    n = torch.tensor([math.sin(t), 0.0, math.cos(t)]).view(3, 1, 1).expand(3, h, w).clone()
    return MapSet(
        diffuse=torch.full((3, h, w), albedo),
        specular=torch.full((3, h, w), 0.04),
        roughness=torch.full((1, h, w), 0.6),
        normal=n,
    )


def _plane_capture(maps, count: int):
    """The 9-light directional dome of ``_rti_capture`` photographing ``maps`` with
    ``count`` of its lights (the first ``count``, or every third for 3)."""
    from matscan.capture import Capture
    from matscan.capture.rti import LightFile, rig_from_lp
    from matscan.capture.virtual import CameraModel, simulate_images

    dirs = []
    for k in range(9):
        e, a = math.radians((20.0, 45.0, 70.0)[k % 3]), 2 * math.pi * k / 9
        dirs.append((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))
    rig = rig_from_lp(LightFile(tuple(f"{k:02d}.png" for k in range(9)), tuple(dirs)), (58.0, 44.0))
    idx = [0, 3, 6] if count == 3 else list(range(count))
    lights = rig.light_set(idx)
    photos = simulate_images(maps, lights, rig.field_mm, CameraModel(read_noise=0.002), seed=1)
    names = tuple(f"{k:02d}.png" for k in idx)
    return Capture(
        rig, rig.field_mm, "srgb", photos, (photos >= 1 - 0.5 / 255).any(1, keepdim=True), tuple(idx), lights, names
    )


def _degrees(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(0).clamp(-1, 1)))


def test_the_shipped_anyrig_network_reads_a_flat_plane():
    """The shipped weights, on a rig they never saw: a flat grey plane (normal up, known
    albedo) from 3 and 9 photos comes back flat within 3° and with its albedo within 0.03."""
    from matscan.anyrig import predict_capture
    from matscan.weights import load_anyrig

    net = load_anyrig("default")
    for albedo in (0.2, 0.5):
        maps = _plane((44, 58), albedo, 0.0)
        for count in (3, 9):
            got = predict_capture(net, _plane_capture(maps, count))
            assert float(_degrees(got["normal"], maps.normal).mean()) < 3.0
            torch.testing.assert_close(got["diffuse"].mean((1, 2)), torch.full((3,), albedo), atol=0.03, rtol=0)


def test_the_solver_holds_the_anyrig_maps_by_photo_count(monkeypatch):
    """``reconstruct`` refines the any-rig network's maps held with ``anyrig_hold`` of the
    photo count (2 from 2 photos, 4 from 3 and 4, the flat start's 0.2 from 5), and flat
    maps with 0.2 at every count."""
    from matscan.reconstruct import ReconstructConfig, job, reconstruct_capture

    seen: list[float] = []
    real = job.solve_maps

    def spy(start, capture, cfg=None, strength=1.0, *args, **kwargs):
        seen.append(strength)
        return real(start, capture, cfg, strength, *args, **kwargs)

    monkeypatch.setattr(job, "solve_maps", spy)
    torch.manual_seed(5)
    net = AnyRigNet(AnyRigConfig()).eval()
    maps = _plane((20, 24), 0.4, 0.0)
    for count, strength in ((2, 2.0), (3, 4.0), (4, 4.0), (5, 0.2), (9, 0.2)):
        cap = _plane_capture(maps, count)
        assert reconstruct_capture(cap, ReconstructConfig(), None, anyrig=net).start == "any-rig network"
        assert reconstruct_capture(cap, ReconstructConfig(), None).start == "flat"
        assert seen[-2:] == [strength, job.FLAT_START_PRIOR]


def test_reconstruct_from_the_shipped_anyrig_network_finds_a_tilted_plane():
    """A plane tilted 15° (the network, trained on samples lying flat, reads it nearly
    flat): from 5 and 9 photos the solver, held loosely, brings the normals within 1° of
    the tilt; from 3, held hard, within 4° (flat maps: 0.5°; docs/rti.md)."""
    from matscan.reconstruct import ReconstructConfig, reconstruct_capture
    from matscan.weights import load_anyrig

    net = load_anyrig("default")
    maps = _plane((44, 58), 0.5, 15.0)
    for count, within in ((3, 4.0), (5, 1.0), (9, 1.0)):
        res = reconstruct_capture(_plane_capture(maps, count), ReconstructConfig(), None, anyrig=net)
        assert res.start == "any-rig network"
        assert float(_degrees(res.maps.normal, maps.normal).mean()) < within


def test_reconstruct_takes_the_shipped_anyrig_network_by_name(tmp_path, capsys):
    import json

    from matscan.cli import main

    capture = _rti_capture(tmp_path)
    assert main(["reconstruct", str(capture), "--out", str(tmp_path / "a"), "--anyrig", "default"]) == 0
    record = json.loads((tmp_path / "a" / "matscan.json").read_text())
    assert record["start"] == "any-rig network"
    assert record["model"]["anyrig_file"].endswith("anyrig-cpu.safetensors")
    assert "started from the any-rig network's maps, refined yes" in capsys.readouterr().out
    report = (tmp_path / "a" / "report.html").read_text(encoding="utf-8")
    assert "maps started from" in report and "anyrig-cpu.safetensors" in report
    assert main(["reconstruct", str(capture), "--out", str(tmp_path / "b"), "--anyrig", "nonsense"]) == 2
    err = capsys.readouterr().err.strip()
    assert "nor a shipped network (default)" in err and len(err.splitlines()) == 1


def test_tilted_turns_a_flat_normal_to_the_drawn_direction_and_keeps_angles():
    from matscan.anyrig import tilted

    flat = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 2, 2).clone()
    for t, phi in ((15.0, 0.0), (30.0, 120.0), (5.0, 270.0)):
        got = tilted(flat, t, phi)[:, 0, 0]
        a, p = math.radians(t), math.radians(phi)
        want = torch.tensor([math.sin(a) * math.cos(p), math.sin(a) * math.sin(p), math.cos(a)])
        torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    n = torch.randn(3, 5, 7)
    n = n / n.norm(dim=0, keepdim=True)
    m = tilted(n, 25.0, 40.0)
    gram = torch.einsum("cp,cq->pq", n.flatten(1), n.flatten(1))
    torch.testing.assert_close(torch.einsum("cp,cq->pq", m.flatten(1), m.flatten(1)), gram, atol=1e-5, rtol=0)
    torch.testing.assert_close(tilted(m, -25.0, 40.0), n, atol=1e-5, rtol=0)


def test_a_tilted_sample_is_its_material_turned_as_a_whole():
    """``train-anyrig --tilt``: a sample's true normals are those of the same material
    turned by one rotation of at most the given angle; without tilt the draws are the old ones."""
    from matscan.anyrig import sample

    plain = sample(torch.Generator().manual_seed(3), 16, 2)
    again = sample(torch.Generator().manual_seed(3), 16, 2, tilt=(0.0, 0.5))
    for key in plain:
        torch.testing.assert_close(again[key], plain[key], atol=0, rtol=0)
    turned = sample(torch.Generator().manual_seed(3), 16, 2, tilt=(20.0, 1.0))
    a, b = plain["normal"].flatten(1), turned["normal"].flatten(1)
    r = torch.linalg.lstsq(a.T.double(), b.T.double()).solution.T  # b = r a
    torch.testing.assert_close((r @ a.double()).float(), b, atol=1e-4, rtol=0)
    torch.testing.assert_close(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-4, rtol=0)
    assert abs(float(torch.linalg.det(r)) - 1) < 1e-4  # a rotation, not a mirror
    angle = math.degrees(math.acos(min(1.0, float(r[2, 2]))))
    assert 0 < angle <= 20.0 + 1e-3


def test_train_anyrig_refuses_a_wild_tilt(tmp_path, capsys):
    from matscan.cli import main

    for bad in ("90,0.5", "10,2", "10"):
        assert main(["train-anyrig", "--out", str(tmp_path / "run"), "--tilt", bad, "--max-steps", "1"]) == 2
        err = capsys.readouterr().err.strip()
        assert "--tilt" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_batch_passes_the_shipped_anyrig_network_to_every_capture(tmp_path):
    import json

    pytest.importorskip("distributed")
    from matscan.cli import main

    captures = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        captures.append(str(_rti_capture(tmp_path / name)))
    assert main(["batch", *captures, "--out", str(tmp_path / "out"), "--anyrig", "default", "--workers", "1"]) == 0
    records = sorted((tmp_path / "out").glob("*/matscan.json"))
    assert len(records) == 2
    for path in records:
        record = json.loads(path.read_text())
        assert record["start"] == "any-rig network"
        assert record["model"]["anyrig_file"].endswith("anyrig-cpu.safetensors")
