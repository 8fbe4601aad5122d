"""pipelines/rigid_share.py: the split of a one-step error into what shape matching keeps and
what it throws away."""
import json

import pytest
import torch
from gns_fixtures import write_toss_dataset

from gns.train import train
from pipelines.rigid_share import main, rigid_projection, rigid_share
from test_gns_train import quiet, tiny


def _two_bodies():
    gen = torch.Generator().manual_seed(2)
    points = torch.randn(17, 3, generator=gen, dtype=torch.float64) + torch.tensor([5.0, 0.0, 1.0], dtype=torch.float64)
    node_graph = torch.cat([torch.zeros(9, dtype=torch.long), torch.ones(8, dtype=torch.long)])
    return points, node_graph


def test_a_rigid_field_is_its_own_projection_and_a_swelling_projects_to_zero():
    points, node_graph = _two_bodies()
    centre = torch.stack([points[:9].mean(0), points[9:].mean(0)])[node_graph]
    shift = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.5, -0.4]], dtype=torch.float64)[node_graph]
    spin = torch.tensor([[0.7, 0.1, -0.3], [-0.2, 0.0, 0.9]], dtype=torch.float64)[node_graph]
    rigid = shift + torch.cross(spin, points - centre, dim=1)
    torch.testing.assert_close(rigid_projection(rigid, points, node_graph, 2), rigid, rtol=0, atol=1e-12)
    swelling = 0.1 * (points - centre)
    assert float(rigid_projection(swelling, points, node_graph, 2).abs().max()) < 1e-12
    # linear: the projection of a sum is the sum of the projections
    torch.testing.assert_close(rigid_projection(rigid + swelling, points, node_graph, 2), rigid, rtol=0, atol=1e-12)


@pytest.mark.filterwarnings("ignore:outside training")
def test_the_shares_of_a_trained_model_are_fractions_and_the_command_reports_them(tmp_path, capsys):
    data = write_toss_dataset(tmp_path / "data", train=3, valid=1, frames=10)
    train(data, tmp_path / "run", tiny("train.steps=4", "valid.every=0", "features.normalizer_steps=2",
                                       "augment.noise_std=0.01"), log=quiet)
    res = rigid_share(tmp_path / "run", data, batches=2, batch_size=4)
    assert set(res["by_noise_std"]) == {"0.01", "0.0"}
    for row in res["by_noise_std"].values():
        assert 0.0 < row["error_nonrigid_share"] < 1.0 and 0.0 <= row["target_nonrigid_share"] < 1.0
    # without input noise the target of a rigid toss has no non-rigid part but the centripetal one
    assert res["by_noise_std"]["0.0"]["target_nonrigid_share"] < res["by_noise_std"]["0.01"]["target_nonrigid_share"]
    assert main(["--run", str(tmp_path / "run"), "--data", str(data), "--batches", "1", "--batch-size", "2",
                 "--json", str(tmp_path / "s.json")]) == 0
    assert "non-rigid" in capsys.readouterr().out
    assert json.loads((tmp_path / "s.json").read_text())["batches"] == 1
    assert main(["--run", str(tmp_path / "run"), "--data", str(tmp_path / "missing")]) == 2
    assert capsys.readouterr().err.startswith("error: ")
