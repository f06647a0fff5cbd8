"""``matscan capture``: take a capture with a camera and the LED controller, never losing a frame.

The sequence: a dark frame (everything off); the exposure, chosen on the rig's LEDs so
that no photo saturates more than ``max_saturated`` of its pixels (a camera whose
exposure is set by its own software keeps it); each LED in turn; with ``backlight``, the
backlight green and blue with the sample, then (the operator asked to remove it) of the
empty stage: the paper's 24 + 4 photos. Every frame is checked
as it arrives: saturation, an all-dark frame (an LED that did not light), and a sample
that moved since the previous LED frame (phase correlation of the log images with the
shading removed; the previous frame, because frames lit from far apart correlate badly:
on the built-in sample, consecutive LED frames measured 0.03–0.71 px apart, LED 0
against the others up to 21 px, and a true 3 px shift measured 2.8 px). A frame that
fails is taken again (``retakes`` times), and the capture stops with a one-line error
if it still fails. The first time a frame fails the dark or the movement check, one
more shot tells a fault from what the sample itself does to the photos:

* a frame as dark as the dark frame: the same LED, and the dark frame, at a longer
  exposure (16 times, and at least the metering's start). If the LED shows there, it
  lit, and the sample sends little of its light toward the camera (a polished metal
  under a grazing LED, a black lacquer at the exposure its highlights allow): the frame
  is kept, and is not the reference for the next frame's movement check.
* a sample that seems to have moved: the previous LED frame's LED again, compared with
  that frame (the same light, so only movement can shift it). Relief, gloss and
  shadows change with the light and can look like movement between two LEDs; if the
  same light shows the sample where it was, the frame is kept.

After the last LED frame, an early LED frame has its LED shot once more and compared
with it (the earliest whose texture the movement check could follow, else the first
that shows the sample): a sample that crept a fraction of a pixel per frame, or
moved in frames too dark to show it, stops the capture here (and on every rerun: its
photos are kept but do not line up); otherwise ``capture.json`` records the shift
(``drift_px``).

With the virtual camera at default settings, on every procedural family and the five
artist-style sets at 128² (``bench/capture_checks.py``), these checks stopped 13 of 28
good captures before; with the extra shots, none, while a dead LED is caught on all 28
(16 before), a 3 px knock on 23 (15 before) and a drift of 0.15 px per photo on 24 (2
before; docs/hardware.md).

Never lost, never overwritten:

* each photo is written under a temporary name and renamed to its final name only when
  complete and checked; a final name is never written twice;
* ``capture.json`` is rewritten (atomically) after every frame, so from its first LED
  frame on the folder is a valid capture of the frames so far at any moment (before
  it, and for a calibration target, ``capture.json`` lists no photos under the lights
  and reading it says so);
* a journal (``capture.journal``, one JSON line per event, flushed to disk) records the
  settings, the exposure and every frame with its SHA-256; running the same command again
  on the folder resumes after the last frame journalled (a frame on disk but not yet
  journalled, as after a kill between the two, is checked against the files and taken
  as done); other settings, or a frame whose file no longer matches, stop with an error;
* the LEDs are commanded off whatever happens (errors, Ctrl-C, SIGTERM), and the
  board's watchdog turns them off if the host dies.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from matscan.atomic import output_lock, write_text
from matscan.capture.folder import EXPOSURE_LIMITS
from matscan.errors import MatscanError, input_error
from matscan.hardware.leds import DARK, Illumination
from matscan.jsonfile import dumps
from matscan.mapset import MapSet
from matscan.rig import BUILTIN_RIGS, Rig, builtin_rig, rig_to_dict

JOURNAL = "capture.journal"
TARGETS = ("grey", "chart", "sphere")
#: The LED controller's levels: thousandths of full brightness (the firmware's MAX_LEVEL).
LEVEL_STEPS = 1000


@dataclass(frozen=True)
class AcquireConfig:
    """How a capture is taken (``matscan capture``'s flags)."""

    lights: Sequence[int] | None = None  # rig lights to photograph (all by default)
    backlight: bool = False  # green and blue backlight frames with the sample, then of the empty stage
    target: str | None = None  # a calibration target on the stage: grey, chart or sphere
    exposure_s: float | None = None  # a fixed exposure; chosen on the LEDs when None
    start_exposure_s: float = 0.01
    max_saturated: float = 0.001  # largest fraction of pixels at the top code in an LED photo
    dark_margin: float = 0.01  # an LED frame's 99th percentile must rise this much above the dark frame
    max_shift_px: float = 1.5  # largest movement of the sample from the previous LED frame
    retakes: int = 2
    level: float = 1.0  # LED level, 0..1

    def __post_init__(self) -> None:
        if self.target is not None and self.target not in TARGETS:
            raise MatscanError(f"--target: {self.target!r} is not one of {', '.join(TARGETS)}")
        if not 0 < self.level <= 1:
            raise MatscanError(f"--level: {self.level!r} must be above 0 and at most 1")
        if not 0 <= self.max_saturated < 1:
            raise MatscanError(f"--max-saturated: {self.max_saturated!r} must be a fraction of the pixels, below 1")
        low, high = EXPOSURE_LIMITS
        if self.exposure_s is not None and not low <= self.exposure_s <= high:
            raise MatscanError(f"--exposure: {self.exposure_s!r} must be a number of seconds from {low:g} to {high:g}")


@dataclass
class Frame:
    """One photo to take: its file stem, what is lit, and which checks apply."""

    stem: str
    light: Illumination
    kind: str  # "dark", "led", "back", "chart"
    rig_light: int | None = None
    empty: bool = False


@dataclass
class Progress:
    done: list[dict[str, Any]] = field(default_factory=list)
    exposure_s: float | None = None
    drift: dict[str, Any] | None = None  # the end-of-capture movement check's journal event


def plan(rig: Rig, cfg: AcquireConfig) -> list[Frame]:
    """The frames of a capture, in order (module doc)."""
    lights = list(cfg.lights) if cfg.lights is not None else list(range(len(rig.lights)))
    frames = [Frame("dark", DARK, "dark")]
    if cfg.target == "chart":  # one photo of the chart under the LED nearest the zenith
        top = max(lights, key=lambda k: rig.lights[k].point(rig.reference_distance_mm)[2])
        return frames + [Frame("chart", Illumination(led=top, level=cfg.level), "chart", top)]
    frames += [Frame(f"led_{k:02d}", Illumination(led=k, level=cfg.level), "led", k) for k in lights]
    if cfg.backlight:
        frames += [Frame(f"back_{c}", Illumination(back=c, level=1.0), "back") for c in ("green", "blue")]
        frames += [Frame(f"empty_{c}", Illumination(back=c, level=1.0), "back", empty=True) for c in ("green", "blue")]
    return frames


def check_level(level: float) -> None:
    """Refuse an LED level between the controller's steps (thousandths): the board would
    light another level than the capture records, and ``led_level`` scales a calibration.
    Checked when a capture starts; one begun before the check resumes at its own level."""
    steps = level * LEVEL_STEPS
    if abs(steps - round(steps)) > 1e-6 * LEVEL_STEPS:
        raise MatscanError(
            f"--level: {level!r} is not a level the LED controller makes: it sets thousandths "
            f"(0.001 to 1; nearest {max(1, round(steps)) / LEVEL_STEPS:g})"
        )


def _settings(rig: Rig, cfg: AcquireConfig, camera, leds: str) -> dict[str, Any]:
    """What a resume must find unchanged: the rig, the capture's settings, the LEDs, and the
    camera with what it photographs by (``camera.settings``: a virtual camera's scene and
    sensor, a folder camera's folder, a tethered camera's aperture, ISO and file type)."""
    settings = {"rig": rig_to_dict(rig), "config": asdict(cfg), "camera": camera.name, "leds": leds}
    if getattr(camera, "settings", None) is not None:
        settings["camera_settings"] = camera.settings
    return settings


#: ``matscan capture``'s flag for each AcquireConfig field (the others have none).
FLAGS = {
    "lights": "--lights",
    "backlight": "--backlight",
    "target": "--target",
    "exposure_s": "--exposure",
    "max_saturated": "--max-saturated",
    "retakes": "--retakes",
    "level": "--level",
}


def _differences(recorded: Any, settings: dict[str, Any]) -> list[str]:
    """Which of ``settings`` differ from a journal's ``recorded`` ones (a journal from
    before ``camera_settings`` was recorded is compared without them)."""
    settings = json.loads(json.dumps(settings))
    if not isinstance(recorded, dict):
        return ["all"]
    if "camera_settings" not in recorded:
        settings.pop("camera_settings", None)
    names = []
    for key in sorted(set(settings) | set(recorded)):
        if key == "config" and isinstance(recorded.get(key), dict):
            names += [FLAGS.get(k, k) for k in sorted(settings[key]) if settings[key].get(k) != recorded[key].get(k)]
            names += [k for k in recorded[key] if k not in settings[key]]
        elif settings.get(key) != recorded.get(key):
            names.append({"camera_settings": "the camera's settings"}.get(key, key))
    return names


class Journal:
    """``capture.journal``: one JSON object per line, each flushed and synced."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._mended = False

    def read(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        events = []
        try:
            text = self.path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise input_error(self.path, f"cannot be read as a capture journal ({exc})") from None
        for number, line in enumerate(text.splitlines(), 1):
            try:
                event = json.loads(line)
            except (ValueError, RecursionError):  # a line cut short by a kill: everything before it stands
                break
            _check_event(self.path, number, event)
            events.append(event)
        return events

    def mend(self) -> None:
        """Cut a last line that a kill left unfinished (no newline at its end), so the next
        event starts a line of its own rather than joining it (which made that event and
        every later one unreadable)."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return
        if not data or data.endswith(b"\n"):
            return
        cut = data.rfind(b"\n") + 1
        try:  # a whole event that lacks only its newline was read (and replayed): keep it
            whole = isinstance(json.loads(data[cut:]), dict)
        except (ValueError, RecursionError):
            whole = False
        with open(self.path, "r+b") as f:
            if whole:
                f.seek(0, 2)
                f.write(b"\n")
            else:
                f.truncate(cut)
            f.flush()
            os.fsync(f.fileno())

    def append(self, event: dict[str, Any]) -> None:
        if not self._mended:
            self.mend()
            self._mended = True
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json.dumps(event, sort_keys=True) + "\n")
            f.flush()
            os.fsync(f.fileno())


