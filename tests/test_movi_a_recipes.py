"""The MOVi-A chains (pipelines/movi_a_recipes.py) are the settings of the shipped models they
claim to reproduce: a typo or a drifted value would otherwise show only hours into a run."""
from dataclasses import replace

import pytest

from gns.checkpoint import read_checkpoint
from gns.config import build_config, config_differences, config_to_dict
from gns.evaluate import checkpoint_of
from pipelines.common import CONFIGS, SETTINGS_FREE
from pipelines.movi_a_recipes import (COMMON, MOVI_A_BEST, MOVI_A_BUDGET, MOVI_A_CANONICAL, MOVI_A_FAST, MOVI_A_HEADING,
                                     MOVI_A_HEADING4, MOVI_A_HEADING_K2, MOVI_A_MID, MOVI_A_MID_SPHERE_EDGES_CHAIN,
                                     MOVI_A_MID_SPOKES, MOVI_A_MID_SPOKES_CHAIN, MOVI_A_MID_SPOKES_CHAIN_AVG,
                                     MOVI_A_LOW_B64, MOVI_A_LOW_B64_DISTILLED, MOVI_A_LOW_B64_S100, MOVI_A_LOW_DISTILLED,
                                     MOVI_A_LOW_B128, MOVI_A_LOW_B128_S100, MOVI_A_LOW_B128_5, MOVI_A_LOW_B128_5_S100,
                                     MOVI_A_LOW_B128_D32, MOVI_A_LOW_B128_D32_S100, MOVI_A_LOW_B128_D32_6,
                                     MOVI_A_LOW_B128_D32_6_S100, MOVI_A_LOW_B128_D32_AGAIN,
                                     MOVI_A_LOW_B128_ALL32, MOVI_A_LOW_B128_ALL32_S100, MOVI_A_LOW_B128_ALL32_8_S100,
                                     MOVI_A_LOW_B128_ALL32_11_S100,
                                     MOVI_A_LOW_B128_D32_DISTILLED, MOVI_A_LOW_B256, MOVI_A_LOW_B256_S100,
                                     MOVI_A_LOW_SPOKES_CHAIN_AVG, MOVI_A_LOW_SPOKES_CHAIN_AVG_S100,
                                     MOVI_A_SPHERE_EDGES_CHAIN, MOVI_A_SPOKES, MOVI_A_SPOKES_CHAIN, MOVI_A_SPOKES_CHAIN_AVG,
                                     MOVI_A_SPOKES_CHAIN_AVG_S100, MOVI_A_SPOKES_CHAIN_S100, MOVI_A_SPOKES_K2,
                                     TINY_MEMBER, stage_overrides)

# how a stage may differ from the file it reproduces: where it starts from and who teaches it (folders
# of this pipeline, not the author's), bf16 where it measures faster (the files: bf16 on a CPU where it did)
FREE = SETTINGS_FREE + ("train.init_from", "train.teacher", "train.autocast")


SHIPPING = (MOVI_A_BEST + MOVI_A_MID_SPOKES + MOVI_A_SPOKES[-1:] + MOVI_A_FAST + MOVI_A_HEADING_K2
            + MOVI_A_MID_SPOKES_CHAIN[-1:] + MOVI_A_SPOKES_CHAIN[-1:] + MOVI_A_SPOKES_CHAIN_S100[-1:]
            + MOVI_A_SPOKES_CHAIN_AVG[-1:] + MOVI_A_SPOKES_CHAIN_AVG_S100[-1:] + MOVI_A_MID_SPOKES_CHAIN_AVG[-1:]
            + MOVI_A_LOW_SPOKES_CHAIN_AVG[-1:] + MOVI_A_LOW_SPOKES_CHAIN_AVG_S100[-1:] + (MOVI_A_LOW_DISTILLED,)
            + MOVI_A_LOW_B64[-1:] + MOVI_A_LOW_B64_S100[-1:] + (MOVI_A_LOW_B64_DISTILLED,)
            + MOVI_A_LOW_B128[-1:] + MOVI_A_LOW_B128_S100[-1:] + MOVI_A_LOW_B128_D32[-1:]
            + MOVI_A_LOW_B128_D32_S100[-1:]
            + tuple(stages[-1] for pair in MOVI_A_LOW_B128_D32_AGAIN.values() for stages in pair)
            + MOVI_A_LOW_B128_ALL32[-1:] + MOVI_A_LOW_B128_ALL32_S100[-1:] + MOVI_A_LOW_B128_ALL32_8_S100[-1:]
            + MOVI_A_LOW_B128_ALL32_11_S100[-1:])


