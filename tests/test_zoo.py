"""The model zoo (gns/models/NAME.toml + weights): every card is complete and true to its
weights and recipe, a wrong name lists the right ones, the scored rollout options travel with
the model, and each model rolls out what it was trained on."""
import json
from pathlib import Path

import numpy as np
import pytest

from plumbing import config_dir
from gns import zoo
from gns.checkpoint import checkpoint_of, read_checkpoint
from gns.cli import main as gns_cli
from gns.config import build_config, config_differences
from gns.spec import RolloutOptions
from pipelines.common import SETTINGS_FREE
from pipelines.recipe import load_recipe, recipe_names, run_overrides

CUBES = Path(__file__).parent / "data" / "contactnets"
CARD_KEYS = {"file", "purpose", "use", "limits", "data", "recipe", "scores"}


def test_the_zoo_is_a_few_models_named_by_purpose_each_with_a_complete_card():
    names = zoo.names()
    assert {"movi_a", "movi_a_fast", "real_cubes", "real_cubes_16", "diagnostic_45"} <= set(names)
    assert len(names) <= 6
    weights = {zoo.card(n).file for n in names}
    # nothing ships without a card, and the package stays small
    assert weights == set(zoo.ZOO.glob("*.pt"))
    assert sum(w.stat().st_size for w in weights) < 15e6
    for name in names:
        c = zoo.card(name)
        assert CARD_KEYS <= set(c.data), (name, CARD_KEYS - set(c.data))
        assert c.file.is_file() and c.data["limits"] and c.data["scores"]
        for key in ("what", "command", "fingerprint"):
            assert c.data["data"][key], (name, key)
        assert c.data["recipe"]["command"].startswith(f"python -m pipelines.recipe ")
        for s in c.data["scores"]:
            assert "test_set" in s and ({"position_error_pct", "rotation_error_deg"} <= set(s) or "sides" in s)
        # the card's data is the data the weights were trained on
        trained_on = read_checkpoint(c.file)["provenance"]["data"]["fingerprint"]
        assert c.data["data"]["fingerprint"] == trained_on, name


@pytest.mark.parametrize("name", sorted(set(zoo.names())))
def test_each_zoo_model_is_reproduced_by_its_named_recipe(name):
    """The card's recipe exists, lists the model, and its last run trains with exactly the settings
    stored in the shipped weights (bar the bookkeeping that does not change what a run learns);
    with a contact network, its last run of each kind: the model's and the contact network's."""
    from gns.checkpoint import CONTACT
    c = zoo.card(name)
    recipe_name = c.data["recipe"]["command"].split()[3]
    assert recipe_name in recipe_names()
    recipe = load_recipe(recipe_name)
    assert name in recipe.zoo
    shipped = read_checkpoint(c.file)
    contact_runs = [r for r in recipe.runs if r.contact]
    assert (CONTACT in shipped) == bool(contact_runs)
    pairs = [(shipped, [r for r in recipe.runs if not r.contact][-1])]
    if contact_runs:
        pairs.append((shipped[CONTACT], contact_runs[-1]))
    for ckpt, last in pairs:
        cfg = build_config(path=config_dir() / f"{recipe.model}.toml", overrides=run_overrides(last, None))
        assert config_differences(ckpt["config"], cfg, ignore=SETTINGS_FREE + ("train.init_from",)) == []
        assert ckpt["seed"] == last.seed and ckpt["step"] == last.steps
        # the weights name where they came from as the card's recipe command lays it out, never a
        # folder of the machine they were trained on
        k = recipe.runs.index(last)
        started = f"runs/zoo/{recipe.name}/runs/{recipe.runs[k - 1].name}" if k else cfg.train.init_from
        assert ckpt["config"]["train"]["init_from"] == started
        assert ckpt["provenance"]["data"]["path"].startswith((f"runs/zoo/{recipe.name}/", "data/"))


def test_the_movi_a_recipe_is_one_schedule_of_warm_restarts_after_its_stages():
    recipe = load_recipe("movi_a")
    restarts = [r for r in recipe.runs if r.name.startswith("restarts_")]
    assert len(restarts) == 7 and [r.seed for r in restarts] == list(range(104, 111))
    # a warm restart changes only the seed: the same steps and settings each cycle
    assert len({(r.steps, r.overrides) for r in restarts}) == 1
    assert sum(r.steps for r in recipe.runs) == 128_580


def test_a_wrong_name_lists_the_zoo(capsys, tmp_path):
    for argv in (["models", "gns_movi_a_low_b128_all32_11_s100"], ["eval", "--run", "movi", "--data", str(tmp_path)]):
        with pytest.raises(SystemExit) as stop:
            gns_cli(argv)
        assert stop.value.code == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and err.startswith("error: ") and all(n in err for n in zoo.names())
    with pytest.raises(zoo.ZooError, match="movi_a_fast"):
        checkpoint_of("movi_b")


def test_gns_models_lists_and_prints_cards(capsys):
    gns_cli(["models"])
    out = capsys.readouterr().out
    assert all(f"{n}\n" in out for n in zoo.names())
    gns_cli(["models", "real_cubes"])
    out = capsys.readouterr().out
    card = zoo.card("real_cubes").data
    assert card["recipe"]["command"] in out and card["scores"][0]["eval_command"] in out
    assert "--symmetrize d2" in out


