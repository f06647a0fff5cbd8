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

import dataclasses
import math
import operator
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
    direction v at every surface point. An orthographic camera gives ``direction``
    (unit, toward the camera) instead of ``position_mm``: v is then that direction at
    every pixel (telecentric lenses; a camera far above a small object).
    """

    position_mm: Vec3 | None = None
    up: Vec3 = (0.0, 1.0, 0.0)
    direction: Vec3 | None = None

    def __post_init__(self) -> None:
        if (self.position_mm is None) == (self.direction is None):
            raise MatscanError("camera: give either position_mm or direction (orthographic), not both")

    @property
    def orthographic(self) -> bool:
        return self.direction is not None

    def point(self, reference_distance_mm: float) -> Vec3:
        """The camera as a point for the renderer: its centre, or for an orthographic
        camera R·direction, a point in the view direction used with w = 0
        (:class:`LightSet`)."""
        if self.direction is not None:
            return _scaled(self.direction, reference_distance_mm)
        assert self.position_mm is not None
        return self.position_mm


@dataclass(frozen=True)
class Light:
    """A point light (an LED) with a cosine-power emission lobe, or a directional light.

    ``intensity`` is RGB, relative: a white Lambertian sample lit head-on by an
    intensity-1 light at the rig's reference distance images to 1.0.
    ``exponent`` is the LED emission exponent m (0: isotropic).
    The LED axis points from ``position_mm`` toward ``aim_mm``.

    A directional light gives ``direction`` (unit, toward the light) instead of
    ``position_mm``: l is that direction at every pixel, with no falloff and no lobe
    (shared/design.md, "Directional lights"), so a white Lambertian sample lit head-on
    by an intensity-1 directional light also images to 1.0.
    """

    position_mm: Vec3 | None = None
    intensity: Vec3 = (1.0, 1.0, 1.0)
    exponent: float = 1.0
    aim_mm: Vec3 = (0.0, 0.0, 0.0)
    direction: Vec3 | None = None

    def __post_init__(self) -> None:
        if (self.position_mm is None) == (self.direction is None):
            raise MatscanError("light: give either position_mm or direction, not both")

    @property
    def directional(self) -> bool:
        return self.direction is not None

    @property
    def axis(self) -> Vec3:
        """Unit LED axis a_k, from the LED toward its aim point (−direction for a
        directional light, which makes its lobe term 1)."""
        if self.direction is not None:
            return (-self.direction[0], -self.direction[1], -self.direction[2])
        assert self.position_mm is not None
        d = [a - p for a, p in zip(self.aim_mm, self.position_mm, strict=True)]
        n = math.sqrt(sum(c * c for c in d))
        return (d[0] / n, d[1] / n, d[2] / n)

    def point(self, reference_distance_mm: float) -> Vec3:
        """The light as a point for the renderer: its position, or for a directional
        light R·direction, used with w = 0 (:class:`LightSet`)."""
        if self.direction is not None:
            return _scaled(self.direction, reference_distance_mm)
        assert self.position_mm is not None
        return self.position_mm


def _scaled(v: Vec3, s: float) -> Vec3:
    return (v[0] * s, v[1] * s, v[2] * s)


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
        if spec is None or (isinstance(spec, str) and spec == "all"):
            return tuple(range(len(self.lights)))
        if isinstance(spec, str):
            spec = spec.strip()
            if spec and not spec.replace(",", "").strip():
                raise MatscanError(f"lights: {spec!r} names no light; give indices like 0,4,8 or a subset's name")
            if spec in self.subsets:
                return tuple(self.subsets[spec])
            names = ", ".join(self.subsets) or "none"
            if "," not in spec:
                raise MatscanError(
                    f"lights: {spec!r} is not a subset of rig {self.name!r} (one of {names}); "
                    "give light indices as a list like 0,4,8 (a single light as 5,)"
                )
            items = [s.strip() for s in spec.split(",")]
            if items[-1] == "":  # "5,": a list of one light
                items.pop()
            try:
                indices = [int(s) for s in items]
            except ValueError:
                raise MatscanError(f"lights: {spec!r} is not a list of light indices like 0,4,8") from None
        else:
            indices = [_light_index(i) for i in spec]
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
        indices = range(len(self.lights)) if indices is None else self.subset(indices)
        chosen = [self.lights[i] for i in indices]
        r = self.reference_distance_mm
        return LightSet.from_lights(chosen, self.camera.point(r), r, dtype, self.camera_w)

    @property
    def camera_w(self) -> float:
        """0 for an orthographic camera, 1 otherwise (:class:`LightSet`)."""
        return 0.0 if self.camera.orthographic else 1.0

    @property
    def camera_point(self) -> Vec3:
        """The camera as a point for the renderer (:meth:`Camera.point`)."""
        return self.camera.point(self.reference_distance_mm)


def _light_index(value: Any) -> int:
    """An integer light index (numpy's and torch's integers too); 2.7 or True is an error,
    not light 2 or 1."""
    if not isinstance(value, bool) and type(value).__name__ not in ("bool", "bool_"):
        try:
            return operator.index(value)
        except TypeError:
            pass
    raise MatscanError(f"lights: {short_repr(value)} is not a light index (an integer)")


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
    w              (…, L)         1 for a point light, 0 for a directional one
    camera_w       (…, L)         1 for a camera centre, 0 for an orthographic camera
    =============  =============  ==========================================

    Lights and cameras are points in homogeneous coordinates: the vector toward the
    light from a surface point p is q − w·p. A directional light is stored as
    q = R·direction with w = 0 (and axis = −direction), so that l = direction, the
    falloff (R/|q|)² is exactly 1 and the lobe term is 1, everywhere in the field; an
    orthographic camera likewise. Every consumer computes geometry with ``w``.

    ``reference_distance_mm`` is R of the image formation model.
    """

    position: Tensor
    intensity: Tensor
    axis: Tensor
    exponent: Tensor
    camera: Tensor
    reference_distance_mm: float
    w: Tensor = None  # type: ignore[assignment]  # filled with ones when not given
    camera_w: Tensor = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        shape = self.position.shape[:-1]
        for name in ("w", "camera_w"):
            value = getattr(self, name)
            if value is None:
                value = torch.ones(shape, dtype=self.position.dtype, device=self.position.device)
            object.__setattr__(self, name, value.to(self.position.dtype).expand(shape))

    def __len__(self) -> int:
        return self.position.shape[-2]

    @property
    def directional(self) -> bool:
        """Whether any light is directional or any camera orthographic."""
        return bool((self.w == 0).any()) or bool((self.camera_w == 0).any())

    @staticmethod
    def from_lights(
        lights: Sequence[Light],
        camera_mm: Vec3 | Sequence[Vec3],
        reference_distance_mm: float,
        dtype: torch.dtype = torch.float32,
        camera_w: float = 1.0,
    ) -> LightSet:
        """Build from :class:`Light` objects and one camera point (or one per light);
        ``camera_w`` 0 makes the camera orthographic (``camera_mm`` = R·direction)."""
        cam = torch.tensor(camera_mm, dtype=dtype)
        if cam.ndim == 1:
            cam = cam.expand(len(lights), 3)
        r = float(reference_distance_mm)
        return LightSet(
            position=torch.tensor([lt.point(r) for lt in lights], dtype=dtype).reshape(-1, 3),
            intensity=torch.tensor([lt.intensity for lt in lights], dtype=dtype).reshape(-1, 3),
            axis=torch.tensor([lt.axis for lt in lights], dtype=dtype).reshape(-1, 3),
            exponent=torch.tensor([0.0 if lt.directional else lt.exponent for lt in lights], dtype=dtype),
            camera=cam.contiguous(),
            reference_distance_mm=r,
            w=torch.tensor([0.0 if lt.directional else 1.0 for lt in lights], dtype=dtype),
            camera_w=torch.full((len(lights),), float(camera_w), dtype=dtype),
        )

    @staticmethod
    def points(
        positions_mm: Tensor | Sequence[Vec3],
        camera_mm: Vec3 | Tensor,
        reference_distance_mm: float,
        intensity: float | Tensor = 1.0,
        exponent: float = 0.0,
        camera_w: float = 1.0,
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
            camera_w=torch.full(pos.shape[:-1], float(camera_w)),
        )

    def _map(self, fn) -> LightSet:
        return LightSet(
            fn(self.position, 2),
            fn(self.intensity, 2),
            fn(self.axis, 2),
            fn(self.exponent, 1),
            fn(self.camera, 2),
            self.reference_distance_mm,
            fn(self.w, 1),
            fn(self.camera_w, 1),
        )

    def to(self, dtype_or_device: torch.dtype | torch.device | str) -> LightSet:
        """The same lights with tensors of another float dtype, or on another device."""
        return self._map(lambda t, _: t.to(dtype_or_device))

    def select(self, indices: Sequence[int]) -> LightSet:
        """A subset of the entries (along the light dimension)."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return self._map(lambda t, k: t.index_select(-k, idx.to(t.device)))

    def batch_item(self, i: int) -> LightSet:
        """Element ``i`` of a leading batch dimension: (B, L, …) → (L, …)."""
        return self._map(lambda t, _: t[i])

    def with_intensity(self, intensity: Tensor) -> LightSet:
        """The same geometry with other intensities (…, L, 3)."""
        return dataclasses.replace(self, intensity=intensity)

    @staticmethod
    def cat(sets: Sequence[LightSet], dim: int = 0) -> LightSet:
        """Sets of one reference distance joined along a leading dimension ``dim``."""
        fields = ("position", "intensity", "axis", "exponent", "camera")
        joined = {f: torch.cat([getattr(s, f) for s in sets], dim) for f in fields}
        return LightSet(
            **joined,
            reference_distance_mm=sets[0].reference_distance_mm,
            w=torch.cat([s.w for s in sets], dim),
            camera_w=torch.cat([s.camera_w for s in sets], dim),
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
_CAMERA_KEYS = {"position_mm": False, "direction": False, "up": False}
_LIGHT_KEYS = {"position_mm": False, "direction": False, "intensity": False, "exponent": False, "aim_mm": False}
#: A direction's length may differ from 1 by this much (it is then normalised).
DIRECTION_TOLERANCE = 1e-3
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


def check_direction(value: Any, where: str, what: str = "a light") -> Vec3:
    """A unit vector above the sample plane (z > 0), 3 finite numbers whose length is 1
    within ``DIRECTION_TOLERANCE`` (returned normalised)."""
    d = check_vector(value, 3, where, -2.0, 2.0)
    norm = math.sqrt(sum(c * c for c in d))
    if abs(norm - 1) > DIRECTION_TOLERANCE:
        raise MatscanError(f"{where}: {list(d)} has length {norm:.4g}; a direction must be a unit vector")
    if d[2] <= 0:
        raise MatscanError(f"{where}: z = {d[2]:g} points below the sample plane ({what} needs z > 0)")
    return (d[0] / norm, d[1] / norm, d[2] / norm)


def check_light(
    position: Vec3 | None,
    intensity: Any,
    exponent: Any,
    aim: Any,
    where: str,
    sep: str = ".",
    direction: Vec3 | None = None,
) -> Light:
    """A :class:`Light` from checked JSON values (``where`` names the light's object);
    a directional one where ``direction`` is given instead of ``position``."""
    inten = check_vector(intensity, 3, f"{where}{sep}intensity", 0.0, MAX_INTENSITY)
    m = check_number(exponent, f"{where}{sep}exponent", 0.0, MAX_EXPONENT)
    aim_mm = _vec(aim, 3, f"{where}{sep}aim_mm")
    if position is not None and math.dist(aim_mm, position) < MIN_AIM_DISTANCE_MM:
        raise MatscanError(f"{where}{sep}aim_mm: equals the light's position; the axis is undefined")
    rgb = (inten[0], inten[1], inten[2])
    return Light(position_mm=position, intensity=rgb, exponent=m, aim_mm=aim_mm, direction=direction)


def _one_of(obj: Mapping[str, Any], where: str) -> str:
    """Which of ``position_mm`` and ``direction`` an object gives (exactly one)."""
    given = [k for k in ("position_mm", "direction") if k in obj]
    if not given:
        raise MatscanError(f"{where}: missing field 'position_mm' (a point) or 'direction' (a unit vector)")
    if len(given) == 2:
        raise MatscanError(f"{where}: give either position_mm (a point) or direction (a unit vector), not both")
    return given[0]


def _lights(raw: Any, where: str) -> tuple[Light, ...]:
    lights = []
    for k, lt in enumerate(check_list(raw, f"{where}: lights", "lights")):
        lw = f"{where}: lights[{k}]"
        _check_keys(lt, _LIGHT_KEYS, lw)
        pos = direction = None
        if _one_of(lt, lw) == "position_mm":
            pos = check_position(lt["position_mm"], f"{lw}.position_mm")
        else:
            direction = check_direction(lt["direction"], f"{lw}.direction")
        lights.append(
            check_light(
                pos,
                lt.get("intensity", [1, 1, 1]),
                lt.get("exponent", 1.0),
                lt.get("aim_mm", [0, 0, 0]),
                lw,
                direction=direction,
            )
        )
    return tuple(lights)


def _subsets(raw: Any, n_lights: int, where: str) -> dict[str, tuple[int, ...]]:
    subsets: dict[str, tuple[int, ...]] = {}
    for key, members in check_object(raw, f"{where}: subsets").items():
        sw = f"{where}: subsets[{key!r}]"
        if not isinstance(members, (list, tuple)):
            raise MatscanError(f"{sw}: expected a list of light indices")
        if not members:
            raise MatscanError(f"{sw}: names no light (a subset lists one light or more)")
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
    up = _vec(cam.get("up", [0, 1, 0]), 3, f"{where}: camera.up")
    if not any(up):
        raise MatscanError(f"{where}: camera.up: must not be the zero vector")
    if _one_of(cam, f"{where}: camera") == "position_mm":
        cam_pos = check_position(cam["position_mm"], f"{where}: camera.position_mm", "the camera")
        camera = Camera(position_mm=cam_pos, up=(up[0], up[1], up[2]))
    else:
        cam_dir = check_direction(cam["direction"], f"{where}: camera.direction", "the camera")
        camera = Camera(direction=cam_dir, up=(up[0], up[1], up[2]))

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
    cam = rig.camera
    camera = {"direction": list(cam.direction)} if cam.direction is not None else {"position_mm": list(cam.position_mm)}
    return {
        "format": RIG_FORMAT,
        "name": rig.name,
        "reference_distance_mm": rig.reference_distance_mm,
        "camera": {**camera, "up": list(cam.up)},
        "field_mm": list(rig.field_mm),
        "lights": [_light_dict(lt) for lt in rig.lights],
        "subsets": {k: list(v) for k, v in rig.subsets.items()},
        "backlight": rig.backlight,
        "per_image_geometry": rig.per_image_geometry,
    }


def _light_dict(lt: Light) -> dict[str, Any]:
    if lt.direction is not None:
        return {"direction": list(lt.direction), "intensity": list(lt.intensity)}
    return {
        "position_mm": list(lt.position_mm),
        "intensity": list(lt.intensity),
        "exponent": lt.exponent,
        "aim_mm": list(lt.aim_mm),
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