#: What each kind of journal event must hold, and of which type, to be replayed.
_EVENT_FIELDS: dict[str, dict[str, type | tuple[type, ...]]] = {
    "start": {"settings": dict},
    "exposure": {"exposure_s": (int, float)},
    "frame": {"stem": str, "file": str, "sha256": str, "kind": str, "light": (int, type(None)), "empty": bool},
    "drift": {"stem": str, "shift_px": (int, float), "response": (int, float), "moved": bool},  # and textured
}


def _check_event(path: Path, number: int, event: Any) -> None:
    """A journal line as :func:`_replay` needs it, or a one-line error naming the line."""
    if not isinstance(event, dict):
        raise input_error(
            path, f"line {number}: is not a journal event (a JSON object); this capture cannot be resumed"
        )
    for name, kind in _EVENT_FIELDS.get(str(event.get("event")), {}).items():
        value = event.get(name)
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
            raise input_error(
                path,
                f"line {number}: this {event['event']} event has no usable {name!r}; this capture cannot be resumed",
            )
    if event.get("event") == "frame" and Path(event["file"]).name != event["file"]:
        raise input_error(path, f"line {number}: {event['file']!r} is not a file name in the capture folder")


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _grey(pixels: np.ndarray) -> np.ndarray:
    return pixels[..., :3].mean(axis=2) if pixels.ndim == 3 else pixels


