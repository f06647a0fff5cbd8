"""The LED controller: firmware logic (on the host, its board faked), the protocol over a
pseudo-terminal through pyserial (the same code path as a real port), and the camera
back-ends' adapters."""

from __future__ import annotations

import sys
import threading
import time
import types

import pytest

from matscan.errors import MatscanError
from matscan.hardware.firmware import main as fw


class Clock:
    def __init__(self) -> None:
        self.ms = 1000

    def __call__(self) -> int:
        return self.ms


def controller():
    levels: dict = {}
    clock = Clock()
    c = fw.Controller(lambda ch, lv: levels.__setitem__(ch, lv), clock)
    return c, levels, clock


def lit(levels: dict) -> list:
    return sorted(str(k) for k, v in levels.items() if v)


def test_protocol_commands_and_replies():
    c, levels, _ = controller()
    assert c.handle("HELLO") == "OK matscan-led/1 leds=24 backlight=green,blue max_level=1000 fw=1.0.1"
    assert lit(levels) == []  # everything starts off
    assert c.handle("LED 5 500") == "OK" and lit(levels) == ["5"] and levels[5] == 500
    # one ring LED at a time: switching another on switches the first off
    assert c.handle("led 7 1000") == "OK" and lit(levels) == ["7"]
    assert c.handle("BACK green") == "OK" and lit(levels) == ["green"] and levels["green"] == 1000
    assert c.handle("BACK blue 200") == "OK" and lit(levels) == ["blue"]
    assert c.handle("LED 3 0") == "OK" and lit(levels) == []
    assert c.handle("LED 3 1") == "OK" and c.handle("OFF") == "OK" and lit(levels) == []
    assert c.handle("PING") == "OK"
    assert c.handle("STATUS").startswith("OK led=- level=0 back=off watchdog_ms=5000 tripped=0")


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        ("FLY", "ERR 1 unknown command FLY"),
        ("", "ERR 1 empty line"),
        ("LED 24 10", "ERR 3 LED index 24 is not 0 to 23"),
        ("LED -1 10", "ERR 3 LED index -1 is not 0 to 23"),
        ("LED 2 1001", "ERR 4 level 1001 is not 0 to 1000"),
        ("LED 2", "ERR 2 usage: LED <index> <level>"),
        ("LED two 5", "ERR 3 LED index two is not 0 to 23"),
        ("BACK red", "ERR 2 usage: BACK green|blue|off [level]"),
        ("WATCHDOG 50", "ERR 6 usage: WATCHDOG <ms>, 100 to 60000"),
        ("PING now", "ERR 2 PING takes no arguments"),
        ("LED " + "1" * 80, "ERR 5 line longer than 64 characters"),
    ],
)
def test_errors_have_codes_and_change_nothing(line, reply):
    c, levels, _ = controller()
    c.handle("LED 4 100")
    assert c.handle(line) == reply
    # a refused command leaves the lights as they were (bad LED and BACK switch nothing)
    assert lit(levels) == ["4"]


def test_watchdog_turns_everything_off_when_the_host_is_silent():
    c, levels, clock = controller()
    assert c.handle("WATCHDOG 300") == "OK"
    c.handle("LED 9 1000")
    clock.ms += 250
    c.tick()
    assert lit(levels) == ["9"]
    clock.ms += 100  # 350 ms since the last command
    c.tick()
    assert lit(levels) == []
    assert "tripped=1" in c.handle("STATUS")
    assert "tripped=0" in c.handle("STATUS")  # reported once


