"""tools/model_card.py keeps the card's unlike section across rewrites: marked stale
once when the weights changed, unmarked again when they are the ones it was made with;
and that section says where the networks' map errors rise with more lights."""

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


def test_unlike_section_names_each_rise_of_a_map_error_with_more_lights():
    tool = load_tool()

    def row(material, lights, method, roughness, degrees):
        scores = {"rmse_diffuse": 0.05, "rmse_specular": 0.1, "rmse_roughness": roughness}
        return {"material": material, "lights": lights, "method": method, "normal_degrees": degrees, **scores}

    # two sets; means of roughness 0.15, 0.12, 0.13 (a rise from 2 to 3) and degrees 8, 7, 7 (none)
    rows = [
        row("photo-a", "1", "nets", 0.10, 8.0),
        row("artist-b", "1", "nets", 0.20, 8.0),
        row("photo-a", "2", "nets", 0.10, 7.0),
        row("artist-b", "2", "nets", 0.14, 7.0),
        row("photo-a", "3", "nets", 0.11, 7.5),
        row("artist-b", "3", "nets", 0.15, 6.5),
        row("photo-a", "3", "fit", 0.90, 30.0),  # other methods do not count
    ]
    assert tool.unlike_rises(rows, ["1", "2", "3"]) == "roughness from 2 to 3 lights (0.120 → 0.130)"
    flat = [r | {"rmse_roughness": 0.1} for r in rows]
    assert tool.unlike_rises(flat, ["1", "2", "3"]) == "nowhere"


def test_a_study_with_procedural_materials_gives_their_own_table_with_the_fit_and_novel_lights(tmp_path):
    import json

    tool = load_tool()

    def row(material, lights, method, novel):
        scores = {"rmse_diffuse": 0.05, "rmse_specular": 0.1, "rmse_roughness": 0.2, "normal_degrees": 3.0}
        return (
            {"material": material, "encoding": "srgb8", "lights": lights, "method": method}
            | scores
            | {"novel_rmse": novel}
        )

    rows = [
        row("photo-a", "1", "nets", 0.05),
        row("photo-a", "1", "fit", 0.06),
        row("procedural-000-x", "1", "nets", 0.04),
        row("procedural-000-x", "1", "fit", 0.03),
        row("procedural-000-x", "1", "baseline", 0.07),
        row("procedural-000-x", "1", "auto:other.safetensors", 0.01),  # candidates stay out of the card
    ]
    results = tmp_path / "results.json"
    results.write_text(json.dumps({"rows": rows, "lights": ["1"]}))
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"w")
    text = "\n".join(tool.unlike_section(results, weights))
    unlike, _, procedural = text.partition(tool.PROCEDURAL)
    assert "| 1 | fit | 0.0500 | 0.1000 | 0.2000 | 3.0 | 0.0600 |" in unlike
    assert "below the fit's at 1 of the 1 light counts (1)" in unlike
    assert "| 1 | fit | 0.0500 | 0.1000 | 0.2000 | 3.0 | 0.0300 |" in procedural
    assert "| 1 | baseline |" in procedural and "other.safetensors" not in text
    # judged on its own rows: the fit relights the procedural material better
    assert "below the fit's at no light count" in procedural and "below the baseline's at 1 of the 1" in procedural
    assert "1 procedural materials (`procedural:1`" in procedural


def test_both_study_sections_are_marked_stale_once_and_unmarked_for_their_own_weights(tmp_path):
    tool = load_tool()
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"new weights")
    old = hashlib.sha256(b"old weights").hexdigest()[:16]
    new = hashlib.sha256(b"new weights").hexdigest()[:16]

    def two(sha: str) -> str:
        proc = [tool.PROCEDURAL, "", f"Weights SHA-256 `{sha}`. Eight procedural.", "", "| 1 | 0.0500 |", ""]
        return card_with(sha) + "\n".join(proc)

    once = rewrite(tool, two(old), weights)
    assert once.count(tool.STALE) == 2 and rewrite(tool, once, weights) == once
    for heading in (tool.UNLIKE, tool.PROCEDURAL):
        assert f"{heading}\n\n{tool.STALE}\n\nWeights SHA-256 `{old}`" in once
    assert once.replace(tool.STALE + "\n\n", "") == two(old)
    assert rewrite(tool, two(new), weights) == two(new)
    marked = two(new).replace("\n\nWeights", f"\n\n{tool.STALE}\n\nWeights")
    assert marked.count(tool.STALE) == 2 and rewrite(tool, marked, weights) == two(new)
