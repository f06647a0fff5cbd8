"""Exports that state their conventions: glTF 2.0, MaterialX, EXR maps, DirectX normals.

* **glTF 2.0** (``material.gltf`` + ``material.bin``): a quad of the sample's real
  size (metres, in the glTF x–y plane facing +z, uv (0, 0) at the image's top-left
  = the sample's (−x, +y) corner), with a metallic-roughness material: base colour
  (RGB, plus alpha when the material has holes: alphaMode MASK, or BLEND when
  alpha takes many in-between values), metallicRoughnessTexture (G roughness,
  B metallic, as the glTF specification packs them), the normal map (glTF's
  tangent frame is ours: +x right, +y up), emission, and
  ``KHR_materials_specular`` where the specular colour is not what the
  metal/rough conversion gives back.
* **glTF binary** (``material.glb``): the same document in one file, the quad and
  every texture embedded (for viewers and engines that take a single file).
* **MaterialX** (``material.mtlx``): a ``standard_surface`` fed by a nodegraph reading
  the same textures (base colour and specular colour in sRGB, the rest raw), made and
  validated with the MaterialX API (:func:`materialx_document` states the F0 mapping).
* **EXR maps** (``exr/``): every map as float32 EXR, linear.
* **DirectX normals** (``normal_directx.png``): green flipped, for engines that
  want that convention.

``matscan reconstruct`` writes these beside its maps; :func:`export_maps` (``matscan
export``) writes them for a map set already made: a reconstruction, a matscan map set, a
public library's folder of maps or a Deschaintre panel image.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from matscan.brdf import DIELECTRIC_F0, metallic_to_specular, specular_to_metallic
from matscan.color import linear_to_srgb
from matscan.errors import MatscanError
from matscan.imagefile import write_image
from matscan.jsonfile import dumps
from matscan.mapset import MapSet, write_maps

#: Mean |F0 error| of the metal/rough round trip above which glTF gets KHR_materials_specular.
SPECULAR_EXTENSION_THRESHOLD = 0.01


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().permute(1, 2, 0).numpy()


def _metal_rough(maps: MapSet) -> tuple[torch.Tensor, torch.Tensor]:
    if maps.basecolor is not None and maps.metallic is not None:
        return maps.basecolor, maps.metallic
    return specular_to_metallic(maps.diffuse, maps.specular)


def write_textures(
    folder: Path, maps: MapSet, split: tuple[torch.Tensor, torch.Tensor] | None = None
) -> dict[str, str]:
    """The PNG textures the glTF and MaterialX documents read, with the metal/rough
    ``split`` given (:func:`specular_split`; the plain conversion by default); returns
    their file names."""
    base, metal = split if split is not None else _metal_rough(maps)
    files = {}
    rgb = linear_to_srgb(base.clamp(0, 1))
    if maps.alpha is not None:
        rgb = torch.cat([rgb, maps.alpha.clamp(0, 1)])
    write_image(folder / "tex_basecolor.png", _hwc(rgb), bits=8, colourspace="srgb")
    files["basecolor"] = "tex_basecolor.png"
    mr = torch.cat([torch.ones_like(metal), maps.roughness.clamp(0, 1), metal.clamp(0, 1)])
    write_image(folder / "tex_metallic_roughness.png", _hwc(mr), bits=8, colourspace="linear")
    files["metallic_roughness"] = "tex_metallic_roughness.png"
    write_image(folder / "tex_roughness.png", _hwc(maps.roughness.clamp(0, 1)), bits=8, colourspace="linear")
    files["roughness"] = "tex_roughness.png"
    write_image(folder / "tex_metallic.png", _hwc(metal.clamp(0, 1)), bits=8, colourspace="linear")
    files["metallic"] = "tex_metallic.png"
    write_image(folder / "tex_normal.png", _hwc((maps.normal + 1) / 2), bits=8, colourspace="linear")
    files["normal"] = "tex_normal.png"
    if maps.emissive is not None:
        write_image(
            folder / "tex_emissive.png", _hwc(linear_to_srgb(maps.emissive.clamp(0, 1))), bits=8, colourspace="srgb"
        )
        files["emissive"] = "tex_emissive.png"
    if maps.alpha is not None:
        write_image(folder / "tex_opacity.png", _hwc(maps.alpha.clamp(0, 1)), bits=8, colourspace="linear")
        files["opacity"] = "tex_opacity.png"
    return files


def specular_split(maps: MapSet) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(base colour, metallic, dielectric F0) for exports that carry a specular colour
    (glTF's KHR_materials_specular, MaterialX's specular_color and IOR).

    Both mix a dielectric lobe and a metal one by metallic m (glTF 2.0 Appendix B; Standard
    Surface's metalness): F0 = (1 − m)·F0_dielectric + m·baseColor. Texels the plain
    metal/rough conversion gives back (F0 within ``SPLIT_TOLERANCE``) keep it, with the
    dielectric's usual 0.04 (so the specular colour is white there, and so is Standard
    Surface's metal edge colour, which is the same input); the others become dielectrics:
    metallic 0, base colour the diffuse, dielectric F0 the map's."""
    base, metal = _metal_rough(maps)
    _, back = metallic_to_specular(base, metal)
    missed = (back - maps.specular).abs().amax(dim=-3, keepdim=True) > SPLIT_TOLERANCE
    metal = torch.where(missed, torch.zeros_like(metal), metal)
    base = torch.where(missed, maps.diffuse.clamp(0, 1), base)
    dielectric = torch.where(missed, maps.specular.clamp(0, 1), torch.full_like(maps.specular, DIELECTRIC_F0))
    return base, metal, dielectric