def frame_checks(
    frame: Frame,
    data,
    dark: np.ndarray | None,
    reference: np.ndarray | None,
    cfg: AcquireConfig,
    lit: bool = False,
) -> tuple[dict[str, float], tuple[str, str] | None]:
    """Measurements of a frame (``data``: :class:`~matscan.imagefile.ImageData`) and the
    problem that makes it fail, if any, as (kind, message): kind ``saturated``,
    ``dark`` or ``moved``. ``lit``: the LED is known to have lit (no dark check)."""
    px = data.pixels
    grey = _grey(px)
    out: dict[str, float] = {"p99": float(np.percentile(grey, 99))}
    if data.kind != "float":
        top = np.iinfo(data.stored.dtype).max
        out["saturated"] = float((data.stored[..., :3] >= top).any(axis=2).mean())
    if frame.kind in ("led", "chart"):
        if out.get("saturated", 0.0) > cfg.max_saturated:
            message = f"{out['saturated']:.2%} of its pixels are saturated (at most {cfg.max_saturated:.2%})"
            return out, ("saturated", message)
        if not lit and dark is not None and out["p99"] < float(np.percentile(dark, 99)) + cfg.dark_margin:
            return out, ("dark", "it is as dark as the dark frame: did the LED light?")
        if reference is not None and cfg.target is None:  # calibration targets have no texture to follow
            shift, response = sample_shift(reference, grey, noise_floor(dark))
            out["shift_px"], out["shift_response"] = shift, response
            if response >= MIN_RESPONSE and shift > cfg.max_shift_px:
                message = f"the sample moved {shift:.1f} px since the last LED frame (at most {cfg.max_shift_px:g})"
                return out, ("moved", message)
    return out, None


def sample_shift(a: np.ndarray, b: np.ndarray, floor: float = 1e-3) -> tuple[float, float]:
    """How far (px) image ``b`` is shifted from ``a``, and the phase correlation's
    response (0..1, how much the two share): phase correlation of their log images with
    the shading removed (minus a Gaussian blur of σ 2 px), which keeps the sample's own
    texture while the light moves. ``floor`` is added before the log: the dark frame's
    99th percentile, so that noise in the darkest pixels does not outweigh the texture
    (measured once: on five dark or glossy procedural materials and three textured ones
    at 128², each captured still and knocked 3 px before LED 12 at its metered exposure,
    LEDs 12-23's frames of the two captures compared pairwise showed the 3 px in 75 of
    96 pairs, against 63 with 1e-3)."""
    import cv2

    def texture(img: np.ndarray) -> np.ndarray:
        log = np.log(img.astype(np.float32) + np.float32(floor))
        return log - cv2.GaussianBlur(log, (0, 0), 2.0)

    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(texture(a), texture(b), window)
    return float(np.hypot(dx, dy)), float(response)


