"""Same seed, same inputs → the same artifacts as the references in tests/reference/.

The references were first written by main at e98c111, before train/ was split into layers (issue 9),
and are rewritten (`python tests/test_reference.py`) only by a change that means to alter what is
written, whose commit says why. `digests.json` holds, for every bundle (each method and layout, a plain
and a sealed payload), the SHA-256 of each of its tensors and its metadata as data (the settings it
records, tiles, cameras), and the SHA-256 of every other artifact (a fitted scene's files and an exported
ONNX file). Each artifact is rebuilt here from seeds alone: a bundle's noise must match byte for byte and
its metadata must equal the reference's as parsed JSON, so a setting renamed or dropped is a readable
difference in the reference, not a different digest; the other files must match byte for byte.
Torch runs one thread, so the bytes do not depend on the machine's core count. They do depend on the float
kernels the CPU takes (vector width and FMA use differ between an AVX2 and an AVX-512 machine, and between
vendors' library paths), so the references are kept per kind of machine, `tests/reference/VENDOR-CAPABILITY/`
(`float_kernels`), each written on such a machine from the same code; a machine of a kind without references
skips, saying which. The ONNX file also depends on the onnx package's serialisation, so that comparison skips
under another torch than the reference's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import platform
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open

from helpers import make_tiny_scene  # run as a script, this file's folder is sys.path[0]

CPU = torch.device("cpu")


def float_kernels() -> str:
    """The kind of machine bytes are reproducible on: its CPU vendor and torch's vector capability."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.is_file() else []
    vendor = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("vendor_id")), platform.machine())
    return f"{vendor}-{torch.backends.cpu.get_cpu_capability()}"


REFERENCES = Path(__file__).resolve().parent / "reference"
REFERENCE = REFERENCES / float_kernels()


@contextlib.contextmanager
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def build_artifacts(folder: Path) -> dict[str, Path]:
    """Every artifact the comparison covers, written into `folder` from fixed seeds."""
    from noisenerf.export.onnx_export import export_scene
    from noisenerf.runtime.payload import Record
    from noisenerf.runtime.sealing import ScryptParams, new_seal
    from noisenerf.train.scene.datasets import load_dataset
    from noisenerf.train.scene.fit import PRESETS, Budget, fit
    from noisenerf.train.hide.plan import HideConfig
    from noisenerf.train.hide.run import hide
    from noisenerf.train.scene.occupancy import OccupancyConfig
    from noisenerf.train.hide.settings import PaperSettings, recipe
    from noisenerf.train.hide.payload import hide_payload
    from noisenerf.train.scene.procedural import write_procedural_dataset

    artifacts = {}
    secret = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    with one_thread():
        scene = bundles_scene()
        for name, config in {
            "exact_compact.bundle": HideConfig(tile_size=16),
            "exact_ray.bundle": HideConfig(layout="ray", tile_size=16, view=2, seed=5),
            "paper_sample.bundle": HideConfig(method="paper", tile_size=16, n_samples=8,
                                              settings=(PaperSettings(iters=6, record_at=(3, 6)),)),
            "paper_text_ray.bundle": HideConfig(method="paper", layout="ray", tile_size=16, n_samples=8,
                                                settings=(recipe("paper", iters=6,
                                                                mu=3, record_at=(6,)),)),
        }.items():
            part = secret[:18, :20] if config.method == "paper" else secret
            hide(scene, part, folder / name, config, CPU)
            artifacts[name] = folder / name
        payload_config = HideConfig(tile_size=16)
        hide_payload(scene, Record("file", b"the eagle lands at noon\n", b"note.txt"), folder / "payload.bundle",
                     payload_config, CPU)
        hide_payload(scene, Record("file", b"the eagle lands at noon\n", b"note.txt"), folder / "sealed.bundle",
                     payload_config, CPU, passphrase=b"reference",
                     seal=new_seal(ScryptParams(log2_n=10, r=8, p=1), salt=bytes(range(16)), nonce=bytes(range(12))))
        artifacts["payload.bundle"] = folder / "payload.bundle"
        artifacts["sealed.bundle"] = folder / "sealed.bundle"

        data = write_procedural_dataset(folder / "data", size=24, n_train=8, n_val=1, n_test=1)
        tiny = dataclasses.replace(PRESETS["small"], batch_rays=128, n_samples=16, warmup_rays=64, warmup_samples=8,
                                   empty_points=64, precrop_steps=4,
                                   occupancy=OccupancyConfig(resolution=16, warmup_steps=8, update_every=4))
        fit(load_dataset(data), folder / "scene", tiny, Budget(iters=12), CPU, curve_seconds=0)
        for name in ("weights.safetensors", "scene.json", "occupancy.safetensors"):
            artifacts[f"scene/{name}"] = folder / "scene" / name

        fine = make_tiny_scene(seed=3, fine=True)
        fine.save(folder / "fine_scene")
        export_scene(folder / "fine_scene", folder / "model.onnx")
        artifacts["model.onnx"] = folder / "model.onnx"
    return artifacts


