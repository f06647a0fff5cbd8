"""Exports: the glTF loads with pygltflib and says what the maps say; the MaterialX document validates."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
import torch

from matscan.brdf import DIELECTRIC_F0, metallic_to_specular, specular_to_metallic
from matscan.color import linear_to_srgb, srgb_to_linear
from matscan.export import export_all, specular_residual
from matscan.imagefile import read_image
from matscan.mapset import MapSet


def _maps(alpha=None, coloured_dielectric=False):
    size = 8
    g = torch.Generator().manual_seed(0)
    base = torch.rand(3, size, size, generator=g) * 0.8 + 0.1
    metal = (torch.arange(size) >= 4).float().view(1, 1, size).expand(1, size, size).clone()
    diffuse, specular = metallic_to_specular(base, metal)
    if coloured_dielectric:
        specular = torch.tensor([0.02, 0.05, 0.09]).view(3, 1, 1).expand(3, size, size).clone()
        diffuse = base
    normal = torch.zeros(3, size, size)
    normal[0], normal[2] = 0.6, 0.8
    return MapSet(
        diffuse,
        specular,
        torch.full((1, size, size), 0.4),
        normal,
        alpha=alpha,
        basecolor=None if coloured_dielectric else base,
        metallic=None if coloured_dielectric else metal,
    )


def test_gltf_loads_and_matches_the_maps(tmp_path):
    import pygltflib

    maps = _maps()
    export_all(tmp_path, maps, (120.0, 60.0), exr=True, directx_normals=True)
    gltf = pygltflib.GLTF2().load(str(tmp_path / "material.gltf"))
    mat = gltf.materials[0]
    assert mat.pbrMetallicRoughness.metallicFactor == 1.0 and mat.alphaMode == "OPAQUE"
    assert gltf.extensionsUsed in ([], None)  # metal/rough represents these maps exactly
    # the quad is the sample's real size in metres
    blob = (tmp_path / "material.bin").read_bytes()
    xs = [struct.unpack_from("<3f", blob, 12 * i) for i in range(4)]
    assert max(p[0] for p in xs) == pytest.approx(0.06) and max(p[1] for p in xs) == pytest.approx(0.03)
    images = [im.uri for im in gltf.images]
    base = read_image(tmp_path / images[mat.pbrMetallicRoughness.baseColorTexture.index]).pixels
    np.testing.assert_allclose(
        srgb_to_linear(torch.from_numpy(base)).numpy(), maps.basecolor.permute(1, 2, 0).numpy(), atol=0.01
    )
    mr = read_image(tmp_path / images[mat.pbrMetallicRoughness.metallicRoughnessTexture.index]).pixels
    np.testing.assert_allclose(mr[..., 1], 0.4, atol=1 / 255)  # G: roughness
    np.testing.assert_allclose(mr[..., 2], maps.metallic[0].numpy(), atol=1 / 255)  # B: metallic
    n = read_image(tmp_path / images[mat.normalTexture.index]).pixels * 2 - 1
    np.testing.assert_allclose(n[0, 0], [0.6, 0.0, 0.8], atol=0.01)
    dx = read_image(tmp_path / "normal_directx.png").pixels * 2 - 1
    assert dx[0, 0, 1] == pytest.approx(-n[0, 0, 1], abs=0.01)
    assert (tmp_path / "exr" / "diffuse.exr").is_file()


def test_alpha_and_specular_extension(tmp_path):
    import pygltflib

    alpha = (torch.arange(8) % 2).float().view(1, 1, 8).expand(1, 8, 8).clone()
    maps = _maps(alpha=alpha, coloured_dielectric=True)
    assert specular_residual(maps) > 0.01
    export_all(tmp_path, maps, (10.0, 10.0))
    gltf = pygltflib.GLTF2().load(str(tmp_path / "material.gltf"))
    mat = gltf.materials[0]
    assert mat.alphaMode == "MASK" and mat.alphaCutoff == 0.5
    assert "KHR_materials_specular" in gltf.extensionsUsed
    ext = json.loads((tmp_path / "material.gltf").read_text())["materials"][0]["extensions"]["KHR_materials_specular"]
    assert ext["specularColorFactor"][0] > 1  # F0 over 0.04: the colour texture is scaled up
    rgba = read_image(tmp_path / "tex_basecolor.png").pixels
    assert rgba.shape[2] == 4 and rgba[0, 1, 3] == 1.0 and rgba[0, 0, 3] == 0.0


def test_materialx_validates(tmp_path):
    import MaterialX as mx

    export_all(tmp_path, _maps(alpha=torch.ones(1, 8, 8)), (10.0, 10.0))
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(tmp_path / "material.mtlx"))
    stdlib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), stdlib)
    doc.importLibrary(stdlib)
    valid, message = doc.validate()
    assert valid, message
    assert doc.getNode("material") is not None


def test_glb_holds_the_gltf_and_its_files(tmp_path):
    # read back with pygltflib's own GLB reader: the same document, with the quad's buffer and
    # each texture byte for byte inside the one file
    import pygltflib

    export_all(tmp_path, _maps(alpha=torch.rand(1, 8, 8)), (100.0, 100.0))
    gltf = json.loads((tmp_path / "material.gltf").read_text())
    glb = pygltflib.GLTF2().load_binary(str(tmp_path / "material.glb"))
    blob = glb.binary_blob()
    assert len(glb.images) == len(gltf["images"]) and glb.materials[0].name == gltf["materials"][0]["name"]
    for image, ref in zip(glb.images, gltf["images"], strict=True):
        view = glb.bufferViews[image.bufferView]
        assert view.byteOffset % 4 == 0 and image.mimeType == "image/png"
        assert blob[view.byteOffset : view.byteOffset + view.byteLength] == (tmp_path / ref["uri"]).read_bytes()
    quad = (tmp_path / "material.bin").read_bytes()
    assert blob[: len(quad)] == quad
    for view, ref in zip(glb.bufferViews, gltf["bufferViews"], strict=False):  # the quad's views unchanged
        assert (view.byteOffset or 0, view.byteLength) == (ref.get("byteOffset", 0), ref["byteLength"])
    raw = (tmp_path / "material.glb").read_bytes()
    magic, version, length = struct.unpack("<3I", raw[:12])
    assert (magic, version, length) == (0x46546C67, 2, len(raw))


def _validator():
    import shutil
    from pathlib import Path

    module = Path(__file__).resolve().parents[1] / ".venv" / "node" / "node_modules" / "gltf-validator"
    if not shutil.which("node") or not module.is_dir():
        pytest.skip("the Khronos glTF validator (npm gltf-validator, installed by make test) is not here")
    return module


def test_khronos_validator_passes_gltf_and_glb(tmp_path):
    import subprocess

    module = _validator()
    export_all(tmp_path, _maps(coloured_dielectric=True), (100.0, 100.0))
    script = (
        "const v = require(process.argv[1]); const fs = require('fs'); const path = require('path');"
        "const f = process.argv[2]; const dir = path.dirname(f);"
        "v.validateBytes(new Uint8Array(fs.readFileSync(f)), {uri: path.basename(f),"
        " externalResourceFunction: (u) => fs.promises.readFile(path.join(dir, decodeURIComponent(u)))"
        ".then((b) => new Uint8Array(b))})"
        ".then((r) => console.log(JSON.stringify(r.issues)));"
    )
    for name in ("material.gltf", "material.glb"):
        out = subprocess.run(
            ["node", "-e", script, str(module), str(tmp_path / name)], capture_output=True, text=True, check=True
        )
        issues = json.loads(out.stdout)
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, (name, issues["messages"])


def test_files_say_their_colour_space(tmp_path):
    # read by Pillow and by OpenEXR, not by matscan: colour maps carry sRGB, data maps gAMA 1.0,
    # and EXR maps the Rec. 709 chromaticities and their convention
    import OpenEXR
    from PIL import Image

    from matscan.mapset import CONVENTIONS, write_maps

    maps = _maps(alpha=torch.rand(1, 8, 8))
    write_maps(tmp_path, maps)
    export_all(tmp_path, maps, (100.0, 100.0))
    for file in ("diffuse.png", "specular.png", "basecolor.png", "tex_basecolor.png"):
        info = Image.open(tmp_path / file).info
        assert info.get("srgb") == 0 and abs(info["gamma"] - 1 / 2.2) < 1e-4, file
    for file in (
        "roughness.png",
        "normal.png",
        "alpha.png",
        "metallic.png",
        "tex_normal.png",
        "tex_metallic_roughness.png",
    ):
        info = Image.open(tmp_path / file).info
        assert "srgb" not in info and info["gamma"] == 1.0, file
    (tmp_path / "exr").mkdir()
    write_maps(tmp_path / "exr", maps, file_format="exr")
    for name in ("diffuse", "normal", "alpha"):
        with OpenEXR.File(str(tmp_path / "exr" / f"{name}.exr")) as f:
            header = dict(f.header())  # a copy: the file's own header goes with it when it closes
        assert np.allclose(header["chromaticities"], (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), atol=1e-6)
        assert header["matscanMap"] == name and header["matscanConvention"] == CONVENTIONS[name]
    # every map a map set can hold has its convention written
    from matscan.mapset import SPECS

    assert set(SPECS) <= set(CONVENTIONS)


def _mtlx(path):
    import MaterialX as mx

    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    stdlib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), stdlib)
    doc.importLibrary(stdlib)
    return doc


def test_materialx_translates_to_usd_preview_surface(tmp_path):
    # MaterialX's own translator (what `translateshader ... UsdPreviewSurface` runs) must take it
    import MaterialX.PyMaterialXGenShader as gen

    export_all(tmp_path, _maps(alpha=torch.rand(1, 8, 8), coloured_dielectric=True), (10.0, 10.0))
    doc = _mtlx(tmp_path / "material.mtlx")
    gen.ShaderTranslator.create().translateAllMaterials(doc, "UsdPreviewSurface")
    valid, message = doc.validate()
    assert valid, message
    shader = doc.getMaterialNodes()[0].getInput("surfaceshader").getConnectedNode()
    assert shader.getCategory() == "UsdPreviewSurface"


def _linear(path) -> torch.Tensor:
    return srgb_to_linear(torch.from_numpy(read_image(path).pixels)).permute(2, 0, 1)


def _raw(path) -> torch.Tensor:
    return torch.from_numpy(read_image(path).pixels).permute(2, 0, 1)


def _graph_value(node, folder) -> torch.Tensor:
    """What a MaterialX nodegraph output computes, for the node kinds the export uses
    (image, sqrt, add, subtract, divide), evaluated here from the MaterialX document."""
    kind = node.getCategory()
    if kind == "image":
        file = folder / node.getInputValue("file")
        srgb = node.getInput("file").getColorSpace() == "srgb_texture"
        return _linear(file) if srgb else _raw(file)

    def arg(name):
        port = node.getInput(name)
        upstream = port.getConnectedNode()
        return _graph_value(upstream, folder) if upstream is not None else torch.tensor(float(port.getValue()))

    if kind == "sqrt":
        return arg("in").sqrt()
    ops = {"add": torch.add, "subtract": torch.sub, "divide": torch.div}
    return ops[kind](arg("in1"), arg("in2"))


def _surface_input(surface, name, folder) -> torch.Tensor:
    port = surface.getInput(name)
    if port.getConnectedOutput() is None:
        return torch.tensor(float(port.getValue()))
    return _graph_value(port.getConnectedOutput().getConnectedNode(), folder)


def _metal_rough_read(folder) -> tuple[torch.Tensor, torch.Tensor]:
    return _linear(folder / "tex_basecolor.png")[:3], _raw(folder / "tex_metallic.png")


def _mixed_maps(size: int = 8) -> MapSet:
    """Texels of several kinds: a dielectric of F0 0.01 (below the 0.04 metal/rough gives
    dielectrics, so an export needs a specular colour), F0 0.2 over diffuse 0.3 (which
    metal/rough gives exactly, as metallic 0.37), a gold metal, a grey iron with a little
    diffuse, coloured F0s either side of 0.25 over a coloured diffuse, and a grey F0 0.3
    over a coloured diffuse (which metal/rough cannot give)."""
    diffuse, specular = torch.full((3, size, size), 0.5), torch.full((3, size, size), 0.01)
    diffuse[:, size // 2 :], specular[:, size // 2 :] = 0.3, 0.2
    diffuse[:, 0, 0], specular[:, 0, 0] = 0.0, torch.tensor([0.9, 0.7, 0.3])
    diffuse[:, 0, 1], specular[:, 0, 1] = 0.05, torch.tensor([0.56, 0.57, 0.58])
    for col, blue in ((2, 0.249), (3, 0.251)):
        diffuse[:, 0, col], specular[:, 0, col] = torch.tensor([0.46, 0.017, 0.21]), torch.tensor([0.238, 0.223, blue])
    diffuse[:, 1, 0], specular[:, 1, 0] = torch.tensor([0.6, 0.3, 0.2]), 0.3
    normal = torch.zeros(3, size, size)
    normal[2] = 1
    return MapSet(diffuse, specular, torch.full((1, size, size), 0.3), normal)


def test_materialx_carries_the_specular_map(tmp_path):
    """Standard Surface (Autodesk 1.0, "Specular" and "Metalness"): a dielectric layer of
    weight ``specular`` with F0 = specular_color · ((IOR − 1)/(IOR + 1))², mixed by
    metalness with a metal of F0 base_color. The weight must stay 1 (it also sets what the
    layer takes from the diffuse beneath: 22.4 there darkened the diffuse to 6%), and the
    mix must give the maps' F0 on texels that are partly metallic too."""
    maps = _mixed_maps()
    export_all(tmp_path, maps, (10.0, 10.0))
    doc = _mtlx(tmp_path / "material.mtlx")
    surface = doc.getNode("material_surface")
    assert surface.getInputValue("specular") == 1.0
    ior = _surface_input(surface, "specular_IOR", tmp_path)
    tint = _surface_input(surface, "specular_color", tmp_path)
    assert float(tint.max()) <= 1.0 and float(ior.min()) >= 1.0
    base, metal = _metal_rough_read(tmp_path)
    assert bool(((metal > 0.05) & (metal < 0.95)).any())  # the case that went wrong: metal and dielectric mixed
    # specular_color is also the metals' edge colour (metal_edgecolor = specular_color ·
    # specular): white wherever there is metal, not the conversion's leftovers
    assert float((tint - 1).abs()[:, metal[0] > 0].max()) < 2 / 255
    f0 = (1 - metal) * tint * ((ior - 1) / (ior + 1)) ** 2 + metal * base
    assert float((f0 - maps.specular).abs().max()) < 0.006  # 8-bit textures (the gold: 0.9 at 1/255)
    assert float(((1 - metal) * base - maps.diffuse).abs().max()) < 0.006
    # without a specular texture: white and weight 1, F0 0.04 as the metal/rough conversion gives
    (tmp_path / "plain").mkdir()
    export_all(tmp_path / "plain", _maps(), (10.0, 10.0))
    plain_doc = _mtlx(tmp_path / "plain" / "material.mtlx")  # held: its nodes need it alive
    plain = plain_doc.getNode("material_surface")
    assert plain.getInput("specular_color") is None and plain.getInputValue("specular") == 1.0
    ior = plain.getInputValue("specular_IOR")
    assert abs(((ior - 1) / (ior + 1)) ** 2 - 0.04) < 1e-9


