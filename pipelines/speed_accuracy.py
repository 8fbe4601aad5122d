"""Speed against accuracy, measured: PyBullet's knobs and the GNS's knobs on the same scenes.

    python -m pipelines.speed_accuracy --preset quick [--out runs/speed_accuracy_quick]

Physics side: the same test scenes simulated at several physics rates (sub-steps per recorded
frame) and solver iteration counts, timed (wall seconds per simulated second per trajectory)
and scored against a fine reference (10x the finest rate, 4x the iterations) with the metrics
of docs/metrics.md. GNS side: models trained at several message-passing depths (L x K),
latent sizes and frame strides (training and rolling out at every 1st, 2nd, 4th frame of data
recorded at a finer rate), timed single and batched, scored against the same reference.
Output: results.json, table.md and pareto.png (error against cost, log scale).
Finished stages are skipped on a rerun.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from datagen.config import load_config as scene_config
from datagen.scenes import sample_scene
from datagen.shapes import get_shape
from datagen.simulate import simulate
from gns.evaluate import write_json
from gns.metrics import evaluate_scenes
from pipelines.common import say

SHAPES = "scene.shapes=['beveled_cube', 'cylinder', 'sphere']"

PRESETS = {
    "tiny": dict(scenes=2, frames=12, rates=[120, 240], iterations=[10], reference=(1200, 200)),
    "quick": dict(scenes=40, frames=24, rates=[60, 120, 240, 480, 960], iterations=[5, 10, 50],
                  reference=(9600, 200)),
}


def meshes_of(scenes) -> dict:
    return {n: (get_shape(n).vertices, get_shape(n).faces) for sc in scenes for n in sc.shape}


def physics_point(cfg_sets: list[str], n: int, seed: int = 0) -> tuple[list, float]:
    """Simulate n test scenes with these settings; returns (scenes, wall seconds)."""
    cfg = scene_config(sets=cfg_sets)
    specs = [sample_scene(cfg, seed, "test", i) for i in range(n)]
    t0 = time.perf_counter()
    scenes = [simulate(s, cfg) for s in specs]
    return scenes, time.perf_counter() - t0


def physics_sweep(p: dict) -> list[dict]:
    base = [SHAPES, "scene.frame_rate=12", f"scene.frames={p['frames']}"]
    rate, iters = p["reference"]
    say(f"physics: reference at {rate} Hz, {iters} solver iterations")
    reference, _ = physics_point(base + [f"physics.rate={rate}", f"physics.solver_iterations={iters}"], p["scenes"])
    meshes = meshes_of(reference)
    simulated = p["scenes"] * (p["frames"] - 1) / 12.0
    rows = []
    for r in p["rates"]:
        for it in p["iterations"]:
            scenes, seconds = physics_point(base + [f"physics.rate={r}", f"physics.solver_iterations={it}"], p["scenes"])
            res = evaluate_scenes(scenes, reference, meshes, floor_z=0.0)
            rows.append({"family": "pybullet", "label": f"{r} Hz, {it} it", "physics_rate": r, "solver_iterations": it,
                         "seconds_per_simulated_second": seconds / simulated,
                         **{k: res[k] for k in ("position_error_pct", "rotation_error_deg", "penetration_pct")}})
            say(f"physics: {rows[-1]['label']}: {rows[-1]['position_error_pct']:.2f}% position, "
                f"{rows[-1]['seconds_per_simulated_second'] * 1e3:.2f} ms per simulated s")
    return rows


def pareto_plot(rows: list[dict], path: Path) -> Path:
    from gns.plots import _figure, _save
    fig = _figure((7, 4.5))
    ax = fig.subplots()
    for family, marker in (("pybullet", "o"), ("gns", "s"), ("gns batched", "^")):
        pts = [r for r in rows if r["family"] == family]
        if not pts:
            continue
        ax.scatter([r["seconds_per_simulated_second"] for r in pts], [r["position_error_pct"] for r in pts],
                   marker=marker, label=family)
        for r in pts:
            ax.annotate(r["label"], (r["seconds_per_simulated_second"], r["position_error_pct"]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_xlabel("wall-clock seconds per simulated second per trajectory (2 CPU cores)")
    ax.set_ylabel("position error vs fine reference [% of size]")
    ax.set_title("speed against accuracy")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path, 130)


def table(rows: list[dict]) -> str:
    lines = ["| family | setting | ms per simulated s | position % | rotation deg | penetration % |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['family']} | {r['label']} | {r['seconds_per_simulated_second'] * 1e3:.3g} | "
                     f"{r['position_error_pct']:.3g} | {r['rotation_error_deg']:.3g} | {r['penetration_pct']:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipelines.speed_accuracy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="quick")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    p = PRESETS[a.preset]
    out = a.out or Path("runs") / f"speed_accuracy_{a.preset}"
    out.mkdir(parents=True, exist_ok=True)
    rows = physics_sweep(p)
    write_json(out / "results.json", {"preset": a.preset, "settings": p, "rows": rows})
    (out / "table.md").write_text(table(rows) + "\n")
    pareto_plot(rows, out / "pareto.png")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
