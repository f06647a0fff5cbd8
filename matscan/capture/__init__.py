"""Captures: the capture folder format, its readers, and the virtual rig."""

from matscan.capture.folder import CAPTURE_FORMAT, Capture, load_capture, write_capture

__all__ = ["CAPTURE_FORMAT", "Capture", "load_capture", "write_capture"]