def test_gltf_specular_extension_gives_the_maps_f0_on_mixed_texels(tmp_path):
    """KHR_materials_specular (its "Implementation"): the dielectric F0 is
    min(0.04 · specularColor, 1) · specular, and glTF 2.0 Appendix B mixes that with the
    metal's baseColor by metallic. The colour texture held the whole F0 / 0.04, so partly
    metallic texels counted the metal's share twice (F0 0.2 read as 0.30)."""
    maps = _mixed_maps()
    export_all(tmp_path, maps, (10.0, 10.0))
    ext = json.loads((tmp_path / "material.gltf").read_text())["materials"][0]["extensions"]["KHR_materials_specular"]
    colour = _linear(tmp_path / "tex_specular_color.png") * torch.tensor(ext["specularColorFactor"]).view(3, 1, 1)
    dielectric = (DIELECTRIC_F0 * colour).clamp(max=1) * ext["specularFactor"]
    base, metal = _metal_rough_read(tmp_path)
    assert bool(((metal > 0.05) & (metal < 0.95)).any())
    f0 = (1 - metal) * dielectric + metal * base
    assert float((f0 - maps.specular).abs().max()) < 0.006
    assert float(((1 - metal) * base - maps.diffuse).abs().max()) < 0.006


def test_usd_keeps_the_metal_rough_conversion_where_gltf_splits_otherwise(tmp_path):
    """UsdPreviewSurface's metallic workflow has no specular colour: its textures stay the
    plain conversion (metallic 0.14 for F0 (0.2, 0.1, 0.05) over diffuse 0.5), not the
    glTF's split (metallic 0 there, an F0 of 0.04), which doubled its F0 error."""
    pytest.importorskip("pxr", reason="usd-core (the usd extra) is not installed")
    from pxr import Usd, UsdShade

    maps = _mixed_maps()
    maps.diffuse[:, 1, 1], maps.specular[:, 1, 1] = 0.5, torch.tensor([0.2, 0.1, 0.05])
    export_all(tmp_path, maps, (10.0, 10.0))
    stage = Usd.Stage.Open(str(tmp_path / "material.usda"))
    material, _ = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/Root/Sample")).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]

    def read(name):
        source = surface.GetInput(name).GetConnectedSources()[0][0].source
        file = UsdShade.Shader(source.GetPrim()).GetInput("file").Get().path
        return _linear(tmp_path / file)[:3] if name == "diffuseColor" else _raw(tmp_path / file)

    base, metal = read("diffuseColor"), read("metallic")
    usd = 0.04 * (1 - metal) + metal * base  # UsdPreviewSurface's metallic workflow
    plain_base, plain_metal = specular_to_metallic(maps.diffuse, maps.specular)
    torch.testing.assert_close(metal, plain_metal, rtol=0, atol=1 / 255)
    assert float(metal[0, 1, 1]) > 0.1
    assert float((usd - maps.specular).abs().mean()) <= float(((0.04 - maps.specular).abs()).mean())


