"""Evaluation: the trivial baseline recovers a flat Lambertian albedo exactly; scores are RMSEs."""

from __future__ import annotations

import pytest
import torch

from matscan.data import DataConfig, SvbrdfDataset
from matscan.evaluate import Scores, baseline_maps
from matscan.mapset import MapSet, write_mapset


def test_baseline_recovers_flat_lambertian_albedo(tmp_path):
    size = 24
    n = torch.zeros(3, size, size)
    n[2] = 1
    rho = torch.tensor([0.4, 0.25, 0.1]).view(3, 1, 1).expand(3, size, size).clone()
    write_mapset(
        tmp_path / "flat",
        MapSet(rho, torch.zeros(3, size, size), torch.full((1, size, size), 0.5), n),
        file_format="exr",
    )
    ds = SvbrdfDataset(
        DataConfig(
            crop=16,
            library=(str(tmp_path / "flat"),),
            library_prob=1.0,
            mix_prob=0.0,
            read_noise=(0.0, 0.0),
            exposure_jitter=0.0,
            white_balance_jitter=0.0,
            led_jitter=0.0,
            srgb_prob=0.0,
            compile=False,
            subsets="6",
        )
    )
    sample = ds[0]
    est = baseline_maps(sample, ds.rig)
    # 16-bit linear quantisation of photos of about 0.1–0.5: relative error well under 1e-3
    torch.testing.assert_close(est["diffuse"], sample["diffuse"], atol=2e-4, rtol=1e-3)
    assert torch.equal(est["normal"][2], torch.ones(16, 16))


def test_scores_are_rmse_and_degrees():
    s = Scores()
    truth = {"diffuse": torch.zeros(1, 3, 2, 2), "normal": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)}
    pred = {"diffuse": torch.full((1, 3, 2, 2), 0.5), "normal": torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1)}
    s.add(pred, truth)
    res = s.result()
    assert res["rmse_diffuse"] == 0.5 and abs(res["normal_degrees"] - 90.0) < 1e-4


def test_map_scores_of_the_truth_are_perfect():
    from conftest import random_maps

    from matscan.evaluate import map_scores, rendering_scores
    from matscan.rig import builtin_rig

    truth = random_maps(16, seed=3)
    s = map_scores(truth, truth)
    assert all(s[f"rmse_{m}"] == 0 for m in ("diffuse", "specular", "roughness", "normal"))
    assert s["normal_degrees"] < 0.05 and abs(s["ssim_diffuse"] - 1) < 1e-6
    r = rendering_scores(truth, truth, builtin_rig("dome24").light_set([0, 9]), (120.0, 120.0), "rig")
    assert r["rig_rmse"] == 0 and r.get("rig_flip", 0.0) == 0.0


def test_study_writes_results(tmp_path):
    import json

    from matscan.evaluate import evaluate_to_folder
    from matscan.materials.photos import photo_material
    from matscan.materials.procedural import random_material

    materials = [("proc", random_material(24, 2**41)[1]), ("brick", photo_material("brick", 24))]
    res = evaluate_to_folder(materials, tmp_path / "ev", ["3", "24"], ["fit"], ["srgb8"], refine_steps=10)
    assert res["rows"] == 4
    rows = json.loads((tmp_path / "ev" / "results.json").read_text())["rows"]
    assert {r["lights"] for r in rows} == {"3", "24"}
    assert all(0 <= r["novel_rmse"] < 0.5 for r in rows)
    text = (tmp_path / "ev" / "results.md").read_text()
    assert "| fit | 3 |" in text and "| fit | 24 |" in text


def test_photo_materials_are_deterministic_and_in_range():
    from matscan.materials.photos import photo_material

    a, b = photo_material("gravel", 32), photo_material("gravel", 32)
    assert torch.equal(a.diffuse, b.diffuse)
    assert 0.04 <= float(a.diffuse.min()) and float(a.diffuse.max()) <= 0.76
    torch.testing.assert_close(a.normal.norm(dim=0), torch.ones(32, 32), atol=1e-5, rtol=0)


