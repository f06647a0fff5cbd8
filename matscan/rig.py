"""The acquisition rig as data: camera, lights, sample field.

A rig is a JSON file (or one of the built-in rigs by name). Rendering, training
and reconstruction read it; nothing about a particular dome lives in code.

Frame (shared/design.md, "Frames and units"): millimetres, the sample in the
plane z = 0 centred at the origin, +z up toward the camera.

Built-in rigs:

* ``dome24``: the paper's dome (§3.2), radius 225 mm, 24 LEDs in three rings of
  eight at elevations 22.5°, 45° and 67.5°, camera at (0, 0, 225).
* ``flash``: a phone flash beside the lens. Light and camera move with every
  photo, so each image of a capture carries its own light and camera position.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from matscan.errors import MatscanError, input_error
from matscan.jsonfile import (
    check_bool,
    check_list,
    check_number,
    check_object,
    check_string,
    check_vector,
    read_json,
    short_repr,
)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Camera:
    """A camera looking down at the sample.

    Captured images are rectified to the sample field (shared/design.md), so the
    camera's only role in image formation is its centre, which sets the view
    direction v at every surface point.
    """

    position_mm: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class Light:
    """A point light (an LED) with a cosine-power emission lobe.

    ``intensity`` is RGB, relative: a white Lambertian sample lit head-on by an
    intensity-1 light at the rig's reference distance images to 1.0.
    ``exponent`` is the LED emission exponent m (0: isotropic).
    The LED axis points from ``position_mm`` toward ``aim_mm``.
    """

    position_mm: Vec3
    intensity: Vec3 = (1.0, 1.0, 1.0)
    exponent: float = 1.0
    aim_mm: Vec3 = (0.0, 0.0, 0.0)

    @property
    def axis(self) -> Vec3:
        """Unit LED axis a_k, from the LED toward its aim point."""
        d = [a - p for a, p in zip(self.aim_mm, self.position_mm, strict=True)]
        n = math.sqrt(sum(c * c for c in d))
        return (d[0] / n, d[1] / n, d[2] / n)


@dataclass(frozen=True)
class Rig:
    """A capture rig.

    Attributes:
        name: identifier, recorded in captures and outputs.
        reference_distance_mm: R of the image formation model; a light of
            intensity I at distance R delivers irradiance I head-on.
        camera: the camera.
        field_mm: (width, height) of the sample field that images cover, mm.
        lights: the rig's lights; a capture's image names one by index.
        subsets: named input subsets (lists of light indices).
        backlight: whether the stage has a green/blue backlight (alpha mattes).
        per_image_geometry: when true (the ``flash`` rig), every image of a
            capture gives its own light and camera position; ``lights[0]`` is
            the template for the other light properties.
    """

    name: str
    reference_distance_mm: float
    camera: Camera
    field_mm: tuple[float, float]
    lights: tuple[Light, ...]
    subsets: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    backlight: bool = False
    per_image_geometry: bool = False

    def subset(self, spec: str | Sequence[int] | None) -> tuple[int, ...]:
        """Light indices for a named subset (``"6"``), a list (``"0,4,8"`` or
        ``[0, 4, 8]``), or all lights (``None`` or ``"all"``)."""
        if spec is None or spec == "all":
            return tuple(range(len(self.lights)))
        if isinstance(spec, str):
            spec = spec.strip()
            if spec in self.subsets:
                return tuple(self.subsets[spec])
            names = ", ".join(self.subsets) or "none"
            if "," not in spec:
                raise MatscanError(
                    f"lights: {spec!r} is not a subset of rig {self.name!r} (one of {names}); "
                    "give light indices as a list like 0,4,8 (a single light as 5,)"
                )
            try:
                indices = [int(s) for s in spec.split(",") if s.strip()]
            except ValueError:
                raise MatscanError(f"lights: {spec!r} is not a list of light indices like 0,4,8") from None
        else:
            indices = [int(i) for i in spec]
        bad = [i for i in indices if not 0 <= i < len(self.lights)]
        if bad:
            raise MatscanError(
                f"lights: index {bad[0]} is not a light of rig {self.name!r} (0 to {len(self.lights) - 1})"
            )
        if len(set(indices)) != len(indices):
            raise MatscanError(f"lights: {spec!r} names a light twice")
        return tuple(indices)

    def light_set(self, indices: Sequence[int] | None = None, dtype: torch.dtype = torch.float32) -> LightSet:
        """The renderer's view of some of this rig's lights (all by default)."""
        if indices is None:
            indices = range(len(self.lights))
        chosen = [self.lights[i] for i in indices]
        return LightSet.from_lights(chosen, self.camera.position_mm, self.reference_distance_mm, dtype)


@dataclass(frozen=True)
class LightSet:
    """Per-image light geometry, as tensors, for the renderer.

    One entry per rendered image. Shapes (L lights, optional leading batch B):

    =============  =============  ==========================================
    position       (…, L, 3)      light position q_k, mm
    intensity      (…, L, 3)      RGB intensity I_k
    axis           (…, L, 3)      unit LED axis a_k (from the LED toward the sample)
    exponent       (…, L)         emission exponent m_k
    camera         (…, L, 3)      camera centre c for that image, mm
    =============  =============  ==========================================

    ``reference_distance_mm`` is R of the image formation model.
    """

    position: Tensor
    intensity: Tensor
    axis: Tensor
    exponent: Tensor
    camera: Tensor
    reference_distance_mm: float

    def __len__(self) -> int:
        return self.position.shape[-2]

    @staticmethod
    def from_lights(
        lights: Sequence[Light],
        camera_mm: Vec3 | Sequence[Vec3],
        reference_distance_mm: float,
        dtype: torch.dtype = torch.float32,
    ) -> LightSet:
        """Build from :class:`Light` objects and one camera centre (or one per light)."""
        cam = torch.tensor(camera_mm, dtype=dtype)
        if cam.ndim == 1:
            cam = cam.expand(len(lights), 3)
        return LightSet(
            position=torch.tensor([lt.position_mm for lt in lights], dtype=dtype).reshape(-1, 3),
            intensity=torch.tensor([lt.intensity for lt in lights], dtype=dtype).reshape(-1, 3),
            axis=torch.tensor([lt.axis for lt in lights], dtype=dtype).reshape(-1, 3),
            exponent=torch.tensor([lt.exponent for lt in lights], dtype=dtype),
            camera=cam.contiguous(),
            reference_distance_mm=float(reference_distance_mm),
        )

    @staticmethod
    def points(
        positions_mm: Tensor | Sequence[Vec3],
        camera_mm: Vec3 | Tensor,
        reference_distance_mm: float,
        intensity: float | Tensor = 1.0,
        exponent: float = 0.0,
    ) -> LightSet:
        """Isotropic (m = 0 by default) point lights aimed at the origin, e.g. novel lights.

        ``positions_mm`` is (…, L, 3); the result keeps its leading dimensions.
        """
        pos = torch.as_tensor(positions_mm, dtype=torch.float32)
        cam = torch.as_tensor(camera_mm, dtype=torch.float32).expand_as(pos)
        inten = torch.as_tensor(intensity, dtype=torch.float32)
        inten = inten.expand(pos.shape) if inten.ndim < 2 else inten
        return LightSet(
            position=pos,
            intensity=inten.expand(pos.shape),
            axis=-pos / pos.norm(dim=-1, keepdim=True),
            exponent=torch.full(pos.shape[:-1], float(exponent)),
            camera=cam,
            reference_distance_mm=float(reference_distance_mm),
        )

    def to(self, dtype: torch.dtype) -> LightSet:
        """The same lights with tensors of another float dtype."""
        return LightSet(
            self.position.to(dtype),
            self.intensity.to(dtype),
            self.axis.to(dtype),
            self.exponent.to(dtype),
            self.camera.to(dtype),
            self.reference_distance_mm,
        )

    def select(self, indices: Sequence[int]) -> LightSet:
        """A subset of the entries (along the light dimension)."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return LightSet(
            self.position.index_select(-2, idx),
            self.intensity.index_select(-2, idx),
            self.axis.index_select(-2, idx),
            self.exponent.index_select(-1, idx),
            self.camera.index_select(-2, idx),
            self.reference_distance_mm,
        )


