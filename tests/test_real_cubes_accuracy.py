"""The real-cube accuracy pipeline: tiny preset end to end, rerun skipping, exported models, bad input."""
import json

from test_real_cubes import SRC

from pipelines import real_cubes_accuracy
from gns.checkpoint import load_model


def test_tiny_preset_end_to_end_and_rerun(tmp_path, capsys):
    out, export = tmp_path / "acc", tmp_path / "models"
    args = ["--src", str(SRC), "--preset", "tiny", "--out", str(out), "--export", str(export)]
    assert real_cubes_accuracy.main(args) == 0
    results = json.loads((out / "results.json").read_text())
    row = results["sizes"]["2"]
    assert set(row) >= {"gns", "pybullet", "mujoco", "steps"}
    for who in ("gns", "pybullet", "mujoco"):
        assert row[who]["num_scenes"] == 1 and row[who]["position_error_pct"] >= 0
    assert row["pybullet"]["given_frames"] in (3, 17)
    assert (out / "plots" / "accuracy.png").stat().st_size > 1000
    assert "| 2 | GNS |" in (out / "report.md").read_text()
    # the GNS trained on the real tosses (x2) and 4 tosses of the MuJoCo tuned on them
    assert row["gns_engine_data"]["num_scenes"] == 1 and row["engine_data"] == {"synthetic": 4, "real_copies": 2}
    from datagen.shards import Dataset
    mixed = Dataset(out / "data" / "mujoco_n2_s0")
    assert mixed.num_scenes("train") == 4 + 2 * 2
    assert "tuned-MuJoCo tosses" in (out / "report.md").read_text()
    sim, cfg = load_model(export / "gns_real_cubes_n2.pt")   # the shipped form loads alone
    assert cfg.features.frame_stride == 8 and cfg.train.all_phases and cfg.augment.body_symmetry
    assert cfg.train.rigid_loss == 1 and cfg.features.floor_clip == 1.5 and cfg.features.floor_signed
    assert cfg.model.message_passing_steps == 10
    load_model(export / "gns_real_cubes_mujoco_n2.pt")
    capsys.readouterr()
    before = (out / "eval" / "gns_n2.json").stat().st_mtime_ns
    assert real_cubes_accuracy.main(args) == 0                 # everything done: nothing retrained
    said = "".join(capsys.readouterr())
    assert "has reached step 30, skipping" in said and "fitting" not in said
    assert (out / "eval" / "gns_n2.json").stat().st_mtime_ns == before


def test_a_missing_source_is_one_line(tmp_path, capsys):
    assert real_cubes_accuracy.main(["--src", str(tmp_path / "nope"), "--preset", "tiny",
                                     "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]


def test_the_64_toss_settings_are_those_of_the_shipped_model():
    """gns_real_cubes_n64 was trained by hand (docs/accuracy.md, session 24) with what the pipeline's
    64-toss stage runs, seed included: the 256-toss levers at 30000 steps."""
    from gns.checkpoint import read_checkpoint
    from gns.config import build_config, config_differences
    from gns.evaluate import checkpoint_of
    from pipelines.common import CONFIGS, SETTINGS_FREE
    p = real_cubes_accuracy.PRESETS["accuracy"]
    cfg = build_config(path=CONFIGS / f"gns_{p.model}.toml", overrides=real_cubes_accuracy.gns_settings(p, 64))
    shipped = read_checkpoint(checkpoint_of("gns_real_cubes_n64"))
    assert config_differences(shipped["config"], cfg, ignore=SETTINGS_FREE) == []
    assert shipped["step"] == cfg.train.steps == 30000 and shipped["seed"] == cfg.train.seed == 0
    assert cfg.model.message_passing_steps == 10 and cfg.train.rigid_loss == 1 and cfg.features.floor_clip == 1.5


def test_the_256_toss_settings_are_those_of_the_shipped_model():
    """gns_real_cubes_n256_deep was trained by hand (docs/accuracy.md, session 22) with what the
    pipeline's 256-toss stage now runs, seed included; gns_real_cubes_n256_floor (seed 1) with the
    same but five message-passing steps."""
    from gns.checkpoint import read_checkpoint
    from gns.config import build_config, config_differences
    from gns.evaluate import checkpoint_of
    from pipelines.common import CONFIGS, SETTINGS_FREE
    p = real_cubes_accuracy.PRESETS["accuracy"]
    cfg = build_config(path=CONFIGS / f"gns_{p.model}.toml", overrides=real_cubes_accuracy.gns_settings(p, 256))
    shipped = read_checkpoint(checkpoint_of("gns_real_cubes_n256_deep"))
    assert config_differences(shipped["config"], cfg, ignore=SETTINGS_FREE) == []
    assert shipped["step"] == cfg.train.steps == 40000 and shipped["seed"] == cfg.train.seed == 0
    assert cfg.model.message_passing_steps == 10
    floor = read_checkpoint(checkpoint_of("gns_real_cubes_n256_floor"))
    differ = config_differences(floor["config"], cfg, ignore=SETTINGS_FREE + ("train.seed",))
    assert [d.split()[0] for d in differ] == ["model.message_passing_steps"], differ


def test_the_16_toss_engine_data_settings_are_those_of_the_shipped_model():
    """gns_real_cubes_mujoco_n16 is the pipeline's own 16-toss GNS trained on the tuned MuJoCo's tosses too
    (docs/accuracy.md, session 25): the many-toss levers, not the plain 16-toss model's symmetric augmentation."""
    from gns.checkpoint import read_checkpoint
    from gns.config import build_config, config_differences
    from gns.evaluate import checkpoint_of
    from pipelines.common import CONFIGS, SETTINGS_FREE
    p = real_cubes_accuracy.PRESETS["accuracy"]
    cfg = build_config(path=CONFIGS / f"gns_{p.model}.toml", overrides=real_cubes_accuracy.gns_settings(p, 16, True))
    shipped = read_checkpoint(checkpoint_of("gns_real_cubes_mujoco_n16"))
    assert config_differences(shipped["config"], cfg, ignore=SETTINGS_FREE) == []
    assert shipped["step"] == cfg.train.steps == 20000 and shipped["seed"] == cfg.train.seed == 0
    assert cfg.model.message_passing_steps == 10 and not cfg.augment.body_symmetry
    plain = build_config(path=CONFIGS / f"gns_{p.model}.toml", overrides=real_cubes_accuracy.gns_settings(p, 16))
    assert plain.augment.body_symmetry and plain.model.message_passing_steps == 5