def test_study_in_two_processes_equals_one_and_baseline_is_the_flat_start(tmp_path):
    from matscan.evaluate import run_study
    from matscan.materials.procedural import random_material

    truth = random_material(24, 2**41 + 5)[1]
    args = ([("proc", truth)], "dome24", ["1", "6"], ["baseline", "fit"], ["srgb8", "linear16"], 5)
    one = run_study(*args)
    two = run_study(*args, jobs=2)
    assert [(r["encoding"], r["lights"], r["method"]) for r in one] == [
        (r["encoding"], r["lights"], r["method"]) for r in two
    ]
    for a, b in zip(one, two, strict=True):
        for k, v in a.items():
            if k not in ("seconds", "material", "encoding", "lights", "method"):
                assert abs(v - b[k]) < 1e-4, (k, v, b[k])
    # the baseline's roughness is 0.5 and its normal is flat: scores in closed form from the truth
    base = next(r for r in one if r["method"] == "baseline")
    assert abs(base["rmse_roughness"] - float((truth.roughness - 0.5).square().mean().sqrt())) < 1e-6
    flat = torch.rad2deg(torch.acos(truth.normal[2].clamp(-1, 1))).mean()
    assert abs(base["normal_degrees"] - float(flat)) < 1e-3


def test_study_refuses_bad_methods_and_a_full_folder_before_working(tmp_path):
    import pytest

    from matscan.errors import MatscanError
    from matscan.evaluate import evaluate_to_folder
    from matscan.materials.procedural import random_material

    materials = [("proc", random_material(16, 2**41)[1])]
    with pytest.raises(MatscanError, match="'magic' is not one of"):
        evaluate_to_folder(materials, tmp_path / "a", ["1"], ["magic"], ["srgb8"])
    with pytest.raises(MatscanError, match="no such weights file"):
        evaluate_to_folder(materials, tmp_path / "a", ["1"], ["nets:missing.safetensors"], ["srgb8"])
    with pytest.raises(MatscanError, match="'jpeg' is not one of"):
        evaluate_to_folder(materials, tmp_path / "a", ["1"], ["fit"], ["jpeg"])
    with pytest.raises(MatscanError, match=r"--lights: '0' is not one of the light counts of rig dome24 \(1, 2, 3, 6,"):
        evaluate_to_folder(materials, tmp_path / "a", ["1", "0"], ["fit"], ["srgb8"])
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(MatscanError, match="not empty"):
        evaluate_to_folder(materials, tmp_path / "full", ["1"], ["fit"], ["srgb8"])


def test_summary_tables_have_a_row_per_method_and_source():
    from matscan.evaluate import summary_table

    rows = [
        {"material": "procedural-000-x", "encoding": "srgb8", "lights": "1", "method": "fit", "rmse_diffuse": 0.1},
        {"material": "procedural-001-y", "encoding": "srgb8", "lights": "1", "method": "fit", "rmse_diffuse": 0.3},
        {"material": "photo-brick", "encoding": "srgb8", "lights": "1", "method": "fit", "rmse_diffuse": 0.5},
    ]
    text = summary_table(rows, "source")
    assert "| fit | procedural | 0.2000 |" in text and "| fit | photo | 0.5000 |" in text


def _lambertian_capture(rho: torch.Tensor, indices, size: int):
    """A capture whose photos are exactly ρ times each dome24 LED's flat irradiance (a
    Lambertian plane, no renderer involved)."""
    from matscan.capture import Capture
    from matscan.render import flat_irradiance, surface_points
    from matscan.rig import builtin_rig

    rig = builtin_rig("dome24")
    ls = rig.light_set(list(indices))
    photos = rho * flat_irradiance(ls, surface_points(rig.field_mm, (size, size)))
    saturated = torch.zeros(len(indices), 1, size, size, dtype=torch.bool)
    return Capture(rig, rig.field_mm, "linear", photos, saturated, tuple(indices), ls, tuple(f"{k}" for k in indices))


