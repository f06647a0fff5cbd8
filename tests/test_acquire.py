"""``matscan capture`` end to end: the virtual camera and the simulated LED board (the
firmware's logic behind a pseudo-terminal, through pyserial), frame checks, faults
injected, and resuming byte for byte."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from matscan.capture import load_capture
from matscan.capture.acquire import JOURNAL, AcquireConfig, acquire, target_maps
from matscan.errors import MatscanError
from matscan.hardware.cameras import FolderCamera, VirtualCamera
from matscan.hardware.leds import VirtualLeds, open_leds
from matscan.mapset import MapSet, read_mapset
from matscan.rig import builtin_rig

pytest.importorskip("serial")

RIG = builtin_rig("dome24")
SIX = AcquireConfig(lights=(0, 4, 8, 12, 16, 20), exposure_s=0.01, max_saturated=0.3)


def small_sample(size: int = 64) -> MapSet:
    maps = read_mapset("@sample")
    present = {
        k: torch.nn.functional.interpolate(v[None], size=(size, size), mode="area")[0]
        for k, v in maps.present().items()
    }
    present["normal"] = present["normal"] / present["normal"].norm(dim=0, keepdim=True)
    return MapSet(**present)


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name != JOURNAL}


def test_a_whole_capture_reconstructs_to_the_virtual_sample(tmp_path):
    """Dark frame, 24 LEDs, backlight with and without the sample, through the simulated
    board over a pseudo-terminal; the capture loads and reconstructs to the sample."""
    from matscan.evaluate import map_scores
    from matscan.reconstruct import ReconstructConfig
    from matscan.reconstruct.job import reconstruct

    leds, board = open_leds("simulated")
    maps = small_sample()
    camera = VirtualCamera(maps, RIG, leds)
    cfg = AcquireConfig(backlight=True, exposure_s=0.01, max_saturated=0.3)
    try:
        record = acquire(tmp_path / "cap", RIG, camera, leds, cfg)
    finally:
        leds.close()
        board.close()
    assert record["frames"] == 29 and record["complete"] and record["exposure_s"] == 0.01
    assert board.lit() == []
    events = [
        line for line in (tmp_path / "cap" / JOURNAL).read_text().splitlines() if '"drift"' in line or "back_" in line
    ]
    assert '"drift"' in events[0] and record["drift_px"] < 0.5  # checked while the sample is still on the stage
    cap = load_capture(tmp_path / "cap")
    assert len(cap.files) == 24 and sorted(cap.backlight) == ["blue", "blue_empty", "green", "green_empty"]
    assert cap.light_indices == tuple(range(24))
    assert "warnings" not in cap.meta  # every key capture writes in acquisition is one matscan knows
    rec = reconstruct(tmp_path / "cap", tmp_path / "maps", ReconstructConfig())
    scores = map_scores(read_mapset(tmp_path / "maps"), maps)
    assert scores["rmse_diffuse"] < 0.02 and scores["normal_degrees"] < 2.0
    assert rec["rerender_rmse"] < 0.01


def test_exposure_is_chosen_so_no_led_saturates(tmp_path):
    leds = VirtualLeds()
    camera = VirtualCamera(small_sample(), RIG, leds)
    cfg = AcquireConfig(lights=(0, 8, 16), start_exposure_s=0.08, max_saturated=0.001)
    record = acquire(tmp_path / "cap", RIG, camera, leds, cfg)
    assert record["exposure_s"] < 0.08
    from matscan.imagefile import read_image

    for k in (0, 8, 16):
        stored = read_image(tmp_path / "cap" / f"led_{k:02d}.png").stored
        assert (stored >= 65535).any(axis=2).mean() <= 0.001


def test_resume_after_a_camera_disconnect_is_byte_for_byte(tmp_path):
    leds = VirtualLeds()
    acquire(tmp_path / "whole", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    broken = VirtualCamera(small_sample(), RIG, leds, fail_after=4)
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cut", RIG, broken, leds, SIX)
    assert leds.state.led is None and leds.state.back is None  # commanded off
    partial = load_capture(tmp_path / "cut")  # a valid capture of the frames so far
    assert len(partial.files) == 3
    acquire(tmp_path / "cut", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    assert files(tmp_path / "cut") == files(tmp_path / "whole")


def test_resume_after_sigkill_is_byte_for_byte(tmp_path):
    """The command killed (SIGKILL) mid-capture, then run again: the same capture."""
    cmd = [
        sys.executable,
        "-m",
        "matscan.cli",
        "capture",
        "--camera",
        "virtual:@sample",
        "--leds",
        "simulated",
        "--exposure",
        "0.01",
        "--max-saturated",
        "0.3",
        "--out",
    ]
    whole = subprocess.run([*cmd, str(tmp_path / "whole")], capture_output=True, text=True, timeout=300)
    assert whole.returncode == 0, whole.stderr
    proc = subprocess.Popen([*cmd, str(tmp_path / "cut")], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (tmp_path / "cut" / "led_06.png").exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert not (tmp_path / "cut" / "led_23.png").exists()
    again = subprocess.run([*cmd, str(tmp_path / "cut")], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert files(tmp_path / "cut") == files(tmp_path / "whole")
    assert not [p for p in (tmp_path / "cut").iterdir() if "partial" in p.name or p.name.startswith(".")]


def test_sigint_stops_with_the_leds_off_and_says_how_to_resume(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "matscan.cli",
        "capture",
        "--camera",
        "virtual:@sample",
        "--leds",
        "simulated",
        "--exposure",
        "0.01",
        "--max-saturated",
        "0.3",
        "--out",
        str(tmp_path / "cap"),
    ]
    # The virtual capture takes a photo every ~40 ms, so on a loaded machine the signal
    # can land after the last one (exit 0): then it is tried again in a fresh folder.
    for _attempt in range(3):
        shutil.rmtree(tmp_path / "cap", ignore_errors=True)
        # SIGINT back to its default in the child: a suite started in the background
        # (`make test &`) runs with SIGINT ignored, and Python then never raises
        # KeyboardInterrupt
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        deadline = time.monotonic() + 120
        while not (tmp_path / "cap" / "led_01.png").exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        if not (proc.returncode == 0 and (tmp_path / "cap" / "led_23.png").exists()):
            break
    assert proc.returncode == 130
    assert "run the same command to resume" in err and "Traceback" not in err
    assert load_capture(tmp_path / "cap").files  # what was taken is a capture
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    whole = [*cmd[:-1], str(tmp_path / "whole")]
    assert subprocess.run(whole, capture_output=True, timeout=300).returncode == 0
    assert files(tmp_path / "cap") == files(tmp_path / "whole")


def test_a_controller_that_stops_answering_stops_the_capture(tmp_path):
    leds, board = open_leds("simulated", timeout=0.5)

    class Hanging(VirtualCamera):
        def shoot(self, exposure_s):
            if self.shots == 3:
                board.hang()
            return super().shoot(exposure_s)

    try:
        with pytest.raises(MatscanError, match="no reply .* the LEDs were commanded off"):
            acquire(tmp_path / "cap", RIG, Hanging(small_sample(), RIG, leds), leds, SIX)
        time.sleep(0.2)
        assert board.lit() == []
    finally:
        leds.port.close()
        board.close()


def test_a_frame_that_never_arrives(tmp_path):
    incoming = tmp_path / "incoming"
    incoming.mkdir()
    leds = VirtualLeds()
    camera = FolderCamera(incoming, timeout=0.5)
    with pytest.raises(MatscanError, match=r"no new photo arrived within 0.5 s"):
        acquire(tmp_path / "cap", RIG, camera, leds, SIX)


def test_a_sample_moved_while_a_capture_was_interrupted_is_caught_on_resume(tmp_path):
    """The resumed capture's first frame is checked against the last frame taken before
    the interruption, and that frame's LED (from the journal) is the one shot again."""
    leds = VirtualLeds()
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=4), leds, SIX)

    class Moved(VirtualCamera):  # put back 4 px off
        lit = []

        def radiance(self, state):
            self.lit.append(state.led)
            return torch.roll(super().radiance(state), 4, dims=2)

    camera = Moved(small_sample(), RIG, leds)
    with pytest.raises(MatscanError, match=r"led_12: the sample moved [3-5]\.\d px .* that frame's LED again shows"):
        acquire(tmp_path / "cap", RIG, camera, leds, SIX)
    assert camera.lit[:2] == [12, 8]  # the new frame, then led_08's LED again