#: How far (F0, any channel) the metal/rough conversion may miss a texel's F0 and keep it
#: in an export with a specular colour.
SPLIT_TOLERANCE = 0.005
#: The largest F0 the MaterialX export's IOR encodes ((1 + √0.98)/(1 − √0.98) ≈ 198).
MAX_MTLX_F0 = 0.98


def specular_residual(maps: MapSet) -> float:
    """Mean |F0 − F0 of the metal/rough round trip|: what glTF's core material would lose."""
    base, metal = _metal_rough(maps)
    _, f0 = metallic_to_specular(base, metal)
    return float((f0 - maps.specular).abs().mean())


def gltf_document(
    maps: MapSet, field_mm: tuple[float, float], textures: dict[str, str], folder: Path, name: str = "material"
) -> dict[str, Any]:
    """Write ``name.bin`` (the quad) and return the glTF JSON object."""
    w, h = field_mm[0] / 1000, field_mm[1] / 1000
    positions = [(-w / 2, h / 2, 0.0), (w / 2, h / 2, 0.0), (w / 2, -h / 2, 0.0), (-w / 2, -h / 2, 0.0)]
    uvs = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
    normals = [(0.0, 0.0, 1.0)] * 4
    tangents = [(1.0, 0.0, 0.0, 1.0)] * 4
    indices = [0, 3, 2, 0, 2, 1]  # counter-clockwise seen from +z
    blob = b"".join(struct.pack("<3f", *p) for p in positions)
    blob += b"".join(struct.pack("<3f", *n) for n in normals)
    blob += b"".join(struct.pack("<4f", *t) for t in tangents)
    blob += b"".join(struct.pack("<2f", *u) for u in uvs)
    blob += struct.pack("<6H", *indices) + b"\0\0"
    (folder / f"{name}.bin").write_bytes(blob)
    views = [
        {"buffer": 0, "byteOffset": 0, "byteLength": 48, "target": 34962},
        {"buffer": 0, "byteOffset": 48, "byteLength": 48, "target": 34962},
        {"buffer": 0, "byteOffset": 96, "byteLength": 64, "target": 34962},
        {"buffer": 0, "byteOffset": 160, "byteLength": 32, "target": 34962},
        {"buffer": 0, "byteOffset": 192, "byteLength": 12, "target": 34963},
    ]
    accessors = [
        {
            "bufferView": 0,
            "componentType": 5126,
            "count": 4,
            "type": "VEC3",
            "min": [-w / 2, -h / 2, 0.0],
            "max": [w / 2, h / 2, 0.0],
        },
        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC4"},
        {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 4, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    images, tex_index = [], {}
    for key, file in textures.items():
        if key in ("basecolor", "metallic_roughness", "normal", "emissive", "specular_color"):
            tex_index[key] = len(images)
            images.append({"uri": file})
    material: dict[str, Any] = {
        "name": name,
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": tex_index["basecolor"]},
            "metallicRoughnessTexture": {"index": tex_index["metallic_roughness"]},
            "metallicFactor": 1.0,
            "roughnessFactor": 1.0,
        },
        "normalTexture": {"index": tex_index["normal"]},
        "doubleSided": False,
    }
    extensions_used = []
    if "emissive" in tex_index:
        material["emissiveTexture"] = {"index": tex_index["emissive"]}
        material["emissiveFactor"] = [1.0, 1.0, 1.0]
    if maps.alpha is not None:
        a = maps.alpha
        between = float(((a > 0.05) & (a < 0.95)).float().mean())
        material["alphaMode"] = "BLEND" if between > 0.1 else "MASK"
        if material["alphaMode"] == "MASK":
            material["alphaCutoff"] = 0.5
    if "specular_color" in tex_index:
        material["extensions"] = {
            "KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularColorTexture": {"index": tex_index["specular_color"]},
                "specularColorFactor": [textures["specular_color_factor"]] * 3,  # type: ignore[list-item]
            }
        }
        extensions_used.append("KHR_materials_specular")
    doc: dict[str, Any] = {
        "asset": {
            "version": "2.0",
            "generator": "matscan",
            "extras": {
                "conventions": "sample in the x-y plane facing +z, metres; normal map in glTF's "
                "tangent frame (+x right, +y up); roughness is perceptual (alpha = r^2)"
            },
        },
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [
            {
                "name": name,
                "primitives": [
                    {
                        "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
                        "indices": 4,
                        "material": 0,
                    }
                ],
            }
        ],
        "materials": [material],
        "textures": [{"source": i, "sampler": 0} for i in range(len(images))],
        "images": images,
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "buffers": [{"uri": f"{name}.bin", "byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    if extensions_used:
        doc["extensionsUsed"] = extensions_used
    return doc


GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


def _padded(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def glb_bytes(doc: dict[str, Any], folder: Path) -> bytes:
    """The glTF document ``doc`` (written beside its files in ``folder``) as one GLB file
    (glTF 2.0 spec, "GLB File Format Specification"): its buffer and every image it
    references moved into the binary chunk, each image a 4-byte-aligned buffer view."""
    import copy

    doc = copy.deepcopy(doc)
    blob = bytearray(_padded((folder / doc["buffers"][0]["uri"]).read_bytes(), b"\0"))
    for image in doc["images"]:
        data = (folder / image.pop("uri")).read_bytes()
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        image["bufferView"] = len(doc["bufferViews"]) - 1
        image["mimeType"] = "image/png"
        blob += _padded(data, b"\0")
    doc["buffers"] = [{"byteLength": len(blob)}]
    text = _padded(dumps(doc, "material.glb").encode("utf-8"), b" ")
    total = 12 + 8 + len(text) + 8 + len(blob)
    return b"".join(
        [
            struct.pack("<3I", GLB_MAGIC, 2, total),
            struct.pack("<2I", len(text), GLB_JSON),
            text,
            struct.pack("<2I", len(blob), GLB_BIN),
            bytes(blob),
        ]
    )


#: IOR of standard_surface's dielectric specular: ((1.5 − 1)/(1.5 + 1))² = 0.04 = DIELECTRIC_F0.
MTLX_IOR = 1.5


def materialx_document(textures: dict[str, Any], name: str = "material") -> str:
    """A MaterialX 1.39 document, made and validated with the MaterialX API: the texture
    reads in a nodegraph (as translators such as ``translateshader … UsdPreviewSurface``
    need them), feeding a ``standard_surface``.

    F0 mapping: standard_surface's dielectric reflectance at normal incidence is
    ``specular_color · ((IOR − 1)/(IOR + 1))²`` (and at grazing ``specular_color``), with
    ``specular`` its weight, which also sets how much light the layer takes from the
    diffuse beneath (so it stays 1: a weight above 1 darkened the diffuse and turned the
    metals' edge colour into a negative IOR). Where the maps need more than the metal/rough
    conversion gives (``textures["specular_tint"]`` and ``["specular_f0"]``: the dielectric
    part's F0, :func:`specular_split`, as its hue, largest channel 1, sRGB-encoded, and that
    largest channel, raw), the hue is ``specular_color`` and the IOR is computed per texel
    in the nodegraph, (1 + √F0)/(1 − √F0); otherwise white and IOR 1.5, F0 0.04. Metals
    take F0 from ``base_color`` through ``metalness``.
    """
    import MaterialX as mx

    doc = mx.createDocument()
    doc.setColorSpace("lin_rec709")
    graph = doc.addNodeGraph(f"NG_{name}")
    surface = doc.addNode("standard_surface", f"{name}_surface", "surfaceshader")

    def image(key: str, kind: str, srgb: bool = False) -> mx.Node:
        node = graph.addNode("image", key, kind)
        node.setInputValue("file", textures[key], "filename")
        if srgb:
            node.getInput("file").setColorSpace("srgb_texture")
        return node

    def connect(surface_input: str, node: mx.Node, kind: str) -> None:
        out = graph.addOutput(f"out_{surface_input}", kind)
        out.setConnectedNode(node)
        port = surface.addInput(surface_input, kind)
        port.setConnectedOutput(out)

    connect("base_color", image("basecolor", "color3", srgb=True), "color3")
    connect("metalness", image("metallic", "float"), "float")
    connect("specular_roughness", image("roughness", "float"), "float")
    normal = graph.addNode("normalmap", "normalmap", "vector3")
    normal.setConnectedNode("in", image("normal", "vector3"))
    connect("normal", normal, "vector3")
    surface.setInputValue("base", 1.0, "float")
    surface.setInputValue("specular", 1.0, "float")
    if "specular_f0" in textures:
        connect("specular_color", image("specular_tint", "color3", srgb=True), "color3")
        root = graph.addNode("sqrt", "specular_sqrt_f0", "float")
        root.setConnectedNode("in", image("specular_f0", "float"))
        over = graph.addNode("add", "specular_ior_over", "float")
        over.setConnectedNode("in1", root)
        over.setInputValue("in2", 1.0, "float")
        under = graph.addNode("subtract", "specular_ior_under", "float")
        under.setInputValue("in1", 1.0, "float")
        under.setConnectedNode("in2", root)
        ior = graph.addNode("divide", "specular_ior", "float")
        ior.setConnectedNode("in1", over)
        ior.setConnectedNode("in2", under)
        connect("specular_IOR", ior, "float")
    else:
        surface.setInputValue("specular_IOR", MTLX_IOR, "float")
    if "emissive" in textures:
        connect("emission_color", image("emissive", "color3", srgb=True), "color3")
        surface.setInputValue("emission", 1.0, "float")
    if "opacity" in textures:
        rgb = graph.addNode("convert", "opacity_rgb", "color3")
        rgb.setConnectedNode("in", image("opacity", "float"))
        connect("opacity", rgb, "color3")
    material = doc.addMaterialNode(name, surface)
    material.setDocString("matscan: roughness is perceptual (GGX alpha = r^2); normals in the OpenGL tangent frame")
    stdlib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), stdlib)
    checked = doc.copy()
    checked.importLibrary(stdlib)
    valid, message = checked.validate()
    if not valid:
        raise MatscanError(f"material.mtlx: the MaterialX document does not validate: {message.strip()}")
    return mx.writeToXmlString(doc)


def usd_files(
    folder: Path, textures: dict[str, Any], field_mm: tuple[float, float], name: str = "material"
) -> list[str]:
    """``material.usda`` (a quad of the sample's size, metres, z up, bound to a
    UsdPreviewSurface reading the textures) and ``material.usdz`` (the same packaged with its
    textures, for AR viewers); nothing when usd-core (the ``usd`` extra) is not installed.

    UsdPreviewSurface's metallic workflow has no specular tint, so the specular colour
    that glTF (KHR_materials_specular) and MaterialX carry is not in these files (which
    read the plain metal/rough conversion, ``tex_usd_*.png`` where that differs from the
    glTF's split, :func:`specular_split`); its
    roughness is perceptual, as ours. Texture coordinates: USD's st has v up, so the
    image's top row is v = 1.
    """
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils
    except ImportError:
        return []
    usda = folder / f"{name}.usda"
    stage = Usd.Stage.CreateNew(str(usda))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    w, h = field_mm[0] / 1000, field_mm[1] / 1000
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Sample")
    mesh.CreatePointsAttr([(-w / 2, h / 2, 0), (-w / 2, -h / 2, 0), (w / 2, -h / 2, 0), (w / 2, h / 2, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])  # counter-clockwise seen from +z
    mesh.CreateNormalsAttr([(0, 0, 1)] * 4)
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateExtentAttr([(-w / 2, -h / 2, 0), (w / 2, h / 2, 0)])
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([(0, 1), (0, 0), (1, 0), (1, 1)])
    material = UsdShade.Material.Define(stage, f"/Root/Looks/{name}")
    surface = UsdShade.Shader.Define(stage, f"/Root/Looks/{name}/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"/Root/Looks/{name}/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")  # string, as the shader registry has it
    reader_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    def texture(key: str, srgb: bool, **extra: Any) -> Any:
        tex = UsdShade.Shader.Define(stage, f"/Root/Looks/{name}/{key}")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"./{textures[key]}")  # anchored to the layer
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB" if srgb else "raw")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader_out)
        for input_name, value in extra.items():
            tex.CreateInput(input_name, Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*value))
        return tex

    def connect(surface_input: str, kind: Any, tex: Any, channels: str) -> None:
        out = tex.CreateOutput(channels, Sdf.ValueTypeNames.Float3 if channels == "rgb" else Sdf.ValueTypeNames.Float)
        surface.CreateInput(surface_input, kind).ConnectToSource(out)

    base, metal = ("usd_basecolor", "usd_metallic") if "usd_metallic" in textures else ("basecolor", "metallic")
    connect("diffuseColor", Sdf.ValueTypeNames.Color3f, texture(base, True), "rgb")
    connect("metallic", Sdf.ValueTypeNames.Float, texture(metal, False), "r")
    connect("roughness", Sdf.ValueTypeNames.Float, texture("roughness", False), "r")
    normal = texture("normal", False, scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0))
    connect("normal", Sdf.ValueTypeNames.Normal3f, normal, "rgb")
    if "emissive" in textures:
        connect("emissiveColor", Sdf.ValueTypeNames.Color3f, texture("emissive", True), "rgb")
    if "opacity" in textures:
        connect("opacity", Sdf.ValueTypeNames.Float, texture("opacity", False), "r")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    written = [usda.name]
    if UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(usda)), str(folder / f"{name}.usdz")):
        written.append(f"{name}.usdz")
    return written


