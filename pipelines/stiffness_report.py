"""The report of pipelines.stiffness: the finding (how much each model's error changes from soft
to hard contact), the plot of error against training size per stiffness, and report.md."""
from __future__ import annotations

import json
from pathlib import Path


def finding(results: dict) -> dict:
    """Soft -> hard: each model's error at hard contact against soft, per size (ratio and
    difference), and where the GNS does not beat the GRU."""
    levels = results["levels"]
    out = {"soft_to_hard": {}, "gns_not_better": []}
    sizes = sorted({int(n) for lv in levels.values() for n in lv["sizes"]})
    for model in ("gns", "gru"):
        for key in ("position_error_pct", "rotation_error_deg"):
            rows = []
            for n in sizes:
                s, h = (levels.get(lv, {}).get("sizes", {}).get(str(n), {}).get(model, {}).get(key)
                        for lv in ("soft", "hard"))
                if s is not None and h is not None:
                    rows.append({"size": n, "soft": s, "hard": h, "hard_minus_soft": h - s, "hard_over_soft": h / s})
            out["soft_to_hard"][f"{model} {key}"] = rows
    for level, lv in levels.items():
        for n, r in lv["sizes"].items():
            for key in ("position_error_pct", "rotation_error_deg"):
                if r["gns"][key] >= r["gru"][key]:
                    out["gns_not_better"].append({"level": level, "size": int(n), "metric": key,
                                                  "gns": r["gns"][key], "gru": r["gru"][key]})
    return out


COLOURS = {"soft": "tab:green", "medium": "tab:orange", "hard": "tab:red"}


def plot(path: Path, results: dict) -> Path:
    """Error against training tosses per level, GNS solid and GRU dashed (the paper's Fig. 6b, c)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, label in zip(axes, ("position_error_pct", "rotation_error_deg"),
                              ("position error (% of the cube's width)", "rotation error (degrees)")):
        for level, lv in results["levels"].items():
            sizes = sorted(int(n) for n in lv["sizes"])
            for model, style in (("gns", "o-"), ("gru", "s--")):
                ax.plot(sizes, [lv["sizes"][str(n)][model][key] for n in sizes], style,
                        color=COLOURS.get(level), label=f"{model.upper()} {level}")
        ax.set_xscale("log")
        ticks = sorted({int(n) for lv in results["levels"].values() for n in lv["sizes"]})
        ax.set_xticks(ticks, [str(n) for n in ticks])
        ax.minorticks_off()
        ax.set_xlabel("training tosses")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"MuJoCo cube tosses by contact stiffness ({results['preset']} preset): GNS vs GRU")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _f(x, digits=1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def report(out: Path, results: dict) -> Path:
    p, levels = results["settings"], results["levels"]
    lines = [f"# Contact stiffness: the GNS against a GRU (preset `{results['preset']}`)", "",
             "The paper's Fig. 6 on the project's own data: MuJoCo cube tosses (`datagen toss --engine mujoco`, "
             "configs/mujoco_cubes.toml), the cube and table of the real ContactNets set-up, starts drawn from "
             f"{results['starts']}; every level tosses the same starts (seed {p['seed']}). Both models are given the "
             "first 3 states (frames 0, 8, 16) of each held-out test toss and scored at every recorded frame with "
             "the ContactNets metrics, averaged over the frames of a toss, then over tosses.", "",
             "## The data: penetration of each level", "",
             "| level | solref timeconst (s), dampratio | mean penetration % | deepest frame % | at rest (last 10 frames) % |",
             "|---|---|---|---|---|"]
    for level, lv in levels.items():
        pen = lv["penetration"]
        lines.append(f"| {level} | {pen['timeconst']:g}, {pen['dampratio']:g} | {_f(pen['mean_pct'], 2)} | "
                     f"{_f(pen['max_pct'], 1)} | {_f(pen['rest_pct'], 2)} |")
    lines += ["", f"Over the {levels[next(iter(levels))]['penetration']['num_tosses']} test tosses of each level, "
              "% of the cube's width (the deepest frame averaged over tosses).", "",
              f"## GNS and GRU by training size ({p['steps']} optimiser steps each, batch "
              f"{results['gru_config']['batch_size']})", "",
              "| level | training tosses | GNS position % | GRU position % | GNS rotation deg | GRU rotation deg | "
              "GNS penetration % | GRU penetration % | truth's penetration % | GNS / GRU train s |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for level, lv in levels.items():
        for n, r in sorted(lv["sizes"].items(), key=lambda kv: int(kv[0])):
            g, u = r["gns"], r["gru"]
            lines.append(f"| {level} | {n} | {_f(g['position_error_pct'])} | {_f(u['position_error_pct'])} | "
                         f"{_f(g['rotation_error_deg'])} | {_f(u['rotation_error_deg'])} | {_f(g['penetration_pct'], 2)} | "
                         f"{_f(u['penetration_pct'], 2)} | {_f(g['true_penetration_pct'], 2)} | {_f(r['gns_train_seconds'], 0)} / "
                         f"{_f(r['gru_train_seconds'], 0)} |")
    f = results["finding"]
    lines += ["", "![error against training size](plots/error_vs_size.png)", "", "## Soft to hard", ""]
    largest = {k: rows[-1] for k, rows in f["soft_to_hard"].items() if rows}
    if len(largest) == 4:
        n = largest["gns position_error_pct"]["size"]
        lines += [f"Hard over soft at {n} training tosses: the GNS's position error "
                  f"x{largest['gns position_error_pct']['hard_over_soft']:.2f}, rotation "
                  f"x{largest['gns rotation_error_deg']['hard_over_soft']:.2f}; the GRU's "
                  f"x{largest['gru position_error_pct']['hard_over_soft']:.2f} and "
                  f"x{largest['gru rotation_error_deg']['hard_over_soft']:.2f}. Every size:", ""]
    for key, unit in (("position_error_pct", "%"), ("rotation_error_deg", " deg")):
        for model in ("gns", "gru"):
            rows = f["soft_to_hard"][f"{model} {key}"]
            if rows:
                lines.append(f"- {model.upper()} {key.split('_')[0]}: " + "; ".join(
                    f"{r['size']} tosses {r['soft']:.1f} -> {r['hard']:.1f}{unit} (x{r['hard_over_soft']:.2f})"
                    for r in rows))
    lines.append("")
    if f["gns_not_better"]:
        lines.append("Where the GNS does not beat the GRU: " + "; ".join(
            f"{r['level']} {r['size']} tosses {r['metric'].split('_')[0]} (GNS {r['gns']:.1f}, GRU {r['gru']:.1f})"
            for r in f["gns_not_better"]) + ".")
    else:
        lines.append("The GNS beats the GRU at every level and size, in position and in rotation.")
    lines += ["", "## How", "",
              f"- GNS: `{p['model']}` with the real-cube zoo model's recipe settings (configs/recipes/real_cubes.toml), "
              f"`gns train --set {' '.join(results['gns_overrides'])}`; scored by `gns eval {' '.join(results['eval_flags'])}`.",
              f"- GRU (baselines/gru.py): {json.dumps(results['gru_config'])}; the same optimiser steps and batch size "
              "as the GNS (so the same number of training windows), its own wall time above.",
              "- Costs (s): " + ", ".join(f"{k} {v:.0f}" for k, v in results["costs_seconds"].items()), ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