def noise_floor(dark: np.ndarray | None) -> float:
    """What :func:`sample_shift` adds before the log: the dark frame's 99th percentile."""
    return 1e-3 if dark is None else max(1e-3, float(np.percentile(dark, 99)))


#: Below this phase-correlation response the images share too little texture for a
#: shift to mean anything (a plain card; consecutive frames of the built-in sample: 0.27
#: and above).
MIN_RESPONSE = 0.15


def choose_exposure(
    shoot_led: Callable[[int, float], Any], lights: Sequence[int], cfg: AcquireConfig
) -> tuple[float, list[dict[str, float]]]:
    """The longest exposure (from ``start_exposure_s``, halving) at which no LED's photo
    saturates more than ``max_saturated`` of its pixels. ``shoot_led(k, exposure)`` gives
    an ImageData. Returns the exposure and the test shots' record.

    At each exposure the LEDs are tried until one saturates, the last to saturate
    first, and an LED whose photo passed at a longer exposure is not tried again (it
    cannot saturate more at a shorter one). An exposure that is too long then costs one
    shot, not every LED up to the brightest: on the 28 materials of
    ``bench/capture_checks.py``, 64 test shots per capture before, 27 after at 64² (59
    and 27 at 256²), and the same exposure chosen for every one.

    The record's ``worst_saturated`` is the largest fraction among the LEDs tried at
    that exposure."""
    exposure = cfg.start_exposure_s
    order = list(lights)
    passed: set[int] = set()
    tests = []
    for _ in range(16):
        worst = 0.0
        for k in [k for k in order if k not in passed]:
            data = shoot_led(k, exposure)
            if data.kind == "float":
                passed.add(k)
                continue
            top = np.iinfo(data.stored.dtype).max
            saturated = float((data.stored[..., :3] >= top).any(axis=2).mean())
            worst = max(worst, saturated)
            if saturated > cfg.max_saturated:
                order.remove(k)
                order.insert(0, k)
                break
            passed.add(k)
        tests.append({"exposure_s": exposure, "worst_saturated": worst})
        if worst <= cfg.max_saturated:
            return exposure, tests
        exposure /= 2
    raise MatscanError(
        f"capture: the LEDs saturate the photos even at {exposure * 2:.3g} s; lower the LED level (--level)"
    )


def capture_json(
    rig: Rig, frames_done: list[dict[str, Any]], acquisition: dict[str, Any], encoding: str
) -> dict[str, Any]:
    images = [{"light": d["light"], "file": d["file"]} for d in frames_done if d["kind"] == "led"]
    doc: dict[str, Any] = {
        "format": "matscan-capture/1",
        "rig": rig.name if rig.name in BUILTIN_RIGS and builtin_rig(rig.name) == rig else rig_to_dict(rig),
        "encoding": encoding,
        "images": images,
        "acquisition": acquisition,
    }
    back = {
        d["stem"].replace("back_", "").replace("empty_", "") + ("_empty" if d["empty"] else ""): d["file"]
        for d in frames_done
        if d["kind"] == "back"
    }
    if len(back) == 4:  # the capture format names all four backlight photos or none
        doc["backlight"] = back
    return doc