def export_all(
    folder: Path, maps: MapSet, field_mm: tuple[float, float], exr: bool = False, directx_normals: bool = False
) -> list[str]:
    """Write the exports into an existing output folder; returns the files written."""
    coloured = specular_residual(maps) > SPECULAR_EXTENSION_THRESHOLD
    plain = _metal_rough(maps)
    base, metal, dielectric = specular_split(maps) if coloured else (*plain, None)
    textures = write_textures(folder, maps, (base, metal))
    written = list(textures.values())
    if dielectric is not None and not torch.equal(metal, plain[1]):
        # USD's metallic workflow has no specular colour: it keeps the plain conversion,
        # the nearest a metal/rough material comes to the maps' F0
        write_image(
            folder / "tex_usd_basecolor.png", _hwc(linear_to_srgb(plain[0].clamp(0, 1))), bits=8, colourspace="srgb"
        )
        write_image(folder / "tex_usd_metallic.png", _hwc(plain[1].clamp(0, 1)), bits=8, colourspace="linear")
        textures["usd_basecolor"], textures["usd_metallic"] = "tex_usd_basecolor.png", "tex_usd_metallic.png"
        written += ["tex_usd_basecolor.png", "tex_usd_metallic.png"]
    if dielectric is not None:
        # glTF (KHR_materials_specular): the dielectric F0 is min(0.04 · colour · factor, 1)
        ratio = (dielectric / DIELECTRIC_F0).clamp(0, 25)
        factor = max(1.0, float(ratio.max()))
        write_image(folder / "tex_specular_color.png", _hwc(linear_to_srgb(ratio / factor)), bits=8, colourspace="srgb")
        textures["specular_color"] = "tex_specular_color.png"
        textures["specular_color_factor"] = factor  # type: ignore[assignment]
        # MaterialX (standard_surface): F0 = specular_color · ((IOR − 1)/(IOR + 1))², the
        # colour the F0's hue (its largest channel 1) and the IOR its size, texel by texel
        peak = dielectric.amax(dim=0, keepdim=True).clamp(1e-4, MAX_MTLX_F0)
        tint = (dielectric / peak).clamp(0, 1)
        write_image(folder / "tex_specular_tint.png", _hwc(linear_to_srgb(tint)), bits=8, colourspace="srgb")
        write_image(folder / "tex_specular_f0.png", _hwc(peak), bits=16, colourspace="linear")
        textures["specular_tint"] = "tex_specular_tint.png"
        textures["specular_f0"] = "tex_specular_f0.png"
        written += ["tex_specular_color.png", "tex_specular_tint.png", "tex_specular_f0.png"]
    doc = gltf_document(maps, field_mm, textures, folder)
    (folder / "material.gltf").write_text(dumps(doc, "material.gltf"), encoding="utf-8")
    (folder / "material.glb").write_bytes(glb_bytes(doc, folder))
    (folder / "material.mtlx").write_text(materialx_document(textures), encoding="utf-8")
    written += ["material.gltf", "material.bin", "material.glb", "material.mtlx"]
    written += usd_files(folder, textures, field_mm)
    if exr:
        (folder / "exr").mkdir(exist_ok=True)
        write_maps(folder / "exr", maps, file_format="exr")
        written.append("exr/")
    if directx_normals:
        dx = maps.normal * torch.tensor([1.0, -1.0, 1.0]).view(3, 1, 1)
        write_image(folder / "normal_directx.png", _hwc((dx + 1) / 2), bits=16, colourspace="linear")
        written.append("normal_directx.png")
    return written