@pytest.mark.parametrize("subset", ["10", "16", "24"])
def test_hsh_with_falloff_relights_a_lambertian_plane_under_lights_at_other_distances(subset):
    # ρ E_k(p) is the constant term times the irradiance: the fit is exact, and so is its
    # relighting under the study's novel lights (R to 2R away, down to 10° elevation),
    # which a fit of directions alone (one per photo, no falloff) cannot give. Seen from a
    # pixel on the field's diagonal, the 10 lights leave one term undetermined: the fit
    # must still keep to the constant
    from matscan.evaluate import evaluation_lights, hsh_images
    from matscan.render import flat_irradiance, surface_points
    from matscan.rig import builtin_rig

    size = 20
    rho = torch.rand(3, size, size, generator=torch.Generator().manual_seed(4)) * 0.8 + 0.1
    capture = _lambertian_capture(rho, builtin_rig("dome24").subsets[subset], size)
    novel = evaluation_lights(capture.rig)
    expected = (rho * flat_irradiance(novel, surface_points(capture.field_mm, (size, size)))).clamp(0, 1)
    torch.testing.assert_close(hsh_images(capture, novel), expected, atol=2e-5, rtol=1e-4)


def test_hsh_leaves_saturated_pixels_out_of_its_fit():
    # a photo clipped at full scale over part of the field, marked saturated as a capture
    # marks it: the fit from the other photos is still exact there (and is not, read as is)
    from dataclasses import replace

    from matscan.evaluate import evaluation_lights, hsh_images
    from matscan.render import flat_irradiance, surface_points
    from matscan.rig import builtin_rig

    size = 12
    rho = torch.full((3, size, size), 0.5)
    capture = _lambertian_capture(rho, builtin_rig("dome24").subsets["24"], size)
    clipped = capture.images.clone()
    clipped[5, :, :6] = 1.0
    marked = capture.saturated.clone()
    marked[5, :, :6] = True
    novel = evaluation_lights(capture.rig)
    expected = (rho * flat_irradiance(novel, surface_points(capture.field_mm, (size, size)))).clamp(0, 1)
    torch.testing.assert_close(hsh_images(replace(capture, images=clipped, saturated=marked), novel), expected)
    unmarked = hsh_images(replace(capture, images=clipped), novel)
    assert float((unmarked - expected).abs().max()) > 0.01


def _directions_to(positions: torch.Tensor, size: int, field_mm: float = 120.0) -> torch.Tensor:
    """Unit vectors (L, H, W, 3) from each pixel centre to each point light, written out
    from design.md's frame: x = (j + 0.5)/W·width − width/2, y = height/2 − (i + 0.5)/H·height."""
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size * field_mm - field_mm / 2
    x, y = c[None, :].expand(size, size), -c[:, None].expand(size, size)
    p = torch.stack([x, y, torch.zeros_like(x)], dim=-1)
    v = positions.double()[:, None, None, :] - p[None]
    return (v / v.norm(dim=-1, keepdim=True)).float()


def test_hsh_relights_its_own_span_under_near_lights_with_each_pixels_directions():
    # photos E_k(p)·Σ c_j b_j(l_k(p)) with c varying over the field and l_k(p) toward each
    # LED from each pixel: relit under the study's novel lights as the same formula says
    # (a direction taken from the field's centre, or y flipped, is off by far more)
    from matscan.capture import Capture
    from matscan.evaluate import evaluation_lights, hsh_images
    from matscan.hsh import HSH_TERMS, hsh_basis
    from matscan.render import flat_irradiance, surface_points
    from matscan.rig import builtin_rig

    size, rig = 16, builtin_rig("dome24")
    indices = list(rig.subset("16"))
    ls, novel = rig.light_set(indices), evaluation_lights(rig)
    pts = surface_points(rig.field_mm, (size, size))
    coef = torch.rand(HSH_TERMS, 3, size, size, generator=torch.Generator().manual_seed(2)) * 0.1
    coef[0] += 0.4

    def images(lights):
        d = _directions_to(lights.position, size)
        b = hsh_basis(d.reshape(-1, 3)).float().view(*d.shape[:3], HSH_TERMS)
        return flat_irradiance(lights, pts) * torch.einsum("khwj,jchw->kchw", b, coef)

    photos = images(ls)
    assert float(photos.min()) > 0 and float(photos.max()) < 1
    saturated = torch.zeros(len(indices), 1, size, size, dtype=torch.bool)
    capture = Capture(rig, rig.field_mm, "linear", photos, saturated, tuple(indices), ls, tuple(map(str, indices)))
    expected = images(novel).clamp(0, 1)
    torch.testing.assert_close(hsh_images(capture, novel), expected, atol=1e-4, rtol=1e-3)


