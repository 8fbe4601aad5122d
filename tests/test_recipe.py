"""Recipes as data (configs/recipes/*.toml, pipelines/recipe.py): stages inherit, a stage of n
cycles is n warm restarts, a run resumes and skips what is done, bad recipes are one line."""
import json

import pytest

from plumbing import config_dir
from datagen.shards import Dataset
from gns.checkpoint import read_checkpoint
from gns.config import build_config, config_differences, config_to_dict
from pipelines.common import SETTINGS_FREE
from pipelines.recipe import load_recipe, main as recipe_main, run_overrides


def test_stages_inherit_settings_and_cycles_are_warm_restarts():
    r = load_recipe("tiny")
    assert [x.name for x in r.runs] == ["a", "b_1", "b_2"]
    assert [x.seed for x in r.runs] == [0, 1, 2]
    a, b1, b2 = (dict(s.split("=", 1) for s in x.overrides) for x in r.runs)
    assert a["train.lr_init"] == b1["train.lr_init"] == "0.001"       # inherited
    assert a["train.lr_decay_steps"] == "10" and b1["train.lr_decay_steps"] == "4"  # replaced
    assert "train.unroll_steps" not in a and b1["train.unroll_steps"] == "2"      # added
    assert b1 == b2


def test_the_tiny_recipe_trains_its_chain_and_resumes(tmp_path, capsys):
    out = tmp_path / "r"
    assert recipe_main(["tiny", "--out", str(out), "--workers", "1"]) == 0
    runs = {n: read_checkpoint(out / "runs" / n / "latest.pt") for n in ("a", "b_1", "b_2")}
    assert [runs[n]["seed"] for n in ("a", "b_1", "b_2")] == [0, 1, 2]
    # each cycle starts from the one before
    assert runs["b_1"]["config"]["train"]["init_from"] == str(out / "runs" / "a")
    assert runs["b_2"]["config"]["train"]["init_from"] == str(out / "runs" / "b_1")
    assert runs["b_2"]["config"]["features"]["centre_node"] and runs["a"]["config"]["features"]["centre_node"] is False
    results = json.loads((out / "results.json").read_text())
    scores = results["rows"]["default options"]["scores"]
    assert all(v == v and v >= 0 for v in scores.values())
    assert (out / "model.pt").is_file() and "| default options |" in (out / "report.md").read_text()
    capsys.readouterr()
    # a rerun trains nothing again
    assert recipe_main(["tiny", "--out", str(out), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert err.count("skipping") >= 4 and "resuming" not in err


def test_a_recipe_whose_data_has_no_test_split_exports_its_model_unscored(tmp_path, capsys):
    text = (config_dir() / "recipes" / "tiny.toml").read_text().replace("test = 2", "test = 0")
    text = text[:text.index("[[stage]]\nname = \"b\"")]     # stage a alone
    (tmp_path / "r.toml").write_text(text)
    assert recipe_main([str(tmp_path / "r.toml"), "--out", str(tmp_path / "out"), "--workers", "1"]) == 0
    assert (tmp_path / "out" / "model.pt").is_file() and not (tmp_path / "out" / "results.json").exists()
    assert "not scored" in capsys.readouterr().err


def test_a_contact_stage_trains_the_contact_network_the_model_carries(tmp_path):
    """A stage with contact = true goes on from the run before it; the model is the last other
    run's, with the contact run's network inside (gns.checkpoint.CONTACT)."""
    from gns.checkpoint import CONTACT, load_model
    text = (config_dir() / "recipes" / "tiny.toml").read_text()
    text = text[:text.index("[[stage]]\nname = \"b\"")].replace('frames = 8 }', 'frames = 8, objects = "2" }')
    text = text.replace("[settings.valid]", "[settings.features]\ncollision_mode = \"vertex\"\n\n[settings.valid]")
    text += "\n[[stage]]\nname = \"touch\"\nsteps = 4\nseed = 5\ncontact = true\n"
    (tmp_path / "r.toml").write_text(text)
    out = tmp_path / "out"
    assert recipe_main([str(tmp_path / "r.toml"), "--out", str(out), "--workers", "1"]) == 0
    touch = read_checkpoint(out / "runs" / "touch" / "latest.pt")
    assert touch["config"]["train"]["init_from"] == str(out / "runs" / "a") and touch["step"] == 4
    model = read_checkpoint(out / "model.pt")
    assert model["step"] == 12 and model[CONTACT]["step"] == 4
    assert load_model(out / "model.pt")[0].contact_model is not None
    assert (out / "results.json").is_file()


def test_a_recipe_with_between_exports_a_strided_model_with_its_reader(tmp_path):
    """between = true: the exported model holds its reader between steps (gns.between), fitted on
    the recipe's training data, and the recipe's scores read by it (a card's at_data_rate)."""
    from gns.checkpoint import BETWEEN
    text = (config_dir() / "recipes" / "tiny.toml").read_text()
    text = text[:text.index("[[stage]]\nname = \"b\"")].replace("frames = 8 }", "frames = 16 }")
    text = text.replace('cost = "seconds"', 'cost = "seconds"\nbetween = true')
    text = text.replace("[settings.valid]", "[settings.features]\nframe_stride = 2\n\n[settings.valid]")
    (tmp_path / "r.toml").write_text(text)
    out = tmp_path / "out"
    assert recipe_main([str(tmp_path / "r.toml"), "--out", str(out), "--workers", "1"]) == 0
    model = read_checkpoint(out / "model.pt")
    assert model[BETWEEN]["stride"] == 2
    assert model[BETWEEN]["data_fingerprint"] == Dataset(out / "data").fingerprint


@pytest.mark.parametrize("text, message", [
    ("zoo = []\n", "no [[stage]]"),
    ("[[stage]]\nname = 'a'\nsteps = 3\n", "stage 1 has no seed"),
    ("[[stage]]\nname = 'a'\nsteps = 3\nseed = 0\ncontact = true\n", "every stage trains a contact network"),
    ("[data]\nkind = 'x'\n[[stage]]\nname = 'a'\nsteps = 3\nseed = 0\n", "unknown data kind 'x'"),
    ("[data]\nkind = 'contactnets'\n[[stage]]\nname = 'a'\nsteps = 3\nseed = 0\n", "give --src"),
    ("[[stage\n", "not valid TOML"),
])
def test_a_bad_recipe_is_one_line(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert recipe_main([str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
    assert recipe_main(["nope"]) == 2
    assert "movi_a" in capsys.readouterr().err


def _config(preset: str, overrides):
    return build_config(path=config_dir() / f"{preset}.toml", overrides=list(overrides))


def test_the_real_cube_sweep_ablates_the_zoo_model_by_its_recipe():
    """pipelines.real_cubes --preset zoo: its full model (the ablations' and noise study's
    reference) is the zoo's real_cubes trained by its recipe."""
    from pipelines.real_cubes import PRESETS
    p = PRESETS["zoo"]
    recipe = load_recipe("real_cubes")
    assert p.sizes == (recipe.data["tosses"],) and p.ablation_size == p.noise_size == recipe.data["tosses"]
    assert (p.test, p.valid) == (recipe.data["test"], recipe.data["valid"])
    ours = _config(f"gns_{p.model}", [f"train.steps={p.steps}", f"train.seed={p.seeds[0]}", *p.train])
    theirs = _config(recipe.model, run_overrides(recipe.runs[-1], None))
    assert config_differences(config_to_dict(theirs), ours, ignore=SETTINGS_FREE) == []


def test_a_zoo_model_stands_for_the_run_it_is_and_for_no_other(tmp_path):
    """pipelines.common.zoo_model_as_run: the zoo preset scores the shipped real_cubes instead of
    training its twin, only when the tosses (fingerprint) and the settings are the run's."""
    from gns_fixtures import write_toss_dataset
    from gns.cli import main as gns_main
    from pipelines.common import done, train_stage, zoo_model_as_run
    data = write_toss_dataset(tmp_path / "data", train=3, valid=0, frames=8)
    other = write_toss_dataset(tmp_path / "other", train=3, valid=0, frames=8, seed=1)
    over = ["train.steps=3", "train.checkpoint_every=3", "valid.every=0"]
    train_stage(data, tmp_path / "run", "tiny", over)
    shipped = tmp_path / "shipped.pt"   # exported, as the zoo holds its models
    gns_main(["export", "--run", str(tmp_path / "run"), "--out", str(shipped)])
    assert zoo_model_as_run(str(shipped), data, "tiny", over) == shipped
    assert zoo_model_as_run(str(shipped), other, "tiny", over) is None                       # other tosses
    assert zoo_model_as_run(str(shipped), data, "tiny", [*over, "train.lr_init=0.01"]) is None  # other settings
    assert zoo_model_as_run(str(shipped), data, "tiny", ["train.steps=6", *over[1:]]) is None    # further trained
    # its scores are kept across reruns: a file outside a run folder counts by its own step
    (tmp_path / "eval.json").write_text(json.dumps({"checkpoint_step": 3}))
    assert done(tmp_path / "eval.json", shipped) == {"checkpoint_step": 3}
    (tmp_path / "eval.json").write_text(json.dumps({"checkpoint_step": 2}))
    assert done(tmp_path / "eval.json", shipped) is None


def test_the_real_cube_pipeline_trains_the_zoo_models_by_their_recipes():
    """pipelines.real_cubes_accuracy trains the same 256-toss and 16 + MuJoCo models as the recipes."""
    from pipelines.real_cubes_accuracy import PRESETS, gns_settings
    p = PRESETS["accuracy"]
    for name, settings in (("real_cubes", gns_settings(p, 256)), ("real_cubes_16", gns_settings(p, 16, True))):
        recipe = load_recipe(name)
        ours = _config(recipe.model, run_overrides(recipe.runs[-1], None))
        theirs = _config(f"gns_{p.model}", settings)
        assert config_differences(config_to_dict(ours), theirs, ignore=SETTINGS_FREE) == [], name