def acquire(
    out: str | Path,
    rig: Rig,
    camera,
    leds,
    cfg: AcquireConfig = AcquireConfig(),
    progress: bool = False,
    ask: Callable[[str], None] | None = None,
    encoding: str = "srgb",
) -> dict[str, Any]:
    """Take (or resume) a capture into ``out`` (module doc). ``camera`` and ``leds`` are
    open back-ends (:mod:`matscan.hardware`); ``ask(message)`` waits for the operator
    (to remove the sample before the empty-stage frames). Returns the acquisition record."""
    from tqdm import tqdm

    from matscan.imagefile import read_image

    out = Path(out)
    frames = plan(rig, cfg)
    if rig.per_image_geometry:
        raise MatscanError(
            f"capture: rig {rig.name!r} moves its light by hand (per-photo geometry); matscan capture drives a "
            "fixed rig's LEDs: photograph such a capture yourself and write its capture.json"
        )
    lights = list(cfg.lights) if cfg.lights is not None else list(range(len(rig.lights)))
    board = getattr(leds, "n_leds", None)  # 0 or None: a controller that does not say
    if board and lights and max(lights) >= board:
        raise MatscanError(
            f"capture: rig {rig.name!r} names light {max(lights)}, but the LED controller {leds.name!r} drives "
            f"{board} LEDs (0 to {board - 1})"
        )
    settings = _settings(rig, cfg, camera, leds.name)
    with output_lock(out):
        journal = Journal(out / JOURNAL)
        events = _open_folder(out, journal, settings)
        state = _replay(out, events, frames, journal)
        exposure = _used(camera, state.exposure_s) if camera.controls_exposure else None
        done = {d["stem"] for d in state.done}
        dark = reference = first = None
        for d in state.done:
            if d["kind"] in ("dark", "led", "chart"):
                px = _grey(read_image(out / d["file"]).pixels)
                if d["kind"] == "dark":
                    dark = px
                elif _shows_sample(px, dark, cfg):  # the last LED frame that does, its light and name
                    current = (px, Illumination(led=d["light"], level=cfg.level), d["stem"])
                    first = _anchor(first, reference, d.get("checks", {}), current)
                    reference = current
        # no end-of-capture check for a capture finished, or already at its backlight
        # frames (the sample may be off the stage), before the check existed
        finished = any(e.get("event") == "complete" for e in events)
        backlit = finished or any(d["kind"] == "back" for d in state.done)
        if state.drift is not None and state.drift["moved"]:
            raise MatscanError(_drift_message(state.drift, cfg))
        t0 = time.perf_counter()
        try:
            leds.off()
            if camera.controls_exposure and exposure is None:
                if cfg.exposure_s is not None:
                    exposure, tests = cfg.exposure_s, []
                else:
                    led_frames = [f.rig_light for f in frames if f.rig_light is not None]
                    exposure, tests = choose_exposure(
                        lambda k, e: _test_shot(camera, leds, k, e, cfg.level, out), led_frames, cfg
                    )
                exposure = _used(camera, exposure)
                journal.append({"event": "exposure", "exposure_s": exposure, "tests": tests})
            bar = tqdm(total=len(frames), initial=len(done), desc="capture", unit="photo", disable=not progress)
            darks: dict[float, float] = {}  # the dark frame at longer exposures (_take)
            emptied = False
            for frame in frames:
                if frame.stem in done:
                    continue
                if frame.kind == "back" and state.drift is None and not backlit:  # the LEDs are done
                    state.drift = _drift_check(out, journal, camera, leds, exposure, cfg, first, dark)
                if frame.empty and not emptied:
                    if hasattr(camera, "sample_present"):  # the virtual stage empties itself
                        camera.sample_present = False
                    elif ask is not None:
                        ask("remove the sample from the stage, then press Enter")
                    else:
                        raise MatscanError(
                            "capture: the empty-stage backlight photos need the sample removed; run the same "
                            "command in a terminal to be asked (the photos so far are kept)"
                        )
                    emptied = True
                entry = _take(out, frame, camera, leds, exposure, cfg, dark, reference, darks)
                journal.append({"event": "frame", **entry})
                state.done.append(entry)
                if frame.kind == "dark":
                    dark = _grey(read_image(out / entry["file"]).pixels)
                elif frame.kind in ("led", "chart"):
                    px = _grey(read_image(out / entry["file"]).pixels)
                    if _shows_sample(px, dark, cfg):  # not a frame kept as dark as the dark frame
                        current = (px, frame.light, frame.stem)
                        first = _anchor(first, reference, entry["checks"], current)
                        reference = current
                _write_capture_json(out, rig, state, camera, leds, exposure, cfg, encoding, complete=False)
                bar.update(1)
            if state.drift is None and not backlit:
                state.drift = _drift_check(out, journal, camera, leds, exposure, cfg, first, dark)
            bar.close()
        except BaseException:
            try:  # everything off, but the error that stopped the capture is the one to report
                leds.off()
            except Exception:
                pass
            raise
        leds.off()
        record = _write_capture_json(out, rig, state, camera, leds, exposure, cfg, encoding, complete=True)
        if not events or events[-1].get("event") != "complete":
            journal.append({"event": "complete", "seconds": round(time.perf_counter() - t0, 3)})
    return record


def _open_folder(out: Path, journal: Journal, settings: dict[str, Any]) -> list[dict[str, Any]]:
    """The journal's events for a resumable folder with the same settings; a new folder
    otherwise. Anything else is an error (nothing is ever overwritten)."""
    if out.exists() and not out.is_dir():
        raise input_error(out, "exists and is not a folder; choose another --out")
    if out.is_dir() and any(out.iterdir()):
        events = journal.read()
        if not events or events[0].get("event") != "start":
            raise input_error(out, "exists and is not an interrupted matscan capture; choose another --out")
        differ = _differences(events[0].get("settings"), settings)
        if differ:
            raise input_error(
                out,
                f"holds a capture taken with other settings ({', '.join(differ)}); resume it with the same "
                "command and camera, or choose another --out",
            )
        return events
    check_level(settings["config"]["level"])  # a new capture: at a level the board makes
    out.mkdir(parents=True, exist_ok=True)
    journal.append({"event": "start", "settings": settings})
    return journal.read()