def test_folder_camera_takes_each_new_file_and_touches_nothing(tmp_path):
    """A camera's own software saving into a folder: a thread plays that software,
    writing the virtual camera's frame for whatever is lit."""
    incoming = tmp_path / "incoming"
    incoming.mkdir()
    (incoming / "old.png").write_bytes(b"not ours")  # already there: never taken, never touched
    leds = VirtualLeds()
    source = VirtualCamera(small_sample(), RIG, leds)
    stop = threading.Event()
    written = []

    class Software(FolderCamera):
        def shoot(self, exposure_s):
            def save():
                time.sleep(0.05)
                path = incoming / f"IMG_{len(written):04d}.png"
                path.write_bytes(source.shoot(0.01))
                written.append(path)

            threading.Thread(target=save).start()
            return super().shoot(exposure_s)

    acquire(tmp_path / "cap", RIG, Software(incoming, timeout=10), leds, SIX)
    stop.set()
    assert (incoming / "old.png").read_bytes() == b"not ours"
    assert all(p.exists() for p in written) and len(written) == 8  # 7 frames, the end's movement check
    assert (tmp_path / "cap" / "led_00.png").read_bytes() == written[1].read_bytes()


def test_a_folder_camera_saving_jpeg_gives_jpeg_frames(tmp_path):
    """The frames take the suffix of the files the camera's software saves, the first
    (the dark frame) too."""
    import cv2

    from matscan.imagefile import read_image

    incoming = tmp_path / "incoming"
    incoming.mkdir()
    leds = VirtualLeds()
    source = VirtualCamera(small_sample(), RIG, leds)

    class Software(FolderCamera):
        def shoot(self, exposure_s):
            def save():
                time.sleep(0.05)
                png = tmp_path / "frame.png"
                png.write_bytes(source.shoot(0.01))
                rgb = (read_image(png).pixels * 255).round().astype(np.uint8)
                cv2.imwrite(str(incoming / f"IMG_{len(list(incoming.iterdir())):04d}.jpg"), rgb[..., ::-1])

            threading.Thread(target=save).start()
            return super().shoot(exposure_s)

    acquire(tmp_path / "cap", RIG, Software(incoming, timeout=10), leds, SIX)
    names = sorted(p.name for p in (tmp_path / "cap").iterdir() if p.suffix in (".png", ".jpg"))
    assert names == ["dark.jpg"] + [f"led_{k:02d}.jpg" for k in SIX.lights]
    assert (tmp_path / "cap" / "dark.jpg").read_bytes()[:2] == b"\xff\xd8"  # JPEG bytes, named so
    assert len(load_capture(tmp_path / "cap").files) == 6