@pytest.mark.parametrize("stage", [s for s in SHIPPING if s.ships_as], ids=lambda s: s.name)
def test_each_stage_has_the_settings_of_the_model_it_reproduces(stage):
    shipped = read_checkpoint(checkpoint_of(stage.ships_as))
    taught = ["train.teacher=x.pt"] if shipped["config"]["train"].get("teacher") else []   # the pipeline adds it
    cfg = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(stage, "x.pt", 0) + taught)
    assert config_differences(shipped["config"], cfg, ignore=FREE) == []
    assert shipped["step"] == stage.steps and shipped["seed"] == stage.seed


@pytest.mark.parametrize("chain", [MOVI_A_BEST, MOVI_A_CANONICAL, MOVI_A_FAST, MOVI_A_MID, MOVI_A_HEADING,
                                   MOVI_A_SPOKES, MOVI_A_MID_SPOKES, MOVI_A_HEADING4, MOVI_A_HEADING_K2,
                                   MOVI_A_SPOKES_CHAIN, MOVI_A_MID_SPOKES_CHAIN, MOVI_A_SPOKES_K2,
                                   MOVI_A_SPHERE_EDGES_CHAIN, MOVI_A_MID_SPHERE_EDGES_CHAIN, MOVI_A_SPOKES_CHAIN_AVG,
                                   MOVI_A_MID_SPOKES_CHAIN_AVG, MOVI_A_LOW_SPOKES_CHAIN_AVG, MOVI_A_LOW_B64,
                                   MOVI_A_LOW_B128, MOVI_A_LOW_B128_5, MOVI_A_LOW_B128_D32,
                                   *(chain for chain, _ in MOVI_A_LOW_B128_D32_AGAIN.values()), MOVI_A_LOW_B128_ALL32,
                                   MOVI_A_LOW_B128_ALL32_8_S100, MOVI_A_LOW_B128_ALL32_11_S100, MOVI_A_LOW_B256],
                         ids=["best", "canonical", "fast", "mid", "heading", "spokes", "mid_spokes", "heading4",
                              "heading_k2", "spokes_chain", "mid_spokes_chain", "spokes_k2", "sphere_edges_chain",
                              "mid_sphere_edges_chain", "spokes_chain_avg", "mid_spokes_chain_avg",
                              "low_spokes_chain_avg", "low_b64", "low_b128", "low_b128_5", "low_b128_d32",
                              *(f"low_b128_d32_{n}" for n in MOVI_A_LOW_B128_D32_AGAIN), "low_b128_all32",
                              "low_b128_all32_8_s100", "low_b128_all32_11_s100", "low_b256"])
def test_every_stage_builds_a_config_and_the_chain_only_adds_levers(chain):
    previous = None
    for stage in chain:
        cfg = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(stage, previous, 0))
        assert cfg.train.steps == stage.steps and cfg.train.autocast == "auto" and cfg.train.compile
        assert (cfg.train.init_from or None) == previous
        previous = f"run_{stage.name}/latest.pt"
    assert all(kv in stage_overrides(chain[0], None, 0) for kv in COMMON)


