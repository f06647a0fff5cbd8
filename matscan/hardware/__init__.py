"""The dome's hardware: the LED controller (protocol, firmware, host side) and cameras.

``firmware/main.py`` is the controller's firmware (MicroPython, RP2040); its logic runs
unchanged on the host in the tests and in ``--leds simulated``. ``leds`` speaks the
protocol over a serial port; ``cameras`` holds the camera back-ends. docs/hardware.md
has the parts, wiring, flashing and the protocol.
"""