def test_checks_dark_and_moved_frames(tmp_path):
    leds = VirtualLeds()

    class DeadLed(VirtualCamera):
        def radiance(self, state):
            return torch.zeros(3, *self.maps.size) if state.led == 8 else super().radiance(state)

    # dark at 0.01 s and at 16 times that: the LED did not light
    with pytest.raises(MatscanError, match=r"led_08: it is as dark as the dark frame, at 0.16 s as well: did the LED"):
        acquire(tmp_path / "a", RIG, DeadLed(small_sample(), RIG, leds), leds, SIX)
    assert (tmp_path / "a" / "led_04.png").exists() and not (tmp_path / "a" / "led_08.png").exists()

    class Knocked(VirtualCamera):
        """Knocked 5 px just before LED 12's photo; it stays there."""

        knocked = False

        def radiance(self, state):
            self.knocked = self.knocked or state.led == 12
            img = super().radiance(state)
            return torch.roll(img, 5, dims=2) if self.knocked else img

    camera = Knocked(small_sample(), RIG, leds)
    with pytest.raises(MatscanError, match=r"led_12: the sample moved [4-6]\.\d px .* that frame's LED again shows"):
        acquire(tmp_path / "b", RIG, camera, leds, SIX)
    assert camera.shots == 1 + 3 + 1 + 1 + 2  # dark; LEDs 0, 4, 8; LED 12; LED 8 again; LED 12 retaken twice

    with pytest.raises(MatscanError, match=r"led_00: .* of its pixels are saturated"):
        acquire(
            tmp_path / "c",
            RIG,
            VirtualCamera(small_sample(), RIG, leds),
            leds,
            AcquireConfig(lights=(0,), exposure_s=1.0, max_saturated=0.01, retakes=0),
        )


def _journal_frames(folder: Path) -> dict[str, dict]:
    import json

    events = [json.loads(line) for line in (folder / JOURNAL).read_text().splitlines()]
    return {e["stem"]: e for e in events if e["event"] == "frame"}


def test_a_frame_dark_only_at_the_metered_exposure_is_kept(tmp_path):
    """A worn metal: the top LEDs' highlights set a short exposure, at which the grazing
    LEDs' photos are as dark as the dark frame though those LEDs lit. Such a frame is
    kept (the LED shows at a longer exposure); before, the capture stopped there."""
    from matscan.imagefile import read_image
    from matscan.materials.artist import artist_material

    maps = artist_material("worn-metal", 32)
    leds = VirtualLeds()
    record = acquire(tmp_path / "cap", RIG, VirtualCamera(maps, RIG, leds), leds, AcquireConfig())
    assert record["complete"] and len(load_capture(tmp_path / "cap").files) == 24

    def p99(image):
        return float(np.percentile(image.pixels[..., :3].mean(axis=2), 99))

    dark = p99(read_image(tmp_path / "cap" / "dark.png"))
    led0 = p99(read_image(tmp_path / "cap" / "led_00.png"))
    assert led0 < dark + 0.01  # the premise: as dark as the dark frame at the metered exposure ...
    leds.led(0)
    lit = VirtualCamera(maps, RIG, leds).shoot(0.01)  # ... while LED 0 shows at the metering's start
    (tmp_path / "lit.png").write_bytes(lit)
    assert p99(read_image(tmp_path / "lit.png")) > dark + 0.05
    frames = _journal_frames(tmp_path / "cap")
    assert frames["led_00"]["checks"]["lit_exposure_s"] == 0.01
    # a frame this dark is no reference for movement: the first LED frame that shows the
    # sample is compared with none
    shown = [f for stem, f in frames.items() if stem.startswith("led_") and "lit_p99" not in f["checks"]]
    assert "shift_px" not in shown[0]["checks"] and all("shift_px" in f["checks"] for f in shown[1:])