def test_board_main_with_the_board_faked(monkeypatch):
    """board_main as on the RP2040: machine, select, sys.stdin/stdout and time.ticks_*
    faked; the pins it drives and the watchdog it feeds are recorded. The fake board
    routes PWM as the RP2040 does: GPIO n is channel n & 1 of slice (n >> 1) & 7, so a
    pin in PWM mode outputs whatever duty its slice's channel has, whichever pin set it
    (GP0 and GP16 share one)."""
    mode: dict = {}  # pin -> "pwm" or the plain output's value
    slice_duty: dict = {}  # (slice, channel) -> duty
    fed = []
    seen = []  # after each command: the pins that are on

    def slot(n):
        return (n >> 1) & 7, n & 1

    class Pin:
        OUT = 1

        def __init__(self, n, mode_=None, value=None):
            self.n = n
            if mode_ is not None:
                assert mode_ == Pin.OUT
                mode[n] = value or 0

    class PWM:
        def __init__(self, pin):
            self.pin = pin.n
            mode[self.pin] = "pwm"

        def freq(self, hz):
            assert hz == fw.PWM_HZ

        def duty_u16(self, value):
            slice_duty[slot(self.pin)] = value

        def deinit(self):
            slice_duty[slot(self.pin)] = 0

    def on_pins():
        return {n for n, m in mode.items() if (slice_duty.get(slot(n), 0) if m == "pwm" else m)}

    class WDT:
        def __init__(self, timeout):
            assert timeout >= 1000

        def feed(self):
            fed.append(1)

    machine = types.SimpleNamespace(Pin=Pin, PWM=PWM, WDT=WDT)
    text = "HELLO\nLED 16 1000\nLED 2 1000\nBACK blue 500\nLED 10 700\nSTATUS\n"
    pos = [0]

    class Stdin:
        def read(self, n):
            c = text[pos[0]]
            pos[0] += 1
            if c == "\n":
                seen.append(None)  # the reply to this line comes before the next read
            return c

    class Poll:
        def register(self, *a):
            pass

        def poll(self, timeout):
            return [1] if pos[0] < len(text) else []

    out = []

    def write(text):
        out.append(text)
        seen[-1] = on_pins()

    fake_time = types.SimpleNamespace(ticks_ms=lambda: 5, ticks_diff=lambda a, b: a - b)
    monkeypatch.setitem(sys.modules, "machine", machine)
    monkeypatch.setitem(sys.modules, "time", fake_time)
    monkeypatch.setattr("select.poll", lambda: Poll())
    monkeypatch.setattr("sys.stdin", Stdin())
    monkeypatch.setattr("sys.stdout", types.SimpleNamespace(write=write))
    fw.board_main(running=lambda: pos[0] < len(text) or len(out) < 6)
    monkeypatch.undo()
    replies = "".join(out).splitlines()
    assert replies[0].startswith("OK matscan-led/1") and replies[1:5] == ["OK"] * 4
    assert replies[5].startswith("OK led=10 level=700 back=off")
    pin = dict(enumerate(fw.LED_PINS))
    # LED 16's twin is LED 0 (GP16, GP0), the blue backlight's LED 12 (GP28, GP12), LED
    # 10's LED 23 (GP10, GP26): each lights alone
    assert seen[1] == {pin[16]} and seen[2] == {pin[2]} and seen[3] == {fw.BLUE_PIN} and seen[4] == {pin[10]}
    assert slot(pin[16]) == slot(pin[0]) and slot(fw.BLUE_PIN) == slot(pin[12]) and slot(pin[10]) == slot(pin[23])
    assert fed  # the hardware watchdog was fed


pytest.importorskip("serial")


@pytest.fixture
def board():
    from matscan.hardware.leds import LedController, SimulatedBoard, open_serial

    b = SimulatedBoard()
    leds = LedController(open_serial(b.path), "simulated board", timeout=1.0)
    yield b, leds
    leds.port.close()
    b.close()


def test_controller_over_a_pseudo_terminal(board):
    b, leds = board
    assert leds.n_leds == 24 and leds.firmware == "1.0.1"
    leds.led(5, 0.5)
    assert b.lit() == ["5"] and b.levels[5] == 500
    assert leds.status()["led"] == "5"
    leds.backlight("green")
    assert b.lit() == ["green"]
    leds.off()
    assert b.lit() == []
    with pytest.raises(MatscanError, match=r"'LED 30 1000' was refused: ERR 3 LED index 30 is not 0 to 23"):
        leds.led(30)


