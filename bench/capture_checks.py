"""How often ``matscan capture``'s frame checks stop a good capture, and how often they
catch a bad one, with the virtual camera (read noise 0.002, 16-bit sRGB) and the
virtual LED board, at the default settings (metered exposure, 2 retakes).

The materials: every procedural family once (seed 1) and the five artist-style sets,
SIZE² over dome24's field. Each is captured four times:

* good: nothing wrong; any stop is a false alarm;
* dead LED: LED 12 never lights; the capture must stop at led_12 saying so;
* knocked: the sample shifts by 3 px (x) just before LED 12's photo and stays there;
  the capture must stop saying it moved: at led_12, or after the last LED frame.
* drift: the sample creeps 0.15 px with every photo (about 4 px over the capture);
  the capture must stop saying it moved (anywhere; counted only where the good
  capture did not stop).

Printed per material: what each capture did (``ok``, or the frame and problem it
stopped on); then the counts, and how many photos the camera took for the good captures
(the metering's test shots and the checks' extra shots included; 25 are kept). Run by hand:

    .venv/bin/python bench/capture_checks.py [SIZE]   (default 128)
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import torch

from matscan.capture.acquire import AcquireConfig, acquire
from matscan.errors import MatscanError
from matscan.hardware.cameras import VirtualCamera
from matscan.hardware.leds import VirtualLeds
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.procedural import FAMILIES, generate
from matscan.rig import builtin_rig

RIG = builtin_rig("dome24")
FAULT_LED = 12


class Counted(VirtualCamera):
    """Counts the metering's test shots: those before the dark frame."""

    metering = None

    def radiance(self, state):
        if self.metering is None and state.led is None and state.back is None:
            self.metering = self.shots - 1
        return super().radiance(state)


class DeadLed(VirtualCamera):
    def radiance(self, state):
        if state.led == FAULT_LED:
            return torch.zeros(3, *self.maps.size)
        return super().radiance(state)


class Knocked(VirtualCamera):
    """The sample shifts 3 px when LED 12 is first lit after the dark frame (the
    metering's test shots come before it), and stays shifted."""

    dark_taken = knocked = False

    def radiance(self, state):
        if state.led is None and state.back is None:
            self.dark_taken = True
        self.knocked = self.knocked or (self.dark_taken and state.led == FAULT_LED)
        img = super().radiance(state)
        return torch.roll(img, 3, dims=2) if self.knocked else img


class Drifting(VirtualCamera):
    """The sample creeps 0.15 px (x) with every photo after the dark frame: 0.15 px from
    one frame to the next, far below what the frame-to-frame check sees, and about 4 px
    over the capture."""

    shots_after_dark = -1

    def radiance(self, state):
        if state.led is None and state.back is None and self.shots_after_dark < 0:
            self.shots_after_dark = 0
        img = super().radiance(state)
        if self.shots_after_dark < 0:
            return img
        self.shots_after_dark += 1
        shift = 0.15 * self.shots_after_dark
        freq = torch.fft.fftfreq(img.shape[-1])
        ramp = torch.exp(-2j * torch.pi * freq * shift)
        return torch.fft.ifft(torch.fft.fft(img, dim=-1) * ramp, dim=-1).real.clamp_min(0)


def outcome(folder: Path, camera_type, maps) -> tuple[str, int, int]:
    """What the capture did, how many photos the camera took, and how many of them were
    the metering's."""
    leds = VirtualLeds()
    camera = camera_type(maps, RIG, leds)
    try:
        acquire(folder, RIG, camera, leds, AcquireConfig())
    except MatscanError as exc:
        return str(exc).removeprefix("capture: ").split(";")[0], camera.shots, getattr(camera, "metering", 0)
    return "ok", camera.shots, getattr(camera, "metering", 0)


def main() -> None:
    from _usage import usage  # bench/ is the script's folder, on sys.path

    usage(__doc__)
    size = int(sys.argv[1]) if len(sys.argv) > 1 else 128
    materials = [(f, generate(f, size, seed=1)) for f in FAMILIES]
    materials += [(f"artist:{n}", artist_material(n, size)) for n in ARTIST_NAMES]
    counts = {"false stops": 0, "dead LED caught": 0, "knock caught at led_12": 0}
    counts |= {"knock caught after the last LED frame": 0, "drift caught": 0}
    counts |= {"photos taken in the good captures": 0, "of which the metering's": 0}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, maps) in enumerate(materials):
            good, shots, metering = outcome(Path(tmp) / f"{i}-good", Counted, maps)
            dead = outcome(Path(tmp) / f"{i}-dead", DeadLed, maps)[0]
            knock = outcome(Path(tmp) / f"{i}-knock", Knocked, maps)[0]
            drift = outcome(Path(tmp) / f"{i}-drift", Drifting, maps)[0]
            counts["drift caught"] += good == "ok" and ("moved" in drift or "no longer matches" in drift)
            counts["photos taken in the good captures"] += shots
            counts["of which the metering's"] += metering
            counts["false stops"] += good != "ok"
            counts["dead LED caught"] += dead.startswith(f"led_{FAULT_LED:02d}: it is as dark")
            counts["knock caught at led_12"] += knock.startswith(f"led_{FAULT_LED:02d}: the sample moved")
            counts["knock caught after the last LED frame"] += knock.startswith(("the sample moved", "the sample no"))
            print(
                f"{name:26s} good: {good[:40]:40s} dead: {dead[:30]:30s} knocked: {knock[:40]:40s} drift: {drift[:40]}",
                flush=True,
            )
    n = len(materials)
    print(f"\n{n} materials at {size}², {time.perf_counter() - t0:.0f} s")
    for key, value in counts.items():
        if "photos" in key:
            print(f"{key}: {value} ({value / n:.1f} each; 25 frames kept)")
        elif "metering" in key:
            print(f"{key}: {value} ({value / n:.1f} each)")
        else:
            print(f"{key}: {value}/{n}")


if __name__ == "__main__":
    main()