def test_an_apparent_move_that_the_same_light_does_not_show_is_kept(tmp_path):
    """A metal mesh: its relief and highlights change so much between LEDs that phase
    correlation finds shifts of several pixels between consecutive frames of a sample
    that never moves. The previous frame's LED shot again shows it still, so the
    capture goes on; before, it stopped. A real 3 px knock is still caught."""
    from matscan.materials.procedural import generate

    maps = generate("mesh", 32, seed=1)
    leds = VirtualLeds()
    record = acquire(tmp_path / "cap", RIG, VirtualCamera(maps, RIG, leds), leds, AcquireConfig())
    assert record["complete"] and len(load_capture(tmp_path / "cap").files) == 24
    overruled = [
        c for c in (f["checks"] for f in _journal_frames(tmp_path / "cap").values()) if "same_light_shift_px" in c
    ]
    assert overruled and all(c["shift_px"] > 1.5 and c["shift_response"] >= 0.15 for c in overruled)
    assert all(c["same_light_shift_px"] <= 1.5 for c in overruled)

    class Knocked(VirtualCamera):
        dark_taken = knocked = False

        def radiance(self, state):
            self.dark_taken = self.dark_taken or (state.led is None and state.back is None)
            self.knocked = self.knocked or (self.dark_taken and state.led == 12)
            img = super().radiance(state)
            return torch.roll(img, 3, dims=2) if self.knocked else img

    with pytest.raises(MatscanError, match=r"led_12: the sample moved [2-4]\.\d px .* that frame's LED again shows"):
        acquire(tmp_path / "knocked", RIG, Knocked(maps, RIG, leds), leds, AcquireConfig())


def test_a_slow_drift_is_caught_after_the_last_led_frame(tmp_path):
    """The sample creeps 0.5 px with every photo: too little from one frame to the next
    for the frame-to-frame check (at most 1.5 px), 3.5 px from the first LED frame to
    the end (4 with the check shot a frame's apparent move takes). After the last LED
    frame, the first frame's LED shot again shows it; the capture stops, keeps its
    photos, and a rerun stops again without shooting. A still sample passes, with its
    drift recorded."""
    import json

    class Drifting(VirtualCamera):
        shift = -1.0

        def radiance(self, state):
            if state.led is None and state.back is None:
                self.shift = max(self.shift, 0.0)
            img = super().radiance(state)
            if self.shift < 0:  # the metering's test shots: the sample has not moved yet
                return img
            self.shift += 0.5
            ramp = torch.exp(-2j * torch.pi * torch.fft.fftfreq(img.shape[-1]) * self.shift)
            return torch.fft.ifft(torch.fft.fft(img, dim=-1) * ramp, dim=-1).real.clamp_min(0)

    leds = VirtualLeds()
    camera = Drifting(small_sample(), RIG, leds)
    with pytest.raises(MatscanError, match=r"the sample moved [3-4]\.\d px during the capture .* led_00's LED"):
        acquire(tmp_path / "cap", RIG, camera, leds, SIX)
    assert len(load_capture(tmp_path / "cap").files) == 6  # every frame passed its checks, and is kept
    assert json.loads((tmp_path / "cap" / "capture.json").read_text())["acquisition"]["complete"] is False
    again = Drifting(small_sample(), RIG, leds)
    with pytest.raises(MatscanError, match=r"during the capture"):
        acquire(tmp_path / "cap", RIG, again, leds, SIX)
    assert again.shots == 0

    record = acquire(tmp_path / "still", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    assert record["complete"] and record["drift_px"] < 0.3


def test_the_end_of_capture_check_on_resume_and_a_sample_taken_away(tmp_path):
    """Killed at the end-of-capture shot: the rerun takes it, once. A capture completed
    before the check existed (no drift line) is left as it is. A sample taken away before
    the end-of-capture shot no longer matches its frame: the capture stops."""
    import json

    leds = VirtualLeds()
    with pytest.raises(MatscanError, match="disconnected"):  # dark + 6 LED frames, then the check's shot
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=7), leds, SIX)
    assert '"drift"' not in (tmp_path / "cap" / JOURNAL).read_text()
    camera = VirtualCamera(small_sample(), RIG, leds)
    record = acquire(tmp_path / "cap", RIG, camera, leds, SIX)
    assert camera.shots == 1 and record["complete"]
    assert (tmp_path / "cap" / JOURNAL).read_text().count('"drift"') == 1

    journal = tmp_path / "cap" / JOURNAL  # as a capture completed before the check existed
    journal.write_text("".join(line + "\n" for line in journal.read_text().splitlines() if '"drift"' not in line))
    before = files(tmp_path / "cap")
    camera = VirtualCamera(small_sample(), RIG, leds)
    record = acquire(tmp_path / "cap", RIG, camera, leds, SIX)
    assert camera.shots == 0 and "drift_px" not in record
    assert {k: v for k, v in files(tmp_path / "cap").items() if k != "capture.json"} == {
        k: v for k, v in before.items() if k != "capture.json"
    }

    class TakenAway(VirtualCamera):  # off the stage after the last LED frame
        def radiance(self, state):
            self.sample_present = self.shots <= 7
            return super().radiance(state)

    with pytest.raises(MatscanError, match=r"the sample no longer matches led_00: its LED shot again"):
        acquire(tmp_path / "away", RIG, TakenAway(small_sample(), RIG, leds), leds, SIX)
    drift = [json.loads(line) for line in (tmp_path / "away" / JOURNAL).read_text().splitlines() if '"drift"' in line]
    assert drift[0]["moved"] and drift[0]["textured"] and drift[0]["response"] < 0.15


