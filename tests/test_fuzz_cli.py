"""Fuzzing the command line with broken inputs (issue 27): random bytes, truncated and mutated
TIFFs, RPC files and GeoJSON AOIs. Every case must end with exit 0 (a mutation that leaves the
input valid) or exit 2 with one error line on stderr (warnings may precede it), never a
traceback, and a failed run must leave nothing in --out.

The cases are drawn from a seeded generator, so a failure names a case that can be replayed
(``FUZZ_SEED`` and the case index in the assertion message).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from satsweep.cli import main

FUZZ_SEED = 2027
# Cases per kind of input. The camera command reads images, RPCs and AOIs as the reconstruction
# does but stops after the camera fit (a valid case costs ~0.2 s); the reconstruction and the
# evaluation get fewer cases of their own inputs.
CAMERA_CASES = 220
RECONSTRUCT_CASES = 24
EVALUATE_CASES = 60
# Bytes at the start of a TIFF that hold its header and first IFD (where a flipped byte breaks
# the layout rather than a pixel).
HEADER_BYTES = 1024
# The small scene's altitude range (m), widened.
ALT = ("90", "170")


@pytest.fixture(scope="module")
def inputs(synthetic_scene, tmp_path_factory):
    """The two views of a 96 px town, each as a TIFF without RPC tag plus an _RPC.TXT sidecar,
    and the AOI as GeoJSON."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import write_rpc_txt
    from satsweep.io.geotiff import write_tiff
    from satsweep.io.images import read_image

    scene = synthetic_scene(seed=3, n_views=2, size_px=96, gsd_m=0.5)
    folder = tmp_path_factory.mktemp("fuzz_inputs")
    images, sidecars = [], []
    for v in scene.views:
        name = Path(v.image).stem
        image = folder / f"{name}.tif"
        write_tiff(image, read_image(v.image))
        write_rpc_txt(folder / f"{name}_RPC.TXT", RPCModel.from_image(v.image))
        images.append(image)
        sidecars.append(folder / f"{name}_RPC.TXT")
    a = scene.aoi
    ring = [[a.lon_min, a.lat_min], [a.lon_max, a.lat_min], [a.lon_max, a.lat_max],
            [a.lon_min, a.lat_max], [a.lon_min, a.lat_min]]
    aoi = folder / "aoi.geojson"
    aoi.write_text(json.dumps({"type": "Polygon", "coordinates": [ring]}))
    return {"images": images, "sidecars": sidecars, "aoi": aoi, "truth": Path(scene.truth_dsm)}


def _mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """One of: random bytes, a truncation, flipped bytes in the header, a zeroed span."""
    kind = rng.integers(4)
    if kind == 0:
        return rng.integers(0, 256, rng.integers(0, 2048), dtype=np.uint8).tobytes()
    if kind == 1:
        return data[:rng.integers(0, len(data))]
    buf = bytearray(data)
    if kind == 2:
        for _ in range(rng.integers(1, 8)):
            buf[rng.integers(0, min(HEADER_BYTES, len(buf)))] = int(rng.integers(0, 256))
        return bytes(buf)
    start = int(rng.integers(0, len(buf)))
    stop = min(len(buf), start + int(rng.integers(1, 4096)))
    buf[start:stop] = bytes(stop - start)
    return bytes(buf)


def _mutate_text(text: str, rng: np.random.Generator) -> str:
    """One of: lines deleted, a number replaced by junk, a truncation, junk inserted."""
    lines = text.splitlines()
    kind = rng.integers(4)
    if kind == 0 and lines:
        for _ in range(rng.integers(1, 4)):
            if lines:
                lines.pop(int(rng.integers(0, len(lines))))
        return "\n".join(lines)
    if kind == 1 and lines:
        junk = ["nan", "inf", "-", "1e999", "abc", "", "0", "1,2", "[]", "null", "{", "\x00"]
        i = int(rng.integers(0, len(lines)))
        tokens = lines[i].split()
        if tokens:
            tokens[int(rng.integers(0, len(tokens)))] = junk[int(rng.integers(0, len(junk)))]
        lines[i] = " ".join(tokens)
        return "\n".join(lines)
    if kind == 2:
        return text[:int(rng.integers(0, max(len(text), 1)))]
    at = int(rng.integers(0, max(len(text), 1)))
    return text[:at] + "".join(chr(int(c)) for c in rng.integers(32, 127, 20)) + text[at:]