def test_hsh_field_fit_matches_per_pixel_least_squares():
    # each pixel's fit against numpy's lstsq of the same weighted problem (target outside
    # the span, each light with its own direction and irradiance at each pixel), with the
    # fit's ridge (1e-6 of AᵀA's trace, every term but the constant) as extra rows
    import numpy as np

    from matscan.hsh import HSH_TERMS, fit_hsh_field, hsh_basis

    g = torch.Generator().manual_seed(9)
    k, h, w = 14, 3, 4
    d = torch.randn(k, h, w, 3, generator=g)
    d[..., 2] = d[..., 2].abs() + 0.3
    d = d / d.norm(dim=-1, keepdim=True)
    e = torch.rand(k, 2, h, w, generator=g) + 0.2
    y = torch.rand(k, 2, h, w, generator=g)
    coef = fit_hsh_field(y, e, d, rows=2)
    for c in range(2):
        for i, j in ((0, 0), (2, 3), (1, 2)):
            a = (e[:, c, i, j, None] * hsh_basis(d[:, i, j])).numpy()
            ridge = np.sqrt(1e-6 * np.trace(a.T @ a)) * np.diag([0.0] + [1.0] * (HSH_TERMS - 1))
            target = np.concatenate([y[:, c, i, j].double().numpy(), np.zeros(HSH_TERMS)])
            ref, *_ = np.linalg.lstsq(np.concatenate([a, ridge]), target, rcond=None)
            np.testing.assert_allclose(coef[:, c, i, j].numpy(), ref, rtol=1e-4, atol=1e-5)
    assert coef.shape == (HSH_TERMS, 2, h, w)


def test_study_scores_hsh_on_relighting_only_and_from_nine_lights(tmp_path):
    import json

    from matscan.errors import MatscanError
    from matscan.evaluate import evaluate_to_folder
    from matscan.materials.photos import photo_material

    materials = [("brick", photo_material("brick", 24))]
    evaluate_to_folder(materials, tmp_path / "ev", ["6", "24"], ["baseline", "hsh"], ["linear16"])
    rows = json.loads((tmp_path / "ev" / "results.json").read_text())["rows"]
    assert [(r["lights"], r["method"]) for r in rows] == [("6", "baseline"), ("24", "baseline"), ("24", "hsh")]
    base, hsh = rows[1], rows[2]
    assert "rmse_diffuse" not in hsh
    # on a nearly Lambertian brick a curve fit to all 24 photos relights several times
    # better than the flat start does (0.0022 against 0.0169 when written)
    assert hsh["novel_rmse"] < 0.5 * base["novel_rmse"] and hsh["rig_rmse"] < 0.5 * base["rig_rmse"]
    text = (tmp_path / "ev" / "results.md").read_text()
    assert "| hsh | 24 |" in text and "| baseline | 6 |" in text
    # the header counts the runs made: hsh's 6-light run was not (1 × 1 × 2 × 2 would be 4)
    assert "1 materials × 1 encodings × 2 light subsets × 2 methods, 3 runs (hsh fits 9 photos or more);" in text
    # the per-source table compares the methods over the counts both have
    assert "mean over the light counts every method has (24) and encodings" in text
    with pytest.raises(MatscanError, match="hsh fits 9 coefficients a pixel and needs a subset of 9 or more"):
        evaluate_to_folder(materials, tmp_path / "ev2", ["6"], ["hsh"], ["srgb8"])