def test_metering_takes_the_longest_exposure_at_which_every_led_passes():
    """LED k saturates min(1, exposure × rate_k) of its pixels. Closed form: the
    brightest (rate 40/s) allows at most 0.001 / 40 = 25 µs, so 10 ms halved 9 times
    (19.5 µs). Each shot either passes an LED (once each) or fails an exposure (once
    each), so at most 6 + 10 shots."""
    from matscan.capture.acquire import choose_exposure
    from matscan.imagefile import ImageData

    rates = [0.05, 3.0, 0.2, 40.0, 1.0, 0.0]
    shots = []

    def shoot(k, exposure):
        shots.append((k, exposure))
        stored = np.zeros((100, 100, 3), np.uint8)
        stored.reshape(-1, 3)[: round(min(1.0, exposure * rates[k]) * 10000)] = 255
        return ImageData(stored, "int", 8)

    exposure, tests = choose_exposure(shoot, range(6), AcquireConfig(start_exposure_s=0.01, max_saturated=0.001))
    assert exposure == 0.01 / 2**9
    assert [t["exposure_s"] for t in tests] == [0.01 / 2**n for n in range(10)]
    assert len(shots) <= 6 + 10
    for k, rate in enumerate(rates):  # every LED was seen within the limit at this exposure or a longer one
        assert any(kk == k and e >= exposure and e * rate <= 0.001 for kk, e in shots)