def _check(rc: int, err: str, out: Path, case: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err, f"{case}: traceback\n{err}"
    assert rc in (0, 2), f"{case}: exit {rc}\n{err}"
    if rc == 2:
        errors = [ln for ln in lines if ln.startswith("satsweep: error:")]
        others = [ln for ln in lines if not ln.startswith(("satsweep: error:", "warning: ",
                                                            "satsweep: warning:"))]
        assert len(errors) == 1 and lines[-1] == errors[0] and not others, f"{case}:\n{err}"
        assert not out.exists() or not any(out.iterdir()), f"{case}: left {list(out.iterdir())}"


def _case_files(inputs, folder: Path, rng: np.random.Generator) -> tuple[list[str], str]:
    """Copies of the inputs with one of them broken: (image paths, --aoi value)."""
    folder.mkdir()
    images = []
    for image, sidecar in zip(inputs["images"], inputs["sidecars"]):
        shutil.copy(image, folder / image.name)
        shutil.copy(sidecar, folder / sidecar.name)
        images.append(folder / image.name)
    aoi = folder / "aoi.geojson"
    shutil.copy(inputs["aoi"], aoi)
    target = rng.integers(3)
    which = int(rng.integers(len(images)))
    if target == 0:
        images[which].write_bytes(_mutate_bytes(images[which].read_bytes(), rng))
    elif target == 1:
        side = folder / inputs["sidecars"][which].name
        side.write_text(_mutate_text(side.read_text(), rng))
    else:
        aoi.write_text(_mutate_text(aoi.read_text(), rng))
    return [str(p) for p in images], str(aoi)


def test_fuzzed_inputs_to_the_cameras_command(inputs, tmp_path, capsys):
    rng = np.random.default_rng(FUZZ_SEED)
    for k in range(CAMERA_CASES):
        images, aoi = _case_files(inputs, tmp_path / f"case{k}", rng)
        out = tmp_path / f"out{k}"
        rc = main(["cameras", *images, "--aoi", aoi, "--alt-range", *ALT, "--out", str(out),
                   "--grid", "8", "8", "4"])
        _check(rc, capsys.readouterr().err, out, f"seed {FUZZ_SEED} cameras case {k}")


def test_fuzzed_inputs_to_reconstruct(inputs, tmp_path, capsys):
    rng = np.random.default_rng(FUZZ_SEED + 1)
    fast = tmp_path / "fast.toml"
    fast.write_text("[camera]\ngrid_size = [10, 10, 4]\n")
    for k in range(RECONSTRUCT_CASES):
        images, aoi = _case_files(inputs, tmp_path / f"case{k}", rng)
        out = tmp_path / f"out{k}"
        rc = main(["reconstruct", *images, "--aoi", aoi, "--alt-range", *ALT, "--out", str(out),
                   "--quiet", "--config", str(fast), "--mrf", "none", "--adjust", "off"])
        _check(rc, capsys.readouterr().err, out, f"seed {FUZZ_SEED + 1} reconstruct case {k}")


def test_fuzzed_dsms_to_evaluate(inputs, tmp_path, capsys):
    rng = np.random.default_rng(FUZZ_SEED + 2)
    truth = inputs["truth"].read_bytes()
    for k in range(EVALUATE_CASES):
        pred, ref = tmp_path / f"pred{k}.tif", tmp_path / f"truth{k}.tif"
        pred.write_bytes(_mutate_bytes(truth, rng) if rng.random() < 0.5 else truth)
        ref.write_bytes(_mutate_bytes(truth, rng) if rng.random() < 0.5 else truth)
        out = tmp_path / f"eval{k}"
        rc = main(["evaluate", str(pred), str(ref), "--out", str(out)])
        captured = capsys.readouterr()
        _check(rc, captured.err, out, f"seed {FUZZ_SEED + 2} evaluate case {k}")