def test_usd_stage_binds_a_preview_surface_reading_the_textures(tmp_path):
    # opened with USD itself: the quad's bound material is a UsdPreviewSurface whose inputs come
    # from UsdUVTexture nodes reading the exported PNGs (sRGB for colour, raw for data)
    pytest.importorskip("pxr", reason="usd-core (the usd extra) is not installed")
    import zipfile

    from pxr import Usd, UsdGeom, UsdShade

    written = export_all(tmp_path, _maps(alpha=torch.rand(1, 8, 8)), (120.0, 80.0))
    assert "material.usda" in written and "material.usdz" in written
    stage = Usd.Stage.Open(str(tmp_path / "material.usda"))
    mesh = stage.GetPrimAtPath("/Root/Sample")
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    extent = UsdGeom.Mesh(mesh).GetExtentAttr().Get()
    assert tuple(extent[1]) == pytest.approx((0.06, 0.04, 0.0))  # 120 × 80 mm
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    spaces = {}
    for name in ("diffuseColor", "metallic", "roughness", "normal", "opacity"):
        source = surface.GetInput(name).GetConnectedSources()[0][0].source
        texture = UsdShade.Shader(source.GetPrim())
        assert texture.GetIdAttr().Get() == "UsdUVTexture"
        asset = texture.GetInput("file").Get()
        assert (tmp_path / asset.path).is_file() and asset.resolvedPath  # the file is there and USD finds it
        spaces[name] = texture.GetInput("sourceColorSpace").Get()
    assert spaces == {"diffuseColor": "sRGB", "metallic": "raw", "roughness": "raw", "normal": "raw", "opacity": "raw"}
    with zipfile.ZipFile(tmp_path / "material.usdz") as z:
        names = z.namelist()
    assert names[0] == "material.usda" and {"tex_basecolor.png", "tex_normal.png"} <= set(names)