def _replay(out: Path, events: list[dict[str, Any]], frames: list[Frame], journal: Journal) -> Progress:
    """What the journal says is done; files it does not list yet but that are complete
    (renamed to their final name) are verified by reading and journalled."""
    from matscan.imagefile import read_image

    state = Progress()
    by_stem = {f.stem: f for f in frames}
    for e in events:
        if e.get("event") == "exposure":
            state.exposure_s = e["exposure_s"]
        elif e.get("event") == "drift":
            state.drift = e
        elif e.get("event") == "frame":
            if e["stem"] not in by_stem or by_stem[e["stem"]].kind != e["kind"]:
                raise input_error(
                    out / JOURNAL, f"frame {e['stem']!r} is not one this capture takes; this capture cannot be resumed"
                )
            path = out / e["file"]
            if not path.is_file() or _sha256(path.read_bytes()) != e["sha256"]:
                raise input_error(path, "is missing or changed since it was taken; this capture cannot be resumed")
            state.done.append(e)
    done = {d["stem"] for d in state.done}
    for frame in frames:
        if frame.stem in done:
            continue
        found = [p for p in out.glob(frame.stem + ".*") if p.is_file() and not p.name.startswith(".")]
        if not found:
            continue
        path = found[0]
        read_image(path)  # a final name holds a complete, checked photo; make sure it reads
        entry = _entry(frame, path.name, path.read_bytes(), {}, 1)
        journal.append({"event": "frame", **entry, "recovered": True})
        state.done.append(entry)
    state.done.sort(key=lambda d: list(by_stem).index(d["stem"]))
    return state


def _entry(frame: Frame, file: str, data: bytes, checks: dict[str, float], attempts: int) -> dict[str, Any]:
    return {
        "stem": frame.stem,
        "file": file,
        "kind": frame.kind,
        "light": frame.rig_light,
        "empty": frame.empty,
        "sha256": _sha256(data),
        "checks": checks,
        "attempts": attempts,
    }


def _used(camera, exposure: float | None) -> float | None:
    """The exposure a camera takes ``exposure`` as (a tethered camera's nearest shutter
    speed not above it): what the photos were made at, so what capture.json records."""
    if exposure is None or not hasattr(camera, "exposure_for"):
        return exposure
    return camera.exposure_for(exposure)


def _light(leds, illumination: Illumination) -> None:
    if illumination.led is not None:
        leds.led(illumination.led, illumination.level)
    elif illumination.back is not None:
        leds.backlight(illumination.back, illumination.level)
    else:
        leds.off()


def _test_shot(camera, leds, k: int, exposure: float, level: float, out: Path):
    return _shot(camera, leds, Illumination(led=k, level=level), exposure, out)


def _shot(camera, leds, illumination: Illumination, exposure: float, out: Path):
    """One photo that is not a frame of the capture (metering, a check), read and deleted."""
    from matscan.imagefile import read_image

    _light(leds, illumination)
    data = camera.shoot(exposure)
    leds.off()
    tmp = out / f".check_shot{camera.suffix}"
    tmp.write_bytes(data)
    try:
        return read_image(tmp)
    except MatscanError as exc:  # named as the camera's photo, not the temporary copy
        source = getattr(camera, "last_file", None) or f"the {camera.name} camera's check photo"
        raise MatscanError(str(exc).replace(str(tmp), str(source), 1)) from None
    finally:
        tmp.unlink(missing_ok=True)


#: How much longer than the capture's the exposure at which a frame as dark as the dark
#: frame is shot again, to see whether its LED lit (module doc).
LONGER_EXPOSURE = 16.0


def _shows_sample(px: np.ndarray, dark: np.ndarray | None, cfg: AcquireConfig) -> bool:
    """Whether an LED frame rises above the dark frame (the dark check's test), so that
    it can be the reference for the next frame's movement check; a frame kept though as
    dark as the dark frame (its LED showed at a longer exposure) cannot. Decided from the
    photo, so a frame recovered on resume is judged as it was when taken."""
    return dark is None or float(np.percentile(px, 99)) >= float(np.percentile(dark, 99)) + cfg.dark_margin


def longer_exposure(exposure: float | None, cfg: AcquireConfig) -> float | None:
    """The exposure at which a frame as dark as the dark frame is shot again, or None
    where there is none (a camera that sets its own exposure; the longest already)."""
    if exposure is None:
        return None
    longer = min(max(cfg.start_exposure_s, LONGER_EXPOSURE * exposure), EXPOSURE_LIMITS[1])
    return longer if longer > exposure else None


def _lit_at(longer: float, frame: Frame, camera, leds, cfg: AcquireConfig, out: Path, darks=None) -> dict | None:
    """For an LED frame as dark as the dark frame: the LED and the dark frame again at
    the ``longer`` exposure (the dark frame once per exposure, kept in ``darks``). Their
    measurements if the LED shows there (it lit), else None."""
    darks = {} if darks is None else darks
    lit = float(np.percentile(_grey(_shot(camera, leds, frame.light, longer, out).pixels), 99))
    if longer not in darks:
        darks[longer] = float(np.percentile(_grey(_shot(camera, leds, DARK, longer, out).pixels), 99))
    off = darks[longer]
    if lit < off + cfg.dark_margin:
        return None
    return {"lit_exposure_s": longer, "lit_p99": lit, "lit_dark_p99": off}