def test_the_scored_options_travel_with_the_model():
    import gns
    for name in ("movi_a", "movi_a_fast", "diagnostic_45"):
        assert gns.load(name).options == zoo.card(name).options
    assert zoo.card("movi_a").options.symmetrize == "d1" and zoo.card("movi_a").options.free_flight
    # a file or run folder has the defaults; a user's choice replaces the card's
    assert gns.load(str(zoo.card("movi_a").file)).options == RolloutOptions()
    assert gns.load("movi_a", options=RolloutOptions()).options == RolloutOptions()
    assert gns.load("movi_a", symmetrize="d2").options.symmetrize == "d2"


def test_the_movi_a_models_roll_out_fresh_scenes_with_their_card_options(tmp_path):
    from datagen.cli import main as datagen
    data = tmp_path / "movi"
    assert datagen(["toss", "--shapes", "beveled_cube,cylinder,sphere", "--scenes", "1", "--test", "6",
                    "--seed", "7", "--quiet", "--out", str(data)]) in (0, None)
    for name in ("movi_a", "movi_a_fast"):
        gns_cli(["eval", "--run", name, "--data", str(data), "--json", str(tmp_path / f"{name}.json")])
        results = json.loads((tmp_path / f"{name}.json").read_text())
        assert results["rollout_options"] == zoo.card(name).options.to_dict()
        assert results["num_scenes"] == 6 and not results["outside_training"]
        # 6 scenes of a seed it never saw; a broken or mismatched model is far off (the card: ~11%)
        assert results["position_error_pct"] < 40 and results["penetration_pct"] < 2


@pytest.mark.parametrize("name", ["real_cubes", "real_cubes_16"])
def test_the_real_cube_models_roll_out_real_tosses(tmp_path, name):
    """The 3 tosses in tests/data are among the 456 shared ones, so among the models' training or
    validation tosses: this checks the shipped file works as trained, not held-out accuracy."""
    from datagen.contactnets import import_contactnets
    data = tmp_path / "cubes"
    import_contactnets(CUBES, data, progress=False)
    gns_cli(["eval", "--run", name, "--data", str(data), "--json", str(tmp_path / "r.json")])
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["num_scenes"] == 3 and results["at_data_rate"]
    assert results["rollout_options"]["symmetrize"] == "d2"
    # both files hold their reader between steps (gns export --between)
    assert results["read_between"] == "learned"
    assert results["position_error_pct"] < 30 and results["rotation_error_deg"] < 30
    assert results["penetration_pct"] < 5


def test_the_240hz_protocol_scores_the_same_rollout_at_50_75_100_frames_of_240_hz(tmp_path):
    from datagen.cli import main as datagen
    from gns.evaluate import evaluate_run
    from plumbing import DataError
    coarse, fine = tmp_path / "at12", tmp_path / "at240"
    toss = ["toss", "--shapes", "beveled_cube,sphere", "--scenes", "0", "--test", "2", "--seed", "5", "--quiet"]
    assert datagen([*toss, "--set", "scene.frames=9", "--out", str(coarse)]) in (0, None)
    assert datagen([*toss, "--set", "scene.frames=161", "scene.frame_rate=240", "--out", str(fine)]) in (0, None)
    plain, pred12, *_ = evaluate_run("movi_a", coarse, progress=False)
    results, pred, true, ds = evaluate_run("movi_a", fine, progress=False, protocol="240hz")
    assert ds.frame_rate == 240 and list(results["horizons"]) == ["50", "75", "100"]
    # the model steps at its own 12 Hz: the same rollout, interpolated between its frames
    for a, b in zip(pred12, pred):
        np.testing.assert_allclose(b.positions[::20], a.positions[:len(b.positions[::20])], atol=1e-5)
    # frame 40 is the last given one (3 frames of 12 Hz); horizon h is frame 40 + h
    for h in (50, 75, 100):
        sq = [np.sum((p.positions[40 + h] - t.positions[40 + h]) ** 2, axis=-1) for p, t in zip(pred, true)]
        assert results["horizons"][str(h)]["translation_rmse"] == pytest.approx(np.sqrt(np.mean(np.concatenate(sq))))
    with pytest.raises(DataError, match="240 frames a second"):
        evaluate_run("movi_a", coarse, progress=False, protocol="240hz")


def test_movi_a_multi_is_movi_a_fast_on_single_objects_and_keeps_crowded_objects_apart(tmp_path):
    from datagen.cli import main as datagen
    from gns.evaluate import evaluate_run
    single, crowded = tmp_path / "single", tmp_path / "crowded"
    toss = ["toss", "--shapes", "beveled_cube,cylinder,sphere", "--scenes", "0", "--seed", "7", "--quiet"]
    assert datagen([*toss, "--test", "4", "--out", str(single)]) in (0, None)
    assert datagen([*toss, "--test", "3", "--objects", "4-6", "--out", str(crowded)]) in (0, None)
    a, pa, *_ = evaluate_run("movi_a_multi", single, progress=False)
    b, pb, *_ = evaluate_run("movi_a_fast", single, progress=False)
    assert a["rollout_options"]["keep_apart"] and not b["rollout_options"]["keep_apart"]
    for x, y in zip(pa, pb):          # no collision edge: the same weights act, to the last bit
        np.testing.assert_array_equal(x.positions, y.positions)
    r, *_ = evaluate_run("movi_a_multi", crowded, progress=False)
    assert r["num_diverged"] == 0 and r["pairs_passing_through_pct"] <= 10
    plain, *_ = evaluate_run("movi_a_multi", crowded, progress=False, keep_apart=False)
    assert r["interpenetration_pct"] < plain["interpenetration_pct"]