def test_folders_that_are_not_this_capture_are_refused(tmp_path):
    leds = VirtualLeds()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "photo.png").write_bytes(b"x")
    with pytest.raises(MatscanError, match="exists and is not an interrupted matscan capture"):
        acquire(tmp_path / "other", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    assert (tmp_path / "other" / "photo.png").read_bytes() == b"x"
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    before = files(tmp_path / "cap")
    with pytest.raises(MatscanError, match="holds a capture taken with other settings"):
        acquire(
            tmp_path / "cap",
            RIG,
            VirtualCamera(small_sample(), RIG, leds),
            leds,
            AcquireConfig(lights=(0, 1), exposure_s=0.01, max_saturated=0.3),
        )
    # the same settings again: already complete, nothing retaken or rewritten
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    assert files(tmp_path / "cap") == before


@pytest.mark.parametrize(
    "line, words",
    [
        ("[1, 2]", "line 2: is not a journal event"),
        ('{"event": "frame"}', "line 2: this frame event has no usable 'stem'"),
        (
            '{"event": "frame", "stem": "led_00", "file": "../x.png", "sha256": "0", "kind": "led", "light": 0, '
            '"empty": false}',
            "'../x.png' is not a file name",
        ),
        (  # a frame event without its kind (it was a KeyError in the resume)
            '{"event": "frame", "stem": "led_00", "file": "led_00.png", "sha256": "0", "light": 0, "empty": false}',
            "line 2: this frame event has no usable 'kind'",
        ),
        (
            '{"event": "frame", "stem": "led_99", "file": "led_99.png", "sha256": "0", "kind": "led", "light": 99, '
            '"empty": false}',
            "frame 'led_99' is not one this capture takes",
        ),
        ('{"event": "exposure", "exposure_s": "fast"}', "this exposure event has no usable 'exposure_s'"),
        (
            '{"event": "drift", "stem": "led_00", "shift_px": 0.1, "response": 0.9, "moved": 1}',
            "this drift event has no usable 'moved'",
        ),
        (
            '{"event": "drift", "stem": "led_00", "shift_px": true, "response": 0.9, "moved": false}',
            "this drift event has no usable 'shift_px'",
        ),
    ],
)
def test_a_damaged_journal_is_one_line_naming_it(tmp_path, line, words):
    leds = VirtualLeds()
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    journal = tmp_path / "cap" / "capture.journal"
    first = journal.read_text().splitlines()[0]
    journal.write_text(first + "\n" + line + "\n")
    before = files(tmp_path / "cap")
    with pytest.raises(MatscanError, match=re.escape(f"{journal}: {words}") if "line 2" in words else re.escape(words)):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    assert files(tmp_path / "cap") == before


def test_calibration_targets(tmp_path):
    """Targets on the virtual stage: a grey card capture that calibrate reads, a chart
    photo it finds the chart in, and sphere photos whose highlights give the LEDs'
    directions."""
    from matscan.calibrate import calibrate
    from matscan.capture.sphere import directions_from_sphere

    leds = VirtualLeds()
    grey = VirtualCamera(target_maps("grey", 128), RIG, leds)
    acquire(tmp_path / "grey", RIG, grey, leds, AcquireConfig(target="grey", exposure_s=0.01, max_saturated=0.3))
    assert grey.shots == 25  # the frames only: a target has no texture to follow, so no movement shots
    assert '"drift"' not in (tmp_path / "grey" / JOURNAL).read_text()
    cal = calibrate(tmp_path / "cal.json", grey=tmp_path / "grey")
    assert len(cal.light_scales) == 24
    assert all(abs(c - 1) < 0.05 for s in cal.light_scales.values() for c in s)
    chart = VirtualCamera(target_maps("chart", 256), RIG, leds)
    acquire(tmp_path / "chart", RIG, chart, leds, AcquireConfig(target="chart", exposure_s=0.01, max_saturated=0.3))
    chart_cal = calibrate(tmp_path / "chart.json", chart=tmp_path / "chart" / "chart.png")  # found, not given
    assert chart_cal.warnings == () and chart_cal.chart_error < 0.05
    sphere = VirtualCamera(target_maps("sphere", 192), RIG, leds)
    acquire(
        tmp_path / "sphere",
        RIG,
        sphere,
        leds,
        AcquireConfig(target="sphere", lights=(0, 9, 18), exposure_s=0.01, max_saturated=0.3),
    )
    found = directions_from_sphere(
        [tmp_path / "sphere" / f"led_{k:02d}.png" for k in (0, 9, 18)], (96 - 0.5, 96 - 0.5), 192 / 6
    )
    for k, d in zip((0, 9, 18), found, strict=True):
        true = np.array(RIG.lights[k].position_mm) / 225.0
        angle = np.degrees(np.arccos(np.clip(np.dot(true, d), -1, 1)))
        # the sphere's highlight assumes a view from straight above; dome24's camera is 225 mm
        # above a 43 mm sphere, which bends the view by up to 5 degrees at its rim (measured 1.6 to 3.7)
        assert angle < 5.0


def test_a_calibration_is_brought_to_each_captures_exposure_and_level(tmp_path):
    """A grey card photographed at 20 ms calibrates captures of one sample taken at 10 ms,
    5 ms, and 20 ms with the LEDs at half level, under the lower two rings' LEDs (whose
    highlights do not saturate). The virtual camera is linear in exposure and level, so
    the reference is the scene itself: corrected, every capture's photos agree with the
    10 ms capture's, and reconstructed, the 5 ms capture's diffuse map is the sample's.
    The same calibration with its exposure struck out (a calibration made before it was
    recorded) leaves the 5 ms photos half as bright as the 10 ms capture's, with a
    warning naming it."""
    import json

    from matscan.calibrate import apply_calibration, calibrate, with_light_gains
    from matscan.capture.folder import with_calibration_file
    from matscan.reconstruct import ReconstructConfig
    from matscan.reconstruct.job import reconstruct

    leds, lights = VirtualLeds(), (0, 4, 8, 12)
    grey = VirtualCamera(target_maps("grey", 64), RIG, leds)
    acquire(tmp_path / "grey", RIG, grey, leds, AcquireConfig(target="grey", lights=lights, exposure_s=0.02))
    cal = calibrate(tmp_path / "cal.json", grey=tmp_path / "grey")
    assert (cal.exposure_s, cal.led_level) == (0.02, 1.0)
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert (doc["exposure_s"], doc["led_level"]) == (0.02, 1.0)
    old = {k: v for k, v in doc.items() if k not in ("exposure_s", "led_level")}
    (tmp_path / "old.json").write_text(json.dumps(old))

    sample = small_sample()
    for name, seconds, level in (("ref", 0.01, 1.0), ("short", 0.005, 1.0), ("dim", 0.02, 0.5)):
        camera = VirtualCamera(sample, RIG, leds)
        acquire(tmp_path / name, RIG, camera, leds, AcquireConfig(lights=lights, exposure_s=seconds, level=level))

    def corrected(name: str, calibration: str):
        capture = apply_calibration(with_calibration_file(load_capture(tmp_path / name), tmp_path / calibration))
        return capture.linear().mean((0, 2, 3)), capture

    ref, _ = corrected("ref", "cal.json")
    assert corrected("ref", "cal.json")[1].meta["exposure_ratio"] == pytest.approx(0.5)
    for name, ratio in (("short", 0.25), ("dim", 0.5)):
        mean, capture = corrected(name, "cal.json")
        assert capture.meta["exposure_ratio"] == pytest.approx(ratio)
        assert torch.allclose(mean / ref, torch.ones(3), atol=0.01), (name, mean / ref)
        assert not [w for w in capture.meta["warnings"] if "exposure" in w]
    mean, capture = corrected("short", "old.json")
    assert torch.allclose(mean / corrected("ref", "old.json")[0], torch.full((3,), 0.5), atol=0.01)
    assert any("old.json does not record its grey card's exposure" in w for w in capture.meta["warnings"])

    # a self-calibration of the 5 ms capture holds at 5 ms: scales a quarter of the card's,
    # lights 8's and 12's (not photographed here) too
    capture = apply_calibration(
        with_calibration_file(load_capture(tmp_path / "short", lights=(0, 4)), tmp_path / "cal.json")
    )
    made = with_light_gains(capture, torch.ones(2, 3))
    assert made["exposure_s"] == 0.005
    for k in ("0", "4", "8", "12"):
        assert made["light_scales"][k] == pytest.approx([0.25 * c for c in doc["light_scales"][k]], rel=1e-5)

    record = reconstruct(
        tmp_path / "short", tmp_path / "maps", ReconstructConfig(calibration=str(tmp_path / "cal.json"))
    )
    assert record["calibration_exposure_ratio"] == pytest.approx(0.25)
    diffuse = read_mapset(tmp_path / "maps").diffuse.mean((1, 2))
    assert torch.allclose(diffuse, sample.diffuse.mean((1, 2)), rtol=0.05), (diffuse, sample.diffuse.mean((1, 2)))


def test_cli_capture_summary(tmp_path, capsys):
    from matscan.cli import main

    args = [
        "capture",
        "--camera",
        "virtual:@sample",
        "--lights",
        "6",
        "--exposure",
        "0.01",
        "--max-saturated",
        "0.3",
        "--out",
        str(tmp_path / "cap"),
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "capture: wrote" in out and "7 photos, exposure 0.01 s, 0 retaken, sample moved 0.00 px" in out
    assert main(["capture", "--camera", "nikon", "--out", str(tmp_path / "x")]) == 2
    assert "--camera: 'nikon' is not virtual:MAPS, folder:PATH or gphoto2" in capsys.readouterr().err


def test_the_operator_is_asked_to_empty_the_stage(tmp_path):
    """A real camera cannot empty the stage itself: the operator is asked once, before the
    empty-stage backlight photos; with no one to ask, the capture stops and keeps its photos."""
    leds = VirtualLeds()
    inner = VirtualCamera(small_sample(), RIG, leds)

    class Tethered:  # a camera with no virtual stage
        name, suffix, controls_exposure = "tethered", ".png", True

        def shoot(self, exposure_s):
            return inner.shoot(exposure_s)

        def close(self):
            pass

    cfg = AcquireConfig(lights=(0, 8, 16), backlight=True, exposure_s=0.01, max_saturated=0.3)
    with pytest.raises(MatscanError, match="need the sample removed; run the same command in a terminal"):
        acquire(tmp_path / "cap", RIG, Tethered(), leds, cfg)
    assert (tmp_path / "cap" / "back_blue.png").exists() and not (tmp_path / "cap" / "empty_green.png").exists()
    asked = []

    def operator(message):
        asked.append(message)
        inner.sample_present = False  # the operator lifts the sample off

    acquire(tmp_path / "cap", RIG, Tethered(), leds, cfg, ask=operator)
    assert asked == ["remove the sample from the stage, then press Enter"]
    cap = load_capture(tmp_path / "cap")
    assert sorted(cap.backlight) == ["blue", "blue_empty", "green", "green_empty"]
    # the empty stage shows no sample: its green photo is the backlight alone, brighter than with the sample
    assert float(cap.backlight["green_empty"].mean()) > float(cap.backlight["green"].mean())


@pytest.mark.parametrize(
    "settings, words",
    [
        ({"max_saturated": 2.0}, "--max-saturated: 2.0 must be a fraction of the pixels"),
        ({"max_saturated": 1.0}, "--max-saturated: 1.0"),  # every pixel may saturate: no check at all
        ({"level": 0.0}, "--level: 0.0 must be above 0"),
    ],
)
def test_acquisition_settings_out_of_range_are_refused(settings, words):
    with pytest.raises(MatscanError, match=words):
        AcquireConfig(**settings)


def test_a_resume_with_another_sample_or_sensor_is_refused(tmp_path):
    """The journal kept only the camera's kind ("virtual"), so a resume photographing
    another sample, or with another seed, finished a capture of two samples."""
    leds = VirtualLeds()
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=4), leds, SIX)
    before = files(tmp_path / "cap")
    other = small_sample()
    other = MapSet(**{**other.present(), "diffuse": other.diffuse.flip(-1) * 0.5})
    for camera in (VirtualCamera(other, RIG, leds), VirtualCamera(small_sample(), RIG, leds, seed=7)):
        with pytest.raises(MatscanError, match=r"holds a capture taken with other settings \(the camera's settings\)"):
            acquire(tmp_path / "cap", RIG, camera, leds, SIX)
        assert files(tmp_path / "cap") == before
    with pytest.raises(MatscanError, match=r"other settings \(--level\)"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, replace(SIX, level=0.5))
    with pytest.raises(MatscanError, match=r"other settings \(--exposure, max_shift_px\)"):  # flags as the CLI has them
        acquire(
            tmp_path / "cap",
            RIG,
            VirtualCamera(small_sample(), RIG, leds),
            leds,
            replace(SIX, exposure_s=0.02, max_shift_px=3.0),
        )
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)  # the same one resumes
    assert len(load_capture(tmp_path / "cap").files) == 6


