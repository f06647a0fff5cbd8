"""tools/model_card.py keeps the card's unlike section across rewrites: marked stale
once when the weights changed, unmarked again when they are the ones it was made with."""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

TOOL = Path(__file__).resolve().parent.parent / "tools" / "model_card.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("model_card", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def card_with(section_sha: str) -> str:
    return "\n".join(
        [
            "# Model card",
            "",
            "Scored in 1 s.",
            "",
            "## On materials unlike the training set",
            "",
            f"Weights SHA-256 `{section_sha}`. Eight map sets.",
            "",
            "| lights | novel |",
            "|---:|---:|",
            "| 1 | 0.0600 |",
            "",
        ]
    )


def rewrite(tool, card: str, weights: Path) -> str:
    """What main() does with the part of the card after the procedural table."""
    head = card.partition(tool.UNLIKE)[0].rstrip("\n").split("\n")
    return "\n".join([*head, "", *tool.kept_unlike(card, weights)])


def test_unlike_section_is_marked_stale_once_and_unmarked_for_its_own_weights(tmp_path):
    tool = load_tool()
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"new weights")
    other = hashlib.sha256(b"old weights").hexdigest()[:16]
    card = card_with(other)
    once = rewrite(tool, card, weights)
    twice = rewrite(tool, once, weights)
    assert once.count(tool.STALE) == 1 and twice == once
    assert "\n\n\n" not in once  # one blank line between the parts, as in the original
    assert once.replace(tool.STALE + "\n\n", "") == card
    # a card whose section names these weights keeps it unmarked; a marked one loses the mark
    own = card_with(hashlib.sha256(b"new weights").hexdigest()[:16])
    assert rewrite(tool, own, weights) == own
    marked = own.replace("set\n\n", "set\n\n" + tool.STALE + "\n\n", 1)
    assert rewrite(tool, marked, weights) == own
