"""Every input is validated at the boundary: mutated files end in one line, never a traceback.

The fuzz tests start from valid documents (a capture with an inline calibration, a
capture whose calibration is a file, a ``flash`` capture with its rig as an object, a
rig file, a map set's ``mapset.json``, a weights file's metadata) and mutate them:
any value at any path replaced (huge integers, ``1e400``, ``NaN``, deep nesting, wrong
types, strings, empty lists, wrong lengths, non-UTF-8 bytes), keys deleted and added.
Each case must end in a :class:`MatscanError` of one line that names the file, or in
a valid result (finite tensors), and must leave the input files byte-identical.

``MATSCAN_FUZZ_EXAMPLES`` sets the examples per reader (default 80: the file runs in
well under a minute on two cores); runs are derandomized, so CI sees the same cases.
The regression tests below pin each crash the fuzzer found.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from safetensors.torch import load_file, save_file

from matscan.calibrate import (
    CALIBRATION_FORMAT,
    apply_calibration,
    check_chart,
    check_scales,
    colorchecker_linear,
    light_scales,
    sample_patches,
    weighted_median,
)
from matscan.capture import Capture, load_capture, write_capture
from matscan.errors import MatscanError
from matscan.imagefile import read_image, write_image
from matscan.jsonfile import loads_text, read_json
from matscan.mapset import MapSet, read_mapset, write_mapset
from matscan.rig import builtin_rig, load_rig, resolve_rig, rig_to_dict, save_rig
from matscan.train import TrainConfig, build_nets, export_weights, load_weights, save_checkpoint, training_record

EXAMPLES = int(os.environ.get("MATSCAN_FUZZ_EXAMPLES", "80"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)
BAD_BYTES = "@@not-utf8@@"


# --- mutation ------------------------------------------------------------------------


class Raw:
    """JSON text put into a document as it is (what Python values cannot express)."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return f"Raw({self.text[:40]!r})"


def to_text(obj: Any) -> str:
    """JSON text of a document that may hold :class:`Raw` pieces."""
    if isinstance(obj, Raw):
        return obj.text
    if isinstance(obj, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {to_text(v)}" for k, v in obj.items()) + "}"
    if isinstance(obj, list):
        return "[" + ", ".join(to_text(v) for v in obj) + "]"
    return json.dumps(obj)


def to_bytes(obj: Any) -> bytes:
    return to_text(obj).encode("utf-8", "surrogatepass").replace(BAD_BYTES.encode(), b"\xff\xfe\xc3")


def _nested(depth: int) -> Any:
    value: Any = 1
    for _ in range(depth):
        value = [value]
    return value