def test_a_journal_line_cut_by_a_kill_does_not_swallow_the_next_events(tmp_path):
    """A kill mid-line left a line without its newline; the next run's first event was
    appended to it, so that event and every later one could no longer be read."""
    from matscan.capture.acquire import Journal

    leds = VirtualLeds()
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=4), leds, SIX)
    journal = tmp_path / "cap" / JOURNAL
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:40])  # the last event cut mid-line
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    events = Journal(journal).read()
    assert events[-1]["event"] == "complete"
    assert all(json.loads(line) for line in journal.read_text().splitlines())  # every line whole
    assert sorted(e["stem"] for e in events if e["event"] == "frame") == sorted(
        ["dark"] + [f"led_{k:02d}" for k in SIX.lights]
    )


def test_a_whole_last_event_without_its_newline_is_kept(tmp_path):
    """The last event complete but for its newline was replayed, then cut by the next
    append: its frame came back as "recovered", its checks lost."""
    leds = VirtualLeds()
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=4), leds, SIX)
    journal = tmp_path / "cap" / JOURNAL
    journal.write_text(journal.read_text().rstrip("\n"))
    last = json.loads(journal.read_text().splitlines()[-1])
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    events = [json.loads(line) for line in journal.read_text().splitlines()]
    assert last in events and not any(e.get("recovered") for e in events)


