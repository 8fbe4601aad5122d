"""Where a model comes from: checkpoint files (written safely, read with one-line errors, rebuilt
into a simulator on a checked device), run folders, and the names of zoo models (whose cards and
exported files are gns.zoo's).

A checkpoint is a `torch.save` dict of format CHECKPOINT_FORMAT: "format", "step", "seed",
"config" (the full config as a dict), "spec" (the dataset feature spec, gns.spec.ModelSpec),
"model" (weights and normalisers), "provenance", and in a training checkpoint also
"optimizer", "rng" and "train_seconds" (the seconds of training that reached it, resumed segments
summed), and with `train.ema_decay` "trained" (the weights training goes on from;
"model" then holds their moving average, gns.weight_average). An exported model
(gns.zoo.export_model) drops the last three, and may carry "contact": the exported model of
its contact network (LearnedSimulator.set_contact_model). docs/model.md documents the keys.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import torch

from plumbing import atomic_file
from gns.config import Config, ConfigError, build_config
from gns.spec import RolloutOptions
from gns.simulator import LearnedSimulator
from gns.spec import ModelSpec, SpecError


CHECKPOINT_FORMAT = 1
LATEST = "latest.pt"
TRAINED = "trained"
TRAIN_SECONDS = "train_seconds"
CONTACT = "contact"   # an exported model's contact network (gns.zoo.export_model), a checkpoint dict itself
BETWEEN = "between"   # an exported strided model's reader of the frames between its steps (gns.between)


def checkpoint_of(run: str | Path) -> Path:
    """A run folder means its latest checkpoint; a .pt file is taken as it is; a bare name that
    is neither is a zoo model's name (gns.zoo.card), and one that is not in the zoo is refused with
    the names that are."""
    if is_name(run):
        from gns.zoo import card   # a zoo name: the only case that reads the cards
        return card(str(run)).file
    run = Path(run)
    if run.is_dir():
        return run / LATEST
    return run


class CheckpointError(Exception):
    """A run folder or checkpoint that cannot be used as asked. One line for a user."""


def is_name(run) -> bool:
    """A bare word that is not a path on disk: meant as a zoo name."""
    run = Path(str(run))
    return not run.exists() and run.parent == Path(".") and run.suffix == "" and str(run) != "."


def default_options(run) -> RolloutOptions:
    """The options a run is rolled out with unless told otherwise: a zoo model's scored ones,
    else the defaults."""
    if is_name(run):
        from gns.zoo import ZOO, card
        if (ZOO / f"{run}.toml").is_file():
            return card(str(run)).options
    return RolloutOptions()


def checkpoint_paths(run: Path) -> list[Path]:
    """Numbered checkpoints of a run folder, oldest first."""
    return sorted(run.glob("ckpt-*.pt"))


def save_checkpoint(run: Path, state: dict, keep: int) -> Path:
    path = run / f"ckpt-{state['step']:06d}.pt"
    with atomic_file(path) as tmp:
        torch.save(state, tmp)
    with atomic_file(run / LATEST) as tmp:
        shutil.copyfile(path, tmp)
    if keep > 0:
        # Numbers beyond this step are left from before a resume that passed them over (unreadable);
        # training overwrites them when it gets there, so the rotation never deletes the new one.
        for old in [p for p in checkpoint_paths(run) if p.name <= path.name][:-keep]:
            old.unlink()
    return path


def read_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for a damaged or foreign file
        # torch's own first line runs on for several sentences of advice; its first says what broke
        reason = str(e).splitlines()[0].split(". ")[0] if str(e) else ""
        if isinstance(e, KeyError) or not reason:  # torch's KeyError carries only a number
            reason = f"not a torch.save file ({type(e).__name__})"
        raise CheckpointError(f"unreadable checkpoint {path}: {reason}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a gns checkpoint of format {CHECKPOINT_FORMAT}")
    try:
        ModelSpec.from_dict(ckpt.get("spec"))  # read again where used: the file stays as written
    except SpecError as e:
        raise CheckpointError(f"{path}: {e}") from None
    return ckpt


def is_exported(ckpt: dict) -> bool:
    """An export_model file: the model without the optimiser and random state."""
    return "optimizer" not in ckpt or "rng" not in ckpt


def exported_model_message(path: Path) -> str:
    return (f"{path} is an exported model (no optimiser state): training cannot resume from it; "
            f"gns eval and gns rollout can use it")


def resume_point(run: str | Path) -> tuple[Path, dict, str | None]:
    """The newest checkpoint of a run that training can resume from: latest.pt, else the
    newest readable ckpt-*.pt (a crash or a full disk can leave latest.pt torn while the
    numbered copies are intact). Returns (path, checkpoint, a one-line note naming the files
    passed over, or None). Nothing is deleted; raises CheckpointError if none is usable."""
    run = Path(run)
    candidates = [p for p in [run / LATEST, *reversed(checkpoint_paths(run))] if p.exists()]
    if not candidates:
        raise CheckpointError(f"nothing to resume: {run / LATEST} does not exist")
    passed = []
    for path in candidates:
        try:
            ckpt = read_checkpoint(path)
        except CheckpointError as e:
            passed.append(str(e))
            continue
        if is_exported(ckpt):
            passed.append(exported_model_message(path))
            continue
        note = None
        if passed:
            note = (f"warning: resuming from {path.name} (step {int(ckpt['step'])}), the newest usable checkpoint; "
                    f"passed over: {'; '.join(passed)}")
        return path, ckpt, note
    if len(passed) == 1:
        raise CheckpointError(passed[0])
    raise CheckpointError(f"nothing to resume in {run}: no checkpoint is usable ({'; '.join(passed)}); "
                          "move them away to train from the start")


def parse_device(name: str, what: str = "train.device") -> torch.device:
    """A device name as a torch device, checked before any work: one line, not torch's assertion."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"{what}={name!r} is not a torch device; use 'cpu' or 'cuda'") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{what}={name} but CUDA is not available in this torch build "
                          f"(torch {torch.__version__}); use {what}=cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(f"{what}={name} but this machine has {torch.cuda.device_count()} CUDA device(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ConfigError(f"{what}={name} but MPS is not available here; use {what}=cpu")
    if device.type not in ("cpu", "cuda", "mps"):
        raise ConfigError(f"{what}={name}: only cpu, cuda and mps are supported")
    return device


def build_simulator(cfg: Config, spec: ModelSpec, options: RolloutOptions | None = None) -> LearnedSimulator:
    return LearnedSimulator(cfg.model, cfg.features, spec, options)


def load_model(checkpoint: str | Path | dict, device: str | torch.device = "cpu",
               options: RolloutOptions | None = None) -> tuple[LearnedSimulator, Config]:
    """Rebuild a trained simulator (in eval mode, on `device`, rolled out with `options`) and its
    config from a checkpoint file, or from one already read with read_checkpoint (its spec and
    step need no second read). The options' ensemble is left to load_simulator."""
    ckpt = checkpoint if isinstance(checkpoint, dict) else read_checkpoint(checkpoint)
    try:
        cfg = build_config(base=ckpt["config"])
    except ConfigError as e:   # a key removed since it was trained, set: one line naming the file
        raise CheckpointError(f"{'' if isinstance(checkpoint, dict) else f'{checkpoint}: '}{e}") from None
    sim = build_simulator(cfg, ModelSpec.from_dict(ckpt["spec"]), options)
    try:
        sim.load_state_dict(ckpt["model"])
    except RuntimeError as e:  # weights that do not fit the model the checkpoint's own config builds
        where = "" if isinstance(checkpoint, dict) else f"{checkpoint}: "
        raise CheckpointError(f"{where}damaged checkpoint, its weights do not fit its model "
                              f"({str(e).splitlines()[1].strip() if len(str(e).splitlines()) > 1 else e})") from None
    sim.to(device).eval()
    if options is not None and (options.autocast != "none" or options.compile):
        # rollouts only: freezing takes the weights as they are now, which a rollout keeps
        sim.set_speed(options.autocast, options.compile, freeze=options.compile)
    if CONTACT in ckpt:
        where = "" if isinstance(checkpoint, dict) else f"{checkpoint}: "
        contact = load_model(ckpt[CONTACT], device, options)[0]
        try:
            sim.set_contact_model(contact)
        except ValueError as e:
            raise CheckpointError(f"{where}{e}") from None
    return sim, cfg


def load_simulator(run: str | Path, device: str | torch.device = "cpu",
                   options: RolloutOptions | None = None) -> tuple[LearnedSimulator, dict]:
    """The model of `run` (folder, checkpoint or shipped name) set up for rollouts with `options`:
    its network's precision and compiled code, and the runs of options.ensemble as members whose
    predictions each step averages (LearnedSimulator.set_ensemble), each member with the same
    options. Returns (simulator, its saved checkpoint)."""
    options = RolloutOptions() if options is None else options
    checkpoints = [read_checkpoint(checkpoint_of(r)) for r in (run, *options.ensemble)]
    sim, *members = [load_model(saved, device, options)[0] for saved in checkpoints]
    if members:
        try:
            sim.set_ensemble(members)
        except ValueError as e:
            raise CheckpointError(f"ensemble: {e}") from None
    return sim, checkpoints[0]