# --- matscan export: a map set already made, exported -------------------------------


def _quad_size_m(folder) -> tuple[float, float]:
    """The glTF quad's width and height (m), read from its binary buffer."""
    blob = (folder / "material.bin").read_bytes()
    xs = [struct.unpack_from("<3f", blob, 12 * i) for i in range(4)]
    return max(p[0] for p in xs) - min(p[0] for p in xs), max(p[1] for p in xs) - min(p[1] for p in xs)


def _digest(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_export_command_writes_the_maps_and_a_quad_of_the_asked_size(tmp_path, capsys):
    from matscan.cli import main
    from matscan.mapset import read_mapset

    out = tmp_path / "out"
    assert main(["export", "@sample", "--out", str(out), "--field-mm", "80,60", "--exr", "--directx-normals"]) == 0
    assert "80×60 mm from field_mm" in capsys.readouterr().out
    assert _quad_size_m(out) == pytest.approx((0.08, 0.06))
    # the folder is a map set again: the sample's maps, within the 16-bit PNGs' steps
    sample, back = read_mapset("@sample"), read_mapset(out)
    for name, t in sample.present().items():
        tol = 1 / 255 if name in ("diffuse", "specular") else 2e-3
        np.testing.assert_allclose(getattr(back, name).numpy(), t.numpy(), atol=tol if name != "height" else 1e-3)
    exr = read_image(out / "exr" / "roughness.exr").pixels[..., 0]
    np.testing.assert_allclose(exr, sample.roughness[0].numpy(), atol=1e-6)
    dx = read_image(out / "normal_directx.png").pixels * 2 - 1
    np.testing.assert_allclose(dx[..., 1], -sample.normal[1].numpy(), atol=2e-3)
    record = json.loads((out / "matscan.json").read_text())
    assert record["command"] == "export" and record["field_mm"] == [80.0, 60.0]
    assert set(record["files"]) == {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} - {
        "matscan.json"
    }


def test_export_takes_the_field_a_record_gives_then_the_rigs(tmp_path, capsys):
    from matscan.cli import main
    from matscan.mapset import write_mapset

    maps = tmp_path / "maps"
    write_mapset(maps, _maps())
    assert main(["export", str(maps), "--out", str(tmp_path / "a")]) == 0  # no record: dome24's 120 mm
    assert _quad_size_m(tmp_path / "a") == pytest.approx((0.12, 0.12))
    assert main(["export", str(maps), "--out", str(tmp_path / "b"), "--rig", "flash"]) == 0
    assert _quad_size_m(tmp_path / "b") == pytest.approx((0.0685, 0.0685))
    # a reconstruction's record says the field its capture covered; an export's keeps it
    (maps / "matscan.json").write_text(json.dumps({"command": "reconstruct", "field_mm": [50, 40]}))
    assert main(["export", str(maps), "--out", str(tmp_path / "c")]) == 0
    assert "50×40 mm from matscan.json of the maps" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "c"), "--out", str(tmp_path / "d")]) == 0
    assert main(["export", str(tmp_path / "d"), "--out", str(tmp_path / "e"), "--field-mm", "30,30"]) == 0
    assert _quad_size_m(tmp_path / "d") == pytest.approx((0.05, 0.04))
    assert _quad_size_m(tmp_path / "e") == pytest.approx((0.03, 0.03))


