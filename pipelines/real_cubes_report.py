"""What the real-cube pipelines show of their results: headline numbers, the identified
parameters' table, the figures (4, 5 and 7 of the paper) and report.md of pipelines/real_cubes.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gns.metrics import METRICS
from gns.plots import METRIC_LABELS as LABELS

ENGINE_LABELS = {"pybullet": "PyBullet", "mujoco": "MuJoCo"}


def summary(results: dict) -> dict:
    """The headline numbers of an evaluation: the metrics over the whole test set."""
    keys = METRICS + ("true_penetration_pct", "num_scenes")
    return {k: results[k] for k in keys}


def fit_summary(fit: dict) -> dict:
    return {"params": fit["params"], "objective": fit["objective"], "start_objective": fit["start_objective"],
            "evaluations": fit["evaluations"], "seconds": fit["seconds"],
            "fit_tosses": fit.get("fit_tosses", len(fit["train_ids"])), "train_tosses": len(fit["train_ids"])}


def describe(engine: str, p: dict) -> str:
    """The identified values of a parameter set, short."""
    if engine == "pybullet":
        s = f"friction {p['friction']:.3f}, restitution {p['restitution']:.3f}"
        if p["stiffness"]:
            s += f", stiffness {p['stiffness']:.3g}, damping ratio {p['damping_ratio']:.2f}"
        s += (f", rolling {p.get('rolling_friction', 0):.3g}, spinning {p.get('spinning_friction', 0):.3g}, "
              f"{p['substeps']} substeps")
    else:
        s = (f"friction {p['friction']:.3f}, torsional {p['torsional_friction']:.3g}, rolling {p['rolling_friction']:.3g}, "
             f"solref ({p['timeconst']:.3g}, {p['dampratio']:.2f}), solimp ({p['dmin']:.3f}, {p['dmax']:.4f}, "
             f"{p['width']:.2g}), impratio {p['impratio']:.3g}, {p['substeps']} substeps")
    return s + f", g {p['gravity']:.1f}, table {p['floor_z']:+.3f}"


def number(v) -> str:
    """A number for a report table: 3 significant digits, "-" for none."""
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.3g}"


def fits_table(rows: list[tuple[str, int, int, dict]]) -> list[str]:
    """Markdown rows of identified parameters: (engine, training tosses, seed, fit_summary)."""
    lines = ["| engine | training tosses | seed | fitted on | evaluations | fit s | objective (start) | parameters |",
             "|---|---|---|---|---|---|---|---|"]
    for engine, n, s, f in rows:
        lines.append(f"| {ENGINE_LABELS[engine]} | {n} | {s} | {f['fit_tosses']} | {f['evaluations']} | {f['seconds']:.0f} | "
                     f"{f['objective']:.2f} ({f['start_objective']:.2f}) | {describe(engine, f['params'])} |")
    return lines


def _by_size(results: dict, who: str, key: str) -> np.ndarray:
    return np.array([[r[who][key] for r in results["sizes"][n]] for n in results["sizes"]], np.float64)


def make_plots(out: Path, results: dict) -> list[Path]:
    from gns.charts import plot_bars, plot_curve
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


def metric_cells(r: dict | None) -> str:
    """Position %, rotation deg and penetration % of a summary as table cells (2 decimals), "-" for none."""
    if r is None:
        return "- | - | -"
    return f"{r['position_error_pct']:.2f} | {r['rotation_error_deg']:.2f} | {r['penetration_pct']:.2f}"


def _row(name: str, r: dict) -> str:
    return f"| {name} | " + " | ".join(number(r[k]) for k in METRICS) + " |"


def _engine_names(engines: list[str]) -> str:
    return " and ".join(ENGINE_LABELS[e] for e in engines)


def _intro(out: Path, results: dict) -> list[str]:
    """Title, the command that made the report and how the tosses were split."""
    preset, split = results["preset"], results["split"]
    cmd = f"python -m pipelines.real_cubes --src {results['src']} --preset {preset} --out {out}" + (
        f" --test-dir {results['external']['dir']}" if results["external"] else "")
    return [f"# Real cube tosses: GNS against identified {_engine_names(results['engines'])}, preset `{preset}`", "",
            f"Made by `{cmd}`.", "",
            f"Tosses: {split['num_tosses']} from `{results['src']}`, split with seed {split['seed']} into "
            f"{split['test']} test, {split['valid']} valid and a pool of {split['pool']} training tosses; "
            f"{len(split['duplicates'])} groups of rotated copies were kept on one side (split.json). Every "
            "model is rolled out from the first 3 frames of each test toss to its end; metrics are averaged over "
            "all frames of a toss, then over tosses (ContactNets convention, docs/metrics.md). "
            f"The ground truth's own penetration is {number(results['true_penetration_pct'])}% (the metric's floor).", ""]


def _sizes_section(results: dict) -> list[str]:
    """Figure 4: errors against the number of training tosses, the verdict and the identified parameters."""
    engines = results["engines"]
    lines = ["## Error against the number of training tosses (Figure 4)", "",
             "Each engine's contact parameters are identified on the training tosses of the row "
             "(pipelines/real_cubes_baselines.py); \"GNS better\" is the share of test tosses on which the GNS "
             "has a lower error than that engine (position / rotation).", "",
             "| training tosses | seed | GNS pos % | GNS rot deg | GNS pen % | "
             + " | ".join(f"{ENGINE_LABELS[e]} pos % | {ENGINE_LABELS[e]} rot deg | {ENGINE_LABELS[e]} pen %" for e in engines)
             + " | " + " | ".join(f"GNS better than {ENGINE_LABELS[e]}" for e in engines) + " |",
             "|---|---|" + "---|---|---|" * (1 + len(engines)) + "---|" * len(engines)]
    for n, rows in results["sizes"].items():
        for r in rows:
            lines.append(f"| {n} | {r['seed']} | " + " | ".join(number(r[who][k]) for who in ["gns", *engines] for k in METRICS)
                         + " | " + " | ".join(f"{r['gns_wins'][e]['position']:.0%} / {r['gns_wins'][e]['rotation']:.0%}"
                                              for e in engines) + " |")
    pub = results["pybullet_published"]
    return lines + ["", f"PyBullet with the published constants (friction 0.18, restitution 0.125, g 187.21): "
                    f"{number(pub['position_error_pct'])}% position, {number(pub['rotation_error_deg'])} degrees, "
                    f"{number(pub['penetration_pct'])}% penetration.", "", verdict(results), "",
                    "![position](plots/fig4_position_error_pct.png) ![rotation](plots/fig4_rotation_error_deg.png) "
                    "![penetration](plots/fig4_penetration_pct.png)", "", "Identified parameters (objective: mean "
                    "position error % + 0.5 x rotation error in degrees on the tosses fitted on):", "",
                    *fits_table([(e, int(n), r["seed"], r["fits"][e]) for n, rows in results["sizes"].items()
                                 for r in rows for e in engines]), ""]


def _ablations_section(results: dict) -> list[str]:
    """Figure 5: the ablations beside the engines identified on the same tosses."""
    head = "| | position error, % of width | rotation error, degrees | penetration, % of width |\n|---|---|---|---|"
    lines = [f"## Ablations at {results['ablation_size']} training tosses (Figure 5)", "", head]
    lines += [_row(name, r) for name, r in results["ablations"].items()]
    row = results["sizes"][str(results["ablation_size"])][0]
    return lines + [_row(f"{ENGINE_LABELS[e]} identified on the same tosses", row[e]) for e in results["engines"]] + [
        "", "\"no shape matching\" is the full model rolled out without the rigid projection; the other rows "
        "are trained anew with one change each.", "", "![ablations](plots/fig5_ablations.png)", ""]


def _noise_section(results: dict) -> list[str]:
    """Figure 7: errors after training on noisy corners or tracks."""
    lines = [f"## Noise in training at {results['noise_size']} training tosses (Figure 7)", "",
             "Corner noise: one Gaussian offset per cube corner (std as a fraction of the cube's size, 2 "
             "half-widths), fixed across the 4 frames of a training window. Tracking noise: Gaussian noise on "
             "the centre at every frame, std as a fraction of that frame's displacement.", "",
             "| noise | std | position error % | rotation error deg | penetration % |", "|---|---|---|---|---|"]
    for kind, levels in results["noise"].items():
        for level, r in levels.items():
            lines.append(f"| {kind} | {level} | " + " | ".join(number(r[k]) for k in METRICS) + " |")
    return lines + ["", "![corner noise](plots/fig7_vertex_noise.png) ![tracking noise](plots/fig7_track_noise.png)", ""]


def _external_section(results: dict) -> list[str]:
    """The scores on a --test-dir folder's tosses; none without one."""
    ext = results["external"]
    if not ext:
        return []
    lines = ["## External test tosses", "", f"All tosses of `{ext['dir']}`, imported and scored the same way.", ""]
    if ext["overlap"]:
        lines += [f"Warning: {len(ext['overlap'])} of them are copies of tosses in the source folder "
                  "(so possibly of training tosses): " + ", ".join(f"{k} = {v}" for k, v in ext["overlap"].items()), ""]
    lines += ["| model | training tosses | seed | position error % | rotation error deg | penetration % |",
              "|---|---|---|---|---|---|",
              "| PyBullet, published constants | - | - | " + " | ".join(number(ext["pybullet_published"][k]) for k in METRICS) + " |"]
    for n, rows in ext["sizes"].items():
        for r in rows:
            for who, label in [("gns", "GNS")] + [(e, f"{ENGINE_LABELS[e]} identified") for e in results["engines"]]:
                lines.append(f"| {label} | {n} | {r['seed']} | " + " | ".join(number(r[who][k]) for k in METRICS) + " |")
    return lines + [""]