#: Bytes an export writes per map pixel, generously: the maps, their glTF textures three
#: times (beside the .gltf, inside the .glb and the .usdz); float EXRs when asked.
EXPORT_BYTES_PER_PIXEL = 96
EXR_BYTES_PER_PIXEL = 60
#: A sample field's sides (mm) an export accepts: a micron to a kilometre.
FIELD_LIMITS_MM = (1e-3, 1e6)


def recorded_field(folder: Path) -> tuple[float, float] | None:
    """The sample field (mm) that a ``matscan.json`` in ``folder`` records (written by
    ``reconstruct`` and by :func:`export_maps`); None where there is none or it records
    no field. A malformed one is an error naming it."""
    from matscan.jsonfile import check_vector, read_json
    from matscan.outputs import RECORD

    path = folder / RECORD
    if not folder.is_dir() or not path.is_file():
        return None
    record = read_json(path)
    if not isinstance(record, dict) or "field_mm" not in record:
        return None
    width, height = check_vector(record["field_mm"], 2, f"{path}: field_mm", FIELD_LIMITS_MM[0], FIELD_LIMITS_MM[1])
    return width, height


def export_maps(
    maps: str | Path,
    out: str | Path,
    field_mm: Sequence[float] | None = None,
    rig: str | Path = "dome24",
    exr: bool = False,
    directx_normals: bool = False,
    normal_convention: str = "auto",
    overwrite: bool = False,
    overwrite_any: bool = False,
) -> dict[str, Any]:
    """Write the map set ``maps`` into a new folder ``out`` as a matscan map set with every
    export ``reconstruct`` writes beside it (glTF, GLB, MaterialX, USD where usd-core is
    installed; ``exr``: float EXR maps; ``directx_normals``: ``normal_directx.png``).

    ``maps``: any layout :func:`matscan.materials.library.read_any` reads (a matscan map
    set or reconstruction, a public library's folder of maps, a Deschaintre panel image),
    or ``"@sample"``; ``normal_convention`` says how a library folder's normal map is
    encoded (``auto``: OpenGL unless its name says DX). The exported quad's size
    (mm): ``field_mm``; else the field a ``matscan.json`` in ``maps`` records (a
    reconstruction's, an earlier export's); else ``rig``'s field, which the maps are
    taken to cover as ``simulate`` and ``render`` take them to. Inputs are never
    written; ``out`` is checked before the work and written atomically (``overwrite``,
    ``overwrite_any``: as for ``reconstruct``). Returns the record written as
    ``matscan.json``."""
    from matscan import __version__
    from matscan.jsonfile import check_vector, dumps
    from matscan.mapset import CONVENTIONS
    from matscan.materials.library import check_normal_convention, read_any
    from matscan.outputs import OUTPUT_FORMAT, RECORD, claim_output
    from matscan.rig import resolve_rig
    from matscan.samples import maps_folder

    t0 = time.perf_counter()
    check_normal_convention(normal_convention)
    source = maps_folder(maps)
    if field_mm is not None:
        field = check_vector(list(field_mm), 2, "field_mm", FIELD_LIMITS_MM[0], FIELD_LIMITS_MM[1])
    inputs: list[str | Path] = [source]
    if str(rig).endswith(".json"):
        inputs.append(Path(rig))
    with claim_output(out, "export", inputs, overwrite=overwrite, overwrite_any=overwrite_any) as claim:
        maps_read = read_any(source, normal_convention)
        if field_mm is not None:
            field_from = "field_mm"
        elif (recorded := recorded_field(source)) is not None:
            field, field_from = recorded, f"{RECORD} of the maps"
        else:
            the_rig = resolve_rig(rig)
            field, field_from = the_rig.field_mm, f"rig {the_rig.name}"
        h, w = maps_read.size
        claim.check_space(h * w * (EXPORT_BYTES_PER_PIXEL + (EXR_BYTES_PER_PIXEL if exr else 0)))
        record: dict[str, Any] = {
            "format": OUTPUT_FORMAT,
            "command": "export",
            "matscan_version": __version__,
            "input": str(source.resolve()),
            "size_px": [w, h],
            "field_mm": list(field),
            "field_from": field_from,
            "maps": sorted(maps_read.present()),
            "conventions": CONVENTIONS,
        }
        with claim.folder() as tmp:
            write_maps(tmp, maps_read)
            record["exports"] = export_all(tmp, maps_read, (field[0], field[1]), exr, directx_normals)
            record["seconds"] = round(time.perf_counter() - t0, 3)
            (tmp / RECORD).write_text(dumps(record, RECORD), encoding="utf-8")
    return record
