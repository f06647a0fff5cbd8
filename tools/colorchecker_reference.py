"""Write matscan/colorchecker24.json: the ColorChecker Classic's reference values, from colour-science.

The values are colour-science's published chromaticities of the chart
(``colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]``: X-Rite's
formulation since November 2014, CIE xyY under the chart's D50 illuminant), and the
linear sRGB (D65) that colour-science converts them to with a Bradford chromatic
adaptation. matscan reads the file; tests/test_calibrate.py checks it against
colour-science where that is installed (the dev extra).

Run: .venv/bin/python tools/colorchecker_reference.py
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

EDITION = "ColorChecker24 - After November 2014"
OUT = Path(__file__).resolve().parent.parent / "matscan" / "colorchecker24.json"


def reference() -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # colour-science warns about optional packages it does not need here
        import colour

    chart = colour.CCS_COLOURCHECKERS[EDITION]
    names = list(chart.data)
    xyy = np.array([chart.data[n] for n in names], dtype=np.float64)
    rgb = colour.XYZ_to_RGB(
        colour.xyY_to_XYZ(xyy),
        colour.RGB_COLOURSPACES["sRGB"],
        illuminant=chart.illuminant,
        chromatic_adaptation_transform="Bradford",
    )
    return {
        "edition": EDITION,
        "source": f"colour-science {colour.__version__}: colour.CCS_COLOURCHECKERS[{EDITION!r}]",
        "illuminant_xy": [float(v) for v in chart.illuminant],
        "linear_srgb": "colour.XYZ_to_RGB to sRGB (D65), Bradford adaptation from the chart's illuminant; unclipped",
        "patches": [
            {"name": n, "xyY": [round(float(v), 6) for v in c], "linear_srgb": [round(float(v), 6) for v in r]}
            for n, c, r in zip(names, xyy, rgb, strict=True)
        ],
    }


def main() -> None:
    OUT.write_text(json.dumps(reference(), indent=1) + "\n", encoding="utf-8")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