BUNDLES = ("exact_compact.bundle", "exact_ray.bundle", "paper_sample.bundle", "paper_text_ray.bundle",
           "payload.bundle", "sealed.bundle")
FILES = ("scene/weights.safetensors", "scene/scene.json", "scene/occupancy.safetensors", "model.onnx")


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def bundles_scene():
    """The scene every reference bundle is hidden in."""
    return make_tiny_scene(seed=0, width=64, depth=4)


def bundle_record(path: Path) -> dict:
    """A bundle as the references keep it: its tensors' digests (dtype, shape and bytes) and its metadata, the
    bundle's JSON parsed, as format 4 wrote it: a masked bundle (format 5) is recorded unmasked, without its mask
    object and as format 4, and a seal's MAC (over the bytes as written, masked) is left out. The mask and the MAC
    are functions of what is recorded and of the hide's identity: tests/test_masking.py checks the mask, and that
    the same seed gives the same bytes; tests/test_payload.py the MAC."""
    from noisenerf.runtime.bundle import METADATA_KEY
    from noisenerf.runtime.masking import checked_mask, mask_key, xor_masked
    from noisenerf.runtime.sealing import MAC_KEY

    with safe_open(path, "np") as file:
        metadata = {key: json.loads(value) if key == METADATA_KEY else value for key, value in file.metadata().items()
                    if key != MAC_KEY}
        stored = {name: file.get_tensor(name) for name in file.keys()}
    meta = metadata[METADATA_KEY]
    if meta.get("mask") is not None:
        stored = xor_masked(stored, mask_key(bundles_scene().digests().mask_secret, checked_mask(meta.pop("mask"))))
        meta["format_version"] = 4
    tensors = {name: sha256(f"{value.dtype.str} {value.shape}".encode() + value.tobytes())
               for name, value in stored.items()}
    return {"tensors": tensors, "metadata": metadata}


def records(artifacts: dict[str, Path]) -> dict:
    """What digests.json holds for these artifacts."""
    return {"torch": torch.__version__, "bundles": {name: bundle_record(artifacts[name]) for name in BUNDLES},
            "sha256": {name: sha256(artifacts[name].read_bytes()) for name in FILES}}


@pytest.fixture(scope="module")
def artifacts(tmp_path_factory):
    if not REFERENCE.is_dir():
        kinds = sorted(path.name for path in REFERENCES.iterdir() if path.is_dir())
        pytest.skip(f"no references for this machine's float kernels ({REFERENCE.name}; kept: {', '.join(kinds)}); "
                    f"`python tests/test_reference.py` writes them")
    return build_artifacts(tmp_path_factory.mktemp("reference"))


@pytest.fixture(scope="module")
def reference(artifacts):
    return json.loads((REFERENCE / "digests.json").read_text())


@pytest.mark.parametrize("name", BUNDLES)
def test_bundle_noise_is_byte_identical_to_the_reference(artifacts, reference, name):
    assert bundle_record(artifacts[name])["tensors"] == reference["bundles"][name]["tensors"]


@pytest.mark.parametrize("name", BUNDLES)
def test_bundle_metadata_equals_the_reference_as_data(artifacts, reference, name):
    from noisenerf.runtime.sealing import MAC_KEY

    kept = {key: value for key, value in reference["bundles"][name]["metadata"].items() if key != MAC_KEY}
    assert bundle_record(artifacts[name])["metadata"] == kept


@pytest.mark.parametrize("name", ["scene/weights.safetensors", "scene/scene.json", "scene/occupancy.safetensors"])
def test_artifact_matches_the_reference_digest(artifacts, reference, name):
    assert sha256(artifacts[name].read_bytes()) == reference["sha256"][name]


def test_onnx_file_matches_the_reference_digest(artifacts, reference):
    if torch.__version__ != reference["torch"]:
        pytest.skip(f"the ONNX reference was exported by torch {reference['torch']}, this is {torch.__version__}")
    assert sha256(artifacts["model.onnx"].read_bytes()) == reference["sha256"]["model.onnx"]


if __name__ == "__main__":  # writes the references (see the module docstring for when)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        REFERENCE.mkdir(exist_ok=True)
        (REFERENCE / "digests.json").write_text(json.dumps(records(build_artifacts(Path(tmp))), indent=1,
                                                           sort_keys=True) + "\n")