SPECIAL = [
    0,
    -1,
    1,
    7,
    23,
    24,
    2**31,
    -(2**63),
    0.5,
    -0.0,
    1e-300,
    1e300,
    -1e300,
    "",
    "x",
    "a\nb",
    "a\x00b",
    "../../nowhere.png",
    "dome24",
    "flash",
    "rig.json",
    "calibration.json",
    "led_00.png",
    "flat_00.exr",
    "matscan-calibration/1",
    "matscan-capture/1",
    "matscan-maps/1",
    "é",
    None,
    True,
    False,
    [],
    {},
    [1],
    [1, 2],
    [1, 2, 3],
    [0, 0, 0],
    [-1, -1, -1],
    [1, 2, 3, 4],
    ["a", "b", "c"],
    [1, None, 3],
    [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
    [[1, 0], [0, 1]],
    {"0": 0},
    {"0": -1.5},
    {"0": "x"},
    {"99": 1.0},
    {"0": 1e-9},
    {"a": 1},
    {"min_mm": "low", "max_mm": 1},
    _nested(40),
    Raw("1e400"),
    Raw("-1e400"),
    Raw("NaN"),
    Raw("Infinity"),
    Raw("-Infinity"),
    Raw("9" * 5000),
    Raw("9007199254740993"),
    Raw("[" * 3000 + "]" * 3000),
    Raw('"\\ud800"'),
    Raw(f'"{BAD_BYTES}"'),
    Raw('{"a": 1, "a": 2}'),
]
KEYS = ["extra", "light", "file", "intensity", "format", "rig", "field_mm", "calibration", "height", "files", "0", "x"]


def values() -> st.SearchStrategy[Any]:
    return st.one_of(
        st.sampled_from(SPECIAL).map(copy.deepcopy),  # a fresh copy: later mutations must not edit SPECIAL
        st.integers(-5, 30),
        st.floats(allow_nan=False, allow_infinity=False, width=64),
        st.text(max_size=8),
    )


def _paths(obj: Any, path: tuple = ()) -> list[tuple]:
    """Every path (keys and indices) into a document, the root included."""
    out = [path]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _paths(v, (*path, i))
    return out


def _get(obj: Any, path: tuple) -> Any:
    for p in path:
        obj = obj[p]
    return obj


def mutate(data: st.DataObject, doc: Any) -> Any:
    """``doc`` (a fresh copy) with one to three mutations drawn from ``data``."""
    doc = json.loads(json.dumps(doc))
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        paths = _paths(doc)
        path = data.draw(st.sampled_from(paths), label="path")
        op = data.draw(st.sampled_from(["replace", "replace", "replace", "delete", "add"]), label="op")
        if not path:
            if op == "replace":
                doc = data.draw(values(), label="root")
            continue
        parent, key = _get(doc, path[:-1]), path[-1]
        if op == "replace":
            parent[key] = data.draw(values(), label="value")
        elif op == "delete":
            del parent[key]
        else:
            target = _get(doc, path)
            if isinstance(target, dict):
                target[data.draw(st.sampled_from(KEYS), label="key")] = data.draw(values(), label="added")
            elif isinstance(target, list):
                target.append(data.draw(values(), label="appended"))
    return doc


# --- outcomes ------------------------------------------------------------------------


def digest(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder``."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def one_line_or_valid(call: Callable[[], Any], names: str, folder: Path, capfd: pytest.CaptureFixture) -> Any:
    """Run ``call``: a MatscanError must be one line naming ``names``, with nothing else on
    the terminal (no library chatter on stderr); the inputs must not change."""
    capfd.readouterr()
    before = digest(folder)
    try:
        result = call()
    except MatscanError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and "\r" not in msg, msg
        msg.encode("utf-8")  # printable by the CLI
        assert names in msg, msg
        result = None
    assert digest(folder) == before
    assert capfd.readouterr().err == ""
    return result


def finite_capture(cap: Capture) -> None:
    assert torch.isfinite(cap.linear()).all()
    for t in (cap.lights.position, cap.lights.intensity, cap.lights.axis, cap.lights.exponent, cap.lights.camera):
        assert torch.isfinite(t).all()
    assert all(np.isfinite(v) and v > 0 for v in cap.field_mm)
    assert all(isinstance(w, str) and "\n" not in w for w in cap.meta.get("warnings", []))


def _load_and_apply(folder: Path) -> Capture:
    cap = apply_calibration(load_capture(folder))
    finite_capture(cap)
    return cap


# --- the valid documents ---------------------------------------------------------------


def photos(n: int = 3, size: int = 8, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, size, size, generator=g) * 0.8 + 0.05


CALIBRATION = {
    "format": CALIBRATION_FORMAT,
    "colour_matrix": [[1.0, 0.02, 0.0], [0.0, 0.98, 0.01], [0.0, 0.0, 1.01]],
    "light_scales": {"0": 1.0, "5": 0.9, "17": 1.1},
    "flat_fields": {"0": "flat_00.exr"},
    "grey_albedo": 0.18,
    "exposure_s": 0.01,
    "led_level": 1.0,
}


def make_capture(root: Path, calibration_file: bool = False) -> Path:
    """A dome24 capture (3 photos, backlight, flat field) with its calibration inline or as a file."""
    folder = root / ("cap_file" if calibration_file else "cap_inline")
    back = {"green": photos(1, seed=1)[0], "blue": photos(1, seed=2)[0]}
    write_capture(folder, photos(), builtin_rig("dome24"), light_indices=[0, 5, 17], backlight=back)
    write_image(folder / "flat_00.exr", np.ones((8, 8, 1), np.float32), bits=32)
    doc = json.loads((folder / "capture.json").read_text())
    doc["simulation"] = {"noise": 0.01}
    doc["acquisition"] = {"camera": "virtual", "exposure_s": 0.005, "led_level": 0.5, "frames": 3}
    if calibration_file:
        (folder / "calibration.json").write_text(json.dumps(CALIBRATION))
        doc["calibration"] = "calibration.json"
    else:
        doc["calibration"] = CALIBRATION
    (folder / "capture.json").write_text(json.dumps(doc))
    return folder


def make_flash(root: Path) -> Path:
    """A flash capture (per-image geometry and intensity) with its rig as an object."""
    folder = root / "flash"
    geometry = [((-27.0, 34.0, 273.0), (-27.0, 34.0, 273.0)), ((10.0, 0.0, 250.0), (12.0, 0.0, 250.0))]
    write_capture(folder, photos(2), builtin_rig("flash"), geometry=geometry, field_mm=(68.5, 60.0))
    doc = json.loads((folder / "capture.json").read_text())
    doc["rig"] = rig_to_dict(builtin_rig("flash"))
    doc["images"][0]["intensity"] = [1.0, 0.9, 1.1]
    (folder / "capture.json").write_text(json.dumps(doc))
    return folder


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fuzz")
    out = {"inline": make_capture(root), "file": make_capture(root, True), "flash": make_flash(root)}
    save_rig(builtin_rig("dome24"), root / "rig.json")
    out["rig"] = root / "rig.json"
    g = torch.Generator().manual_seed(0)
    maps = MapSet(
        diffuse=torch.rand(3, 8, 8, generator=g),
        specular=torch.rand(3, 8, 8, generator=g) * 0.3,
        roughness=torch.rand(1, 8, 8, generator=g),
        normal=torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 8, 8).clone(),
        height=torch.randn(1, 8, 8, generator=g),
    )
    out["maps"] = write_mapset(root / "maps", maps)
    cfg = TrainConfig(preset="tiny")
    nets = build_nets(cfg)
    save_checkpoint(root / "ckpt.safetensors", nets, torch.optim.Adam(nets.parameters()), 3, cfg, 1.5)
    weights = root / "weights" / "w.safetensors"
    weights.parent.mkdir()
    out["weights"] = export_weights(root / "ckpt.safetensors", weights)
    return out


def _fuzz_file(data: st.DataObject, path: Path, doc: Any) -> None:
    path.write_bytes(to_bytes(mutate(data, doc)))


# --- the fuzz tests --------------------------------------------------------------------


@FUZZ
@given(data=st.data())
def test_fuzz_capture_json_with_inline_calibration(bases, capfd, data):
    folder = bases["inline"]
    path = folder / "capture.json"
    doc = json.loads(path.read_text())
    try:
        _fuzz_file(data, path, doc)
        one_line_or_valid(lambda: _load_and_apply(folder), str(folder), folder, capfd)
    finally:
        path.write_text(json.dumps(doc))


@FUZZ
@given(data=st.data())
def test_fuzz_calibration_file(bases, capfd, data):
    folder = bases["file"]
    path = folder / "calibration.json"
    doc = json.loads(path.read_text())
    try:
        _fuzz_file(data, path, doc)
        one_line_or_valid(lambda: _load_and_apply(folder), str(folder), folder, capfd)
    finally:
        path.write_text(json.dumps(doc))


@FUZZ
@given(data=st.data())
def test_fuzz_flash_capture_and_rig_object(bases, capfd, data):
    folder = bases["flash"]
    path = folder / "capture.json"
    doc = json.loads(path.read_text())
    try:
        _fuzz_file(data, path, doc)
        one_line_or_valid(lambda: _load_and_apply(folder), str(folder), folder, capfd)
    finally:
        path.write_text(json.dumps(doc))


def _rig_is_valid(path: Path) -> None:
    rig = load_rig(path)
    ls = rig.light_set()
    for t in (ls.position, ls.intensity, ls.axis, ls.exponent, ls.camera):
        assert torch.isfinite(t).all()
    assert resolve_rig(rig_to_dict(rig)) == rig


@FUZZ
@given(data=st.data())
def test_fuzz_rig_file(bases, capfd, data):
    path = bases["rig"]
    doc = json.loads(path.read_text())
    try:
        _fuzz_file(data, path, doc)
        one_line_or_valid(lambda: _rig_is_valid(path), str(path), path.parent, capfd)
    finally:
        path.write_text(json.dumps(doc))


def _maps_are_valid(folder: Path) -> None:
    for name, t in read_mapset(folder).present().items():
        assert torch.isfinite(t).all(), name


@FUZZ
@given(data=st.data())
def test_fuzz_mapset_json(bases, capfd, data):
    folder = bases["maps"]
    path = folder / "mapset.json"
    doc = json.loads(path.read_text())
    try:
        _fuzz_file(data, path, doc)
        one_line_or_valid(lambda: _maps_are_valid(folder), str(folder), folder, capfd)
    finally:
        path.write_text(json.dumps(doc))


def _mutate_metadata(data: st.DataObject, meta: dict[str, str]) -> dict[str, str]:
    """Metadata with JSON values mutated inside, or plain values replaced, deleted, added."""
    meta = dict(meta)
    key = data.draw(st.sampled_from(sorted(meta)), label="meta key")
    op = data.draw(st.sampled_from(["inside", "inside", "replace", "delete", "add"]), label="meta op")
    if op == "inside":
        text = to_text(mutate(data, json.loads(meta[key]) if meta[key][:1] in "{[" else meta[key]))
        meta[key] = text.replace(BAD_BYTES, "\ufffd")
    elif op == "replace":
        meta[key] = data.draw(st.sampled_from(["", "x", "1e400", "NaN", "-3", "1.5", "{}", "[]", "9" * 5000]))
    elif op == "delete":
        del meta[key]
    else:
        meta[data.draw(st.sampled_from(["init_networks", "init_step", "maps", "format", "x"]))] = data.draw(
            st.sampled_from(["", "{}", "diffuse", "3", '{"diffuse": {"steps": 1}}'])
        )
    return meta


@FUZZ
@given(data=st.data())
def test_fuzz_weights_metadata(bases, capfd, data):
    path = bases["weights"]
    original = path.read_bytes()
    tensors = load_file(str(path))
    meta = load_weights(path)[1]
    fuzzed = path.with_name("fuzzed.safetensors")
    try:
        save_file(tensors, str(fuzzed), metadata=_mutate_metadata(data, meta))

        def load() -> None:
            nets, got = load_weights(fuzzed)
            assert not nets.training
            json.dumps(training_record(got), allow_nan=False)

        one_line_or_valid(load, str(fuzzed), path.parent, capfd)
    finally:
        fuzzed.unlink(missing_ok=True)
    assert path.read_bytes() == original


# --- regressions: each crash the fuzzer found ------------------------------------------


def _capture(tmp_path: Path, mutate_doc: Callable[[dict], None], flash: bool = False) -> Path:
    folder = make_flash(tmp_path) if flash else make_capture(tmp_path)
    doc = json.loads((folder / "capture.json").read_text())
    mutate_doc(doc)
    (folder / "capture.json").write_bytes(to_bytes(doc))
    return folder


def _refused(folder: Path, words: str, call: Callable[[], Any] | None = None) -> str:
    """The one-line error of reading ``folder`` (or ``call``); the folder stays byte-identical."""
    before = digest(folder)
    with pytest.raises(MatscanError, match=words) as info:
        (call or (lambda: apply_calibration(load_capture(folder))))()
    assert "\n" not in str(info.value)
    assert digest(folder) == before
    return str(info.value)


def _set(*path: Any, value: Any) -> Callable[[dict], None]:
    def edit(doc: dict) -> None:
        _get(doc, path[:-1])[path[-1]] = value

    return edit


@pytest.mark.parametrize(
    "edit, words",
    [
        (
            _set("images", 1, "light", value=Raw("9" * 5000)),
            r"capture\.json: images\[1\]\.light: the integer 9+… \(5000",
        ),
        (_set("field_mm", value=[Raw("1e400"), 60]), r"capture\.json: field_mm\[0\]: the number 1e400 is out of range"),
        (_set("field_mm", value=[Raw("Infinity"), 60]), r"capture\.json: field_mm\[0\]: Infinity is not a number"),
        (_set("field_mm", value=[1e300, 60]), r"capture\.json: field_mm\[0\]: 1e\+300 is out of range"),
        (_set("simulation", value=_nested(40)), r"capture\.json: nested deeper than 32 levels"),
        (_set("simulation", value=Raw("[" * 5000 + "]" * 5000)), r"capture\.json: nested deeper than 32 levels"),
        (_set("images", 0, "file", value="led\n00.png"), r"capture\.json: images\[0\]: file: 'led\\n00\.png' is not"),
        (
            _set("calibration", "colour_matrix", value=[["a", 0, 0], [0, 1, 0], [0, 0, 1]]),
            r"calibration\.colour_matrix\[0\]: expected 3 finite",
        ),
        (_set("calibration", "colour_matrix", value=[[1, 0], [0, 1]]), r"calibration\.colour_matrix: .*3 × 3"),
        (_set("calibration", "light_scales", value={"0": "x"}), r"calibration\.light_scales\['0'\]: expected a fin"),
        (_set("calibration", "light_scales", value=[1, 2]), r"calibration\.light_scales: expected an object"),
        (_set("calibration", "light_scales", value={"24": 1.0}), r"light_scales: key '24' is not a light of rig"),
        (_set("calibration", "light_scales", value={"5": 0}), r"light_scales\['5'\]: light 5 has scale 0"),
        (_set("calibration", "light_scales", value={"5": -2}), r"light_scales\['5'\]: light 5 has scale -2"),
        (_set("calibration", "light_positions_mm", value=[1, 2]), r"light_positions_mm: expected an object"),
        (_set("calibration", "light_positions_mm", value={"0": [1, 2]}), r"mm\['0'\]: expected 3 finite numbers"),
        (_set("calibration", "light_positions_mm", value={"24": [0, 0, 9]}), r"key '24' is not a light of rig"),
        (
            _set("calibration", "light_positions_mm", value={"3": [80, 0, -5]}),
            r"light_positions_mm\['3'\]: light 3 would be at z = -5 mm, not above the sample plane",
        ),
        (_set("calibration", "flat_fields", value=123), r"calibration\.flat_fields: expected an object"),
        (_set("calibration", "flat_fields", value={"0": 7}), r"calibration\.flat_fields\['0'\]: expected a file"),
        (_set("calibration", "flat_fields", value={"0": "gone.exr"}), r"flat_fields\['0'\]: no such file"),
        (_set("calibration", "flat_fields", value={"0": "capture.json"}), r"capture\.json: unsupported image type"),
    ],
)
def test_capture_and_calibration_regressions(tmp_path, edit, words):
    folder = _capture(tmp_path, edit)
    msg = _refused(folder, words)
    assert str(folder) in msg


@pytest.mark.parametrize(
    "value, words",
    [
        ("bright", r"images\[0\]\.intensity: expected 3 finite numbers, got 'bright'"),
        ([1, 1], r"images\[0\]\.intensity: expected 3 finite numbers, got \[1, 1\]"),
        ([1, 1, -1], r"images\[0\]\.intensity\[2\]: -1 is out of range"),
        ([1, Raw("NaN"), 1], r"images\[0\]\.intensity\[1\]: NaN is not a number"),
    ],
)
def test_flash_intensity_regressions(tmp_path, value, words):
    folder = _capture(tmp_path, _set("images", 0, "intensity", value=value), flash=True)
    _refused(folder, r"capture\.json: " + words)


def test_a_light_scale_of_zero_is_refused_not_turned_into_black_maps(tmp_path):
    folder = make_capture(tmp_path, calibration_file=True)
    cal = dict(CALIBRATION, light_scales={"0": 1.0, "5": 0.0, "17": 1.0})
    (folder / "calibration.json").write_text(json.dumps(cal))
    msg = _refused(folder, r"calibration\.json: light_scales\['5'\]: light 5 has scale 0; a scale must be positive")
    assert str(folder / "calibration.json") in msg


@pytest.mark.parametrize(
    "flat, words",
    [
        (np.zeros((8, 8, 1)), r"flat field's median is 0; a flat field is a relative gain of mean 1"),
        (np.full((8, 8, 1), 200.0), r"flat field's median is 200;"),  # a white card's raw codes
        (np.full((8, 8, 1), -1.0), r"flat field holds negative values \(down to -1\)"),
    ],
)
def test_a_flat_field_far_from_mean_one_is_refused(tmp_path, flat, words):
    """The photos are divided by a light's flat field: an all-zero one (clamped to 1e-3)
    made that light's photos 1000 times brighter, silently."""
    folder = make_capture(tmp_path, calibration_file=True)
    write_image(folder / "flat_00.exr", flat.astype(np.float32), bits=32)
    msg = _refused(folder, r"flat_00\.exr: " + words)
    assert str(folder / "flat_00.exr") in msg


def test_a_flat_field_of_mean_one_is_applied(tmp_path):
    # the check's other side: a light's photo is divided by its flat field, pixel by pixel
    folder = make_capture(tmp_path, calibration_file=True)
    even = apply_calibration(load_capture(folder)).linear(positions=[0])[0]  # flat_00.exr is all ones
    flat = np.linspace(0.5, 1.5, 64, dtype=np.float32).reshape(8, 8, 1)
    write_image(folder / "flat_00.exr", flat, bits=32)
    uneven = apply_calibration(load_capture(folder)).linear(positions=[0])[0]
    expected = np.broadcast_to(1 / flat[..., 0], (3, 8, 8))
    np.testing.assert_allclose((uneven / even).numpy(), expected, rtol=2e-3)


def test_an_unknown_acquisition_key_is_warned_of(tmp_path):
    """``exposure`` for ``exposure_s`` drops the calibration's exposure ratio: said, not silent."""
    folder = make_capture(tmp_path)
    doc = json.loads((folder / "capture.json").read_text())
    assert "warnings" not in load_capture(folder).meta
    doc["acquisition"] = {"camera": "virtual", "exposure": 0.005, "led_level": 0.5}
    (folder / "capture.json").write_text(json.dumps(doc))
    (warning,) = load_capture(folder).meta["warnings"]
    assert re.fullmatch(r".*capture\.json: acquisition: key 'exposure' not known to matscan, ignored .*", warning)


def test_non_utf8_rig_and_mapset_files(tmp_path, bases):
    rig = tmp_path / "rig.json"
    rig.write_bytes(json.dumps(rig_to_dict(builtin_rig("dome24"))).encode().replace(b"dome24", b"dome\xff24"))
    _refused(tmp_path, r"rig\.json: not UTF-8 text \(byte \d+\); save it as UTF-8", lambda: load_rig(rig))
    maps = tmp_path / "maps"
    write_mapset(maps, read_mapset(bases["maps"]))
    (maps / "mapset.json").write_bytes(b'{"format": "matscan-maps/1", "x": "\xff"}')
    _refused(maps, r"mapset\.json: not UTF-8 text", lambda: read_mapset(maps))


@pytest.mark.parametrize(
    "doc, words",
    [
        ([1, 2], r"mapset\.json: expected an object, got a list"),
        ({"height": {"min_mm": "low", "max_mm": 1.0}}, r"mapset\.json: height\.min_mm: expected a finite number"),
        ({"height": {"min_mm": 1.0, "max_mm": 0.0}}, r"mapset\.json: height: max_mm 0 is below min_mm 1"),
        ({"height": [0, 1]}, r"mapset\.json: height: expected an object, got a list"),
        ({"files": {"diffuse": "diffuse.png"}}, r"mapset\.json: files\.diffuse: expected an object"),
        ({"size": "big"}, r"mapset\.json: size: expected a non-empty list"),
        ({"format": "other/1"}, r"mapset\.json: format: 'other/1' is not one of matscan-maps/1"),
    ],
)
def test_mapset_json_regressions(tmp_path, bases, doc, words):
    maps = tmp_path / "maps"
    write_mapset(maps, read_mapset(bases["maps"]))
    (maps / "mapset.json").write_text(json.dumps(doc))
    _refused(maps, words, lambda: read_mapset(maps))


def test_rig_numbers_must_be_finite_and_in_range(tmp_path):
    for edit, words in [
        (lambda d: d["lights"][0].update(exponent=1e300), r"lights\[0\]\.exponent: 1e\+300 is out of range"),
        (lambda d: d["lights"][1].update(position_mm=[1e300, 0, 10]), r"lights\[1\]\.position_mm\[0\]: 1e\+300"),
        (
            lambda d: d["lights"][2].update(aim_mm=[v + 1e-9 for v in d["lights"][2]["position_mm"]]),
            r"lights\[2\]\.aim_mm: equals the light's position",
        ),
        (lambda d: d["camera"].update(up=[0, 0, 0]), r"camera\.up: must not be the zero vector"),
        (lambda d: d.update(name="a\nb"), r"name: 'a\\nb' holds control"),
    ]:
        data = rig_to_dict(builtin_rig("dome24"))
        edit(data)
        path = tmp_path / "rig.json"
        path.write_text(json.dumps(data))
        msg = _refused(tmp_path, words, lambda p=path: load_rig(p))
        assert str(path) in msg


def test_a_fully_saturated_grey_card_names_the_light(tmp_path):
    write_capture(tmp_path / "grey", torch.ones(2, 3, 8, 8) * 2, builtin_rig("dome24"), light_indices=[3, 9])
    grey = load_capture(tmp_path / "grey")
    with pytest.raises(MatscanError, match=r"every pixel saturated under light 3; lower the exposure"):
        light_scales(grey)
    with pytest.raises(MatscanError, match="no values"):
        weighted_median(torch.zeros(0), torch.zeros(0))


def test_library_messages_stay_off_the_terminal(tmp_path, capfd):
    ok = tmp_path / "ok.png"
    write_image(ok, np.full((8, 8, 3), 0.5))
    data = ok.read_bytes()
    bad = tmp_path / "bad.png"
    bad.write_bytes(data[:40] + b"\x00\x00" + data[42:])  # a damaged chunk header: libpng complains
    before = digest(tmp_path)
    for name, blob in [("bad.png", None), ("cut.png", data[:60]), ("bad.exr", b"v/1\x01" + bytes(64))]:
        if blob is not None:
            (tmp_path / name).write_bytes(blob)
            before = digest(tmp_path)
        with pytest.raises(MatscanError, match=rf"{name.replace('.', '[.]')}: cannot read as") as info:
            read_image(tmp_path / name)
        assert "\n" not in str(info.value)
    assert digest(tmp_path) == before
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_json_reader_limits(tmp_path):
    path = tmp_path / "x.json"
    for text, words in [
        ('{"a": NaN}', r"x\.json: a: NaN is not a number"),
        ('{"a": [1, 1e400]}', r"x\.json: a\[1\]: the number 1e400 is out of range"),
        ('{"a": ' + "7" * 5000 + "}", r"x\.json: a: the integer 7+… \(5000 digits\) is too large"),
        ('{"a": 9007199254740993}', r"too large \(at most 2\*\*53"),
        ("[" * 100000, r"x\.json: nested deeper than 32 levels"),
        ('{"a": 1, "a": 2}', r"x\.json: key 'a' appears twice"),
        ('"\\udc00"', r"x\.json: value: holds an unpaired surrogate"),
        ("{", r"x\.json: not valid JSON \(line 1"),
    ]:
        path.write_text(text)
        with pytest.raises(MatscanError, match=words) as info:
            read_json(path)
        assert "\n" not in str(info.value)
    path.write_bytes(b"\xef\xbb\xbf" + b'{"a": 9007199254740992}')  # a UTF-8 byte-order mark is accepted
    assert read_json(path) == {"a": 2**53}
    with pytest.raises(MatscanError, match=r"meta: not valid JSON"):
        loads_text("{", "meta")


def test_calibration_warnings(tmp_path):
    folder = make_capture(tmp_path)
    doc = json.loads((folder / "capture.json").read_text())
    doc["calibration"] = dict(CALIBRATION, light_scales={"0": 1.0, "5": 5000.0})
    (folder / "capture.json").write_text(json.dumps(doc))
    warnings = apply_calibration(load_capture(folder)).meta["warnings"]
    assert any("implausible light scale (light 5: 5000" in w for w in warnings)
    assert any(w.startswith("light 17 has no scale in capture.json's calibration; they are used") for w in warnings)
    assert check_scales({"0": 1.0}) == []
    doc["calibration"] = dict(CALIBRATION, light_scales={"0": 1.0})
    (folder / "capture.json").write_text(json.dumps(doc))
    assert any("lights 5, 17 have no scale" in w for w in apply_calibration(load_capture(folder)).meta["warnings"])


def test_chart_checks():
    chart = colorchecker_linear()
    assert check_chart(chart) == []
    grey = chart.mean(dim=1, keepdim=True).expand(24, 3)
    assert "the photo shows no colour chart" in check_chart(grey)[0]
    assert "does not run from white to black" in check_chart(chart.flip(0))[0]
    photo = torch.rand(3, 40, 60)
    with pytest.raises(MatscanError, match=r"corners: patch 1 of the chart falls at .* outside the 60×40 photo"):
        sample_patches(photo, [(-30, -20), (60, 0), (60, 40), (0, 40)])
    with pytest.raises(MatscanError, match=r"corners\[1\]: expected 2 finite numbers"):
        sample_patches(photo, [(0, 0), (float("nan"), 0), (60, 40), (0, 40)])
    assert sample_patches(photo).shape == (24, 3)


def test_weights_metadata_regressions(bases, tmp_path):
    tensors = load_file(str(bases["weights"]))
    meta = load_weights(bases["weights"])[1]
    path = tmp_path / "w.safetensors"
    for key, value, words in [
        ("net_config", '{"base": 1e400}', r"net_config: base: the number 1e400 is out of range"),
        ("net_config", '{"base": 100000}', r"net_config\.base: 100000 is out of range"),
        ("net_config", '{"photo_statistic": []}', r"net_config\.photo_statistic: expected a non-empty string"),
        ("net_config", '{"base": 12}', r"weights do not fit the networks its metadata describes"),
        ("train_config", '{"preset": ["tiny"]}', r"train_config\.preset: expected a non-empty string"),
        ("train_config", '{"maps": "diffuse"}', r"train_config\.maps: expected a non-empty list"),
        ("train_config", '{"rig": "0"}', r"train_config\.rig: rig: '0' is not a built-in rig"),
        ("maps", "diffuse,shiny", r"maps\[1\]: 'shiny' is not one of"),
        ("step", "many", r"step: not valid JSON"),
        ("networks", '{"diffuse": {"steps": -1}}', r"networks: no record of the specular network"),
    ]:
        save_file(tensors, str(path), metadata={**meta, key: value})
        msg = _refused(tmp_path, words, lambda: load_weights(path))
        assert str(path) in msg
