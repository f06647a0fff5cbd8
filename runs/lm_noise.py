"""How the ``lm`` solver's maps hold up when the photos are noisy at the scale the fit
sees them: the study's eight map sets unlike the training set (artist-style and
photo-built) and the built-in sample, photographed by dome24 at exposure E (radiance × E
before the sensor: read noise 0.002 of full scale plus shot noise, ``--bits`` sRGB) and
divided by E again, as a calibration made at another exposure does (the capture's photos
E times dimmer than the grey card's). E = 1 is the study's photographs (highlights clip);
at 1/8 and 1/32 nothing clips and the diffuse regions sit a few code values above black,
where the auto exposure of ``matscan capture`` puts a glossy sample.

For each, ``reconstruct_capture`` as the command runs it (networks, then the solver),
with ``SolverConfig.reweight`` set to each of ``--reweight`` (default 0,1,2; 0 is the
solver before it), ``noise_floor`` to ``--floor`` (default 0) and ``reweight_from`` to
``--from`` (default 1: every pixel; the solver ships with 6), and scored against the
truth: per-map RMSE, mean normal error, and the novel-light RMSE of the study (16 lights
the rig does not have). ``python runs/lm_noise.py [--size=128] [--lights=24,6]
[--exposures=1,0.125,0.03125] [--bits=16] [--reweight=0,1,2] [--floor=3] [--from=1]
[--set=unlike|selection:N] [--always]`` from the repository root (E = 1 is 8-bit unless
``--bits`` is given; ``selection:N``: N procedural materials of prior v4, seeds 2^42 + i).
``--always`` runs the passes wherever there are ``--from`` photos, as the runs before the
third rule of runs/lm-noise/README.md did: the solver's trigger (no passes where the
measured floor is at most τ) is patched out by keeping the floor at least τ × (1 + 1e-9).
"""

import sys
import time

import torch

from matscan.capture import Capture
from matscan.capture.folder import Correction
from matscan.capture.virtual import CameraModel, simulate_images
from matscan.evaluate import evaluation_lights, map_scores, rendering_scores
from matscan.mapset import MapSet, read_mapset
from matscan.materials.artist import ARTIST_NAMES, artist_material
from matscan.materials.photos import photo_material
from matscan.materials.procedural import random_material
from matscan.reconstruct import ReconstructConfig, lm, reconstruct_capture
from matscan.rig import builtin_rig
from matscan.weights import load_model


def option(name: str, default: str) -> str:
    for a in sys.argv[1:]:
        if a.startswith(f"--{name}="):
            return a.split("=", 1)[1]
    return default


def small(maps: MapSet, size: int) -> MapSet:
    present = {
        k: torch.nn.functional.interpolate(v[None], size=(size, size), mode="area")[0]
        for k, v in maps.present().items()
    }
    present["normal"] = present["normal"] / present["normal"].norm(dim=0, keepdim=True)
    return MapSet(**present)


def capture(truth: MapSet, rig, subset: str, exposure: float, bits: int, seed: int) -> Capture:
    indices = list(rig.subset(subset))
    ls = rig.light_set(indices)
    camera = CameraModel(exposure=exposure, read_noise=0.002, encoding="srgb", bits=bits)
    photos = simulate_images(truth, ls, rig.field_mm, camera, seed=seed)
    top = 1.0 - 0.5 / ((1 << bits) - 1)
    n = len(indices)
    return Capture(
        rig,
        rig.field_mm,
        "srgb",
        photos,
        (photos >= top).any(1, keepdim=True),
        tuple(indices),
        ls,
        tuple(f"led_{k:02d}" for k in indices),
        correction=Correction(None, torch.full((n, 3), exposure), (None,) * n),
    )


def main() -> None:
    torch.set_num_threads(2)
    size = int(option("size", "128"))
    subsets = option("lights", "24,6").split(",")
    exposures = [float(e) for e in option("exposures", "1,0.125,0.03125").split(",")]
    bits = int(option("bits", "") or 16)
    passes = [int(r) for r in option("reweight", "0,1,2").split(",")]
    floor, start = float(option("floor", "0")), int(option("from", "1"))
    if "--always" in sys.argv[1:]:
        measured = lm.noise_tau
        lm.noise_tau = lambda model, residual, cfg: max(cfg.tau * (1 + 1e-9), measured(model, residual, cfg))
    rig = builtin_rig("dome24")
    nets, _ = load_model("default")
    which = option("set", "unlike")
    if which.startswith("selection"):  # procedural prior v4, seeds 2^42 + i (tools/solver_priors.py)
        count = int(which.partition(":")[2] or 24)
        materials = [
            (f"v4-{i:02d}-{f}", m) for i in range(count) for f, m in [random_material(size, 2**42 + i, prior="v4")]
        ]
    else:
        materials = [(n, artist_material(n, size)) for n in ARTIST_NAMES]
        materials += [(f"photo-{n}", photo_material(n, size)) for n in ("brick", "grass", "gravel")]
        materials += [("sample", small(read_mapset("@sample"), size))]
    bits_of = (
        {e: (8 if e == 1 else bits) for e in exposures} if option("bits", "") == "" else {e: bits for e in exposures}
    )
    novel = evaluation_lights(rig)
    keys = ("rmse_diffuse", "rmse_specular", "rmse_roughness", "normal_degrees", "novel_rmse")
    depth = ", ".join(f"E={e:g} {b}-bit" for e, b in bits_of.items())
    print(
        f"{which}, {size}², sRGB ({depth}), read noise 0.002, floor {floor:g}, from {start}; "
        f"mean over {len(materials)} map sets: " + ", ".join(keys)
    )
    for subset in subsets:
        for exposure in exposures:
            caps = [capture(t, rig, subset, exposure, bits_of[exposure], seed=i) for i, (_, t) in enumerate(materials)]
            for r in passes:
                cfg = ReconstructConfig(lm=lm.SolverConfig(reweight=r, noise_floor=floor, reweight_from=start))
                t0 = time.perf_counter()
                rows = []
                for (name, truth), cap in zip(materials, caps, strict=True):
                    res = reconstruct_capture(cap, cfg, nets)
                    row = map_scores(res.maps, truth)
                    row.update(rendering_scores(res.maps, truth, novel, rig.field_mm, "novel", flip=False))
                    rows.append(row)
                    print(
                        f"  {subset:>2} lights E={exposure:g} reweight {r} {name:16s} "
                        + " ".join(f"{row[k]:.4f}" for k in keys),
                        flush=True,
                    )
                mean = {k: sum(row[k] for row in rows) / len(rows) for k in keys}
                print(
                    f"{subset:>2} lights E={exposure:<8g} reweight {r}: "
                    + " ".join(f"{mean[k]:.4f}" for k in keys)
                    + f"  ({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )


if __name__ == "__main__":
    main()