def test_a_silent_board_is_an_error_and_leaves_the_leds_off(board):
    b, leds = board
    leds.led(3)
    b.hang()
    t0 = time.monotonic()
    with pytest.raises(MatscanError, match=r"no reply to 'LED 4 1000' within 1 s .* the LEDs were commanded off"):
        leds.led(4)
    assert time.monotonic() - t0 < 3
    time.sleep(0.2)
    assert b.lit() == []  # the board still heard the OFF


def test_the_board_watchdog_over_the_port(board):
    b, leds = board
    leds.command("WATCHDOG 200")
    leds.led(11)
    assert b.lit() == ["11"]
    time.sleep(0.5)
    assert b.lit() == []
    assert leds.status()["tripped"] == "1"


def test_a_board_speaking_another_protocol_is_refused():
    import os
    import pty

    from matscan.hardware.leds import LedController, open_serial

    master, slave = pty.openpty()
    from matscan.hardware.leds import _raw

    _raw(slave)

    def answer():
        os.read(master, 100)
        os.write(master, b"OK some-other-thing/2\n")

    threading.Thread(target=answer, daemon=True).start()
    with pytest.raises(MatscanError, match="speaks 'some-other-thing/2', not matscan-led/1"):
        LedController(open_serial(os.ttyname(slave)), "fake", timeout=1.0)
    os.close(master)
    os.close(slave)


def test_gphoto2_adapter_with_a_fake_library():
    from matscan.hardware.cameras import Gphoto2Camera, _seconds

    assert _seconds("1/125") == pytest.approx(0.008) and _seconds("30s") == 30 and _seconds("bulb") is None

    class GPhoto2Error(Exception):
        pass

    class Widget:
        def __init__(self, choices, value):
            self.choices, self.value = choices, value

        def count_choices(self):
            return len(self.choices)

        def get_choice(self, i):
            return self.choices[i]

        def set_value(self, v):
            self.value = v

    widgets = {
        "shutterspeed": Widget(["1/1000", "1/250", "1/60", "1/15", "1/4", "1", "bulb"], "1/60"),
        "iso": Widget(["100", "200", "400"], "100"),
        "imageformat": Widget(["RAW", "Large Fine JPEG"], "RAW"),
    }

    class Config:
        def get_child_by_name(self, name):
            if name not in widgets:
                raise GPhoto2Error(name)
            return widgets[name]

    shots = []

    class Camera:
        def init(self):
            pass

        def get_config(self):
            return Config()

        def set_config(self, config):
            pass

        def capture(self, kind):
            if len(shots) == 2:
                raise GPhoto2Error("-7: I/O problem")
            shots.append(widgets["shutterspeed"].value)
            return types.SimpleNamespace(folder="/store", name=f"IMG_{len(shots):04d}.CR2")

        def file_get(self, folder, name, kind):
            return types.SimpleNamespace(get_data_and_size=lambda: bytearray(b"raw" + name.encode()))

        def exit(self):
            pass

    gp = types.SimpleNamespace(Camera=Camera, GPhoto2Error=GPhoto2Error, GP_CAPTURE_IMAGE=0, GP_FILE_TYPE_NORMAL=1)
    cam = Gphoto2Camera(iso="400", gp=gp)
    assert widgets["iso"].value == "400"
    assert cam.shoot(0.02) == b"rawIMG_0001.CR2" and shots[-1] == "1/60"  # the longest speed not above 20 ms
    assert cam.suffix == ".cr2" and cam.actual_exposure == pytest.approx(1 / 60)
    assert cam.exposure_for(0.02) == pytest.approx(1 / 60)  # what a capture records for it
    assert cam.exposure_for(0.0001) == pytest.approx(1 / 1000)
    cam.shoot(0.0001)
    assert shots[-1] == "1/1000"  # shorter than any: the shortest there is
    with pytest.raises(MatscanError, match="the capture failed .* still connected"):
        cam.shoot(1.0)
    with pytest.raises(MatscanError, match="iso '3200' is not one of 100, 200, 400"):
        cam.set("iso", "3200")
