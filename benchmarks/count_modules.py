"""How many of the project's own modules the path from data to a score goes through.

Runs `datagen toss` (which writes the shards), `gns train` and `gns eval` on a tiny dataset,
each in a fresh interpreter that lists, at exit, the project modules it imported (sys.modules
entries of the packages in pyproject's [tool.setuptools] packages). Prints each command's
modules and the union: the modules a user's toss -> train -> eval depends on.

    python benchmarks/count_modules.py [--verbose]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("plumbing", "datagen", "gns", "baselines", "pipelines", "rigid_gns_configs", "configs")

# the command's main() run to its end, then the project's modules printed, one a line, after a marker
PROBE = """
import atexit, runpy, sys
def _report():
    names = sorted(m for m in sys.modules if m.split(".")[0] in {packages!r})
    print("\\n@@modules@@\\n" + "\\n".join(names), file=sys.stderr)
atexit.register(_report)
sys.argv = {argv!r}
runpy.run_module({module!r}, run_name="__main__")
"""


def modules_of(module: str, argv: list[str]) -> list[str]:
    code = PROBE.format(packages=PACKAGES, argv=[module, *argv], module=module)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{module} {' '.join(argv)} failed:\n{done.stderr[-2000:]}")
    listed = done.stderr.split("@@modules@@\n", 1)[1].split()
    # runpy runs the command's own module as __main__: it is on the path too
    return sorted({*listed, module})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--verbose", action="store_true", help="list every command's modules")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data, run = Path(tmp) / "data", Path(tmp) / "run"
        steps = [("datagen toss", "datagen.cli", ["toss", "--shapes", "cube", "--scenes", "4", "--valid", "1",
                                                   "--test", "2", "--set", "scene.frames=8", "--out", str(data)]),
                 ("gns train", "gns.cli", ["train", "--data", str(data), "--out", str(run), "--config", "gns_tiny",
                                           "--steps", "2", "--set", "valid.every=0", "train.threads=1"]),
                 ("gns eval", "gns.cli", ["eval", "--run", str(run), "--data", str(data)])]
        union: set[str] = set()
        for label, module, argv in steps:
            found = modules_of(module, argv)
            union |= set(found)
            print(f"{label}: {len(found)} project modules")
            if args.verbose:
                print("  " + "\n  ".join(found))
    print(f"toss -> shard -> train -> eval: {len(union)} project modules")
    if args.verbose:
        print("  " + "\n  ".join(sorted(union)))


if __name__ == "__main__":
    main()
