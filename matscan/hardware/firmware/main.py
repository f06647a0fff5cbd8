# matscan LED controller firmware, protocol matscan-led/1 (docs/hardware.md).
#
# MicroPython on an RP2040 board (Raspberry Pi Pico): copy this file to the board as
# main.py. The protocol logic (Controller) uses no hardware and runs unchanged on a PC:
# matscan's tests and `matscan capture --leds simulated` drive it through a pseudo-
# terminal. Only board_main() touches the board (machine, sys.stdin, select).
#
# Safety: at most one ring LED is on at a time (switching one on switches the others
# off, and the backlight); a host that stops talking for WATCHDOG_MS turns everything
# off; a hardware watchdog resets a hung board, and every pin starts low (off).

PROTOCOL = "matscan-led/1"
FIRMWARE = "1.0.1"
N_LEDS = 24
MAX_LEVEL = 1000  # per mille of full brightness
WATCHDOG_MS = 5000
WATCHDOG_RANGE = (100, 60000)
MAX_LINE = 64

# error codes (ERR <code> <text>)
E_UNKNOWN = 1
E_ARGUMENTS = 2
E_INDEX = 3
E_LEVEL = 4
E_TOO_LONG = 5
E_WATCHDOG = 6

# GPIO of each ring LED (index 0..23: ring 0 at 22.5 deg, then 45, then 67.5; 8 per
# ring from +x toward +y) and of the backlight's green and blue channels
LED_PINS = tuple(range(0, 23)) + (26,)
GREEN_PIN = 27
BLUE_PIN = 28
PWM_HZ = 20000


class Controller:
    """The protocol's state machine. ``outputs(channel, level)`` sets a channel's
    brightness: channel 0..N_LEDS-1 for the ring, "green"/"blue" for the backlight;
    level 0..MAX_LEVEL."""

    def __init__(self, outputs, now_ms, ticks_diff=lambda a, b: a - b):
        self.outputs = outputs
        self.now_ms = now_ms
        self.diff = ticks_diff  # time.ticks_diff on the board, where the clock wraps
        self.led = -1
        self.level = 0
        self.back = "off"
        self.watchdog_ms = WATCHDOG_MS
        self.tripped = False
        self.last = now_ms()
        self.started = self.last
        self.all_off()

    def all_off(self):
        for k in range(N_LEDS):
            self.outputs(k, 0)
        self.outputs("green", 0)
        self.outputs("blue", 0)
        self.led, self.level, self.back = -1, 0, "off"

    def tick(self):
        """Called often: the watchdog turns everything off when the host is silent."""
        if self.diff(self.now_ms(), self.last) > self.watchdog_ms and (self.led >= 0 or self.back != "off"):
            self.all_off()
            self.tripped = True

    def handle(self, line):
        """One command line in, one reply line out (without the newline)."""
        self.last = self.now_ms()
        if len(line) > MAX_LINE:
            return "ERR %d line longer than %d characters" % (E_TOO_LONG, MAX_LINE)
        words = line.strip().split()
        if not words:
            return "ERR %d empty line" % E_UNKNOWN
        cmd, args = words[0].upper(), words[1:]
        if cmd == "HELLO":
            return "OK %s leds=%d backlight=green,blue max_level=%d fw=%s" % (PROTOCOL, N_LEDS, MAX_LEVEL, FIRMWARE)
        if cmd == "PING":
            return "OK" if not args else "ERR %d PING takes no arguments" % E_ARGUMENTS
        if cmd == "OFF":
            self.all_off()
            return "OK"
        if cmd == "LED":
            if len(args) != 2:
                return "ERR %d usage: LED <index> <level>" % E_ARGUMENTS
            k, level = _int(args[0]), _int(args[1])
            if k is None or not 0 <= k < N_LEDS:
                return "ERR %d LED index %s is not 0 to %d" % (E_INDEX, args[0], N_LEDS - 1)
            if level is None or not 0 <= level <= MAX_LEVEL:
                return "ERR %d level %s is not 0 to %d" % (E_LEVEL, args[1], MAX_LEVEL)
            self.all_off()
            if level > 0:
                self.outputs(k, level)
                self.led, self.level = k, level
            return "OK"
        if cmd == "BACK":
            if len(args) not in (1, 2) or args[0].lower() not in ("green", "blue", "off"):
                return "ERR %d usage: BACK green|blue|off [level]" % E_ARGUMENTS
            level = _int(args[1]) if len(args) == 2 else MAX_LEVEL
            if level is None or not 0 <= level <= MAX_LEVEL:
                return "ERR %d level %s is not 0 to %d" % (E_LEVEL, args[1], MAX_LEVEL)
            self.all_off()
            colour = args[0].lower()
            if colour != "off" and level > 0:
                self.outputs(colour, level)
                self.back, self.level = colour, level
            return "OK"
        if cmd == "WATCHDOG":
            ms = _int(args[0]) if len(args) == 1 else None
            if ms is None or not WATCHDOG_RANGE[0] <= ms <= WATCHDOG_RANGE[1]:
                return "ERR %d usage: WATCHDOG <ms>, %d to %d" % (E_WATCHDOG, WATCHDOG_RANGE[0], WATCHDOG_RANGE[1])
            self.watchdog_ms = ms
            return "OK"
        if cmd == "STATUS":
            tripped, self.tripped = self.tripped, False
            return "OK led=%s level=%d back=%s watchdog_ms=%d tripped=%d uptime_ms=%d" % (
                self.led if self.led >= 0 else "-",
                self.level,
                self.back,
                self.watchdog_ms,
                1 if tripped else 0,
                self.diff(self.now_ms(), self.started),
            )
        return "ERR %d unknown command %s" % (E_UNKNOWN, words[0][:16])