def test_export_reads_a_library_folder_in_the_metallic_workflow(tmp_path):
    """A public library's maps (base colour, DirectX normal, roughness, metalness) come out
    with glTF's packing of the same values: G roughness, B metalness; the normal map in
    OpenGL's frame."""
    from matscan.cli import main
    from matscan.imagefile import write_image

    lib = tmp_path / "Metal007_1K"
    lib.mkdir()
    rng = np.random.default_rng(4)
    rough = rng.uniform(0.2, 0.9, (16, 16, 1)).astype(np.float32)
    metal = (np.arange(16) >= 8).astype(np.float32)[None, :, None].repeat(16, 0)
    normal_dx = np.zeros((16, 16, 3), np.float32)
    normal_dx[..., 1], normal_dx[..., 2] = 0.6, 0.8  # DirectX: +y down, so the surface leans to −y
    write_image(lib / "Metal007_1K_Color.png", rng.uniform(0.2, 0.8, (16, 16, 3)).astype(np.float32), bits=8)
    write_image(lib / "Metal007_1K_Roughness.png", rough, bits=16, colourspace="linear")
    write_image(lib / "Metal007_1K_Metalness.png", metal, bits=8, colourspace="linear")
    write_image(lib / "Metal007_1K_NormalDX.png", (normal_dx + 1) / 2, bits=16, colourspace="linear")
    before = _digest(lib)
    out = tmp_path / "out"
    assert main(["export", str(lib), "--out", str(out), "--field-mm", "100,100"]) == 0
    assert _digest(lib) == before
    mr = read_image(out / "tex_metallic_roughness.png").pixels
    np.testing.assert_allclose(mr[..., 1], rough[..., 0], atol=1 / 255 + 1e-3)
    np.testing.assert_allclose(mr[..., 2], metal[..., 0], atol=1 / 255)
    n = read_image(out / "normal.png").pixels * 2 - 1
    np.testing.assert_allclose(n[0, 0], [0.0, -0.6, 0.8], atol=2e-3)


