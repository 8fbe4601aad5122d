"""The paper's real-cube experiments (Figures 4, 5, 7): a GNS against tuned PyBullet and MuJoCo.

    python -m pipelines.real_cubes --src DATA --preset quick [--out runs/real_cubes_quick] [--test-dir DIR]

DATA is the ContactNets `data/` folder (tosses_processed/N.pt, params_processed/experiment.json)
or a flat folder of N.pt files. The tosses are split once, with a fixed seed, into test, valid
and a training pool; rotated copies of a toss (the data hold 22 such pairs) always land on the
same side. GNS models are trained on the first n tosses of the pool for each size n (nested
subsets; seed s > 0 reorders the pool and seeds the model), and PyBullet's and MuJoCo's contact
parameters are identified on the very same tosses (pipelines/real_cubes_baselines.py; MuJoCo
only if the [mujoco] extra is installed). Everything is rolled out from the
first 3 frames of the same test tosses and scored with the ContactNets metrics over the whole
toss (docs/metrics.md). At one size: ablations (absolute encoding, no shape matching at rollout,
one message-passing step, no rotation augmentation); at another: training with noise on the
cube's corners and on its tracked pose. --test-dir DIR scores every model and baseline on the
tosses of DIR as well (e.g. the ContactNets tosses kept out of the shared set).

Output in --out: report.md, results.json, plots/, split.json, and the data/, runs/, eval/,
baseline/ folders of the stages. Rerunning continues where the last run stopped: finished
stages are skipped. Presets (docs/real_cubes.md has their measured costs):
  tiny   the test suite's smoke run: sizes 1 and 2, a tiny model, 30 steps
  quick  sizes 8, 32, 128, one seed, the CPU model for 6000 steps; ablations at 128, noise at 32
  full   sizes 8 to 256, three seeds, 30000 steps; ablations and noise at 256
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from datagen.contactnets import import_contactnets, list_toss_ids, read_toss
from datagen.outputs import check_writable
from datagen.shards import Dataset, DataError
from gns.evaluate import evaluate_run, write_json
from gns.train import read_checkpoint
from pipelines.common import guarded, done, remove_output, say, train_stage, trained_step
from pipelines.real_cubes_baselines import LABELS as ENGINE_LABELS
from pipelines.real_cubes_baselines import available_engines, baselines_stage, fit_summary, fits_table

SPLIT_SEED = 2022
DUPLICATE_TOL = 1e-6   # half-widths; the known rotated copies agree to 1e-15
METRICS = ("position_error_pct", "rotation_error_deg", "penetration_pct")
LABELS = {"position_error_pct": "position error [% of width]", "rotation_error_deg": "rotation error [deg]",
          "penetration_pct": "penetration [% of width]"}
# Everything run() writes into --out: --fresh deletes a folder holding only these.
OUTPUTS = {"split.json", "costs.json", "data", "runs", "eval", "baseline", "plots", "results.json", "report.md"}
ABLATIONS = {  # name: (label, training overrides); "nosm" reuses the full model's checkpoint
    "abs": ("absolute encoding", ["features.encoding=absolute"]),
    "1mp": ("1 message-passing step", ["model.message_passing_steps=1", "model.processor_repeats=1"]),
    "noaug": ("no rotation augmentation", ["augment.rotate=false"]),
}


@dataclass(frozen=True)
class Preset:
    test: int                      # test tosses (rotated copies kept together: may exceed by one)
    valid: int                     # validation tosses for the trainer's curves
    sizes: tuple[int, ...]         # training set sizes (Figure 4)
    seeds: tuple[int, ...]
    model: str                     # configs/gns_<model>.toml
    steps: int
    train: tuple[str, ...] = ()    # further training overrides
    baseline_budget: int = 120     # objective evaluations per baseline fit (each engine)
    baseline_tosses: int | None = 64   # fit on a seeded random subset of at most this many tosses
    ablation_size: int = 0         # one of sizes (Figure 5)
    noise_size: int = 0            # one of sizes (Figure 7)
    vertex_noise: tuple[float, ...] = ()   # std, fraction of the cube's size
    track_noise: tuple[float, ...] = ()    # std, fraction of the per-frame displacement
    plots: bool = True             # trajectory plots and GIFs of the largest size


# Real-cube windows are 8-vertex graphs: the CPU model (latent 64, L=5) runs ~25 steps/s on one
# core with 32 graphs a step, 2.6x the graphs/s of 8 a step, and with lr 1e-3 it reached a
# third less error than batch 8 at 5e-4 in the same 7000 steps (128 tosses: 28% vs 42% position).
# The input-noise std is scaled to these data: MOVi's 0.003 is a third of the free-fall
# acceleration per frame here (187 / 148^2 = 0.0085 half-widths) and gave worse rollouts than
# 0.0003 at 32 tosses; 0.001 beat 0.0005 at 128 tosses (22% vs 28% position, 3% vs 6% penetration).
_TRAIN = ("train.threads=1", "train.batch_size=32", "train.lr_init=1e-3", "augment.noise_std=0.001",
          "valid.rollout_scenes=8", "valid.rollout_steps=50")
PRESETS = {
    "tiny": Preset(test=1, valid=0, sizes=(1, 2), seeds=(0,), model="tiny", steps=30,
                   train=_TRAIN + ("valid.every=0", "train.checkpoint_every=30"), baseline_budget=3,
                   baseline_tosses=None,
                   ablation_size=2, noise_size=2, vertex_noise=(0.05,), track_noise=(0.5,), plots=False),
    "quick": Preset(test=96, valid=32, sizes=(8, 32, 128), seeds=(0,), model="cpu", steps=6000,
                    train=_TRAIN + ("train.lr_decay_steps=6000", "valid.every=1000", "train.checkpoint_every=1000"),
                    baseline_budget=120, ablation_size=128, noise_size=32, vertex_noise=(0.02, 0.1),
                    track_noise=(0.02, 0.1)),
    "full": Preset(test=96, valid=32, sizes=(8, 16, 32, 64, 128, 256), seeds=(0, 1, 2), model="cpu", steps=30000,
                   train=_TRAIN + ("train.lr_decay_steps=10000", "valid.every=2000"),
                   baseline_budget=200, ablation_size=256, noise_size=256, vertex_noise=(0.01, 0.03, 0.1),
                   track_noise=(0.01, 0.03, 0.1)),
}


# ---- the split -----------------------------------------------------------------------------

def read_tosses(src: Path) -> dict[int, np.ndarray]:
    """Every N.pt toss of a ContactNets folder, checked: {id: (T, 13)}."""
    ids = list_toss_ids(src)
    if not ids:
        raise DataError(f"no N.pt toss files in {src} (nor in {src}/tosses_processed)")
    root = src / "tosses_processed" if (src / "tosses_processed").is_dir() else src
    return {i: read_toss(root / f"{i}.pt") for i in ids}


def _profile(toss: np.ndarray) -> np.ndarray:
    """What a rotation about the vertical axis leaves unchanged: the height and the speed of the
    centre at every frame."""
    speed = np.linalg.norm(np.diff(toss[:, 0:3], axis=0), axis=1)
    return np.concatenate([toss[:, 2], speed])


def same_toss(a: np.ndarray, b: np.ndarray, tol: float = DUPLICATE_TOL) -> bool:
    """Whether two tosses are one toss, possibly turned about z and moved on the table: equal
    length, and heights and per-frame speeds equal within tol at every frame."""
    return a.shape == b.shape and bool(np.abs(_profile(a) - _profile(b)).max() <= tol)


def duplicate_groups(tosses: dict[int, np.ndarray], tol: float = DUPLICATE_TOL) -> list[list[int]]:
    """Tosses grouped with their copies (sorted groups, sorted by first id); singletons included."""
    parent = {i: i for i in tosses}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    by_length: dict[int, list[int]] = {}
    for i, t in tosses.items():
        by_length.setdefault(len(t), []).append(i)
    for ids in by_length.values():
        profiles = {i: _profile(tosses[i]) for i in ids}
        for x, i in enumerate(ids):
            for j in ids[x + 1:]:
                if np.abs(profiles[i] - profiles[j]).max() <= tol:
                    parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for i in tosses:
        groups.setdefault(root(i), []).append(i)
    return sorted(sorted(g) for g in groups.values())


def make_split(groups: list[list[int]], n_test: int, n_valid: int, seed: int = SPLIT_SEED) -> dict:
    """Shuffle the groups with `seed`; fill test, then valid, the rest is the training pool (in
    the shuffled order, which fixes the nested training subsets). A group is never cut, so test
    or valid can exceed its count by one."""
    order = np.random.default_rng(seed).permutation(len(groups))
    test, valid, pool = [], [], []
    for k in order:
        g = groups[k]
        if sum(map(len, test)) < n_test:
            test.append(g)
        elif sum(map(len, valid)) < n_valid:
            valid.append(g)
        else:
            pool.append(g)
    n = sum(map(len, groups))
    if not pool:
        raise DataError(f"only {n} tosses: not enough for {n_test} test + {n_valid} valid tosses and a training pool")
    flat = lambda gs: sorted(i for g in gs for i in g)  # noqa: E731
    return {"seed": seed, "test": flat(test), "valid": flat(valid), "pool": pool,
            "duplicates": [g for g in groups if len(g) > 1], "num_tosses": n}


def training_ids(split: dict, n: int, seed: int) -> list[int]:
    """The n training tosses of a seed: the first n of the pool, in the split's order for seed
    0 and in a reordering of its groups (seeded by seed) otherwise. Nested across sizes."""
    pool = split["pool"]
    size = sum(map(len, pool))
    if n > size:
        raise DataError(f"training size {n} needs {n} tosses but the training pool holds only {size} "
                        f"(after {len(split['test'])} test and {len(split['valid'])} valid tosses)")
    if seed:
        pool = [pool[k] for k in np.random.default_rng([SPLIT_SEED, seed]).permutation(len(pool))]
    return [i for g in pool for i in g][:n]


def overlaps(external: dict[int, np.ndarray], source: dict[int, np.ndarray]) -> dict[int, list[int]]:
    """External tosses that are (possibly rotated) copies of source tosses: {external id: [ids]}."""
    by_length: dict[int, list[int]] = {}
    for i, t in source.items():
        by_length.setdefault(len(t), []).append(i)
    out = {}
    for e, t in external.items():
        hits = [i for i in by_length.get(len(t), []) if same_toss(t, source[i])]
        if hits:
            out[e] = hits
    return out


# ---- stages ----------------------------------------------------------------------------------

class Costs:
    """Wall-clock seconds of the stages that ran, kept across resumed runs in costs.json."""

    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.exists() else {}

    def add(self, name: str, seconds: float) -> None:
        self.data[name] = round(seconds, 2)
        write_json(self.path, self.data)


def import_stage(src: Path, out: Path, splits: dict[str, list[int]]) -> Path:
    """A dataset of these tosses per split, unless `out` already holds exactly that."""
    try:
        meta = Dataset(out).meta
        if {s: v.get("toss_ids") for s, v in meta["splits"].items()} == splits:
            return out
    except DataError:
        pass
    import_contactnets(src, out, splits=splits, overwrite=True, progress=False)
    return out


def _scored_on(results: dict | None, data: Path) -> bool:
    """Whether saved results were computed on exactly the test tosses of `data`."""
    if results is None:
        return False
    scored = [r["scene_id"] for r in results.get("per_scene", [])] + list(results.get("diverged_scenes", []))
    return sorted(scored) == sorted(Dataset(data).meta["splits"]["test"]["toss_ids"])


def gns_eval_stage(path: Path, ckpt: Path, data: Path, costs: Costs, shape_matching: bool = True,
                   plots_dir: Path | None = None) -> dict:
    results = done(path, ckpt)
    if _scored_on(results, data):
        return results
    t0 = time.perf_counter()
    results, *_ = evaluate_run(ckpt, data, "test", shape_matching=shape_matching, plots_dir=plots_dir, progress=False)
    results["checkpoint_step"] = int(read_checkpoint(ckpt)["step"])
    write_json(path, results)
    costs.add(f"eval {path.stem}", time.perf_counter() - t0)
    return results


def summary(results: dict) -> dict:
    keys = METRICS + ("true_penetration_pct", "num_scenes")
    return {k: results[k] for k in keys}


# ---- the experiment ----------------------------------------------------------------------------

def check_preset(p: Preset) -> None:
    if p.ablation_size not in p.sizes or p.noise_size not in p.sizes:
        raise ValueError("ablation_size and noise_size must be training sizes of the preset")


def run(preset: str, src: Path, out: Path, test_dir: Path | None = None) -> dict:
    p = PRESETS[preset]
    check_preset(p)
    src = Path(src)
    if not src.is_dir():
        raise DataError(f"source folder does not exist: {src}")
    if test_dir is not None and not Path(test_dir).is_dir():
        raise DataError(f"--test-dir folder does not exist: {test_dir}")
    check_writable(out)
    t_start = time.perf_counter()
    tosses = read_tosses(src)
    split = make_split(duplicate_groups(tosses), p.test, p.valid)
    for n in p.sizes:  # refuse an impossible size before anything is trained
        for s in p.seeds:
            training_ids(split, n, s)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "split.json", {**split, "src": str(src), "preset": preset,
                                    "note": "pool: groups of rotated copies, in the order training subsets take them"})
    costs = Costs(out / "costs.json")
    say(f"split: {len(split['test'])} test, {len(split['valid'])} valid, {sum(map(len, split['pool']))} pool tosses; "
        f"{len(split['duplicates'])} groups of copies kept together")

    test_data = import_stage(src, out / "data" / "test", {"test": split["test"]})
    external = None
    if test_dir is not None:
        ext = read_tosses(Path(test_dir))
        external = {"dir": str(test_dir), "data": import_stage(Path(test_dir), out / "data" / "external",
                                                               {"test": sorted(ext)}),
                    "overlap": overlaps(ext, tosses)}
        if external["overlap"]:
            say(f"warning: {len(external['overlap'])} --test-dir tosses are copies of tosses in {src}")

    main_runs = {}
    for n in p.sizes:
        for s in p.seeds:
            ids = training_ids(split, n, s)
            splits = {"train": ids, **({"valid": split["valid"]} if split["valid"] else {})}
            data = import_stage(src, out / "data" / f"train_n{n}_s{s}", splits)
            main_runs[(n, s)] = (data, ids, [f"train.steps={p.steps}", f"train.seed={s}", *p.train])
    runs = {f"gns_n{n}_s{s}": (data, over) for (n, s), (data, _, over) in main_runs.items()}
    data_a, _, over_a = main_runs[(p.ablation_size, p.seeds[0])]
    for name, (_, extra) in ABLATIONS.items():
        runs[f"ablation_{name}"] = (data_a, over_a + extra)
    data_n, _, over_n = main_runs[(p.noise_size, p.seeds[0])]
    for level in p.vertex_noise:
        runs[f"vertex_noise_{level:g}"] = (data_n, over_n + [f"augment.vertex_noise={level}"])
    for level in p.track_noise:
        runs[f"track_noise_{level:g}"] = (data_n, over_n + [f"augment.track_noise={level}"])

    largest = (max(p.sizes), p.seeds[0])
    engines = available_engines()
    base = baselines_stage(out / "baseline", {k: (data, ids) for k, (data, ids, _) in main_runs.items()}, test_data,
                           engines, p.baseline_budget, p.baseline_tosses, costs,
                           external_data=external["data"] if external is not None else None,
                           plots_for=largest if p.plots else None)

    evals, ext_evals = {}, {}
    for name, (data, over) in runs.items():
        t0, before = time.perf_counter(), trained_step(out / "runs" / name)
        ckpt = train_stage(data, out / "runs" / name, p.model, over)
        if trained_step(out / "runs" / name) != before:  # it trained: add this session to any earlier one
            earlier = costs.data.get(f"train {name}", 0.0) if before > 0 else 0.0
            costs.add(f"train {name}", earlier + time.perf_counter() - t0)
        plots = out / "plots" / name if p.plots and name == f"gns_n{largest[0]}_s{largest[1]}" else None
        evals[name] = gns_eval_stage(out / "eval" / f"{name}.json", ckpt, test_data, costs, plots_dir=plots)
        if name == f"gns_n{p.ablation_size}_s{p.seeds[0]}":
            evals["ablation_nosm"] = gns_eval_stage(out / "eval" / "ablation_nosm.json", ckpt, test_data, costs,
                                                    shape_matching=False)
        if external is not None and name.startswith("gns_"):
            ext_evals[name] = gns_eval_stage(out / "eval" / f"{name}.external.json", ckpt, external["data"], costs)

    results = collect(preset, p, src, split, evals, base, external, ext_evals, costs)
    results["pipeline_seconds_this_call"] = round(time.perf_counter() - t_start, 1)
    write_json(out / "results.json", results)
    make_plots(out / "plots", p, results)
    path = report(out, results)
    say(f"report: {path}")
    return results


def _paired(gns: dict, base: dict, key: str = "position_error_pct") -> float:
    """Fraction of test tosses on which the GNS has the lower error."""
    b = {r["scene_id"]: r[key] for r in base["per_scene"]}
    wins = [r[key] < b[r["scene_id"]] for r in gns["per_scene"] if r["scene_id"] in b]
    return float(np.mean(wins)) if wins else float("nan")


def collect(preset, p, src, split, evals, base, external, ext_evals, costs) -> dict:
    engines = list(base["fits"])
    sizes = {}
    for n in p.sizes:
        rows = []
        for s in p.seeds:
            g, name = evals[f"gns_n{n}_s{s}"], f"n{n}_s{s}"
            rows.append({"seed": s, "gns": summary(g), **{e: summary(base["evals"][e][name]) for e in engines},
                         "fits": {e: fit_summary(base["fits"][e][name]) for e in engines},
                         "gns_wins": {e: {"position": _paired(g, base["evals"][e][name]),
                                          "rotation": _paired(g, base["evals"][e][name], "rotation_error_deg")}
                                      for e in engines}})
        sizes[str(n)] = rows
    full_name = f"gns_n{p.ablation_size}_s{p.seeds[0]}"
    ablations = {"full model": summary(evals[full_name]), "no shape matching": summary(evals["ablation_nosm"])}
    ablations.update({label: summary(evals[f"ablation_{k}"]) for k, (label, _) in ABLATIONS.items()})
    noise_ref = summary(evals[f"gns_n{p.noise_size}_s{p.seeds[0]}"])
    noise = {"vertex": {"0": noise_ref, **{f"{v:g}": summary(evals[f"vertex_noise_{v:g}"]) for v in p.vertex_noise}},
             "track": {"0": noise_ref, **{f"{v:g}": summary(evals[f"track_noise_{v:g}"]) for v in p.track_noise}}}
    ext = None
    if external is not None:
        ext = {"dir": external["dir"], "overlap": {str(k): v for k, v in external["overlap"].items()},
               "pybullet_published": summary(base["external"]["published"][""]),
               "sizes": {str(n): [{"seed": s, "gns": summary(ext_evals[f"gns_n{n}_s{s}"]),
                                   **{e: summary(base["external"][e][f"n{n}_s{s}"]) for e in engines}}
                                  for s in p.seeds] for n in p.sizes}}
    return {"preset": preset, "src": str(src), "preset_settings": asdict(p),
            "split": {k: split[k] for k in ("seed", "num_tosses", "duplicates")} | {
                "test": len(split["test"]), "valid": len(split["valid"]), "pool": sum(map(len, split["pool"]))},
            "engines": engines, "sizes": sizes, "pybullet_published": summary(base["evals"]["published"][""]),
            "true_penetration_pct": base["evals"]["published"][""]["true_penetration_pct"],
            "ablation_size": p.ablation_size, "ablations": ablations, "noise_size": p.noise_size, "noise": noise,
            "external": ext, "costs_seconds": costs.data,
            "total_cost_seconds": round(sum(costs.data.values()), 1)}


# ---- figures and report ---------------------------------------------------------------------------

def _by_size(results: dict, who: str, key: str) -> np.ndarray:
    return np.array([[r[who][key] for r in results["sizes"][n]] for n in results["sizes"]], np.float64)


def make_plots(out: Path, p: Preset, results: dict) -> list[Path]:
    from gns.plots import plot_bars, plot_curve
    paths = []
    xs = [int(n) for n in results["sizes"]]
    for key in METRICS:
        refs = {"PyBullet, published constants": results["pybullet_published"][key]}
        if key == "penetration_pct":
            refs["ground truth's own penetration"] = results["true_penetration_pct"]
        curves = {"GNS": _by_size(results, "gns", key)}
        curves.update({f"{ENGINE_LABELS[e]}, identified on the same tosses": _by_size(results, e, key)
                       for e in results["engines"]})
        paths.append(plot_curve(xs, curves,
                                out / f"fig4_{key}.png", baseline=refs, ylabel=LABELS[key],
                                title=f"held-out real tosses ({results['sizes'][str(xs[0])][0]['gns']['num_scenes']})"))
    labels = list(results["ablations"])
    row = results["sizes"][str(results["ablation_size"])][0]
    paths.append(plot_bars(labels, {LABELS[k]: [results["ablations"][a][k] for a in labels] for k in METRICS},
                           out / "fig5_ablations.png",
                           references={LABELS[k]: {f"{ENGINE_LABELS[e]} identified": row[e][k] for e in results["engines"]}
                                       for k in METRICS},
                           title=f"ablations, {results['ablation_size']} training tosses"))
    row = results["sizes"][str(results["noise_size"])][0]
    refs = {f"{ENGINE_LABELS[e]} identified, {what}": row[e][key] for e in results["engines"]
            for what, key in (("position", "position_error_pct"), ("rotation", "rotation_error_deg"))}
    for kind, xlabel in (("vertex", "std of the corner noise [fraction of the cube size]"),
                         ("track", "std of the pose noise [fraction of the per-frame displacement]")):
        levels = results["noise"][kind]
        xs_n = [float(v) for v in levels]
        paths.append(plot_curve(xs_n, {"GNS position [% of width]": [levels[v]["position_error_pct"] for v in levels],
                                       "GNS rotation [deg]": [levels[v]["rotation_error_deg"] for v in levels]},
                                out / f"fig7_{kind}_noise.png", log2=False, xlabel=xlabel, ylabel="error",
                                baseline=refs,
                                title=f"{kind} noise in training, {results['noise_size']} tosses"))
    return paths


def _f(v) -> str:
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.3g}"


def _row(name: str, r: dict) -> str:
    return f"| {name} | " + " | ".join(_f(r[k]) for k in METRICS) + " |"


def report(out: Path, results: dict) -> Path:
    preset, split = results["preset"], results["split"]
    head = "| | position error, % of width | rotation error, degrees | penetration, % of width |\n|---|---|---|---|"
    cmd = f"python -m pipelines.real_cubes --src {results['src']} --preset {preset} --out {out}" + (
        f" --test-dir {results['external']['dir']}" if results["external"] else "")
    engines = results["engines"]
    names = " and ".join(ENGINE_LABELS[e] for e in engines)
    lines = [f"# Real cube tosses: GNS against identified {names}, preset `{preset}`", "",
             f"Made by `{cmd}`.", "",
             f"Tosses: {split['num_tosses']} from `{results['src']}`, split with seed {split['seed']} into "
             f"{split['test']} test, {split['valid']} valid and a pool of {split['pool']} training tosses; "
             f"{len(split['duplicates'])} groups of rotated copies were kept on one side (split.json). Every "
             "model is rolled out from the first 3 frames of each test toss to its end; metrics are averaged over "
             "all frames of a toss, then over tosses (ContactNets convention, docs/metrics.md). "
             f"The ground truth's own penetration is {_f(results['true_penetration_pct'])}% (the metric's floor).", "",
             "## Error against the number of training tosses (Figure 4)", "",
             "Each engine's contact parameters are identified on the training tosses of the row "
             "(pipelines/real_cubes_baselines.py); \"GNS better\" is the share of test tosses on which the GNS "
             "has a lower error than that engine (position / rotation).", "",
             "| training tosses | seed | GNS pos % | GNS rot deg | GNS pen % | "
             + " | ".join(f"{ENGINE_LABELS[e]} pos % | {ENGINE_LABELS[e]} rot deg | {ENGINE_LABELS[e]} pen %" for e in engines)
             + " | " + " | ".join(f"GNS better than {ENGINE_LABELS[e]}" for e in engines) + " |",
             "|---|---|" + "---|---|---|" * (1 + len(engines)) + "---|" * len(engines)]
    for n, rows in results["sizes"].items():
        for r in rows:
            lines.append(f"| {n} | {r['seed']} | " + " | ".join(_f(r[who][k]) for who in ["gns", *engines] for k in METRICS)
                         + " | " + " | ".join(f"{r['gns_wins'][e]['position']:.0%} / {r['gns_wins'][e]['rotation']:.0%}"
                                              for e in engines) + " |")
    pub = results["pybullet_published"]
    lines += ["", f"PyBullet with the published constants (friction 0.18, restitution 0.125, g 187.21): "
              f"{_f(pub['position_error_pct'])}% position, {_f(pub['rotation_error_deg'])} degrees, "
              f"{_f(pub['penetration_pct'])}% penetration.", "", verdict(results), "",
              "![position](plots/fig4_position_error_pct.png) ![rotation](plots/fig4_rotation_error_deg.png) "
              "![penetration](plots/fig4_penetration_pct.png)", "", "Identified parameters (objective: mean "
              "position error % + 0.5 x rotation error in degrees on the tosses fitted on):", "",
              *fits_table([(e, int(n), r["seed"], r["fits"][e]) for n, rows in results["sizes"].items()
                           for r in rows for e in engines]), "",
              f"## Ablations at {results['ablation_size']} training tosses (Figure 5)", "", head]
    lines += [_row(name, r) for name, r in results["ablations"].items()]
    row = results["sizes"][str(results["ablation_size"])][0]
    lines += [_row(f"{ENGINE_LABELS[e]} identified on the same tosses", row[e]) for e in engines] + ["",
              "\"no shape matching\" is the full model rolled out without the rigid projection; the other rows "
              "are trained anew with one change each.", "", "![ablations](plots/fig5_ablations.png)", "",
              f"## Noise in training at {results['noise_size']} training tosses (Figure 7)", "",
              "Corner noise: one Gaussian offset per cube corner (std as a fraction of the cube's size, 2 "
              "half-widths), fixed across the 4 frames of a training window. Tracking noise: Gaussian noise on "
              "the centre at every frame, std as a fraction of that frame's displacement.", "",
              "| noise | std | position error % | rotation error deg | penetration % |", "|---|---|---|---|---|"]
    for kind, levels in results["noise"].items():
        for level, r in levels.items():
            lines.append(f"| {kind} | {level} | " + " | ".join(_f(r[k]) for k in METRICS) + " |")
    lines += ["", "![corner noise](plots/fig7_vertex_noise.png) ![tracking noise](plots/fig7_track_noise.png)", ""]
    ext = results["external"]
    if ext:
        lines += ["## External test tosses", "", f"All tosses of `{ext['dir']}`, imported and scored the same way.", ""]
        if ext["overlap"]:
            lines += [f"Warning: {len(ext['overlap'])} of them are copies of tosses in the source folder "
                      "(so possibly of training tosses): " + ", ".join(f"{k} = {v}" for k, v in ext["overlap"].items()), ""]
        lines += ["| model | training tosses | seed | position error % | rotation error deg | penetration % |",
                  "|---|---|---|---|---|---|",
                  "| PyBullet, published constants | - | - | " + " | ".join(_f(ext["pybullet_published"][k]) for k in METRICS) + " |"]
        for n, rows in ext["sizes"].items():
            for r in rows:
                for who, label in [("gns", "GNS")] + [(e, f"{ENGINE_LABELS[e]} identified") for e in engines]:
                    lines.append(f"| {label} | {n} | {r['seed']} | " + " | ".join(_f(r[who][k]) for k in METRICS) + " |")
        lines.append("")
    costs = results["costs_seconds"]
    lines += ["## Cost", "", f"Wall-clock seconds of the stages, summed: {results['total_cost_seconds']:.0f} s "
              f"(training {sum(v for k, v in costs.items() if k.startswith('train')):.0f} s, baseline fits "
              f"{sum(v for k, v in costs.items() if k.startswith('baseline')):.0f} s, evaluations "
              f"{sum(v for k, v in costs.items() if k.startswith('eval')):.0f} s); costs.json has each stage.", ""]
    largest = max(int(n) for n in results["sizes"])
    if results["preset_settings"]["plots"]:
        lines += ["## Trajectories", "", f"GNS trained on {largest} tosses, then {names} identified on them; "
                  "worst, median and best test toss by position error.", ""]
        for who in [f"gns_n{largest}_s0"] + [f"{e}_n{largest}_s0" for e in engines]:
            lines += [f"![{who} {w}](plots/{who}/trajectory_{w}.png)" for w in ("worst", "median", "best")] + [""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def verdict(results: dict) -> str:
    """One honest sentence per size: the mean errors, lowest first."""
    parts = []
    for n, rows in results["sizes"].items():
        who = ["gns", *results["engines"]]
        label = {"gns": "GNS", **ENGINE_LABELS}
        text = []
        for key, what in (("position_error_pct", "position"), ("rotation_error_deg", "rotation")):
            means = sorted((np.mean([r[w][key] for r in rows]), label[w]) for w in who)
            text.append(f"{what} " + " < ".join(f"{name} {_f(v)}" for v, name in means))
        parts.append(f"{n} tosses: " + ", ".join(text))
    return "Mean errors, lowest first: " + "; ".join(parts) + "."


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.real_cubes", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, required=True, help="ContactNets data folder (tosses_processed/N.pt)")
    ap.add_argument("--preset", choices=sorted(PRESETS), default="quick")
    ap.add_argument("--out", type=Path, help="output folder (default runs/real_cubes_<preset>)")
    ap.add_argument("--test-dir", type=Path, help="a further folder of N.pt tosses to score everything on")
    ap.add_argument("--fresh", action="store_true", help="delete the output folder first instead of resuming")
    a = ap.parse_args(argv)
    out = a.out or Path("runs") / f"real_cubes_{a.preset}"
    import torch
    torch.set_num_threads(1)  # rollouts of 8-vertex graphs: a second thread only waits on the first

    def stages():
        if a.fresh:
            remove_output(out, OUTPUTS)
        run(a.preset, a.src, out, a.test_dir)
    return guarded(stages)


if __name__ == "__main__":
    sys.exit(main())