@pytest.mark.parametrize("chain, control, differ", [
    (MOVI_A_HEADING, MOVI_A_BUDGET, ("features.canonical_heading",)),
    (MOVI_A_SPOKES_CHAIN, MOVI_A_HEADING4, ("features.surface_edges",)),
    (MOVI_A_MID_SPOKES_CHAIN, MOVI_A_HEADING4, ("features.surface_edges", "features.mesh_vertices")),
    (MOVI_A_SPOKES_K2, MOVI_A_HEADING_K2, ("features.surface_edges",)),
    (MOVI_A_SPHERE_EDGES_CHAIN, MOVI_A_SPOKES_CHAIN, ("features.surface_edge_shapes",)),
    (MOVI_A_MID_SPHERE_EDGES_CHAIN, MOVI_A_MID_SPOKES_CHAIN, ("features.surface_edge_shapes",)),
    (MOVI_A_SPOKES_CHAIN_AVG, MOVI_A_SPOKES_CHAIN, ("train.lr_final", "train.ema_decay")),
    (MOVI_A_SPOKES_CHAIN_AVG_S100, MOVI_A_SPOKES_CHAIN_S100, ("train.lr_final", "train.ema_decay")),
    (MOVI_A_MID_SPOKES_CHAIN_AVG, MOVI_A_MID_SPOKES_CHAIN, ("train.lr_final", "train.ema_decay")),
    (MOVI_A_LOW_SPOKES_CHAIN_AVG, MOVI_A_SPOKES_CHAIN_AVG, ("features.lowest_vertices", "features.highest_vertices")),
    (MOVI_A_LOW_SPOKES_CHAIN_AVG_S100, MOVI_A_SPOKES_CHAIN_AVG_S100,
     ("features.lowest_vertices", "features.highest_vertices")),
    (MOVI_A_LOW_B64, MOVI_A_LOW_SPOKES_CHAIN_AVG, ("train.batch_size", "train.lr_init", "train.lr_decay_steps",
                                                   "train.steps")),
    (MOVI_A_LOW_B128, MOVI_A_LOW_B64, ("train.batch_size", "train.lr_init", "train.lr_decay_steps", "train.steps")),
    (MOVI_A_LOW_B128_S100, MOVI_A_LOW_B64_S100, ("train.batch_size", "train.lr_init", "train.lr_decay_steps",
                                                 "train.steps")),
    (MOVI_A_LOW_B256, MOVI_A_LOW_B128, ("train.batch_size", "train.lr_init", "train.lr_decay_steps", "train.steps")),
    (MOVI_A_LOW_B256_S100, MOVI_A_LOW_B128_S100, ("train.batch_size", "train.lr_init", "train.lr_decay_steps",
                                                  "train.steps")),
], ids=["heading", "spokes_chain", "mid_spokes_chain", "spokes_k2", "sphere_edges_chain", "mid_sphere_edges_chain",
        "spokes_chain_avg", "spokes_chain_avg_s100", "mid_spokes_chain_avg", "low_spokes_chain_avg",
        "low_spokes_chain_avg_s100", "low_b64", "low_b128", "low_b128_s100", "low_b256", "low_b256_s100"])
def test_a_chain_compared_with_its_control_differs_only_in_its_lever(chain, control, differ):
    """The A/Bs of docs/accuracy.md compare these chains stage by stage (the heading chain with
    `budget`, session 18; the spokes chains with `heading4`, session 20; the sphere-edges chains with
    the spokes chains, session 21): only the lever may differ."""
    assert len(chain) == len(control)
    for stage, base in zip(chain, control):
        a = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(stage, None, 0))
        b = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(base, None, 0))
        assert {d.split()[0] for d in config_differences(config_to_dict(b), a)} == set(differ)


@pytest.mark.parametrize("chain, base", [(MOVI_A_LOW_B128_5, MOVI_A_LOW_B128), (MOVI_A_LOW_B128_5_S100, MOVI_A_LOW_B128_S100)],
                         ids=["s0", "s100"])
def test_the_fifth_stage_is_the_fourth_schedule_again_over_more_steps(chain, base):
    """Session 35's fifth stage (docs/accuracy.md) continues the shipped chain: the same first four
    stages, then the fourth's settings with only the length, the decay and the seed changed."""
    assert chain[:-1] == base
    fourth, fifth = (build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(s, None, 0))
                     for s in (base[-1], chain[-1]))
    assert {d.split()[0] for d in config_differences(config_to_dict(fourth), fifth)} == {
        "train.steps", "train.lr_decay_steps", "train.seed"}
    assert (fifth.train.steps, fifth.train.lr_decay_steps, fifth.train.seed) == (9_600, 4_800, base[-1].seed + 1)