def test_export_never_writes_into_its_input_and_replaces_only_its_own(tmp_path, capsys):
    from matscan.cli import main
    from matscan.mapset import write_mapset

    maps = tmp_path / "maps"
    write_mapset(maps, _maps())
    before = _digest(maps)
    for out in (maps, maps / "exports"):
        assert main(["export", str(maps), "--out", str(out), "--overwrite", "--overwrite-any"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("matscan: ") and "\n" not in err
    assert _digest(maps) == before
    out = tmp_path / "out"
    assert main(["export", str(maps), "--out", str(out)]) == 0
    assert main(["export", str(maps), "--out", str(out)]) == 2  # exists
    assert "--overwrite" in capsys.readouterr().err
    assert main(["export", str(maps), "--out", str(out), "--overwrite", "--field-mm", "10,10"]) == 0
    assert _quad_size_m(out) == pytest.approx((0.01, 0.01))
    (out / "notes.txt").write_text("mine")
    assert main(["export", str(maps), "--out", str(out), "--overwrite"]) == 2
    assert "notes.txt" in capsys.readouterr().err and (out / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--field-mm", "0,5"], "--field-mm: '0,5' must be two positive sizes"),
        (["--field-mm", "5"], "--field-mm: '5' is not 2 comma-separated numbers"),
        (["--rig", "dome99"], "dome99"),
    ],
)
def test_export_bad_arguments_are_one_line(tmp_path, capsys, argv, words):
    from matscan.cli import main

    assert main(["export", "@sample", "--out", str(tmp_path / "o"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "\n" not in err and not (tmp_path / "o").exists()


def test_export_of_a_missing_folder_or_a_bad_record_names_the_file(tmp_path, capsys):
    from matscan.cli import main
    from matscan.mapset import write_mapset

    assert main(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    assert "nothing: no such map folder" in capsys.readouterr().err
    maps = tmp_path / "maps"
    write_mapset(maps, _maps())
    (maps / "matscan.json").write_text(json.dumps({"field_mm": [50, "wide"]}))
    assert main(["export", str(maps), "--out", str(tmp_path / "o")]) == 2
    assert "matscan.json: field_mm: expected 2 finite numbers" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def _numbers_apart(a: str, b: str) -> float:
    """The largest relative difference between the numbers of two texts that are equal
    once their numbers are taken out (inf where they are not)."""
    import re

    number = r"-?\d+\.\d+(?:e-?\d+)?"
    if re.sub(number, "#", a) != re.sub(number, "#", b):
        return math.inf
    pairs = zip(map(float, re.findall(number, a)), map(float, re.findall(number, b)), strict=True)
    return max((abs(x - y) / max(abs(x), 1e-12) for x, y in pairs), default=0.0)


#: The textures that hold the metal/rough split and the specular colour.
SPLIT_TEXTURES = (
    "tex_basecolor.png",
    "tex_metallic.png",
    "tex_metallic_roughness.png",
    "tex_specular_color.png",
    "tex_specular_tint.png",
    "tex_specular_f0.png",
)


def _material_read(folder) -> torch.Tensor:
    """The diffuse and F0 an export's glTF textures say, and the F0 its MaterialX
    textures say, stacked (glTF 2.0 Appendix B with KHR_materials_specular; Standard
    Surface's F0 from specular_color and an IOR from F0, as the nodegraph computes it)."""
    factor = json.loads((folder / "material.gltf").read_text())["materials"][0]["extensions"]
    factor = factor["KHR_materials_specular"]["specularColorFactor"][0]
    base, metal = _metal_rough_read(folder)
    gltf = _linear(folder / "tex_specular_color.png") * factor * DIELECTRIC_F0
    mtlx = _linear(folder / "tex_specular_tint.png") * _raw(folder / "tex_specular_f0.png")
    mix = [(1 - metal) * part + metal * base for part in (gltf, mtlx)]
    return torch.cat([(1 - metal) * base, *mix])


def test_export_of_a_reconstruction_writes_its_exports_again(tmp_path):
    """What ``reconstruct`` wrote from its maps in memory, ``export`` writes again from the
    maps it saved: the same bytes, but where the specular map's 8-bit sRGB file shows (the
    specular colour texture within one code, its factor in the glTF and MaterialX files
    within 1%)."""
    from matscan.cli import main

    assert main(["simulate", "@sample", "--out", str(tmp_path / "cap"), "--size", "32", "--lights", "6"]) == 0
    assert main(["reconstruct", str(tmp_path / "cap"), "--out", str(tmp_path / "rec")]) == 0
    assert main(["export", str(tmp_path / "rec"), "--out", str(tmp_path / "exp")]) == 0
    made = json.loads((tmp_path / "rec" / "matscan.json").read_text())["exports"]
    assert json.loads((tmp_path / "exp" / "matscan.json").read_text())["exports"] == made
    assert {"material.gltf", "tex_normal.png", "tex_specular_color.png"} <= set(made)  # the sample's F0 is tinted
    for name in made:
        rec, exp = tmp_path / "rec" / name, tmp_path / "exp" / name
        if name in SPLIT_TEXTURES:
            # made from F0 and diffuse as their 8-bit files hold them, so a texel may be split
            # otherwise between metal and dielectric: what they say is the same
            a, b = (_material_read(folder) for folder in (tmp_path / "rec", tmp_path / "exp"))
            # within 0.01, or two 8-bit sRGB codes where those are more (0.0156 at 0.55, where
            # a metal's F0 sits)
            top = torch.maximum(a, b).clamp(0, 1)
            code = top - srgb_to_linear((linear_to_srgb(top) - 1 / 255).clamp(min=0))
            assert bool(((a - b).abs() <= torch.clamp(2 * code, min=0.01)).all()), name
        elif name in ("material.gltf", "material.mtlx"):
            # the specular colour's factor is its texture's largest dielectric F0: a texel at the
            # split's tolerance may turn metal in one and not the other (the material read above
            # is still the same), so the factor is held to 1% only where the split is the same
            apart = _numbers_apart(rec.read_text(), exp.read_text())
            same_split = (tmp_path / "rec" / "tex_metallic.png").read_bytes() == (
                tmp_path / "exp" / "tex_metallic.png"
            ).read_bytes()
            assert apart < (0.01 if same_split else 0.1), name
        elif name not in ("material.glb", "material.usdz"):  # these hold the files above
            assert exp.read_bytes() == rec.read_bytes(), name