def test_the_exposure_recorded_is_the_one_the_camera_used(tmp_path):
    """A tethered camera takes the nearest shutter speed not above the one asked for;
    capture.json recorded the one asked for (0.03 s made at 1/40 s), and a calibration's
    exposure ratio was off by that much."""

    class Stepped(VirtualCamera):
        def exposure_for(self, exposure_s):
            return max(s for s in (1 / 100, 1 / 50, 1 / 40) if s <= exposure_s)

        def shoot(self, exposure_s):
            return super().shoot(self.exposure_for(exposure_s))

    leds = VirtualLeds()
    record = acquire(tmp_path / "cap", RIG, Stepped(small_sample(), RIG, leds), leds, replace(SIX, exposure_s=0.03))
    assert record["exposure_s"] == pytest.approx(1 / 40)
    assert load_capture(tmp_path / "cap").meta["exposure_s"] == pytest.approx(1 / 40)


def test_what_the_board_or_capture_cannot_do_is_refused_before_any_photo(tmp_path):
    leds = VirtualLeds()
    with pytest.raises(MatscanError, match=r"rig 'flash' moves its light by hand"):
        acquire(tmp_path / "a", builtin_rig("flash"), VirtualCamera(small_sample(), RIG, leds), leds, SIX)
    wide = dataclasses.replace(RIG, name="dome30", lights=RIG.lights + RIG.lights[:6])
    with pytest.raises(MatscanError, match=r"names light 25, but the LED controller .* drives 24 LEDs"):
        acquire(tmp_path / "b", wide, VirtualCamera(small_sample(), wide, leds), leds, replace(SIX, lights=(0, 25)))
    camera = VirtualCamera(small_sample(), RIG, leds)
    with pytest.raises(MatscanError, match=r"--level: 0\.0004 is not a level the LED controller makes"):
        acquire(tmp_path / "c", RIG, camera, leds, replace(SIX, level=0.0004))  # the board would light 0
    with pytest.raises(MatscanError, match=r"--level: 0\.0015 .* nearest 0\.002"):
        acquire(tmp_path / "c", RIG, camera, leds, replace(SIX, level=0.0015))
    assert camera.shots == 0
    assert not any((tmp_path / name).exists() for name in "abc")


def test_a_capture_begun_at_a_level_between_steps_still_resumes(tmp_path, monkeypatch):
    """Captures begun before levels were checked against the board's steps resume at
    their own level (the check refused the only command that could resume them)."""
    import matscan.capture.acquire as acquire_module

    leds = VirtualLeds()
    odd = replace(SIX, level=0.3333)
    monkeypatch.setattr(acquire_module, "check_level", lambda level: None)  # as before the check
    with pytest.raises(MatscanError, match="disconnected"):
        acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds, fail_after=3), leds, odd)
    monkeypatch.undo()
    acquire(tmp_path / "cap", RIG, VirtualCamera(small_sample(), RIG, leds), leds, odd)
    assert len(load_capture(tmp_path / "cap").files) == 6


def test_an_unreadable_photo_from_a_folder_camera_is_named_and_leaves_nothing(tmp_path):
    incoming = tmp_path / "incoming"
    incoming.mkdir()
    leds = VirtualLeds()

    class Garbage(FolderCamera):
        def shoot(self, exposure_s):
            threading.Timer(0.05, lambda: (incoming / "IMG_0001.png").write_bytes(b"garbage")).start()
            return super().shoot(exposure_s)

    with pytest.raises(MatscanError, match=r"incoming/IMG_0001\.png: cannot read as PNG") as info:
        acquire(tmp_path / "cap", RIG, Garbage(incoming, timeout=10), leds, SIX)
    assert ".partial" not in str(info.value)
    assert sorted(p.name for p in (tmp_path / "cap").iterdir()) == [JOURNAL]


def test_end_of_input_at_the_operators_prompt_is_one_line(monkeypatch):
    from matscan.cli import _ask_operator

    def closed(prompt):
        raise EOFError

    monkeypatch.setattr("builtins.input", closed)
    with pytest.raises(MatscanError, match=r"capture: no answer \(end of input\); the photos so far are kept"):
        _ask_operator("remove the sample from the stage, then press Enter")
