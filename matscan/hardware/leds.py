"""The host side of the LED controller: protocol ``matscan-led/1`` over a serial port.

:class:`LedController` speaks to any board running ``firmware/main.py`` (or anything
that speaks the protocol) through a pyserial port: a real one (``serial:/dev/ttyACM0``),
a pseudo-terminal, or any pyserial URL. Every command waits for its one-line reply; a
reply that does not come within ``timeout`` seconds, or an ``ERR``, is a MatscanError
naming the port, after which the controller is told to switch everything off (the
board's own watchdog does so too when the host goes silent). ``--leds simulated`` runs
the firmware's logic on the host behind a pseudo-terminal (:class:`SimulatedBoard`),
so the same serial code path is exercised without a board; ``--leds virtual`` skips the
serial line altogether (:class:`VirtualLeds`).

Both kinds keep :attr:`state`: what the board was last told and acknowledged (the ring
LED on and its level, or the backlight colour), which the virtual camera renders.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

from matscan.errors import MatscanError
from matscan.hardware.firmware import main as firmware

PROTOCOL = firmware.PROTOCOL
MAX_LEVEL = firmware.MAX_LEVEL
#: Seconds a reply may take.
REPLY_TIMEOUT = 2.0


@dataclass(frozen=True)
class Illumination:
    """What is lit: ring LED ``led`` (or None) at ``level`` (0..1), or the backlight
    (``"green"``/``"blue"``), or nothing."""

    led: int | None = None
    back: str | None = None
    level: float = 0.0


DARK = Illumination()


class VirtualLeds:
    """An LED controller with no hardware: it only remembers what is lit."""

    name = "virtual"

    def __init__(self, n_leds: int = firmware.N_LEDS) -> None:
        self.n_leds = n_leds
        self.state = DARK

    def led(self, k: int, level: float = 1.0) -> None:
        if not 0 <= k < self.n_leds:
            raise MatscanError(f"LEDs: index {k} is not 0 to {self.n_leds - 1}")
        self.state = Illumination(led=k, level=level)

    def backlight(self, colour: str, level: float = 1.0) -> None:
        self.state = DARK if colour == "off" else Illumination(back=colour, level=level)

    def off(self) -> None:
        self.state = DARK

    def keepalive(self) -> None:
        pass

    def close(self) -> None:
        self.off()


class LedController:
    """A board speaking ``matscan-led/1`` over ``port`` (an open pyserial port)."""

    def __init__(self, port, name: str, timeout: float = REPLY_TIMEOUT) -> None:
        self.port = port
        self.name = name
        self.timeout = timeout
        self.state = DARK
        self.port.reset_input_buffer()
        hello = self.command("HELLO")
        words = hello.split()
        if not words or words[0] != PROTOCOL:
            raise MatscanError(
                f"LEDs on {name}: the board speaks {hello!r}, not {PROTOCOL}; flash docs/hardware.md's firmware"
            )
        fields = dict(w.split("=", 1) for w in words[1:] if "=" in w)
        self.n_leds = int(fields.get("leds", "0"))
        self.firmware = fields.get("fw", "?")
        self.off()

    def command(self, line: str) -> str:
        """Send one command; return the text after ``OK``. An ``ERR`` reply or silence
        is a MatscanError (and, for silence, everything is commanded off once more)."""
        self.port.write((line + "\n").encode("ascii"))
        self.port.flush()
        reply = self._read_line()
        if reply is None:
            self._try_off()
            raise MatscanError(
                f"LEDs on {self.name}: no reply to {line!r} within {self.timeout:g} s (is the board connected and "
                "running the matscan firmware?); the LEDs were commanded off"
            )
        if reply.startswith("OK"):
            return reply[2:].strip()
        raise MatscanError(f"LEDs on {self.name}: {line!r} was refused: {reply}")

    def _read_line(self) -> str | None:
        deadline = time.monotonic() + self.timeout
        data = b""
        while time.monotonic() < deadline:
            chunk = self.port.readline()
            data += chunk
            if data.endswith(b"\n"):
                text = data.decode("ascii", "replace").strip()
                if text:
                    return text
                data = b""
        return None

    def _try_off(self) -> None:
        try:
            self.port.write(b"OFF\n")
            self.port.flush()
        except Exception:  # the port itself may be gone; the board's watchdog still turns off
            pass
        self.state = DARK

    def led(self, k: int, level: float = 1.0) -> None:
        self.command(f"LED {k} {round(level * MAX_LEVEL)}")
        self.state = Illumination(led=k, level=level)

    def backlight(self, colour: str, level: float = 1.0) -> None:
        self.command(f"BACK {colour} {round(level * MAX_LEVEL)}" if colour != "off" else "BACK off")
        self.state = DARK if colour == "off" else Illumination(back=colour, level=level)

    def off(self) -> None:
        self.command("OFF")
        self.state = DARK

    def keepalive(self) -> None:
        self.command("PING")

    def status(self) -> dict[str, str]:
        return dict(w.split("=", 1) for w in self.command("STATUS").split() if "=" in w)

    def close(self) -> None:
        """Everything off and the port closed; a board that no longer answers is left to
        its watchdog (which turns everything off) rather than hiding the error before."""
        try:
            self.off()
        except MatscanError:
            pass
        finally:
            self.port.close()


class SimulatedBoard:
    """The firmware's logic on the host, behind a pseudo-terminal: open its
    :attr:`path` as a serial port. ``outputs`` records each channel's level;
    :meth:`hang` makes it stop answering (a fault to test)."""

    def __init__(self) -> None:
        import pty

        self.master, self.slave = pty.openpty()
        _raw(self.slave)
        self.path = os.ttyname(self.slave)
        self.levels: dict = {}
        self.silent = threading.Event()
        self.stopped = threading.Event()
        self.controller = firmware.Controller(self._output, lambda: int(time.monotonic() * 1000))
        self.thread = threading.Thread(target=self._run, name="simulated-led-board", daemon=True)
        self.thread.start()

    def _output(self, channel, level) -> None:
        self.levels[channel] = level

    def _run(self) -> None:
        import select

        buf = b""

        def read_line(timeout_ms):
            nonlocal buf
            while b"\n" not in buf:
                ready, _, _ = select.select([self.master], [], [], timeout_ms / 1000)
                if not ready:
                    return None
                try:
                    buf += os.read(self.master, 256)
                except OSError:
                    self.stopped.set()
                    return None
            line, buf = buf.split(b"\n", 1)
            return line.decode("ascii", "replace")

        def write_line(text):
            if not self.silent.is_set():
                os.write(self.master, (text + "\n").encode("ascii"))

        firmware.serve(read_line, write_line, self.controller, running=lambda: not self.stopped.is_set())

    def lit(self) -> list:
        """The channels whose level is above 0."""
        return sorted((str(k) for k, v in self.levels.items() if v > 0))

    def hang(self) -> None:
        self.silent.set()

    def close(self) -> None:
        self.stopped.set()
        self.thread.join(timeout=2)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def _raw(fd: int) -> None:
    """No echo, no line editing: a pseudo-terminal that behaves like a USB serial port."""
    import termios
    import tty

    tty.setraw(fd, termios.TCSANOW)


def open_serial(url: str, timeout: float = REPLY_TIMEOUT):
    """A pyserial port for a device path, a pseudo-terminal or a pyserial URL."""
    try:
        import serial
    except ImportError:
        raise MatscanError("--leds serial: needs pyserial: pip install 'matscan[serial]'") from None
    try:
        return serial.serial_for_url(url, baudrate=115200, timeout=0.05)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise MatscanError(f"LEDs: cannot open {url} ({exc})") from None


def open_leds(spec: str, timeout: float = REPLY_TIMEOUT):
    """``virtual``, ``simulated`` (the firmware on the host, over a pseudo-terminal) or
    ``serial:PORT``. Returns (controller, board or None)."""
    if spec == "virtual":
        return VirtualLeds(), None
    if spec == "simulated":
        board = SimulatedBoard()
        try:
            return LedController(open_serial(board.path, timeout), "simulated board", timeout), board
        except Exception:
            board.close()
            raise
    if spec.startswith("serial:") and len(spec) > len("serial:"):
        port = spec[len("serial:") :]
        return LedController(open_serial(port, timeout), port, timeout), None
    raise MatscanError(f"--leds: {spec!r} is not virtual, simulated or serial:PORT")