def _same_light(camera, leds, exposure, reference, dark, out: Path) -> dict[str, float]:
    """For a frame that seems to have moved: the previous LED frame's LED again, compared
    with that frame (the same light, so only movement shifts it)."""
    image, light, _ = reference
    again = _grey(_shot(camera, leds, light, exposure if exposure is not None else 0.0, out).pixels)
    shift, response = sample_shift(image, again, noise_floor(dark))
    return {"same_light_shift_px": shift, "same_light_response": response}


def _anchor(anchor, previous, checks: dict[str, Any], current):
    """The LED frame the end-of-capture check compares (``(image, light, stem,
    textured)``): the earliest whose texture the movement check could follow (the one
    before the first frame that matched its predecessor), else the first that shows the
    sample. ``previous`` and ``current`` are the last reference and the new frame."""
    if anchor is not None and anchor[3]:
        return anchor
    if previous is not None and checks.get("shift_response", 0.0) >= MIN_RESPONSE:
        return (*previous, True)
    return anchor or (*current, False)


def _drift_check(out: Path, journal: Journal, camera, leds, exposure, cfg: AcquireConfig, first, dark):
    """After the last LED frame: the :func:`_anchor` frame, its LED shot again and
    compared with it (the same light), which sees a slow drift or a move that the
    frame-to-frame check missed. Journalled; a sample that moved stops the capture
    (also on every rerun: its photos do not line up). None where there is nothing to
    compare (calibration targets, no frame that shows the sample)."""
    if first is None or cfg.target is not None:
        return None
    image, light, stem, textured = first
    again = _grey(_shot(camera, leds, light, exposure if exposure is not None else 0.0, out).pixels)
    shift, response = sample_shift(image, again, noise_floor(dark))
    # a frame whose texture the movement check followed must match itself under its own
    # light; one that never showed texture enough can only show a move it matches
    lost = textured and response < MIN_RESPONSE
    moved = lost or (response >= MIN_RESPONSE and shift > cfg.max_shift_px)
    event = {"event": "drift", "stem": stem, "shift_px": shift, "response": response, "moved": moved}
    event["textured"] = bool(textured)
    journal.append(event)
    if moved:
        raise MatscanError(_drift_message(event, cfg))
    return event


def _drift_message(event: dict[str, Any], cfg: AcquireConfig) -> str:
    if event["response"] < MIN_RESPONSE:
        seen = (
            f"the sample no longer matches {event['stem']}: its LED shot again after the last LED frame "
            "shows something else (the sample turned, fell or was taken away, or the LED failed)"
        )
    else:
        seen = (
            f"the sample moved {event['shift_px']:.1f} px during the capture (at most {cfg.max_shift_px:g}): "
            f"{event['stem']}'s LED shot again after the last LED frame shows it elsewhere"
        )
    return (
        f"capture: {seen}, so the photos do not line up; take the capture again in a new folder (these photos are kept)"
    )


def _take(
    out: Path, frame: Frame, camera, leds, exposure, cfg: AcquireConfig, dark, reference, darks: dict | None = None
) -> dict:
    """Shoot a frame until it passes its checks, or one more shot shows that its problem
    is the sample's own (module doc); write it under its final name. ``reference`` is the
    last LED frame that shows the sample, its light and name, or None; ``darks`` keeps
    the dark frames' 99th percentiles at longer exposures between frames."""
    from matscan.imagefile import read_image

    problem = None
    asked: set[str] = set()  # the problems whose extra shot was taken (once per frame)
    found: dict[str, tuple[str, str]] = {}  # what those shots showed, for the last word
    for attempt in range(1, cfg.retakes + 2):
        _light(leds, frame.light)
        data = camera.shoot(exposure if exposure is not None else 0.0)
        leds.off()
        final = out / f"{frame.stem}{camera.suffix}"  # a folder camera's suffix is its last file's
        tmp = out / f".{frame.stem}.partial{camera.suffix}"
        if final.exists():  # never overwrite a photo
            raise input_error(final, "exists but the journal does not list it; this capture cannot be resumed")
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        try:
            image = read_image(tmp)
        except MatscanError as exc:  # named as the camera's photo, not the temporary copy
            tmp.unlink(missing_ok=True)
            source = getattr(camera, "last_file", None) or f"the {camera.name} camera's {frame.stem} photo"
            raise MatscanError(str(exc).replace(str(tmp), str(source), 1)) from None
        checks, problem = frame_checks(frame, image, dark, reference and reference[0], cfg)
        if problem is not None and problem[0] == "dark" and "dark" not in asked:
            asked.add("dark")
            longer = longer_exposure(exposure, cfg)
            shown = None if longer is None else _lit_at(longer, frame, camera, leds, cfg, out, darks)
            if shown is not None:  # no movement check: a frame this dark shows little of the texture
                checks, problem = frame_checks(frame, image, dark, None, cfg, lit=True)
                checks.update(shown)
            elif longer is None and exposure is not None:  # already the longest exposure
                found["dark"] = ("dark", f"it is as dark as the dark frame at {exposure:g} s: did the LED light?")
            elif longer is None:
                found["dark"] = (
                    "dark",
                    f"{problem[1]} (or the sample sends almost none of its light to the camera: "
                    "if the LED lit, start a new capture with a longer exposure)",
                )
            else:
                found["dark"] = (
                    "dark",
                    f"it is as dark as the dark frame, at {longer:g} s as well: did the LED light?",
                )
        elif problem is not None and problem[0] == "moved" and "moved" not in asked:
            asked.add("moved")
            same = _same_light(camera, leds, exposure, reference, dark, out)
            if same["same_light_response"] >= MIN_RESPONSE and same["same_light_shift_px"] <= cfg.max_shift_px:
                checks.update(same)  # the sample is where it was: the light moved, not the sample
                problem = None
            else:  # it moved, or no longer matches at all (turned, fell, taken away)
                shown = "shows it moved" if same["same_light_response"] >= MIN_RESPONSE else "no longer matches it"
                found["moved"] = (
                    "moved",
                    f"the sample moved {checks['shift_px']:.1f} px since the last LED frame (at most "
                    f"{cfg.max_shift_px:g}), and that frame's LED again {shown}; the photos so far "
                    "show it where it was: start a new capture (or put it back exactly and run again)",
                )
        if problem is None:
            os.replace(tmp, final)
            _sync_dir(out)
            return _entry(frame, final.name, data, checks, attempt)
        tmp.unlink(missing_ok=True)
    problem = found.get(problem[0], problem)
    raise MatscanError(
        f"capture: {frame.stem}: {problem[1]}; tried {cfg.retakes + 1} times, stopping (run again to resume)"
    )


