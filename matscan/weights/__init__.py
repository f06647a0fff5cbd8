"""Trained weights shipped with matscan, loaded by name.

``default``: the four map networks for the dome24 rig, ``cpu`` preset, trained on
the procedural prior on a 2-core CPU (docs/model-card.md says how and how well).

Any-rig ``default``: the network that reads any rig (:mod:`matscan.anyrig`), used where
``reconstruct --anyrig default`` is asked for (docs/model-card-anyrig.md).
"""

from __future__ import annotations

from pathlib import Path

from matscan.errors import MatscanError
from matscan.jsonfile import short_repr

ROOT = Path(__file__).parent
SHIPPED = {"default": "dome24-cpu.safetensors"}
ANYRIG_SHIPPED = {"default": "anyrig-cpu.safetensors"}


def _shipped(text: str, what: str, names: dict[str, str]) -> Path | None:
    """The file of a shipped name in ``names`` (None for any other text); a name whose file
    is missing from this installation is a one-line error."""
    if not text or not text.isprintable():
        raise MatscanError(f"{what}: {short_repr(text)} is not a name or a usable file name")
    if text not in names:
        return None
    path = ROOT / names[text]
    if not path.is_file():
        raise MatscanError(f"{what} {text!r}: its weights ({path.name}) are not in this installation")
    return path


def model_path(name_or_path: str | Path) -> Path:
    """The file of a shipped model name, or the given path to a weights file."""
    text = str(name_or_path)
    if (shipped := _shipped(text, "model", SHIPPED)) is not None:
        return shipped
    path = Path(text)
    if path.suffix != ".safetensors" and not path.is_file():
        raise MatscanError(f"model: {text!r} is neither a shipped model ({', '.join(SHIPPED)}) nor a weights file")
    return path


def load_model(name_or_path: str | Path = "default"):
    """(MapNets in eval mode, metadata) for a shipped name or a weights file.

    The file's metadata is checked field by field (:func:`matscan.weights.format.load_weights`):
    a damaged or foreign file is a one-line error naming it. No training code is imported.
    """
    from matscan.weights.format import load_weights

    return load_weights(model_path(name_or_path))


def anyrig_path(name_or_path: str | Path) -> Path:
    """The weights file of a shipped any-rig network's name (:mod:`matscan.anyrig`), or the
    given path to one, checked to exist."""
    text = str(name_or_path)
    if (shipped := _shipped(text, "anyrig", ANYRIG_SHIPPED)) is not None:
        return shipped
    if not Path(text).is_file():
        names = ", ".join(ANYRIG_SHIPPED)
        raise MatscanError(f"anyrig: no such weights file {text!r}, nor a shipped network ({names})")
    return Path(text)


def load_anyrig(name_or_path: str | Path = "default"):
    """The any-rig network (eval mode) of a shipped name, or of a weights or checkpoint
    file; a damaged or foreign file is a one-line error naming it."""
    from matscan.anyrig import load

    return load(anyrig_path(name_or_path))