def _cost_section(results: dict) -> list[str]:
    costs = results["costs_seconds"]
    return ["## Cost", "", f"Wall-clock seconds of the stages, summed: {results['total_cost_seconds']:.0f} s "
            f"(training {sum(v for k, v in costs.items() if k.startswith('train')):.0f} s, baseline fits "
            f"{sum(v for k, v in costs.items() if k.startswith('baseline')):.0f} s, evaluations "
            f"{sum(v for k, v in costs.items() if k.startswith('eval')):.0f} s); costs.json has each stage.", ""]


def _trajectories_section(results: dict) -> list[str]:
    """The worst, median and best test toss of each model at the largest size; none when the preset has no plots."""
    if not results["preset_settings"]["plots"]:
        return []
    engines = results["engines"]
    largest = max(int(n) for n in results["sizes"])
    lines = ["## Trajectories", "", f"GNS trained on {largest} tosses, then {_engine_names(engines)} identified on "
             "them; worst, median and best test toss by position error.", ""]
    for who in [f"gns_n{largest}_s0"] + [f"{e}_n{largest}_s0" for e in engines]:
        lines += [f"![{who} {w}](plots/{who}/trajectory_{w}.png)" for w in ("worst", "median", "best")] + [""]
    return lines


def report(out: Path, results: dict) -> Path:
    lines = [*_intro(out, results), *_sizes_section(results), *_ablations_section(results),
             *_noise_section(results), *_external_section(results), *_cost_section(results),
             *_trajectories_section(results)]
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
            text.append(f"{what} " + " < ".join(f"{name} {number(v)}" for v, name in means))
        parts.append(f"{n} tosses: " + ", ".join(text))
    return "Mean errors, lowest first: " + "; ".join(parts) + "."