def transform_points(points: Tensor, rotations: int = 0, flip_x: bool = False) -> Tensor:
    """Positions (…, 3) mirrored x → −x when ``flip_x``, then turned ``rotations`` × 90°
    counter-clockwise about +z: the transform :meth:`matscan.mapset.MapSet.transformed`
    applies to a material."""
    x, y, z = points.unbind(-1)
    if flip_x:
        x = -x
    for _ in range(rotations % 4):
        x, y = -y, x
    return torch.stack([x, y, z], dim=-1)


# --- the built-in rigs ---------------------------------------------------------

#: The paper's Table 4 input subsets for dome24, named by count.
DOME24_SUBSETS: dict[str, tuple[int, ...]] = {
    "1": (0,),
    "2": (0, 16),
    "3": (0, 16, 23),
    "6": (0, 4, 8, 12, 16, 20),
    "10": (4, 6, 8, 10, 12, 14, 16, 18, 20, 22),
    "16": (0, 2, 4, 5, 6, 8, 10, 11, 12, 14, 16, 17, 18, 20, 22, 23),
    "24": tuple(range(24)),
}


def _dome24() -> Rig:
    radius = 225.0
    lights = []
    for k in range(24):
        elevation = math.radians(22.5 * (k // 8 + 1))
        azimuth = math.radians(45.0 * (k % 8))
        lights.append(
            Light(
                position_mm=(
                    radius * math.cos(elevation) * math.cos(azimuth),
                    radius * math.cos(elevation) * math.sin(azimuth),
                    radius * math.sin(elevation),
                ),
                exponent=1.0,
            )
        )
    return Rig(
        name="dome24",
        reference_distance_mm=radius,
        camera=Camera(position_mm=(0.0, 0.0, radius)),
        field_mm=(120.0, 120.0),
        lights=tuple(lights),
        subsets=DOME24_SUBSETS,
        backlight=True,
    )


def _flash() -> Rig:
    return Rig(
        name="flash",
        reference_distance_mm=300.0,
        camera=Camera(position_mm=(0.0, 0.0, 300.0)),
        field_mm=(68.5, 68.5),
        lights=(Light(position_mm=(0.0, 0.0, 300.0), exponent=0.0),),
        per_image_geometry=True,
    )


BUILTIN_RIGS = {"dome24": _dome24, "flash": _flash}


def builtin_rig(name: str) -> Rig:
    """A built-in rig by name (``dome24`` or ``flash``)."""
    try:
        return BUILTIN_RIGS[name]()
    except KeyError:
        raise MatscanError(
            f"rig: {name!r} is not a built-in rig (one of {', '.join(BUILTIN_RIGS)}) nor a .json file"
        ) from None


def resolve_rig(spec: str | Path | Mapping[str, Any] | Rig, base: Path | None = None) -> Rig:
    """A rig from a built-in name, a path to a rig JSON file, or a rig object.

    A relative path is taken relative to ``base`` (a capture folder, say).
    """
    if isinstance(spec, Rig):
        return spec
    if isinstance(spec, Mapping):
        return rig_from_dict(spec, "rig")
    if not isinstance(spec, (str, Path)):
        raise MatscanError(f"rig: expected a built-in rig name, a .json file or a rig object, got {short_repr(spec)}")
    text = str(spec)
    if text in BUILTIN_RIGS:
        return builtin_rig(text)
    if text.endswith(".json"):
        path = Path(text)
        if base is not None and not path.is_absolute():
            path = base / path
        return load_rig(path)
    return builtin_rig(text)


# --- JSON ----------------------------------------------------------------------

_RIG_KEYS = {
    "name": True,
    "reference_distance_mm": True,
    "camera": True,
    "field_mm": True,
    "lights": True,
    "subsets": False,
    "backlight": False,
    "per_image_geometry": False,
    "format": False,
}
_CAMERA_KEYS = {"position_mm": True, "up": False}
_LIGHT_KEYS = {"position_mm": True, "intensity": False, "exponent": False, "aim_mm": False}
RIG_FORMAT = "matscan-rig/1"


#: Bounds on a rig's numbers: far beyond any real rig, and small enough that squared
#: distances and intensities stay finite in float32.
MAX_MM = 1e6
MAX_INTENSITY = 1e6
MAX_EXPONENT = 1e3
#: A light's aim point must be this far (mm) from the light for its axis to be defined.
MIN_AIM_DISTANCE_MM = 1e-3


def _check_keys(obj: Any, spec: dict[str, bool], where: str) -> Mapping[str, Any]:
    return check_object(obj, where, spec)


def _vec(value: Any, n: int, where: str) -> tuple[float, ...]:
    return check_vector(value, n, where, -MAX_MM, MAX_MM)


def _number(value: Any, where: str, positive: bool = False) -> float:
    return check_number(value, where, positive=positive)


def check_position(value: Any, where: str, what: str = "a light") -> Vec3:
    """A point above the sample plane: 3 finite numbers (mm) within ``MAX_MM``, z > 0."""
    pos = _vec(value, 3, where)
    if pos[2] <= 0:
        raise MatscanError(f"{where}: z = {pos[2]:g} is below the sample plane ({what} needs z > 0)")
    return (pos[0], pos[1], pos[2])


def check_light(position: Vec3, intensity: Any, exponent: Any, aim: Any, where: str, sep: str = ".") -> Light:
    """A :class:`Light` from checked JSON values (``where`` names the light's object)."""
    inten = check_vector(intensity, 3, f"{where}{sep}intensity", 0.0, MAX_INTENSITY)
    m = check_number(exponent, f"{where}{sep}exponent", 0.0, MAX_EXPONENT)
    aim_mm = _vec(aim, 3, f"{where}{sep}aim_mm")
    if math.dist(aim_mm, position) < MIN_AIM_DISTANCE_MM:
        raise MatscanError(f"{where}{sep}aim_mm: equals the light's position; the axis is undefined")
    return Light(position_mm=position, intensity=(inten[0], inten[1], inten[2]), exponent=m, aim_mm=aim_mm)


def _lights(raw: Any, where: str) -> tuple[Light, ...]:
    lights = []
    for k, lt in enumerate(check_list(raw, f"{where}: lights", "lights")):
        lw = f"{where}: lights[{k}]"
        _check_keys(lt, _LIGHT_KEYS, lw)
        pos = check_position(lt["position_mm"], f"{lw}.position_mm")
        lights.append(
            check_light(pos, lt.get("intensity", [1, 1, 1]), lt.get("exponent", 1.0), lt.get("aim_mm", [0, 0, 0]), lw)
        )
    return tuple(lights)


def _subsets(raw: Any, n_lights: int, where: str) -> dict[str, tuple[int, ...]]:
    subsets: dict[str, tuple[int, ...]] = {}
    for key, members in check_object(raw, f"{where}: subsets").items():
        sw = f"{where}: subsets[{key!r}]"
        if not isinstance(members, (list, tuple)):
            raise MatscanError(f"{sw}: expected a list of light indices")
        idx = []
        for m in members:
            if not isinstance(m, int) or isinstance(m, bool) or not 0 <= m < n_lights:
                raise MatscanError(f"{sw}: {short_repr(m)} is not a light index (0 to {n_lights - 1})")
            idx.append(m)
        if len(set(idx)) != len(idx):
            raise MatscanError(f"{sw}: names a light twice")
        subsets[str(key)] = tuple(idx)
    return subsets


def rig_from_dict(data: Mapping[str, Any], where: str = "rig") -> Rig:
    """Build a :class:`Rig` from its JSON object, checking every field.

    Errors name ``where`` (a file name) and the field, e.g.
    ``rig.json: lights[3].position_mm: z = -10 is below the sample plane``.
    Every number must be finite; positions and sizes within ``MAX_MM``, intensities
    in [0, ``MAX_INTENSITY``], exponents in [0, ``MAX_EXPONENT``].
    """
    _check_keys(data, _RIG_KEYS, where)
    if "format" in data:
        check_string(data["format"], f"{where}: format", (RIG_FORMAT,))
    name = check_string(data["name"], f"{where}: name")
    ref = check_number(data["reference_distance_mm"], f"{where}: reference_distance_mm", high=MAX_MM, positive=True)

    cam = _check_keys(data["camera"], _CAMERA_KEYS, f"{where}: camera")
    cam_pos = check_position(cam["position_mm"], f"{where}: camera.position_mm", "the camera")
    up = _vec(cam.get("up", [0, 1, 0]), 3, f"{where}: camera.up")
    if not any(up):
        raise MatscanError(f"{where}: camera.up: must not be the zero vector")
    camera = Camera(position_mm=cam_pos, up=(up[0], up[1], up[2]))

    fld = _vec(data["field_mm"], 2, f"{where}: field_mm")
    if min(fld) <= 0:
        raise MatscanError(f"{where}: field_mm: {list(fld)} must be two positive sizes (width, height) in mm")

    lights = _lights(data["lights"], where)
    subsets = _subsets(data.get("subsets", {}), len(lights), where)
    for flag in ("backlight", "per_image_geometry"):
        if flag in data:
            check_bool(data[flag], f"{where}: {flag}")
    return Rig(
        name=name,
        reference_distance_mm=ref,
        camera=camera,
        field_mm=(fld[0], fld[1]),
        lights=lights,
        subsets=subsets,
        backlight=bool(data.get("backlight", False)),
        per_image_geometry=bool(data.get("per_image_geometry", False)),
    )


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    """The JSON object of a rig (inverse of :func:`rig_from_dict`)."""
    return {
        "format": RIG_FORMAT,
        "name": rig.name,
        "reference_distance_mm": rig.reference_distance_mm,
        "camera": {"position_mm": list(rig.camera.position_mm), "up": list(rig.camera.up)},
        "field_mm": list(rig.field_mm),
        "lights": [
            {
                "position_mm": list(lt.position_mm),
                "intensity": list(lt.intensity),
                "exponent": lt.exponent,
                "aim_mm": list(lt.aim_mm),
            }
            for lt in rig.lights
        ],
        "subsets": {k: list(v) for k, v in rig.subsets.items()},
        "backlight": rig.backlight,
        "per_image_geometry": rig.per_image_geometry,
    }


def load_rig(path: str | Path) -> Rig:
    """Read a rig JSON file; errors name the file and the field."""
    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such rig file")
    return rig_from_dict(read_json(path), str(path))


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write a rig JSON file (atomically: a temporary name, then renamed)."""
    path = Path(path)
    from matscan.atomic import write_text
    from matscan.jsonfile import dumps

    write_text(path, dumps(rig_to_dict(rig), str(path)))