def _int(text):
    try:
        return int(text)
    except ValueError:
        return None


def serve(read_line, write_line, controller, running=lambda: True):
    """The firmware's loop: ``read_line(timeout_ms)`` gives a line or None; every reply
    goes to ``write_line``; the watchdog ticks between lines."""
    while running():
        line = read_line(50)
        if line is not None:
            write_line(controller.handle(line))
        controller.tick()


def board_main(running=lambda: True):
    import select
    import sys
    import time

    import machine

    wdt = machine.WDT(timeout=2000)
    pins = dict(enumerate(LED_PINS))
    pins["green"], pins["blue"] = GREEN_PIN, BLUE_PIN
    for pin in pins.values():  # every pin a plain output, low (off)
        machine.Pin(pin, machine.Pin.OUT, value=0)
    lit = {}

    def outputs(channel, level):
        # A pin is a PWM output only while its channel is lit. The RP2040's pins 16 apart
        # (GP0 and GP16, GP10 and GP26, GP11 and GP27, GP12 and GP28) share one PWM slice
        # and channel, so a pin left in PWM mode would light with its twin; the Controller
        # switches every channel off before it lights one, so no twin is ever in PWM mode.
        pin = pins[channel]
        if level <= 0:
            p = lit.pop(channel, None)
            if p is not None:
                p.duty_u16(0)
                p.deinit()
            machine.Pin(pin, machine.Pin.OUT, value=0)  # back to a plain output, low
            return
        if channel not in lit:
            lit[channel] = machine.PWM(machine.Pin(pin))
            lit[channel].freq(PWM_HZ)
        lit[channel].duty_u16(level * 65535 // MAX_LEVEL)

    poll = select.poll()
    poll.register(sys.stdin, select.POLLIN)
    buf = []

    def read_line(timeout_ms):
        wdt.feed()
        while poll.poll(timeout_ms):
            c = sys.stdin.read(1)
            if c in ("\n", "\r"):
                if buf:
                    line = "".join(buf)
                    del buf[:]
                    return line
            elif len(buf) <= MAX_LINE:
                buf.append(c)
            timeout_ms = 0
        return None

    def write_line(text):
        sys.stdout.write(text + "\n")

    serve(read_line, write_line, Controller(outputs, time.ticks_ms, time.ticks_diff), running)


if __name__ == "__main__":  # pragma: no cover
    board_main()