@pytest.mark.parametrize("chain, base", [(MOVI_A_LOW_B128_D32, MOVI_A_LOW_B128_5),
                                         (MOVI_A_LOW_B128_D32_S100, MOVI_A_LOW_B128_5_S100)], ids=["s0", "s100"])
def test_the_more_scenes_chain_is_the_fifth_stage_chain_on_its_data(chain, base):
    """Session 37's A/B (docs/accuracy.md): the pipeline generates 32,000 scenes, of which the first
    four stages keep to the first 4000 (the scenes every other chain trains on) and the fifth takes
    all; nothing else differs from session 35's fifth-stage chain."""
    assert len(chain) == len(base)
    for stage, control in zip(chain, base):
        a = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(stage, None, 0))
        b = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(control, None, 0))
        differ = config_differences(config_to_dict(b), a)
        assert differ == ([] if stage is chain[-1] else ["train.scenes is 0 in the checkpoint, 4000 now"])
    assert chain[-1].ships_as.startswith("gns_movi_a_low_b128_d32") and not any(s.ships_as for s in chain[:-1])
    from pipelines.movi_a import PRESETS
    assert PRESETS["low_b128_d32_pair"]["counts"]["train"] == 32_000
    assert PRESETS["low_b128_pair"]["counts"] == {**PRESETS["low_b128_d32_pair"]["counts"], "train": 4000}


@pytest.mark.parametrize("chain, base", [(MOVI_A_LOW_B128_ALL32, MOVI_A_LOW_B128_D32),
                                         (MOVI_A_LOW_B128_ALL32_S100, MOVI_A_LOW_B128_D32_S100)], ids=["s0", "s100"])
def test_the_all_scenes_chain_is_the_d32_chain_without_the_4000_limit(chain, base):
    """Session 41's A/B (docs/accuracy.md): the d32 chain's steps, seeds and schedules, every stage on
    all 32,000 scenes; its own run folders (a d32 pipeline's runs are not taken for it)."""
    assert len(chain) == len(base) and not any(s.ships_as for s in chain[:-1])
    assert chain[-1].ships_as.startswith("gns_movi_a_low_b128_all32")
    assert not {s.name for s in chain} & {s.name for s in base}
    for stage, control in zip(chain, base):
        a = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(stage, None, 0))
        b = build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(control, None, 0))
        assert config_differences(config_to_dict(b), a) == ([] if stage is chain[-1] else
                                                            ["train.scenes is 4000 in the checkpoint, 0 now"])
    from pipelines.movi_a import PRESETS
    assert PRESETS["low_b128_all32_pair"]["counts"] == PRESETS["low_b128_d32_pair"]["counts"]


@pytest.mark.parametrize("chain, n, ships_as", [(MOVI_A_LOW_B128_ALL32_8_S100, 8, "gns_movi_a_low_b128_all32_8_s100"),
                                                (MOVI_A_LOW_B128_ALL32_11_S100, 11, "gns_movi_a_low_b128_all32_11_s100")],
                         ids=["8", "11"])
def test_the_speed_issues_chain_is_the_all_scenes_member_with_its_last_stage_again_and_again(chain, n, ships_as):
    """Sessions 42-43 (docs/speed.md): the seed-100 all32 chain, then its d32 stage again with the next seed each
    time, from where the one before ended (stages 6 to n); only the last stage ships; resumes the all32 chain's
    run folders, and the longer chain the shorter one's."""
    base = MOVI_A_LOW_B128_ALL32_S100
    assert chain[:len(base) - 1] == base[:-1] and len(chain) == len(base) + n - 5
    d32 = base[-1]
    assert chain[len(base) - 1] == replace(d32, ships_as="")
    for k, stage in enumerate(chain[len(base):], 1):
        assert (stage.settings, stage.steps, stage.seed) == (d32.settings, d32.steps, d32.seed + k)
    assert len({s.name for s in chain}) == len(chain)
    assert [s.ships_as for s in chain if s.ships_as] == [ships_as]
    shorter = MOVI_A_LOW_B128_ALL32_8_S100
    if n > 8:
        assert chain[:len(shorter) - 1] == shorter[:-1] and chain[len(shorter) - 1] == replace(shorter[-1], ships_as="")
    from pipelines.movi_a import PRESETS
    preset = PRESETS[ships_as.removeprefix("gns_movi_a_")]
    assert preset["chain"] == chain and preset["rollout"]["symmetrize"] == "d1" and not preset["members"]