def _sync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_capture_json(out, rig, state, camera, leds, exposure, cfg, encoding, complete: bool) -> dict[str, Any]:
    acquisition = {
        "camera": camera.name,
        "leds": leds.name,
        "exposure_s": exposure,
        "led_level": cfg.level,
        "dark": next((d["file"] for d in state.done if d["kind"] == "dark"), None),
        "target": cfg.target,
        "frames": len(state.done),
        "retakes": sum(d.get("attempts", 1) - 1 for d in state.done),  # so a resumed capture counts the same
        "complete": complete,
    }
    if state.drift is not None:  # the sample's movement over the capture (the end-of-capture check)
        follows = state.drift["response"] >= MIN_RESPONSE  # below, the shift is the noise's
        acquisition["drift_px"] = round(state.drift["shift_px"], 3) if follows else None
        acquisition["drift_response"] = round(state.drift["response"], 3)
    chart = next((d["file"] for d in state.done if d["kind"] == "chart"), None)
    if chart is not None:
        acquisition["chart"] = chart
    doc = capture_json(rig, state.done, acquisition, encoding)
    write_text(out / "capture.json", dumps(doc, str(out / "capture.json")))
    return acquisition


def target_maps(target: str, size: int) -> MapSet:
    """What a virtual camera sees on the stage for a calibration target, size² over the
    field: an 18% grey card (Lambertian), a ColorChecker Classic (its 24 reference colours on
    a dark body), or a chrome sphere (F0 0.9, roughness 0.1, a third of the field across)
    on a grey card."""
    import torch

    from matscan.calibrate import colorchecker_linear

    h = w = size
    flat = torch.zeros(3, h, w)
    flat[2] = 1
    diffuse = torch.full((3, h, w), 0.18)
    specular = torch.zeros(3, h, w)  # Lambertian, as calibrate models a grey card
    roughness = torch.full((1, h, w), 0.9)
    normal = flat.clone()
    if target == "chart":
        diffuse = torch.full((3, h, w), 0.03)
        ref = colorchecker_linear().clamp(0, 1)
        cell = w / 8
        for i in range(24):
            r, c = divmod(i, 6)
            y0, x0 = int(h / 2 - 2 * cell + r * cell + 0.1 * cell), int(cell + c * cell + 0.1 * cell)
            diffuse[:, y0 : y0 + int(0.8 * cell), x0 : x0 + int(0.8 * cell)] = ref[i].view(3, 1, 1)
    elif target == "sphere":
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5 - h / 2, torch.arange(w) + 0.5 - w / 2, indexing="ij")
        radius = w / 6
        x, y = xs / radius, -ys / radius
        inside = x * x + y * y < 1
        z = (1 - x * x - y * y).clamp_min(0).sqrt()
        normal = torch.where(inside, torch.stack([x, y, z]), flat)
        diffuse = torch.where(inside, torch.zeros_like(diffuse), diffuse)
        specular = torch.where(inside, torch.full_like(specular, 0.9), specular)
        roughness = torch.where(inside, torch.full_like(roughness, 0.1), roughness)
    return MapSet(diffuse=diffuse, specular=specular, roughness=roughness, normal=normal)
