"""The typed model spec: every checkpoint written so far reads into it and back unchanged."""
from pathlib import Path

import pytest
import torch

from gns.spec import Floor, ModelSpec, SpecError
from gns.checkpoint import CheckpointError, read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = sorted((ROOT / "gns" / "models").glob("*.pt")) + [ROOT / "tests" / "data" / "gns_movi_a_small.pt"]


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and (list(map(type, a)) == list(map(type, b)) if isinstance(a, list) else True) and a == b


@pytest.mark.parametrize("path", CHECKPOINTS, ids=lambda p: p.name)
def test_every_shipped_spec_round_trips(path):
    stored = torch.load(path, map_location="cpu", weights_only=True)["spec"]
    spec = ModelSpec.from_dict(stored)
    back = spec.to_dict()
    # the keys it holds come back equal, of the same types, in the same order; older checkpoints
    # lack some keys, which come back with their defaults
    assert _same(stored, {k: back[k] for k in stored})
    assert set(back) - set(stored) <= {"collision_edges", "collision_features"}
    assert ModelSpec.from_dict(back) == spec
    assert spec.frame_rate > 0 and len(spec.gravity) == 3 and isinstance(spec.floor, Floor)


def test_derived_quantities_are_those_the_simulator_always_used():
    spec = ModelSpec.from_dict(torch.load(CHECKPOINTS[0], weights_only=True)["spec"])
    g, rate = spec.to_dict()["gravity"], spec.to_dict()["frame_rate"]
    assert spec.gravity_step == float(torch.tensor(g).norm()) / rate ** 2
    assert torch.equal(spec.gravity_per_frame, torch.tensor(g, dtype=torch.float64) / rate ** 2)
    assert spec.floor_z == 0.0 and ModelSpec(materials_vary=True).gravity_step is None


def test_a_spec_without_frame_rate_is_one_clear_error(tmp_path):
    ckpt = torch.load(CHECKPOINTS[-1], weights_only=True)
    del ckpt["spec"]["frame_rate"]
    with pytest.raises(SpecError, match=r"^model spec lacks 'frame_rate'$"):
        ModelSpec.from_dict(ckpt["spec"])
    torch.save(ckpt, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="bad.pt: model spec lacks 'frame_rate'") as e:
        read_checkpoint(tmp_path / "bad.pt")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("change, message", [
    ({"gravity": [0.0, -10.0]}, "gravity is not 3 numbers"),
    ({"floor": {"height": 0.0}}, "floor .* needs 'z' and has unknown 'height'"),
    ({"shapes": "cube"}, "shapes is not a list of names"),
    ({"colour": "red"}, "unknown key.* 'colour'"),
])
def test_a_malformed_spec_names_the_key(change, message):
    stored = torch.load(CHECKPOINTS[-1], weights_only=True)["spec"]
    with pytest.raises(SpecError, match=message):
        ModelSpec.from_dict({**stored, **change})