# each stage's shorter chain and twin: the d32 pair's, then the stage before's
_BEFORE = {6: (MOVI_A_LOW_B128_D32, MOVI_A_LOW_B128_D32_S100),
           **{n + 1: pair for n, pair in MOVI_A_LOW_B128_D32_AGAIN.items()}}


@pytest.mark.parametrize("chain, base", [(pair[k], _BEFORE[n][k]) for n, pair in MOVI_A_LOW_B128_D32_AGAIN.items()
                                         for k in (0, 1)],
                         ids=[f"{n}_{seed}" for n in MOVI_A_LOW_B128_D32_AGAIN for seed in ("s0", "s100")])
def test_the_later_stages_are_the_fifth_again_from_where_it_ended(chain, base):
    """Sessions 38-40: the shorter chain's run folders unchanged (a finished pipeline resumes into
    the next stage), then its last stage once more with the next seed and nothing else changed."""
    assert [s.name for s in chain[:-1]] == [s.name for s in base] and not any(s.ships_as for s in chain[:-1])
    before, again = (build_config(path=CONFIGS / "gns_cpu.toml", overrides=stage_overrides(s, None, 0))
                     for s in (base[-1], chain[-1]))
    assert config_differences(config_to_dict(before), again) == [f"train.seed is {before.train.seed} in the checkpoint, "
                                                                 f"{before.train.seed + 1} now"]
    assert chain[-1].ships_as.startswith(f"gns_movi_a_low_b128_d32_{len(chain) - len(MOVI_A_LOW_B128_D32) + 5}")


def test_the_d32_distilled_stage_is_the_batch_64_one_taught_by_the_sixth_stage_pair():
    """Session 39's A/B of distillation on the d32_6 pair: gns_movi_a_low_b64_distilled's stage (steps,
    schedule, seed), another teacher and student (the d32_6 pair and its seed-0 member) on the 32,000
    scenes. It did not gain over its student, so nothing ships from it."""
    assert not MOVI_A_LOW_B128_D32_DISTILLED.ships_as
    assert MOVI_A_LOW_B128_D32_DISTILLED.settings == MOVI_A_LOW_B64_DISTILLED.settings
    assert (MOVI_A_LOW_B128_D32_DISTILLED.steps, MOVI_A_LOW_B128_D32_DISTILLED.seed) == (10_000, 40)
    from pipelines.movi_a import PRESETS
    preset = PRESETS["low_b128_d32_distilled"]
    assert preset["chain"] is MOVI_A_LOW_B128_D32_6 and preset["members"] == (MOVI_A_LOW_B128_D32_6_S100,)
    assert preset["distilled"] is MOVI_A_LOW_B128_D32_DISTILLED and preset["counts"]["train"] == 32_000


def test_fresh_may_delete_the_run_folder_of_every_chain_stage():
    """`--fresh` deletes a folder only if it holds nothing but the pipeline's outputs: a chain
    stage's run folder missing from them would make `--fresh` refuse a folder it wrote itself."""
    from pipelines.movi_a import OUTPUTS, PRESETS
    chains = [c for p in PRESETS.values() for c in (p.get("chain", ()), *p.get("members", ())) if c]
    assert MOVI_A_BEST in chains and MOVI_A_FAST in chains and TINY_MEMBER in chains   # an ensemble's other chains too
    assert {f"run_{s.name}" for chain in chains for s in chain} <= OUTPUTS
