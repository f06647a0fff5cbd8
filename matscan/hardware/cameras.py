"""Camera back-ends for ``matscan capture``, behind one interface.

A camera has a ``name``, the file ``suffix`` of its frames, whether it
``controls_exposure``, ``shoot(exposure_s) -> bytes`` (one frame's file, as the camera
wrote it), ``settings`` (what it photographs by, which a resumed capture must find
unchanged) and ``close()``. The capture job writes those bytes under the frame's final
name only once they are complete and checked.

* :class:`VirtualCamera` renders a map set through the rig under whatever the LED
  controller has lit, with the virtual rig's sensor model (tests, demos, training staff).
  A frame depends only on the scene, what is lit and the exposure (its noise too), so a
  capture that is interrupted and resumed is byte for byte the one an uninterrupted run
  writes.
* :class:`FolderCamera` waits for the next image file that a camera's own software
  writes into a folder (industrial cameras, phones, tethering tools). Nothing in that
  folder is ever moved or deleted.
* :class:`Gphoto2Camera` drives a tethered camera through libgphoto2 (the ``camera``
  extra, python-gphoto2): shutter speed, aperture, ISO, RAW or JPEG. Frames stay on the
  camera's card too.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import torch

from matscan.errors import MatscanError
from matscan.hardware.leds import Illumination

#: The virtual camera's exposure at which a rendering is imaged as it is (seconds).
VIRTUAL_BASE_EXPOSURE = 0.01
#: Image files a folder camera waits for.
FOLDER_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf")


class VirtualCamera:
    """Renders ``maps`` through ``rig`` under ``leds.state`` (module doc)."""

    name = "virtual"
    suffix = ".png"
    controls_exposure = True

    def __init__(self, maps, rig, leds, camera=None, seed: int = 0, fail_after: int | None = None) -> None:
        from matscan.capture.virtual import CameraModel

        self.maps = maps
        self.rig = rig
        self.leds = leds
        self.camera = camera or CameraModel(read_noise=0.002, encoding="srgb", bits=16)
        self.seed = seed
        self.settings = {"scene": _scene_digest(maps), "seed": seed, "sensor": _sensor(self.camera)}
        self.sample_present = True
        self.fail_after = fail_after  # a fault for tests: the camera disconnects after this many frames
        self.shots = 0

    def radiance(self, state: Illumination) -> torch.Tensor:
        from matscan.capture.virtual import simulate_backlight
        from matscan.render import render_maps

        h, w = self.maps.size
        if state.led is not None:
            lights = self.rig.light_set([state.led])
            lights = lights.with_intensity(lights.intensity * state.level)
            maps = self.maps if self.sample_present else _empty_stage(self.maps)
            return render_maps(maps, lights, self.rig.field_mm)[0]
        if state.back is not None:
            from matscan.capture.virtual import CameraModel

            maps = self.maps if self.sample_present else _empty_stage(self.maps)
            back = simulate_backlight(maps, CameraModel(exposure=state.level, encoding="linear", bits=32), 0)
            return back[state.back if self.sample_present else f"{state.back}_empty"]
        return torch.zeros(3, h, w)

    def shoot(self, exposure_s: float) -> bytes:
        from matscan.capture.virtual import apply_camera
        from matscan.color import linear_to_srgb
        from matscan.imagefile import encode_image

        if self.fail_after is not None and self.shots >= self.fail_after:
            raise MatscanError("camera virtual: disconnected (a fault injected by the test)")
        self.shots += 1
        state = self.leds.state
        radiance = self.radiance(state) * (exposure_s / VIRTUAL_BASE_EXPOSURE)
        # the noise follows the scene: the same scene shot again gives the same bytes (a
        # resumed capture is the one an uninterrupted run writes), a changed one (a
        # sample that moved) new noise, as a sensor's would be
        key = f"{self.seed}|{state.led}|{state.back}|{state.level:.6f}|{exposure_s:.9g}|{self.sample_present}|"
        scene = hashlib.sha256(key.encode())
        scene.update((radiance * 2**16).round().to(torch.int64).numpy().tobytes())  # not the last bits
        seed = int.from_bytes(scene.digest()[:8], "little") % (2**63)
        photo = apply_camera(radiance, self.camera, torch.Generator().manual_seed(seed)).clamp(0, 1)
        if self.camera.encoding == "srgb":
            photo = linear_to_srgb(photo)
        return encode_image(photo.permute(1, 2, 0).numpy(), bits=self.camera.bits)

    def close(self) -> None:
        pass


def _scene_digest(maps) -> str:
    """A short digest of a map set's values: which sample a virtual camera photographs."""
    digest = hashlib.sha256()
    for name, t in sorted(maps.present().items()):
        digest.update(name.encode())
        digest.update(t.detach().float().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def _sensor(camera) -> dict:
    from dataclasses import asdict

    return {k: v for k, v in asdict(camera).items() if isinstance(v, (int, float, str, bool)) or v is None}


def _empty_stage(maps):
    """The stage alone: the maps with alpha 0 everywhere (what the backlight shows empty)."""
    from matscan.mapset import MapSet

    present = maps.present()
    present["alpha"] = torch.zeros_like(maps.roughness)
    return MapSet(**present)


class FolderCamera:
    """Waits for the next image file in ``folder`` (module doc)."""

    name = "folder"
    controls_exposure = False

    def __init__(
        self,
        folder: str | Path,
        timeout: float = 60.0,
        settle: float = 0.3,
        keepalive: Callable[[], None] | None = None,
    ) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise MatscanError(f"camera folder:{folder}: is not a folder")
        self.timeout = timeout
        self.settle = settle
        self.keepalive = keepalive
        self.seen = set(self._files())
        self.suffix = ".png"
        self.settings = {"folder": str(self.folder.resolve())}
        self.last_file: Path | None = None  # the file the last shot read

    def _files(self) -> list[Path]:
        return [p for p in self.folder.iterdir() if p.is_file() and p.suffix.lower() in FOLDER_SUFFIXES]

    def shoot(self, exposure_s: float) -> bytes:
        deadline = time.monotonic() + self.timeout
        ping = time.monotonic()
        while time.monotonic() < deadline:
            new = sorted((p for p in self._files() if p not in self.seen), key=lambda p: p.stat().st_mtime)
            if new:
                path = new[0]
                size = -1
                while size != path.stat().st_size:  # wait until the writer has finished
                    size = path.stat().st_size
                    time.sleep(self.settle)
                self.seen.add(path)
                self.suffix = path.suffix.lower()
                self.last_file = path
                return path.read_bytes()
            if self.keepalive is not None and time.monotonic() - ping > 1.0:
                self.keepalive()
                ping = time.monotonic()
            time.sleep(0.05)
        raise MatscanError(
            f"camera folder:{self.folder}: no new photo arrived within {self.timeout:g} s "
            "(did the camera fire, and does its software save into this folder?)"
        )

    def close(self) -> None:
        pass


def _seconds(text: str) -> float | None:
    """A shutter-speed choice as seconds: '1/125', '0.5', '2', '30s', '1/4000s'."""
    t = text.strip().lower().rstrip("s").strip()
    try:
        return float(Fraction(t))
    except (ValueError, ZeroDivisionError):
        return None


class Gphoto2Camera:
    """A tethered camera through libgphoto2 (python-gphoto2)."""

    name = "gphoto2"
    controls_exposure = True

    def __init__(self, aperture: str | None = None, iso: str | None = None, raw: bool = True, gp=None) -> None:
        if gp is None:
            try:
                import gphoto2 as gp
            except ImportError:
                raise MatscanError("--camera gphoto2: needs python-gphoto2: pip install 'matscan[camera]'") from None
        self.gp = gp
        try:
            self.camera = gp.Camera()
            self.camera.init()
        except gp.GPhoto2Error as exc:
            raise MatscanError(f"camera gphoto2: no camera found or it is busy ({exc})") from None
        self.suffix = ".cr2" if raw else ".jpg"
        self.exposure: float | None = None
        self.settings = {"aperture": aperture, "iso": iso, "raw": raw}
        self.set("imageformat", "RAW" if raw else "Large Fine JPEG", required=False)
        if aperture:
            self.set("aperture", aperture)
        if iso:
            self.set("iso", iso)

    def _widget(self, name: str):
        config = self.camera.get_config()
        try:
            return config, config.get_child_by_name(name)
        except self.gp.GPhoto2Error:
            return config, None

    def set(self, name: str, value: str, required: bool = True) -> None:
        config, widget = self._widget(name)
        if widget is None:
            if required:
                raise MatscanError(f"camera gphoto2: the camera has no {name} setting")
            return
        choices = [widget.get_choice(i) for i in range(widget.count_choices())]
        if value not in choices:
            if not required:
                return
            raise MatscanError(f"camera gphoto2: {name} {value!r} is not one of {', '.join(choices[:20])}")
        widget.set_value(value)
        self.camera.set_config(config)

    def shutter_choices(self) -> list[tuple[float, str]]:
        _, widget = self._widget("shutterspeed")
        if widget is None:
            return []
        out = []
        for i in range(widget.count_choices()):
            text = widget.get_choice(i)
            s = _seconds(text)
            if s is not None and s > 0:
                out.append((s, text))
        return sorted(out)

    def _speed(self, exposure_s: float) -> tuple[float, str] | None:
        """The shutter speed taken for ``exposure_s``: the longest not above it (the
        shortest, if all are longer); None for a camera without the setting."""
        choices = self.shutter_choices()
        if not choices:
            return None
        return ([c for c in choices if c[0] <= exposure_s * 1.0001] or choices[:1])[-1]

    def exposure_for(self, exposure_s: float) -> float:
        """The exposure (s) a frame asked for at ``exposure_s`` is made at."""
        speed = self._speed(exposure_s)
        return exposure_s if speed is None else speed[0]

    def shoot(self, exposure_s: float) -> bytes:
        gp = self.gp
        speed = self._speed(exposure_s)
        if speed is not None:
            seconds, text = speed
            if seconds != self.exposure:
                self.set("shutterspeed", text)
                self.exposure = seconds
        try:
            path = self.camera.capture(gp.GP_CAPTURE_IMAGE)
            camera_file = self.camera.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL)
            data = camera_file.get_data_and_size()
        except gp.GPhoto2Error as exc:
            raise MatscanError(f"camera gphoto2: the capture failed ({exc}); is the camera still connected?") from None
        self.suffix = Path(path.name).suffix.lower() or self.suffix
        return bytes(memoryview(data))

    @property
    def actual_exposure(self) -> float | None:
        return self.exposure

    def close(self) -> None:
        try:
            self.camera.exit()
        except Exception:
            pass


def open_camera(
    spec: str,
    rig,
    leds,
    seed: int = 0,
    target_maps=None,
    aperture: str | None = None,
    iso: str | None = None,
    raw: bool = True,
):
    """``virtual:MAPS`` (a map set folder or ``@sample``), ``folder:PATH`` or
    ``gphoto2``; ``target_maps`` replaces the virtual camera's sample (calibration
    targets); ``aperture``, ``iso`` and ``raw`` set a gphoto2 camera."""
    if spec.startswith("virtual:") and len(spec) > len("virtual:"):
        from matscan.mapset import read_mapset
        from matscan.samples import maps_folder

        maps = target_maps if target_maps is not None else read_mapset(maps_folder(spec[len("virtual:") :]))
        return VirtualCamera(maps, rig, leds, seed=seed)
    if spec.startswith("folder:") and len(spec) > len("folder:"):
        return FolderCamera(spec[len("folder:") :], keepalive=leds.keepalive)
    if spec == "gphoto2":
        return Gphoto2Camera(aperture=aperture, iso=iso, raw=raw)
    raise MatscanError(f"--camera: {spec!r} is not virtual:MAPS, folder:PATH or gphoto2")
